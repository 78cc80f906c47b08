"""EM for linear-Gaussian models (``torchmm.learn.em``, issue 45), against pykalman on its robot data (the
MATLAB log-likelihoods it ships) and against properties EM guarantees: the likelihood never decreases,
each iteration's likelihood is the filter's at that iteration's parameters, a batch of series with
parameters of their own equals the separate fits, and shared parameters over copies of one series equal
that series' fit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pykalman = pytest.importorskip("pykalman")

from pykalman import KalmanFilter as PyKalman  # noqa: E402
from pykalman.datasets import load_robot  # noqa: E402

from torchmm import GaussianBelief, KalmanFilter  # noqa: E402
from torchmm.learn import em, negative_log_likelihood  # noqa: E402
from torchmm.models import LinearMeasurement, LinearMotion  # noqa: E402

F64 = torch.float64


def _t(a):
    return torch.as_tensor(np.asarray(a, dtype=float), dtype=F64)


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _robot_filter(d):
    """pykalman's robot model in torchmm: its time-varying transition offsets as inputs (``B = I``), its
    fixed observation offset taken off the data, its masked observations NaN."""
    motion = LinearMotion(_t(d.transition_matrix), _t(d.initial_transition_covariance), input_matrix=torch.eye(5, dtype=F64))
    sensor = LinearMeasurement(_t(d.observation_matrix), _t(d.initial_observation_covariance))
    y = _t(np.ma.filled(d.observations.astype(float), np.nan) - d.observation_offset)
    u = torch.cat([torch.zeros(1, 5, dtype=F64), _t(d.transition_offsets)])  # u_t: the offset into step t
    return KalmanFilter(motion, sensor), GaussianBelief(_t(d.initial_state_mean), _t(d.initial_state_covariance)), y, u


def _pykalman(d, em_vars):
    return PyKalman(d.transition_matrix, d.observation_matrix, d.initial_transition_covariance,
                    d.initial_observation_covariance, d.transition_offsets, d.observation_offset, d.initial_state_mean,
                    d.initial_state_covariance, em_vars=em_vars)


def test_robot_em_equals_pykalman_and_its_matlab_loglikelihoods(robot):
    """EM of Q and R (pykalman's own test): 10 iterations' log-likelihoods equal the MATLAB values pykalman
    ships (1e-8) and pykalman's; the parameters after 9 iterations equal pykalman's."""
    kf, b0, y, u = _robot_filter(robot)
    out = em(kf, b0, y, ["Q", "R"], iterations=9, controls=u, progress=False)
    np.testing.assert_allclose(out.loglik, robot.loglikelihoods[:10], rtol=1e-8, atol=1e-8)
    ref = _pykalman(robot, ["transition_covariance", "observation_covariance"])
    lls = []
    for _ in range(10):
        lls.append(ref.loglikelihood(robot.observations))
        if len(lls) < 10:
            ref.em(X=robot.observations, n_iter=1)
    np.testing.assert_allclose(out.loglik, lls, rtol=1e-10)
    np.testing.assert_allclose(kf.motion.Q.numpy(), ref.transition_covariance, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(kf.measurement.R.numpy(), ref.observation_covariance, rtol=1e-8, atol=1e-12)
    assert out.monotone and out.iterations == 9


def _simulated(T=80, runs=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    F = torch.tensor([[0.9, 0.2], [-0.1, 0.8]], dtype=F64)
    b = torch.tensor([0.5, -0.2], dtype=F64)
    H = torch.tensor([[1.0, 0.5]], dtype=F64)
    x = torch.zeros(runs, 2, dtype=F64)
    ys = []
    for _ in range(T):
        x = x @ F.mT + b + 0.3 * torch.randn(runs, 2, dtype=F64, generator=g)
        ys.append(x @ H.mT + 0.5 * torch.randn(runs, 1, dtype=F64, generator=g))
    return torch.stack(ys)  # (T, runs, 1)


def _start_filter():
    motion = LinearMotion(torch.eye(2, dtype=F64) * 0.5, torch.eye(2, dtype=F64), offset=torch.zeros(2, dtype=F64))
    sensor = LinearMeasurement(torch.tensor([[1.0, 1.0]], dtype=F64), torch.eye(1, dtype=F64))
    return KalmanFilter(motion, sensor), GaussianBelief(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64) * 2)


def test_every_parameter_equals_pykalman():
    """EM of F, the offset, Q, H, R and the start's mean and covariance together (pykalman's em_vars
    without the observation offsets, which torchmm's LinearMeasurement has not): 5 iterations equal."""
    y = _simulated()[:, 0]
    kf, b0 = _start_filter()
    out = em(kf, b0, y, iterations=5, progress=False)
    ref = PyKalman(np.eye(2) * 0.5, np.array([[1.0, 1.0]]), np.eye(2), np.eye(1), np.zeros(2), np.zeros(1),
                   np.zeros(2), np.eye(2) * 2,
                   em_vars=["transition_matrices", "transition_offsets", "transition_covariance",
                            "observation_matrices", "observation_covariance", "initial_state_mean",
                            "initial_state_covariance"])
    ref.em(y.numpy(), n_iter=5)
    for ours, theirs in ((kf.motion.F, ref.transition_matrices), (kf.motion.offset, ref.transition_offsets),
                         (kf.motion.Q, ref.transition_covariance), (kf.measurement.H, ref.observation_matrices),
                         (kf.measurement.R, ref.observation_covariance), (out.belief0.mean, ref.initial_state_mean),
                         (out.belief0.cov, ref.initial_state_covariance)):
        np.testing.assert_allclose(ours.numpy(), theirs, rtol=1e-8, atol=1e-10)
    assert out.monotone


@pytest.mark.parametrize("update_first", [True, False])
def test_each_iterations_likelihood_is_the_filters_and_never_decreases(update_first):
    y = _simulated(60)[:, 0]
    y[10:14] = torch.nan  # missing steps inform the state only
    kf, b0 = _start_filter()
    out = em(kf, b0, y, iterations=12, update_first=update_first, progress=False)
    assert out.monotone and all(b >= a - 1e-9 * abs(a) for a, b in zip(out.loglik, out.loglik[1:]))
    nll = float(negative_log_likelihood(kf, out.belief0, y, reduction="sum", update_first=update_first))
    assert out.loglik[-1] == pytest.approx(-nll, rel=1e-12)


def test_a_batch_of_fits_equals_the_separate_fits():
    y = _simulated(50, runs=4, seed=3)
    kf, b0 = _start_filter()
    out = em(kf, b0.expand(4), y, iterations=6, per_series=True, progress=False)
    assert kf.motion.Q.shape == (4, 2, 2) and out.loglik[-1].shape == (4,)
    for r in range(4):
        one, start = _start_filter()
        alone = em(one, start, y[:, r], iterations=6, progress=False)
        torch.testing.assert_close(kf.motion.F[r], one.motion.F, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(kf.measurement.R[r], one.measurement.R, rtol=1e-9, atol=1e-12)
        assert float(out.loglik[-1][r]) == pytest.approx(alone.loglik[-1], rel=1e-10)


def test_shared_parameters_over_copies_of_a_series_are_that_series_fit():
    y = _simulated(50, seed=4)
    kf2, b0 = _start_filter()
    both = em(kf2, b0.expand(2), y.expand(50, 2, 1).clone(), ["F", "Q", "R"], iterations=5, progress=False)
    kf1, b1 = _start_filter()
    one = em(kf1, b1, y[:, 0], ["F", "Q", "R"], iterations=5, progress=False)
    torch.testing.assert_close(kf2.motion.Q, kf1.motion.Q, rtol=1e-9, atol=1e-12)
    assert both.loglik[-1] == pytest.approx(2 * one.loglik[-1], rel=1e-10)


def test_em_errors_name_the_argument():
    kf, b0 = _start_filter()
    y = _simulated(20)[:, 0]
    with pytest.raises(ValueError, match="^parameters: \\['G'\\]"):
        em(kf, b0, y, ["G"])
    with pytest.raises(TypeError, match="^parameters"):
        em(kf, b0, y, "Q")
    partial = torch.cat([y, y], -1)
    partial[3, 0] = torch.nan
    kf2 = KalmanFilter(kf.motion, LinearMeasurement(torch.eye(2, dtype=F64), torch.eye(2, dtype=F64)))
    with pytest.raises(ValueError, match="^measurements: a vector with some components missing"):
        em(kf2, b0, partial, ["Q"])
    with pytest.raises(ValueError, match="^controls"):
        em(kf, b0, y, ["Q"], controls=torch.zeros(20, 2, dtype=F64))


def _two_sensor_data(T=300, runs=3, seed=7):
    """A 2-state model measured by two sensors (H = [[1, 0], [0.5, 1]]), diagonal Q and R."""
    g = torch.Generator().manual_seed(seed)
    F = torch.tensor([[0.9, 0.2], [-0.1, 0.8]], dtype=F64)
    b = torch.tensor([0.5, -0.2], dtype=F64)
    H = torch.tensor([[1.0, 0.0], [0.5, 1.0]], dtype=F64)
    x, ys = torch.zeros(runs, 2, dtype=F64), []
    for _ in range(T):
        x = x @ F.mT + b + torch.tensor([0.3, 0.5], dtype=F64) * torch.randn(runs, 2, dtype=F64, generator=g)
        ys.append(x @ H.mT + torch.tensor([0.5, 0.3], dtype=F64) * torch.randn(runs, 2, dtype=F64, generator=g))
    return torch.stack(ys)


def _two_sensor_filter():
    return KalmanFilter(LinearMotion(torch.tensor([[0.9, 0.2], [-0.1, 0.8]], dtype=F64), 0.2 * torch.eye(2, dtype=F64),
                                     offset=torch.tensor([0.5, 0.0], dtype=F64)),
                        LinearMeasurement(torch.tensor([[1.0, 0.0], [0.5, 1.0]], dtype=F64), 0.2 * torch.eye(2, dtype=F64)))


DIAGONAL = [[False, True], [True, False]]
MASKS = {"H": [[True, True], [False, False]], "Q": DIAGONAL, "R": DIAGONAL, "offset": [False, True],
         "initial_mean": [False, True]}


def test_fixed_entries_the_constrained_maximum_is_a_fixed_point():
    """EM with fixed entries (issue 45): H's first row, Q's and R's off-diagonal entries (diagonal
    covariances), one offset and one start entry held. Started at the constrained maximum-likelihood
    estimate (torchmm.learn.estimate with the same entries fixed), one EM iteration stays there - the
    maximum is a fixed point of an exact constrained M-step - and keeps the fixed entries bit for bit;
    without the masks the same step moves away."""
    from torchmm.learn import Param

    y = _two_sensor_data()
    kf = _two_sensor_filter()
    b0 = GaussianBelief(torch.zeros(3, 2, dtype=F64), 2 * torch.eye(2, dtype=F64))
    mle = estimate(kf, b0, y, {"measurement.H": Param(fixed=torch.tensor([[True, True], [False, False]])),
                               "motion.F": "free", "motion.offset": Param(fixed=torch.tensor([False, True])),
                               "motion.Q": "variance", "measurement.R": "variance",
                               "belief0.mean": Param(fixed=torch.tensor([[False, True]] * 3))},
                   update_first=True, progress=False, se=False)
    assert mle.converged
    tensors = lambda f: [f.measurement.H, f.motion.F, f.motion.offset, f.motion.Q, f.measurement.R]  # noqa: E731
    before = [t.clone() for t in tensors(kf)]
    out = em(kf, mle.belief0, y, ["H", "R", "F", "offset", "Q", "initial_mean"], iterations=1, fixed=MASKS,
             progress=False)
    for a, b in zip(tensors(kf), before):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    torch.testing.assert_close(out.belief0.mean, mle.belief0.mean, rtol=0, atol=1e-4)  # (a flat direction)
    assert torch.equal(kf.measurement.H[0], before[0][0]) and float(kf.motion.offset[1]) == float(before[2][1])
    assert float(kf.motion.Q[0, 1]) == 0.0 and float(kf.measurement.R[1, 0]) == 0.0
    assert bool((out.belief0.mean[:, 1] == 0).all()) and out.loglik[1] >= out.loglik[0] - 1e-9
    # the same step without the masks leaves the constrained maximum
    free = _two_sensor_filter()
    for t, v in zip(tensors(free), before):
        t.copy_(v)
    em(free, mle.belief0, y, ["H", "R", "F", "offset", "Q", "initial_mean"], iterations=1, progress=False)
    assert float((free.measurement.H[0] - before[0][0]).abs().max()) > 1e-3


def test_fixed_entries_per_series_and_monotone():
    """Masks with a batch of fits (per_series): every series keeps the fixed entries and its likelihood
    never falls."""
    y = _two_sensor_data(80, runs=4, seed=9)
    kf = _two_sensor_filter()
    b0 = GaussianBelief(torch.zeros(2, dtype=F64), 2 * torch.eye(2, dtype=F64)).expand(4)
    out = em(kf, b0, y, ["H", "R", "F", "offset", "Q"], iterations=15, per_series=True, progress=False,
             fixed={k: v for k, v in MASKS.items() if k != "initial_mean"})
    assert out.monotone and kf.measurement.H.shape == (4, 2, 2)
    assert bool((kf.measurement.H[:, 0] == torch.tensor([1.0, 0.0], dtype=F64)).all())
    assert bool((kf.motion.Q[:, 0, 1] == 0).all()) and bool((kf.motion.offset[:, 1] == 0).all())


@pytest.mark.parametrize("fixed, message", [
    ({"F": [[True, True], [True, True]]}, r"^fixed\['F'\]: every entry is fixed"),
    ({"G": [True]}, r"^fixed\['G'\]: not an estimated parameter"),
    ({"Q": [[False, False], [True, False]]}, r"^fixed\['Q'\]: a covariance's mask must be symmetric"),
    ({"H": [[True, True, True]]}, r"^fixed\['H'\]: expected a boolean mask of shape \(2, 2\)"),
])
def test_fixed_entry_errors_name_the_mask(fixed, message):
    kf = _two_sensor_filter()
    b0 = GaussianBelief(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    with pytest.raises(ValueError, match=message):
        em(kf, b0, _two_sensor_data(10, runs=1)[:, 0], ["F", "Q", "H"], fixed=fixed, progress=False)


def test_a_covariance_mask_without_a_closed_form_is_refused():
    kf = _two_sensor_filter()
    kf.motion.Q.copy_(torch.tensor([[1.0, 0.3], [0.3, 1.0]], dtype=F64))
    b0 = GaussianBelief(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    y = _two_sensor_data(10, runs=1)[:, 0]
    with pytest.raises(ValueError, match=r"^fixed\['Q'\]: the fixed entries between a free block and the rest must be 0"):
        em(kf, b0, y, ["Q"], fixed={"Q": DIAGONAL}, progress=False)
    with pytest.raises(ValueError, match=r"^fixed\['Q'\]: the free entries of a covariance must form diagonal blocks"):
        em(kf, b0, y, ["Q"], fixed={"Q": [[True, False], [False, False]]}, progress=False)


# --- switching models: em_switching ------------------------------------------------------------------------
sm = pytest.importorskip("statsmodels.api")

from experiments.realdata import fedfunds_imm, load_fedfunds  # noqa: E402
from torchmm.learn import em_switching, estimate  # noqa: E402


def _regime_params(imm):
    P = imm.transition.matrix()
    return np.array([float(P[0, 0]), float(P[1, 0]), *imm.bank.filter.measurement.H.flatten().tolist(),
                     *imm.bank.filter.measurement.R.flatten().tolist()])


FEDFUNDS = {"transition.value": "stochastic", "bank.filter.measurement.H": "free",
            "bank.filter.measurement.R": "variance"}


@pytest.fixture(scope="module")
def fedfunds():
    y = load_fedfunds()[:, 0].numpy()
    return y, sm.tsa.MarkovRegression(y, k_regimes=2, trend="c", switching_variance=True)


def test_switching_em_reaches_the_maximum_likelihood(fedfunds):
    """With a start distribution of the regimes that does not depend on the parameters (here uniform), the
    Baum-Welch steps are the exact EM of the Markov-switching mean and variance: its fixed point is the
    maximum L-BFGS-B finds from there (estimates 1e-6, log-likelihood 1e-9), every iteration raising the
    likelihood."""
    y, model = fedfunds
    p00, p10, c0, c1, s0, s1 = model.start_params
    imm, b0 = fedfunds_imm([c0, c1], [s0, s1], [[p00, 1 - p00], [p10, 1 - p10]], mode_probs=[0.5, 0.5])
    z = torch.as_tensor(y).reshape(-1, 1)
    out = em_switching(imm, b0, z, ["transition", "H", "R"], iterations=500, tol=1e-14, progress=False)
    assert out.converged and out.monotone
    at_em = _regime_params(imm)
    est = estimate(imm, b0, z, FEDFUNDS, progress=False)
    np.testing.assert_allclose(_regime_params(imm), at_em, rtol=1e-6)
    assert est.loglik == pytest.approx(out.loglik[-1], abs=1e-9)


def test_switching_em_takes_trailing_nan_padding_as_the_end_of_a_series(fedfunds):
    """Fed funds split into series of 90 and 136 quarters, NaN-padded to 200: without ``present`` each
    series ends at its last datum, so the iterates equal those of the explicit ``present`` and of the
    unpadded batch (5 iterations: before, the 64-174 padding steps entered the chain's counts as latent steps:
    p00 0.9297 against 0.9618)."""
    y = torch.as_tensor(fedfunds[0])
    lengths, T = (90, 136), 200
    z = torch.full((T, 2, 1), float("nan"), dtype=torch.float64)
    present = torch.zeros(T, 2, dtype=torch.bool)
    for col, (start, steps) in enumerate(zip((0, 90), lengths)):
        z[:steps, col, 0], present[:steps, col] = y[start:start + steps], True
    fits = []
    for data, mask in ((z, present), (z, None), (z[:136], present[:136])):
        imm, b0 = fedfunds_imm([0.0, 2.714], [1.154, 11.540], [[0.5, 0.5], [0.5, 0.5]])
        out = em_switching(imm, b0.expand(2), data, ["transition", "H", "R"], iterations=5, present=mask,
                           progress=False)
        fits.append((_regime_params(imm), out.loglik[-1]))
    for params, loglik in fits[1:]:
        np.testing.assert_allclose(params, fits[0][0], rtol=1e-12)
        assert loglik == pytest.approx(fits[0][1], rel=1e-12)


def test_switching_em_step_is_statsmodels_for_the_regimes_measurements(fedfunds):
    """One iteration from statsmodels' start: each regime's mean and variance equal statsmodels' EM step
    (its smoothed probabilities are ours); the transition matrix differs by design - statsmodels divides
    the pair counts by the smoothed probabilities of s_t, not of s_{t-1} (Hamilton's M-step, ours), so its
    rows do not sum to one exactly (it warns and rescales when they exceed it)."""
    y, model = fedfunds
    p00, p10, c0, c1, s0, s1 = model.start_params
    imm, b0 = fedfunds_imm([c0, c1], [s0, s1], [[p00, 1 - p00], [p10, 1 - p10]])
    em_switching(imm, b0, torch.as_tensor(y).reshape(-1, 1), ["transition", "H", "R"], iterations=1, ergodic=True,
                 progress=False)
    theirs = model._em_iteration(model.start_params)
    theirs = np.asarray(theirs[1] if isinstance(theirs, tuple) else theirs)
    np.testing.assert_allclose(_regime_params(imm)[2:], theirs[2:], rtol=1e-9)


def _regression_data(seed: int = 11, T: int = 150, runs: int = 2, *, slopes=(0.7, 0.7), sds=(0.5, 1.5)):
    """A simulated 2-regime regression y = c_s + b_s x + e_s (constants 0 and 2, transition [[0.9, 0.1],
    [0.2, 0.8]]) over ``runs`` series: ``y (T, runs, 1)`` and the regressor ``x (T, runs, 1)``."""
    g = torch.Generator().manual_seed(seed)
    P = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=F64)
    s = torch.zeros(runs, dtype=torch.long)
    x = torch.randn(T, runs, dtype=F64, generator=g)
    ys = []
    for t in range(T):
        s = torch.multinomial(P[s], 1, generator=g)[:, 0]
        c, b, sd = (torch.tensor(v, dtype=F64)[s] for v in ((0.0, 2.0), slopes, sds))
        ys.append(c + b * x[t] + sd * torch.randn(runs, dtype=F64, generator=g))
    return torch.stack(ys).unsqueeze(-1), x.unsqueeze(-1)


def test_switching_em_with_regressors_batched_over_series():
    """A simulated 2-regime regression y = c_s + b_s x + e (3 series sharing the parameters, the regressor
    as the motion model's input): EM and L-BFGS-B reach the same optimum (1e-5)."""
    T, runs = 120, 3
    y, u = _regression_data(7, T, runs, slopes=(1.0, -0.5), sds=(0.5, 1.0))  # u (T, runs, 1)

    def build():
        from torchmm import IMM
        Fm = torch.tensor([[1.0, 0.0], [0.0, 0.0]], dtype=F64).expand(2, 2, 2).clone()
        B = torch.tensor([[0.0], [1.0]], dtype=F64).expand(2, 2, 1).clone()
        motion = LinearMotion(Fm, torch.zeros(2, 2, 2, dtype=F64), input_matrix=B)
        sensor = LinearMeasurement(torch.tensor([[[0.5, 0.5]], [[1.5, 0.0]]], dtype=F64),
                                   torch.tensor([[[1.0]], [[2.0]]], dtype=F64))
        imm = IMM(KalmanFilter(motion, sensor), torch.tensor([[0.8, 0.2], [0.3, 0.7]], dtype=F64))
        start = GaussianBelief(torch.tensor([1.0, 0.0], dtype=F64).expand(runs, 2),
                               torch.zeros(runs, 2, 2, dtype=F64))
        return imm, imm.initial_belief(start, torch.tensor([0.5, 0.5], dtype=F64))

    imm, b0 = build()
    out = em_switching(imm, b0, y, ["transition", "H", "R"], iterations=2000, tol=1e-12, controls=u, progress=False)
    assert out.converged and out.monotone
    at_em = _regime_params(imm)
    est = estimate(imm, b0, y, FEDFUNDS, controls=u, progress=False)
    np.testing.assert_allclose(_regime_params(imm), at_em, rtol=1e-5)
    assert est.loglik == pytest.approx(out.loglik[-1], abs=1e-7)
    np.testing.assert_allclose(at_em[2:], [0.0, 1.0, 2.0, -0.5, 0.25, 1.0], atol=0.35)  # near the truth




def _regression_imm(runs: int, H, transition):
    from torchmm import IMM
    Fm = torch.tensor([[1.0, 0.0], [0.0, 0.0]], dtype=F64).expand(2, 2, 2).clone()
    B = torch.tensor([[0.0], [1.0]], dtype=F64).expand(2, 2, 1).clone()
    motion = LinearMotion(Fm, torch.zeros(2, 2, 2, dtype=F64), input_matrix=B)
    sensor = LinearMeasurement(torch.tensor(H, dtype=F64), torch.tensor([[[1.0]], [[2.0]]], dtype=F64))
    imm = IMM(KalmanFilter(motion, sensor), torch.tensor(transition, dtype=F64))
    start = GaussianBelief(torch.tensor([1.0, 0.0], dtype=F64).expand(runs, 2), torch.zeros(runs, 2, 2, dtype=F64))
    return imm, imm.initial_belief(start, torch.tensor([0.5, 0.5], dtype=F64))


def test_switching_em_with_shared_and_fixed_entries_reaches_the_constrained_maximum():
    """Entry-wise sharing and fixed entries in switching EM (issue 45): the regression's slope shared by the
    regimes while the variances switch (the weighted least squares over the regimes, an ECM step), and a
    transition entry held; EM's fixed point is the maximum L-BFGS-B finds with the same constraints
    (Param groups / fixed): estimates 1e-5, log-likelihood 1e-7; every iteration raises the likelihood.
    Then a constant held at 0 in regime 0 (statsmodels' trend="n" for one regime) likewise."""
    from torchmm.learn import Param

    y, u = _regression_data()
    shared_slope = torch.tensor([[False, True]])
    hold = torch.tensor([[False, True], [False, False]])  # P[0, 1] held at its start 0.1
    imm, b0 = _regression_imm(2, [[[0.5, 0.2]], [[1.5, 0.2]]], [[0.9, 0.1], [0.3, 0.7]])
    out = em_switching(imm, b0, y, ["transition", "H", "R"], iterations=3000, tol=1e-13, controls=u,
                       shared={"H": shared_slope}, fixed={"transition": hold}, progress=False)
    assert out.monotone and out.converged
    H = imm.bank.filter.measurement.H
    assert float(H[0, 0, 1]) == float(H[1, 0, 1])  # the slope one value
    assert float(imm.transition.matrix()[0, 1]) == pytest.approx(0.1, abs=1e-15)
    at_em = _regime_params(imm)
    groups = torch.tensor([[[-1, 0]], [[-1, 0]]])
    est = estimate(imm, b0, y, {"transition.value": Param("stochastic", fixed=hold),
                                "bank.filter.measurement.H": Param("free", groups=groups),
                                "bank.filter.measurement.R": "variance"}, controls=u, progress=False)
    np.testing.assert_allclose(_regime_params(imm), at_em, rtol=1e-5, atol=1e-7)
    assert est.loglik == pytest.approx(out.loglik[-1], abs=1e-7)
    assert abs(float(H[0, 0, 1]) - 0.7) < 0.15  # (near the truth)

    fixed_const = torch.tensor([[[True, False]], [[False, False]]])  # regime 0's constant held at 0
    imm, b0 = _regression_imm(2, [[[0.0, 0.5]], [[1.5, 0.2]]], [[0.9, 0.1], [0.3, 0.7]])
    out = em_switching(imm, b0, y, ["transition", "H", "R"], iterations=3000, tol=1e-13, controls=u,
                       fixed={"H": fixed_const}, progress=False)
    assert out.monotone and out.converged and float(imm.bank.filter.measurement.H[0, 0, 0]) == 0.0
    at_em = _regime_params(imm)
    est = estimate(imm, b0, y, {"transition.value": "stochastic",
                                "bank.filter.measurement.H": Param("free", fixed=fixed_const),
                                "bank.filter.measurement.R": "variance"}, controls=u, progress=False)
    np.testing.assert_allclose(_regime_params(imm), at_em, rtol=1e-5, atol=1e-7)
    assert est.loglik == pytest.approx(out.loglik[-1], abs=1e-7)


def test_switching_em_masks_are_checked():
    y, u = _regression_data(T=20)
    imm, b0 = _regression_imm(2, [[[0.5, 0.2]], [[1.5, 0.2]]], [[0.9, 0.1], [0.3, 0.7]])
    with pytest.raises(ValueError, match=r"shared: H's mask must be \(1, 2\)"):
        em_switching(imm, b0, y, ["H"], controls=u, shared={"H": torch.ones(2, 2, dtype=torch.bool)}, progress=False)
    with pytest.raises(ValueError, match="fixed: a row of the transition with every entry fixed"):
        em_switching(imm, b0, y, ["transition"], controls=u, fixed={"transition": torch.tensor([[True, True],
                                                                                                 [False, False]])},
                     progress=False)
    with pytest.raises(ValueError, match="fixed: expected masks of H or transition"):
        em_switching(imm, b0, y, ["R"], controls=u, fixed={"R": torch.ones(1, 1, dtype=torch.bool)}, progress=False)
    with pytest.raises(ValueError, match="shared: R is shared whole"):
        em_switching(imm, b0, y, ["R"], controls=u, shared={"R": torch.ones(1, 1)}, progress=False)


def test_switching_em_of_a_time_varying_transition_reaches_the_maximum():
    """EM of a LogisticTransition (issue 45): the transition's M-step a weighted multinomial logistic
    regression of the pair probabilities (Newton with step halving, never lowering its objective). Fed funds
    with statsmodels' exog_tvtp columns (a constant and the output gap), a start that does not depend on the
    parameters: EM raises the likelihood every iteration and its fixed point is the maximum L-BFGS-B finds
    from there (log-likelihood 1e-6, estimates 1e-4)."""
    from tests.experiments.test_markov_switching import _statsmodels_test_data
    from torchmm import IMM, LogisticTransition

    ff, ogap = _statsmodels_test_data("fedfunds", "ogap")
    y, X = ff[4:], np.c_[np.ones(len(ff) - 4), ogap[4:]]
    z, u = torch.as_tensor(y, dtype=F64).reshape(-1, 1), torch.as_tensor(X, dtype=F64)
    one = torch.ones(2, 1, 1, dtype=F64)

    def build():
        imm = IMM(KalmanFilter(LinearMotion(one, 0 * one, input_matrix=torch.zeros(2, 1, 2, dtype=F64)),
                               LinearMeasurement(torch.tensor([[[2.0]], [[8.0]]], dtype=F64),
                                                 torch.tensor([[[1.0]], [[8.0]]], dtype=F64))),
                  LogisticTransition(torch.tensor([[[2.0, 0.0]], [[-2.0, 0.0]]], dtype=F64), columns=[0, 1]))
        start = GaussianBelief(torch.ones(1, dtype=F64), torch.zeros(1, 1, dtype=F64))
        return imm, imm.initial_belief(start, torch.tensor([0.5, 0.5], dtype=F64))

    imm, b0 = build()
    out = em_switching(imm, b0, z, ["transition", "H", "R"], iterations=2000, tol=1e-13, controls=u, progress=False)
    assert out.monotone and out.converged, (out.decreases, out.iterations)
    at_em = torch.cat([imm.transition.coef.flatten(), imm.bank.filter.measurement.H.flatten(),
                       imm.bank.filter.measurement.R.flatten()])
    est = estimate(imm, b0, z, {"transition.coef": "free", "bank.filter.measurement.H": "free",
                                "bank.filter.measurement.R": "variance"}, controls=u, progress=False)
    at_mle = torch.cat([imm.transition.coef.flatten(), imm.bank.filter.measurement.H.flatten(),
                        imm.bank.filter.measurement.R.flatten()])
    assert est.loglik == pytest.approx(out.loglik[-1], abs=1e-6)
    np.testing.assert_allclose(at_em.numpy(), at_mle.numpy(), rtol=1e-4, atol=1e-4)
    assert out.loglik[-1] > out.loglik[0] + 10

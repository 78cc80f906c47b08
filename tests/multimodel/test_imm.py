"""IMM / GPB1 / GPB2: FilterPy and NumPy references, degenerate-case identities, banks, properties."""

from __future__ import annotations

import math
from functools import partial

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import BATCH_SHAPES, assert_symmetric_psd, random_psd, random_system, random_transition
from tests.reference import mm_numpy
from torchmm import (
    GPB1,
    GPB2,
    IMM,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    LinearMotion,
    ListBank,
    ModeBelief,
    UnscentedKalmanFilter,
    VectorizedBank,
    run_filter,
)

close = partial(torch.testing.assert_close, rtol=1e-9, atol=1e-9)


def _mode_bank(n, m, M, rng):
    """M motion models sharing a sensor; returns numpy pieces and the torch filter bank."""
    base = random_system(n, m, rng)
    models = []
    for _ in range(M):
        F = base.F + 0.2 * rng.normal(size=(n, n))
        F = 0.95 * F / max(1.0, np.abs(np.linalg.eigvals(F)).max())
        models.append((F, 2.0 * rng.normal(size=n), random_psd(n, rng, 0.5)))
    motion = LinearMotion(
        torch.tensor(np.array([F for F, _, _ in models])),
        torch.tensor(np.array([Q for _, _, Q in models])),
        offset=torch.tensor(np.array([b for _, b, _ in models])),
    )
    return base, models, KalmanFilter(motion, LinearMeasurement(torch.tensor(base.H), torch.tensor(base.R)))


def _simulate_switching(base, models, Pi, steps, rng):
    x = rng.multivariate_normal(base.x0, base.P0)
    mode = rng.integers(len(models))
    zs = []
    for _ in range(steps):
        mode = rng.choice(len(models), p=Pi[mode])
        F, b, Q = models[mode]
        x = F @ x + b + rng.multivariate_normal(np.zeros(len(x)), Q)
        zs.append(base.H @ x + rng.multivariate_normal(np.zeros(len(base.R)), base.R))
    return np.array(zs)


@pytest.mark.parametrize("n,m,M", [(2, 1, 2), (2, 1, 3), (3, 2, 3), (4, 2, 4)], ids=str)
def test_imm_matches_filterpy(n, m, M):
    pytest.importorskip("filterpy")
    from filterpy.kalman import IMMEstimator
    from filterpy.kalman import KalmanFilter as FPKalmanFilter

    rng = np.random.default_rng(100 + 10 * M + n)
    base, models, bank = _mode_bank(n, m, M, rng)
    Pi = random_transition(M, rng)  # not symmetric: catches a transposed convention
    zs = _simulate_switching(base, models, Pi, 30, rng)
    mu0 = np.full(M, 1.0 / M)

    imm = IMM(bank, torch.tensor(Pi))
    traj = run_filter(imm, imm.initial_belief(base.prior(), torch.tensor(mu0)), torch.tensor(zs))
    est = traj.estimate()

    fps = []
    for F, b, Q in models:
        kf = FPKalmanFilter(dim_x=n, dim_z=m, dim_u=1)
        kf.F, kf.Q, kf.H, kf.R, kf.B = F, Q, base.H, base.R, b.reshape(n, 1)
        kf.x, kf.P = base.x0.reshape(n, 1).copy(), base.P0.copy()
        fps.append(kf)
    ref = IMMEstimator(fps, mu0, Pi)
    for k, z in enumerate(zs):
        ref.predict(u=np.ones((1, 1)))
        ref.update(z.reshape(m, 1))
        close(est.mean[k], torch.tensor(ref.x.ravel()))
        close(est.cov[k], torch.tensor(ref.P))
        close(traj.belief.mode_probs[k], torch.tensor(ref.mu))
        for j, f in enumerate(fps):
            close(traj.belief.components.mean[k, j], torch.tensor(f.x.ravel()))


@pytest.mark.parametrize(
    "estimator,reference",
    [(IMM, mm_numpy.imm), (GPB1, mm_numpy.gpb1), (GPB2, mm_numpy.gpb2)],
    ids=["IMM", "GPB1", "GPB2"],
)
@pytest.mark.parametrize("n,m,M", [(2, 1, 2), (3, 2, 3)], ids=str)
def test_against_numpy_reference(estimator, reference, n, m, M):
    rng = np.random.default_rng(7 * M + n)
    base, models, bank = _mode_bank(n, m, M, rng)
    Pi = random_transition(M, rng)
    zs = _simulate_switching(base, models, Pi, 25, rng)
    mu0 = rng.dirichlet(np.ones(M))
    filt = estimator(bank, torch.tensor(Pi))
    traj = run_filter(filt, filt.initial_belief(base.prior(), torch.tensor(mu0)), torch.tensor(zs))
    x_ref, P_ref, mu_ref = reference(models, base.H, base.R, Pi, base.x0, base.P0, mu0, zs)
    est = traj.estimate()
    close(est.mean, torch.tensor(x_ref))
    close(est.cov, torch.tensor(P_ref))
    close(traj.belief.mode_probs, torch.tensor(mu_ref))


@pytest.mark.parametrize("estimator", [IMM, GPB1, GPB2])
def test_single_mode_equals_its_filter(estimator):
    rng = np.random.default_rng(1)
    system = random_system(3, 2, rng)
    _, zs = system.simulate(20, rng)
    kf = KalmanFilter(system.motion(), system.measurement())
    filt = estimator(kf, torch.ones(1, 1))
    traj = run_filter(filt, filt.initial_belief(system.prior()), torch.tensor(zs))
    ref = run_filter(kf, system.prior(), torch.tensor(zs))
    close(traj.estimate().mean, ref.belief.mean)
    close(traj.estimate().cov, ref.belief.cov)
    close(traj.log_likelihood, ref.log_likelihood)


@pytest.mark.parametrize("estimator", [IMM, GPB1, GPB2])
@pytest.mark.parametrize("seed", [0, 1])
def test_identical_modes_equal_single_filter_for_any_transition(estimator, seed):
    rng = np.random.default_rng(seed)
    system = random_system(2, 1, rng)
    _, zs = system.simulate(20, rng)
    M = 3
    kf = KalmanFilter(system.motion(), system.measurement())
    Pi = torch.tensor(random_transition(M, rng))
    mu0 = torch.tensor(rng.dirichlet(np.ones(M)))
    filt = estimator([kf] * M, Pi)
    traj = run_filter(filt, filt.initial_belief(system.prior(), mu0), torch.tensor(zs))
    ref = run_filter(kf, system.prior(), torch.tensor(zs))
    close(traj.estimate().mean, ref.belief.mean)
    close(traj.estimate().cov, ref.belief.cov)
    close(traj.log_likelihood, ref.log_likelihood)
    # identical likelihoods: mode probabilities just propagate through the chain, mu_k = mu_0 Pi^k
    expected, mu = [], mu0
    for _ in range(20):
        mu = mu @ Pi
        expected.append(mu)
    close(traj.belief.mode_probs, torch.stack(expected))


def test_gpb1_equals_imm_when_transition_rows_are_identical():
    rng = np.random.default_rng(5)
    base, models, bank = _mode_bank(2, 1, 3, rng)
    row = rng.dirichlet(np.ones(3))
    Pi = torch.tensor(np.tile(row, (3, 1)))
    zs = torch.tensor(_simulate_switching(base, models, Pi.numpy(), 20, rng))
    a, b = IMM(bank, Pi), GPB1(bank, Pi)
    ta = run_filter(a, a.initial_belief(base.prior()), zs)
    tb = run_filter(b, b.initial_belief(base.prior()), zs)
    close(ta.estimate().mean, tb.estimate().mean)
    close(ta.belief.mode_probs, tb.belief.mode_probs)


def test_identity_transition_is_an_independent_bank():
    rng = np.random.default_rng(6)
    base, models, bank = _mode_bank(2, 1, 3, rng)
    zs = torch.tensor(_simulate_switching(base, models, np.eye(3), 15, rng))
    imm = IMM(bank, torch.eye(3))
    traj = run_filter(imm, imm.initial_belief(base.prior()), zs)
    for j, (F, b, Q) in enumerate(models):
        kf = KalmanFilter(LinearMotion(torch.tensor(F), torch.tensor(Q), offset=torch.tensor(b)),
                          LinearMeasurement(torch.tensor(base.H), torch.tensor(base.R)))
        ref = run_filter(kf, base.prior(), zs)
        close(traj.belief.components.mean[:, j], ref.belief.mean)


def test_list_bank_of_heterogeneous_filters_equals_vectorized_bank():
    rng = np.random.default_rng(9)
    base, models, bank = _mode_bank(3, 2, 3, rng)
    Pi = torch.tensor(random_transition(3, rng))
    zs = torch.tensor(_simulate_switching(base, models, Pi.numpy(), 15, rng)).unsqueeze(1).expand(15, 2, 2)
    sensor = LinearMeasurement(torch.tensor(base.H), torch.tensor(base.R))
    motions = [LinearMotion(torch.tensor(F), torch.tensor(Q), offset=torch.tensor(b)) for F, b, Q in models]
    hetero = [KalmanFilter(motions[0], sensor), ExtendedKalmanFilter(motions[1], sensor),
              UnscentedKalmanFilter(motions[2], sensor)]
    a, b = IMM(bank, Pi), IMM(hetero, Pi)
    assert isinstance(a.bank, VectorizedBank) and isinstance(b.bank, ListBank)
    prior = base.prior().expand(2)
    ta = run_filter(a, a.initial_belief(prior), zs)
    tb = run_filter(b, b.initial_belief(prior), zs)
    close(ta.estimate().mean, tb.estimate().mean)
    close(ta.belief.mode_probs, tb.belief.mode_probs)
    close(ta.log_likelihood, tb.log_likelihood)
    assert ta.innovation.shape == tb.innovation.shape == (15, 2, 3, 2)


def test_list_of_kalman_filters_is_fused_into_a_vectorized_bank():
    rng = np.random.default_rng(10)
    systems = [random_system(2, 1, rng) for _ in range(3)]
    imm = IMM([KalmanFilter(s.motion(), s.measurement()) for s in systems], torch.eye(3) * 0.7 + 0.1)
    assert isinstance(imm.bank, VectorizedBank)


@pytest.mark.parametrize("estimator", [IMM, GPB1, GPB2])
@pytest.mark.parametrize("batch_shape", BATCH_SHAPES, ids=str)
def test_shapes(estimator, batch_shape):
    rng = np.random.default_rng(0)
    base, _, bank = _mode_bank(3, 2, 3, rng)
    filt = estimator(bank, torch.tensor(random_transition(3, rng)))
    prior = GaussianBelief(torch.zeros(*batch_shape, 3), torch.eye(3))
    traj = run_filter(filt, filt.initial_belief(prior), torch.randn(4, *batch_shape, 2))
    assert traj.belief.mode_log_probs.shape == (4, *batch_shape, 3)
    assert traj.belief.components.mean.shape == (4, *batch_shape, 3, 3)
    assert traj.estimate().mean.shape == (4, *batch_shape, 3)
    assert traj.estimate().cov.shape == (4, *batch_shape, 3, 3)
    assert traj.log_likelihood.shape == (4, *batch_shape)
    per_pair = (3,) if estimator is GPB2 else ()
    assert traj.innovation.shape == (4, *batch_shape, *per_pair, 3, 2)


@pytest.mark.parametrize("estimator", [IMM, GPB1, GPB2])
def test_missing_measurement_keeps_predicted_mode_probabilities(estimator):
    rng = np.random.default_rng(12)
    base, models, bank = _mode_bank(2, 1, 3, rng)
    Pi = torch.tensor(random_transition(3, rng))
    filt = estimator(bank, Pi)
    belief = filt.initial_belief(base.prior().expand(2), torch.tensor([0.2, 0.3, 0.5]))
    out = filt.step(belief, torch.tensor([[0.4], [torch.nan]]))
    close(out.belief.mode_probs[1], torch.tensor([0.2, 0.3, 0.5]) @ Pi)
    assert out.log_likelihood[1].item() == 0.0
    assert bool(torch.isfinite(out.belief.estimate().mean).all())


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), M=st.integers(2, 4), estimator=st.sampled_from([IMM, GPB1, GPB2]))
def test_probabilities_normalised_and_covariances_psd(seed, M, estimator):
    rng = np.random.default_rng(seed)
    base, models, bank = _mode_bank(2, 1, M, rng)
    Pi = random_transition(M, rng)
    zs = torch.tensor(_simulate_switching(base, models, Pi, 12, rng)) * 3  # outliers stress underflow
    filt = estimator(bank, torch.tensor(Pi))
    traj = run_filter(filt, filt.initial_belief(base.prior()), zs)
    close(traj.belief.mode_probs.sum(-1), torch.ones(12))
    assert bool(torch.isfinite(traj.belief.mode_log_probs).all())
    assert_symmetric_psd(traj.estimate().cov)
    assert_symmetric_psd(traj.belief.components.cov)


def test_log_space_survives_extreme_outliers():
    """A measurement 1e4 sigmas away underflows every linear-space likelihood; log space does not."""
    rng = np.random.default_rng(13)
    base, _, bank = _mode_bank(2, 1, 3, rng)
    imm = IMM(bank, torch.tensor(random_transition(3, rng)))
    out = imm.step(imm.initial_belief(base.prior()), torch.tensor([1e6]))
    assert bool(torch.isfinite(out.belief.mode_log_probs).all())
    assert bool(torch.isfinite(out.log_likelihood))
    close(out.belief.mode_probs.sum(), torch.tensor(1.0))


# -- update_first: the first datum updates the start belief, no prediction ---------------------------
def _update_first_case(M=3, batch=(4,), steps=6, seed=21):
    rng = np.random.default_rng(seed)
    base, models, bank = _mode_bank(2, 1, M, rng)
    Pi = torch.tensor(random_transition(M, rng))
    mu0 = torch.tensor(rng.dirichlet(np.ones(M)))
    prior = base.prior().expand(*batch)
    zs = torch.tensor(np.stack([_simulate_switching(base, models, Pi.numpy(), steps, rng)
                                for _ in range(int(np.prod(batch)))], 1)).reshape(steps, *batch, -1)
    return bank, Pi, mu0, prior, zs


def test_gpb2_update_first_step0_is_the_mode_updates_weighted_by_the_start_probabilities():
    """GPB2's step 0 with ``update_first``: every mode filter updates its start belief with the first
    datum (no mode switch before it); mode j's posterior probability is ``mu0_j l_j / sum_l mu0_l l_l``
    and the log-likelihood ``log sum_j mu0_j l_j`` - written out here with the bank's Kalman filter."""
    bank, Pi, mu0, prior, zs = _update_first_case()
    gpb2 = GPB2(bank, Pi)
    traj = run_filter(gpb2, gpb2.initial_belief(prior, mu0), zs, update_first=True, fast_path=False)
    # by hand: each mode's Kalman update of the prior (the bank's models broadcast over the mode axis)
    out = bank.update(prior.unsqueeze(-1).expand(*prior.batch_shape, 3), zs[0].unsqueeze(-2))
    joint = out.log_likelihood + mu0.log()
    close(traj.log_likelihood[0], torch.logsumexp(joint, -1))
    close(traj.belief.mode_probs[0], torch.softmax(joint, -1))
    close(traj.belief.components.mean[0], out.belief.mean)
    close(traj.belief.components.cov[0], out.belief.cov)
    # the same step as the IMM's and GPB1's (their update_first is the same update of the start belief)
    for other in (IMM(bank, Pi), GPB1(bank, Pi)):
        ref = run_filter(other, other.initial_belief(prior, mu0), zs[:1], update_first=True, fast_path=False)
        close(traj.belief.mode_probs[0], ref.belief.mode_probs[0])
        close(traj.estimate().mean[0], ref.estimate().mean[0])
        close(traj.estimate().cov[0], ref.estimate().cov[0])
    # the trajectory stacks: step 0's prior is over the M^2 pairs like every later step's
    assert traj.prior.mode_log_probs.shape == (6, 4, 9)
    assert traj.innovation.shape == (6, 4, 3, 3, 1)


def test_gpb2_update_first_then_steps_and_kernels_agree():
    """The rest of the run continues from step 0's posterior; the default (kernels on) gives the numbers
    of the steps (the kernels decline update_first), and fast_path=True says why it cannot."""
    bank, Pi, mu0, prior, zs = _update_first_case()
    gpb2 = GPB2(bank, Pi)
    belief0 = gpb2.initial_belief(prior, mu0)
    steps = run_filter(gpb2, belief0, zs, update_first=True, fast_path=False)
    first = IMM(bank, Pi).update(belief0, zs[0])  # the update of the start belief
    rest = run_filter(gpb2, first.belief, zs[1:], fast_path=False)
    close(steps.log_likelihood, torch.cat([first.log_likelihood.unsqueeze(0), rest.log_likelihood]))
    close(steps.estimate().mean[1:], rest.estimate().mean)
    close(steps.belief.mode_probs[1:], rest.belief.mode_probs)
    default = run_filter(gpb2, belief0, zs, update_first=True)  # fast_path=None: kernels on
    close(default.log_likelihood, steps.log_likelihood, rtol=1e-12, atol=1e-12)
    close(default.estimate().mean, steps.estimate().mean, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="^fast_path: no fast path .*update_first"):
        run_filter(gpb2, belief0, zs, fast_path=True, update_first=True)
    # and without update_first the runs differ (the comparison tells the conventions apart)
    assert not torch.allclose(run_filter(gpb2, belief0, zs).log_likelihood[0], steps.log_likelihood[0])


def test_gpb2_update_first_with_one_mode_is_its_kalman_filter():
    rng = np.random.default_rng(3)
    system = random_system(3, 2, rng)
    _, zs = system.simulate(10, rng)
    kf = KalmanFilter(system.motion(), system.measurement())
    gpb2 = GPB2(kf, torch.ones(1, 1))
    traj = run_filter(gpb2, gpb2.initial_belief(system.prior()), torch.tensor(zs), update_first=True)
    ref = run_filter(kf, system.prior(), torch.tensor(zs), update_first=True)
    close(traj.estimate().mean, ref.belief.mean)
    close(traj.estimate().cov, ref.belief.cov)
    close(traj.log_likelihood, ref.log_likelihood)


def test_gpb2_update_refuses_a_belief_of_another_mode_count():
    bank, Pi, mu0, prior, zs = _update_first_case()
    gpb2 = GPB2(bank, Pi)
    start = gpb2.initial_belief(prior, mu0)
    four = ModeBelief(torch.full((4, 4), -math.log(4)), start.components[:, :1].expand(4, 4))
    with pytest.raises(ValueError, match=r"^belief: expected 3 modes .* or 9 pairs .*got 4"):
        gpb2.update(four, zs[0])


@pytest.mark.parametrize("combinator", [IMM, GPB1])
def test_controls_read_by_the_transition_only(combinator):
    """A LogisticTransition reads the controls; motions without an input matrix do not: the eager steps pass
    them to the transition only, as the linear kernel does (before: 'u: this LinearMotion has no
    input_matrix'), and equal the same model with a zero input matrix. With a fixed transition nothing reads
    the controls and the refusal names ``u``."""
    from torchmm import LogisticTransition, kernels

    d = torch.float64
    g = torch.Generator().manual_seed(0)
    F, Q = torch.eye(1, dtype=d).expand(2, 1, 1), 0.1 * torch.eye(1, dtype=d).expand(2, 1, 1)
    sensor = LinearMeasurement(torch.ones(2, 1, 1, dtype=d), torch.tensor([[[1.0]], [[4.0]]], dtype=d))
    trans = LogisticTransition(torch.tensor([[[2.0, 0.0]], [[-2.0, 0.0]]], dtype=d), columns=[0, 1])
    z = torch.randn(6, 1, dtype=d, generator=g)
    u = torch.stack([torch.ones(6, dtype=d), torch.randn(6, dtype=d, generator=g)], -1)
    prior = GaussianBelief(torch.zeros(1, dtype=d), torch.eye(1, dtype=d))
    lls = {}
    for G in (None, torch.zeros(2, 1, 2, dtype=d)):
        f = combinator(KalmanFilter(LinearMotion(F, Q, input_matrix=G), sensor), trans)
        b0 = f.initial_belief(prior, torch.tensor([0.5, 0.5], dtype=d))
        with kernels.switched_off(*kernels.names()):
            lls[G is None] = run_filter(f, b0, z, controls=u, fast_path=False).log_likelihood
    close(lls[True], lls[False])
    f = combinator(KalmanFilter(LinearMotion(F, Q), sensor), trans)
    b0 = f.initial_belief(prior, torch.tensor([0.5, 0.5], dtype=d))
    fast = run_filter(f, b0, z, controls=u, fast_path=True)
    assert fast.provenance.kernel != "eager steps"
    close(fast.log_likelihood, lls[True])
    P = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=d)
    fixed = combinator(KalmanFilter(LinearMotion(F, Q), sensor), P)
    with pytest.raises(ValueError, match="^u: "):
        run_filter(fixed, fixed.initial_belief(prior), z, controls=u, fast_path=False)


@pytest.fixture
def float32_default():
    """torch's own default dtype (float32) for one test, restored after (tests/conftest.py sets float64)."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float32)
    yield
    torch.set_default_dtype(previous)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_static_bank_takes_the_filters_dtype(float32_default, dtype):
    """StaticMM built its identity transition in the default dtype: a float64 filter under float32's default
    was refused ('belief: dtype torch.float64 differs from the filter's torch.float32 (transition.value)').
    Its run equals one Kalman filter per mode (the static bank: no interaction) with Bayes' mode weights."""
    from torchmm import StaticMM

    F = torch.eye(2, dtype=dtype)
    Q = torch.stack([0.1 * torch.eye(2, dtype=dtype), torch.eye(2, dtype=dtype)])
    sensor = LinearMeasurement(torch.ones(1, 2, dtype=dtype), torch.eye(1, dtype=dtype))
    s = StaticMM(KalmanFilter(LinearMotion(F.expand(2, 2, 2).clone(), Q), sensor), 2)
    assert s.transition.matrix().dtype == dtype
    prior = GaussianBelief(torch.zeros(3, 2, dtype=dtype), torch.eye(2, dtype=dtype))
    z = torch.randn(4, 3, 1, generator=torch.Generator().manual_seed(0)).to(dtype)
    traj = run_filter(s, s.initial_belief(prior, torch.tensor([0.5, 0.5], dtype=dtype)), z, fast_path=False)
    per_mode = [run_filter(KalmanFilter(LinearMotion(F, Q[j]), sensor), prior, z,
                           fast_path=False).log_likelihood for j in range(2)]
    joint = torch.stack(per_mode, -1).double().cumsum(0) + math.log(0.5)  # log p(z_1:t, mode)
    want = torch.logsumexp(joint, -1).diff(dim=0, prepend=torch.zeros(1, 3, dtype=torch.float64))
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(traj.log_likelihood.double(), want, rtol=tol, atol=tol)

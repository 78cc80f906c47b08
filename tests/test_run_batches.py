"""run_filter's entry checks of the batches it is handed besides the belief's and the measurements'
(docs/robustness.md): the controls' (shared by the runs: taken by every path alike; enlarging the batch or of
another width: a ValueError naming ``controls``), a per-run transition ``(*B, M, M)`` (taken by the eager
steps and the Numba kernel, declined with a reason by the batch-last kernels; a batch that is not the runs':
a ValueError naming ``transition``) and the model parameters' (per-run: fine; a batch that does not
broadcast, or adds runs: a ValueError naming the parameter). Numbers against a hand-written float64 NumPy
Kalman filter / IMM / GPB1 / GPB2 (tests/reference/mm_numpy.py) run by run."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.reference import mm_numpy
from torchmm import GPB1, GPB2, IMM, GaussianBelief, KalmanFilter, kernels, run_filter
from torchmm.models import ConstantVelocity, LinearMeasurement, LinearMotion, PositionMeasurement
from torchmm.run import Keep
from torchmm.smooth import smooth

D = torch.float64
B, T = 4, 6


def _kf_with_input(F=None, R=None):
    F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=D) if F is None else F
    G = torch.tensor([[0.5], [1.0]], dtype=D)
    return KalmanFilter(LinearMotion(F, 0.1 * torch.eye(2, dtype=D), input_matrix=G),
                        LinearMeasurement(torch.tensor([[1.0, 0.0]], dtype=D),
                                          torch.eye(1, dtype=D) if R is None else R)), G


def _reference_kf(F, b, Q, H, R, x0, P0, zs):
    """A run's log-likelihoods and posterior means (``b (T, n)``: each step's input term)."""
    x, P, lls, means = x0.copy(), P0.copy(), [], []
    for z, bt in zip(zs, b):
        x, P, lik = mm_numpy.kf_step(x, P, F, bt, Q, H, R, z)
        lls.append(math.log(lik))
        means.append(x)
    return np.array(lls), np.array(means)


@pytest.mark.parametrize("shape", [(T, 1), (T, 1, 1)])
def test_controls_shared_by_the_runs_on_every_path(shape):
    """Controls ``(T, k)`` or ``(T, 1, k)`` shared by the runs: the Numba kernel (which raised a RuntimeError
    expanding ``(T, k)`` to ``(T, *B, k)``) and the eager steps give the NumPy reference's numbers."""
    kf, G = _kf_with_input()
    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(B, 2, dtype=D, generator=g)
    z = torch.randn(T, B, 1, dtype=D, generator=g)
    u = torch.linspace(-1.0, 1.0, T, dtype=D).reshape(shape)
    fast = run_filter(kf, GaussianBelief(x0, torch.eye(2, dtype=D)), z, controls=u)
    assert fast.provenance.kernel == "linear_gaussian"
    slow = run_filter(kf, GaussianBelief(x0, torch.eye(2, dtype=D)), z, controls=u, fast_path=False)
    b = (G.numpy() @ u.reshape(T, 1).numpy().T).T  # (T, n)
    for traj in (fast, slow):
        assert traj.belief.mean.shape == (T, B, 2) and traj.belief.cov.shape == (T, B, 2, 2)
        for r in range(B):
            lls, means = _reference_kf(kf.motion.F.numpy(), b, kf.motion.Q.numpy(), kf.measurement.H.numpy(),
                                       kf.measurement.R.numpy(), x0[r].numpy(), np.eye(2), z[:, r].numpy())
            np.testing.assert_allclose(traj.log_likelihood[:, r].numpy(), lls, rtol=1e-10)
            np.testing.assert_allclose(traj.belief.mean[:, r].numpy(), means, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("shape", [(T, B + 1, 1), (T, 2, B, 1), (T, B, 2)])
def test_controls_that_do_not_fit_the_run_are_named(shape):
    """A batch of one run too many (a bare RuntimeError before), one that enlarges the batch (before: a
    Trajectory of mean (6, 2, 4, 2) and cov (6, 4, 2, 2)), or more inputs than the input matrix reads."""
    kf, _ = _kf_with_input()
    prior = GaussianBelief(torch.zeros(B, 2, dtype=D), torch.eye(2, dtype=D))
    z = torch.zeros(T, B, 1, dtype=D)
    for fast_path in (None, False):
        with pytest.raises(ValueError, match=r"^controls: "):
            run_filter(kf, prior, z, controls=torch.ones(shape, dtype=D), fast_path=fast_path)


def _transitions():
    P = torch.tensor([[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.25, 0.25, 0.5]], dtype=D)
    sticky = torch.tensor([[0.9, 0.05, 0.05], [0.1, 0.8, 0.1], [0.2, 0.2, 0.6]], dtype=D)
    return torch.stack([P, sticky, sticky.mT / sticky.mT.sum(-1, keepdim=True), P])  # (B, M, M)


def _mode_run():
    motion = ConstantVelocity(1, dt=1.0, q=1.0, acceleration=[[0.25], [0.0], [-0.25]]).to(D)
    sensor = PositionMeasurement(2, [0], 4.0).to(D)
    prior = GaussianBelief(torch.tensor([[10.0, 1.0]], dtype=D).expand(B, 2), torch.eye(2, dtype=D) * 4)
    z = 10 + torch.randn(T, B, 1, dtype=D, generator=torch.Generator().manual_seed(0))
    return KalmanFilter(motion, sensor), prior, z


@pytest.mark.parametrize(("cls", "reference", "kernel"), [(IMM, mm_numpy.imm, "linear_gaussian"),
                                                          (GPB1, mm_numpy.gpb1, "linear_gaussian"),
                                                          (GPB2, mm_numpy.gpb2, kernels.EAGER)])
def test_per_run_transition_on_the_default_path(cls, reference, kernel):
    """A transition ``(B, M, M)``: the default path (a RuntimeError in the batch-last kernel's frame before)
    takes the Numba kernel (IMM, GPB1) or the eager steps, the batch-last kernel declining with its reason;
    every path gives run ``r`` the NumPy reference's numbers with its own matrix."""
    kf, prior, z = _mode_run()
    Pb = _transitions()
    f = cls(kf, Pb)
    b0 = f.initial_belief(prior)
    runs = {"default": run_filter(f, b0, z)}
    assert runs["default"].provenance.kernel == kernel
    with kernels.switched_off("linear_gaussian"):
        runs["batch_last declined"] = run_filter(f, b0, z)
    assert runs["batch_last declined"].provenance.kernel == kernels.EAGER
    assert "batch_last: a per-run transition" in runs["batch_last declined"].provenance.declined
    runs["eager"] = run_filter(f, b0, z, fast_path=False)
    models = [(kf.motion.F.numpy(), kf.motion.offset[j].numpy(), kf.motion.Q.numpy()) for j in range(3)]
    for name, traj in runs.items():
        est = traj.estimate()
        assert est.mean.shape == (T, B, 2) and traj.belief.mode_log_probs.shape == (T, B, 3), name
        for r in range(B):
            x, _, mu = reference(models, kf.measurement.H.numpy(), kf.measurement.R.numpy(), Pb[r].numpy(),
                                 prior.mean[r].numpy(), prior.cov.numpy(), np.full(3, 1 / 3), z[:, r].numpy())
            np.testing.assert_allclose(est.mean[:, r].numpy(), x, rtol=1e-9, atol=1e-10, err_msg=name)
            probs = traj.belief.mode_log_probs[:, r].exp().numpy()
            np.testing.assert_allclose(probs, mu, rtol=1e-9, atol=1e-12, err_msg=name)


def test_per_run_transition_gradient_and_smoother_on_the_kernel():
    """The Numba kernel's reverse pass through a per-run transition equals autograd's through the eager steps,
    and Kim's smoother of its run (the compiled smoother declines: it reads one matrix) the eager one's."""
    kf, prior, z = _mode_run()
    Pb = _transitions().clone().requires_grad_(True)
    f = IMM(kf, Pb)
    b0 = f.initial_belief(prior)
    fast = run_filter(f, b0, z, record=Keep("log_likelihood", "belief"))
    assert fast.provenance.kernel == "linear_gaussian"
    (g_fast,) = torch.autograd.grad(fast.log_likelihood.sum(), Pb)
    slow = run_filter(f, b0, z, fast_path=False)
    (g_slow,) = torch.autograd.grad(slow.log_likelihood.sum(), Pb)
    torch.testing.assert_close(fast.log_likelihood, slow.log_likelihood, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(g_fast, g_slow, rtol=1e-9, atol=1e-12)
    with torch.no_grad():
        full = run_filter(f, b0, z)
        kim = smooth(f, full, method="kim")
        with kernels.switched_off(*kernels.names()):
            eager = smooth(f, run_filter(f, b0, z, fast_path=False), method="kim")
    torch.testing.assert_close(kim.belief.mode_log_probs, eager.belief.mode_log_probs, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(kim.belief.components.mean, eager.belief.components.mean, rtol=1e-9,
                               atol=1e-12)


def test_per_run_transition_in_a_prepared_likelihood():
    """An optimiser's likelihood (the Numba kernel's prepared evaluation) through a per-run transition: the
    eager steps' loss and gradient."""
    from torchmm.kernels.linear import Prepared
    from torchmm.learn import Objective, negative_log_likelihood

    kf, prior, z = _mode_run()
    Pb = _transitions().clone().requires_grad_(True)
    f = IMM(kf, Pb)
    b0 = f.initial_belief(prior)
    assert isinstance(Objective(f, b0, z)._prepared, Prepared)
    (g_fast,) = torch.autograd.grad(fast := negative_log_likelihood(f, b0, z), Pb)
    with kernels.switched_off(*kernels.names()):
        (g_slow,) = torch.autograd.grad(slow := negative_log_likelihood(f, b0, z), Pb)
    torch.testing.assert_close(fast, slow, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(g_fast, g_slow, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("lead", [(B + 1,), (2, B), (2, 1)])
def test_a_transition_batch_that_is_not_the_runs_is_named(lead):
    kf, prior, z = _mode_run()
    f = IMM(kf, _transitions()[0].expand(*lead, 3, 3))
    for fast_path in (None, False):
        with pytest.raises(ValueError, match=r"^transition: "):
            run_filter(f, f.initial_belief(prior), z, fast_path=fast_path)


@pytest.mark.parametrize(("which", "lead"), [("motion.F", (B + 1,)), ("measurement.R", (B + 1,)),
                                             ("motion.F", (2, 1)), ("measurement.R", (2, 1))])
def test_a_parameter_batch_that_is_not_the_runs_is_named(which, lead):
    """A parameter of batch ``(B + 1,)`` (a bare RuntimeError before) or ``(2, 1)`` (before: the output batch
    silently enlarged to ``(T, 2, B)``)."""
    F, R = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=D), torch.eye(1, dtype=D)
    F, R = (F.expand(*lead, 2, 2), R) if which == "motion.F" else (F, R.expand(*lead, 1, 1))
    kf, _ = _kf_with_input(F=F, R=R)
    prior = GaussianBelief(torch.zeros(B, 2, dtype=D), torch.eye(2, dtype=D))
    for fast_path in (None, False):
        with pytest.raises(ValueError, match=rf"^{which}: parameter batch"):
            run_filter(kf, prior, torch.zeros(T, B, 1, dtype=D), fast_path=fast_path)


def test_per_run_parameters_keep_working():
    """``F (B, n, n)`` and ``R (B, 1, 1)``, one per run: run ``r`` is the reference with its own matrices."""
    g = torch.Generator().manual_seed(3)
    F = torch.eye(2, dtype=D) + 0.1 * torch.randn(B, 2, 2, dtype=D, generator=g)
    R = torch.linspace(0.5, 2.0, B, dtype=D).reshape(B, 1, 1)
    kf, _ = _kf_with_input(F=F, R=R)
    x0 = torch.randn(B, 2, dtype=D, generator=g)
    z = torch.randn(T, B, 1, dtype=D, generator=g)
    for fast_path in (None, False):
        traj = run_filter(kf, GaussianBelief(x0, torch.eye(2, dtype=D)), z, fast_path=fast_path)
        for r in range(B):
            lls, _ = _reference_kf(F[r].numpy(), np.zeros((T, 2)), kf.motion.Q.numpy(),
                                   kf.measurement.H.numpy(), R[r].numpy(), x0[r].numpy(), np.eye(2),
                                   z[:, r].numpy())
            np.testing.assert_allclose(traj.log_likelihood[:, r].numpy(), lls, rtol=1e-10)


@pytest.mark.parametrize("cls", [IMM, GPB1, GPB2], ids=lambda c: c.__name__)
@pytest.mark.parametrize("method", ["kim", "two_filter", "two_filter_info"])
def test_every_smoother_of_a_per_run_transition_equals_each_run_alone(cls, method):
    """The two-filter smoother's prior mode probabilities multiplied ``(*B, M) @ (*B, M, M)`` (a
    ``(B, B, M)`` product, then a RuntimeError in ``stack``); every smoother now gives run ``r`` the numbers
    of run ``r`` smoothed alone with its own matrix (the two-filter smoother's flat start amplifies rounding
    about 1e7-fold, docs/smoothing.md: to 1e-8 there)."""
    kf, prior, z = _mode_run()
    Pb = _transitions()
    f = cls(kf, Pb)
    both = smooth(f, run_filter(f, f.initial_belief(prior), z), z, method=method)
    tol = 1e-8 if method == "two_filter" else 1e-12
    for r in range(B):
        alone = cls(kf, Pb[r])
        b0 = alone.initial_belief(GaussianBelief(prior.mean[r], prior.cov))
        one = smooth(alone, run_filter(alone, b0, z[:, r]), z[:, r], method=method)
        torch.testing.assert_close(both.belief.components.mean[:, r], one.belief.components.mean,
                                   rtol=tol, atol=tol)
        torch.testing.assert_close(both.belief.mode_log_probs[:, r].exp(), one.belief.mode_log_probs.exp(),
                                   rtol=tol, atol=tol)


def test_an_objective_names_a_batch_that_does_not_fit_when_it_is_built():
    """``Objective`` checks once, at construction, what ``run_filter``'s entry checks (its calls skip them)."""
    from torchmm.learn import Objective

    kf, _ = _kf_with_input()
    prior, z = GaussianBelief(torch.zeros(B, 2, dtype=D), torch.eye(2, dtype=D)), torch.zeros(T, B, 1, dtype=D)
    with pytest.raises(ValueError, match=r"^controls: batch shape \(2, 4\)"):
        Objective(kf, prior, z, controls=torch.ones(T, 2, B, 1, dtype=D))
    with pytest.raises(ValueError, match=r"^controls: 2 inputs a step"):
        Objective(kf, prior, z, controls=torch.ones(T, B, 2, dtype=D))
    with pytest.raises(ValueError, match=r"^motion\.F: parameter batch \(2, 1\) would enlarge"):
        Objective(_kf_with_input(F=torch.eye(2, dtype=D).expand(2, 1, 2, 2))[0], prior, z)

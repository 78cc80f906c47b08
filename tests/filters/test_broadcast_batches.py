"""Batch shapes that broadcast (docs/architecture.md: a start covariance or measurements shared by the runs,
model parameters with unit batch axes): the eager steps (torchmm/linalg.py ``condition``) and the Numba
kernel (torchmm/kernels/linear.py) return the same shapes and numbers, checked against a hand-written
float64 NumPy Kalman filter (tests/reference/mm_numpy.py) run by run."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.reference.mm_numpy import kf_step
from torchmm import IMM, GaussianBelief, KalmanFilter, kernels, run_filter
from torchmm.kernels import linear
from torchmm.models import LinearMeasurement, LinearMotion
from torchmm.smooth import smooth

D = torch.float64


@pytest.fixture(autouse=True)
def _short_runs_take_the_kernel(monkeypatch):
    monkeypatch.setattr(linear, "LONG_RUN", 0)  # (as tests/kernels/test_linear_kernel.py)


def _reference(F, Q, H, R, x0, P0, zs):
    """Per-step log-likelihoods and posterior means of one run (NaN rows: a missing step, predict only)."""
    x, P, lls, means = x0.copy(), P0.copy(), [], []
    for z in zs:
        if np.isnan(z).all():
            x, P, ll = F @ x, F @ P @ F.T + Q, 0.0
        else:
            x, P, lik = kf_step(x, P, F, np.zeros(len(x)), Q, H, R, z)
            ll = math.log(lik)
        lls.append(ll)
        means.append(x)
    return np.array(lls), np.array(means)


def _both(f, b0, z):
    """The kernel's and the eager steps' trajectories (the kernel's checked to have run)."""
    fast = run_filter(f, b0, z)
    assert fast.provenance.kernel == "linear_gaussian"
    with kernels.switched_off(*kernels.names()):
        slow = run_filter(f, b0, z, fast_path=False)
    return fast, slow


@pytest.mark.parametrize("z_shape", [(5, 1, 2), (5, 2)])
def test_shared_covariance_and_shared_measurements(z_shape):
    g = torch.Generator().manual_seed(1)
    F, Q = torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=D), 0.1 * torch.eye(2, dtype=D)
    H, R = torch.tensor([[1.0, 0.0], [0.3, 1.0]], dtype=D), torch.eye(2, dtype=D)
    kf = KalmanFilter(LinearMotion(F, Q), LinearMeasurement(H, R))
    x0, P0 = torch.randn(3, 2, dtype=D, generator=g), torch.eye(2, dtype=D)  # P0 shared by the 3 runs
    z = torch.randn(*z_shape, dtype=D, generator=g)  # one series seen by every run
    with kernels.switched_off(*kernels.names()):
        slow = run_filter(kf, GaussianBelief(x0, P0), z, fast_path=False)
    assert slow.log_likelihood.shape == (5, 3)
    zs = z.reshape(5, 2).numpy()
    for r in range(3):
        lls, means = _reference(F.numpy(), Q.numpy(), H.numpy(), R.numpy(), x0[r].numpy(), P0.numpy(), zs)
        np.testing.assert_allclose(slow.log_likelihood[:, r].numpy(), lls, rtol=1e-10)
        np.testing.assert_allclose(slow.belief.mean[:, r].numpy(), means, rtol=1e-10, atol=1e-12)
    if len(z_shape) == 3:  # (the kernel takes (T, 1, m); (T, m) it leaves to the eager steps)
        fast = run_filter(kf, GaussianBelief(x0, P0), z)
        assert fast.provenance.kernel == "linear_gaussian"
        torch.testing.assert_close(fast.log_likelihood, slow.log_likelihood, rtol=1e-12, atol=1e-12)


def test_imm_with_measurements_shared_by_the_runs():
    g = torch.Generator().manual_seed(2)
    F = torch.eye(2, dtype=D).expand(2, 2, 2).clone()
    kf = KalmanFilter(LinearMotion(F, torch.stack([0.1 * torch.eye(2, dtype=D), torch.eye(2, dtype=D)])),
                      LinearMeasurement(torch.eye(2, dtype=D), torch.eye(2, dtype=D)))
    imm = IMM(kf, torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=D))
    b0 = imm.initial_belief(GaussianBelief(torch.randn(3, 2, dtype=D, generator=g), torch.eye(2, dtype=D)),
                            torch.tensor([0.5, 0.5], dtype=D))
    z = torch.randn(4, 1, 2, dtype=D, generator=g)
    z[1, 0, 0] = float("nan")
    fast, slow = _both(imm, b0, z)
    assert slow.log_likelihood.shape == (4, 3)
    torch.testing.assert_close(fast.log_likelihood, slow.log_likelihood, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("which", ["Q", "R"])
def test_parameters_with_a_unit_batch_axis_and_one_run(which):
    """A Kalman filter whose ``Q`` or ``R`` is ``(1, d, d)`` and a start belief of batch ``()``: the run's
    batch is ``(1,)`` (broadcast, as the eager steps give it), on both paths, with a missing step."""
    F, Q = torch.eye(2, dtype=D), 0.1 * torch.eye(2, dtype=D)
    H, R = torch.ones(1, 2, dtype=D), torch.eye(1, dtype=D)
    Qm, Rm = (Q.unsqueeze(0), R) if which == "Q" else (Q, R.unsqueeze(0))
    kf = KalmanFilter(LinearMotion(F, Qm), LinearMeasurement(H, Rm))
    b0 = GaussianBelief(torch.zeros(2, dtype=D), torch.eye(2, dtype=D))
    z = torch.randn(4, 1, dtype=D, generator=torch.Generator().manual_seed(0))
    z[2] = float("nan")
    fast, slow = _both(kf, b0, z)
    for traj in (fast, slow):
        assert traj.belief.mean.shape == (4, 1, 2) and traj.log_likelihood.shape == (4, 1)
        assert traj.innovation.shape == (4, 1, 1)
    lls, means = _reference(F.numpy(), Q.numpy(), H.numpy(), R.numpy(), np.zeros(2), np.eye(2), z.numpy())
    for traj in (fast, slow):
        np.testing.assert_allclose(traj.log_likelihood[:, 0].numpy(), lls, rtol=1e-10)
        np.testing.assert_allclose(traj.belief.mean[:, 0].numpy(), means, rtol=1e-10, atol=1e-12)
    smoothed = smooth(kf, fast)
    with kernels.switched_off(*kernels.names()):
        eager_smoothed = smooth(kf, slow)
    torch.testing.assert_close(smoothed.belief.mean, eager_smoothed.belief.mean, rtol=1e-10, atol=1e-12)

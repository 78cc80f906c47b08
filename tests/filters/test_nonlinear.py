"""EKF / UKF: equal to the KF on linear models; Jacobians; sigma-point exactness; smoother oracle."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from tests.conftest import random_psd, random_system
from torchmm import (
    CubatureSigmaPoints,
    ExtendedKalmanFilter,
    GaussianBelief,
    JulierSigmaPoints,
    KalmanFilter,
    MerweScaledSigmaPoints,
    MotionModel,
    NonlinearCoordinatedTurn,
    RangeBearing,
    UnscentedKalmanFilter,
    rts_smoother,
    run_filter,
)
from torchmm.beliefs import psd_sqrt
from torchmm.models import CoordinatedTurn, forward_jacobian

close = partial(torch.testing.assert_close, rtol=1e-9, atol=1e-9)

STRATEGIES = {
    "merwe": MerweScaledSigmaPoints(alpha=1.0, beta=2.0, kappa=0.0),
    "merwe-small-alpha": MerweScaledSigmaPoints(alpha=0.5, beta=2.0, kappa=1.0),
    "julier": JulierSigmaPoints(kappa=1.0),
    "cubature": CubatureSigmaPoints(),
}


class GenericLinear(MotionModel):
    """A linear map written as a plain nn.Module (no matrix attribute): forces the autograd path."""

    def __init__(self, F, Q, offset):
        super().__init__()
        self.lin = nn.Linear(F.shape[1], F.shape[0])
        with torch.no_grad():
            self.lin.weight.copy_(F)
            self.lin.bias.copy_(offset)
        self.register_buffer("Q", Q)
        self.state_dim = F.shape[0]

    def forward(self, x, *, u=None):
        return self.lin(x)

    def noise_cov(self, x=None):
        return self.Q


def _filters(system):
    motion, measurement = system.motion(), system.measurement()
    generic = GenericLinear(torch.tensor(system.F), torch.tensor(system.Q), torch.tensor(system.offset))
    out = {"ekf": ExtendedKalmanFilter(motion, measurement), "ekf-autograd": ExtendedKalmanFilter(generic, measurement)}
    for name, strategy in STRATEGIES.items():
        out[f"ukf-{name}"] = UnscentedKalmanFilter(motion, measurement, strategy)
    return out


@pytest.mark.parametrize("name", ["ekf", "ekf-autograd"] + [f"ukf-{s}" for s in STRATEGIES])
@pytest.mark.parametrize("n,m", [(2, 1), (3, 2), (4, 3)], ids=str)
def test_nonlinear_filters_equal_kf_on_linear_models(name, n, m):
    rng = np.random.default_rng(n * 7 + m)
    system = random_system(n, m, rng)
    _, zs = system.simulate(20, rng)
    zs = torch.tensor(zs).unsqueeze(1).expand(20, 3, m)  # a batch of 3 identical runs
    prior = system.prior().expand(3)
    ref = run_filter(KalmanFilter(system.motion(), system.measurement()), prior, zs)
    traj = run_filter(_filters(system)[name], prior, zs)
    close(traj.belief.mean, ref.belief.mean)
    close(traj.belief.cov, ref.belief.cov)
    close(traj.log_likelihood, ref.log_likelihood)


def test_forward_jacobian_matches_autograd_functional():
    model = NonlinearCoordinatedTurn(dt=1.0, q=1.0)
    x = torch.tensor([[10.0, 3.0, -4.0, 1.0, 0.05], [0.0, -2.0, 5.0, 2.0, -0.2], [1.0, 1.0, 1.0, 1.0, 0.0]])
    jac = model.jacobian(x)
    for r in range(3):
        ref = torch.autograd.functional.jacobian(lambda v: model(v), x[r])
        close(jac[r], ref)
    sensor = RangeBearing(5, torch.diag(torch.tensor([1.0, 1e-4])))
    jac = sensor.jacobian(x)
    for r in range(3):
        close(jac[r], torch.autograd.functional.jacobian(lambda v: sensor(v), x[r]))


def test_forward_jacobian_is_differentiable():
    w = torch.randn(3, 3, requires_grad=True)
    x = torch.randn(4, 3)
    jac = forward_jacobian(lambda s: torch.tanh(s @ w.mT), x)
    (grad,) = torch.autograd.grad(jac.sum(), w)
    assert grad.abs().sum() > 0 and bool(torch.isfinite(grad).all())


def test_coordinated_turn_limits_and_bank():
    turn = CoordinatedTurn(torch.tensor([0.0, 0.1, -0.1]), dt=2.0)
    cv = turn.F[0]
    expected_cv = torch.tensor([[1.0, 2.0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2.0], [0, 0, 0, 1]])
    close(cv, expected_cv)
    # a turn preserves speed
    x = torch.tensor([0.0, 3.0, 0.0, 4.0])
    speeds = (turn(x.expand(3, 4))[:, [1, 3]]).norm(dim=-1)
    close(speeds, torch.full((3,), 5.0))
    # the nonlinear CT with omega in the state agrees with the known-rate matrix
    nl = NonlinearCoordinatedTurn(dt=2.0)
    state = torch.tensor([1.0, 3.0, 2.0, 4.0, 0.1])
    close(nl(state)[:4], turn.F[1] @ state[:4])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 5), strategy=st.sampled_from(sorted(STRATEGIES)))
def test_sigma_points_are_exact_for_linear_maps(seed, n, strategy):
    rng = np.random.default_rng(seed)
    mean = torch.tensor(rng.normal(size=n))
    cov = torch.tensor(random_psd(n, rng))
    A = torch.tensor(rng.normal(size=(3, n)))
    sp = STRATEGIES[strategy]
    wm, wc = sp.weights(n, mean.dtype, mean.device)
    pts = sp.points(mean, cov)
    y = pts @ A.T
    y_mean = (wm[:, None] * y).sum(0)
    y_cov = torch.einsum("s,si,sj->ij", wc, y - y_mean, y - y_mean)
    close(wm.sum(), torch.tensor(1.0))
    close(y_mean, A @ mean)
    close(y_cov, A @ cov @ A.T)


def _exact_smoothing_posterior(system, zs):
    """Posterior of x_1..x_T given z_1..z_T by conditioning the stacked joint Gaussian."""
    n, steps = system.F.shape[0], len(zs)
    mean_x, cov_x = system.joint_state_moments(steps)
    H = np.kron(np.eye(steps), system.H)
    S = H @ cov_x @ H.T + np.kron(np.eye(steps), system.R)
    gain = cov_x @ H.T @ np.linalg.inv(S)
    post_mean = mean_x + gain @ (zs.ravel() - H @ mean_x)
    post_cov = cov_x - gain @ S @ gain.T
    blocks = [post_cov[k * n : (k + 1) * n, k * n : (k + 1) * n] for k in range(steps)]
    return post_mean.reshape(steps, n), np.array(blocks)


@pytest.mark.parametrize("n,m", [(2, 1), (3, 2)], ids=str)
def test_rts_smoother_equals_exact_joint_posterior(n, m):
    rng = np.random.default_rng(21 + n)
    system = random_system(n, m, rng)
    _, zs = system.simulate(8, rng)
    kf = KalmanFilter(system.motion(), system.measurement())
    traj = run_filter(kf, system.prior(), torch.tensor(zs))
    smoothed = rts_smoother(kf.motion, traj.belief, traj.prior)
    mean, cov = _exact_smoothing_posterior(system, zs)
    torch.testing.assert_close(smoothed.mean, torch.tensor(mean), rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(smoothed.cov, torch.tensor(cov), rtol=1e-8, atol=1e-8)
    # smoothing never increases the variance
    assert bool((smoothed.cov.diagonal(dim1=-2, dim2=-1) <= traj.belief.cov.diagonal(dim1=-2, dim2=-1) + 1e-12).all())


def test_rts_smoother_batched():
    rng = np.random.default_rng(8)
    system = random_system(2, 1, rng)
    kf = KalmanFilter(system.motion(), system.measurement())
    zs = torch.randn(10, 4, 1)
    traj = run_filter(kf, system.prior().expand(4), zs)
    smoothed = rts_smoother(kf.motion, traj.belief, traj.prior)
    assert smoothed.mean.shape == (10, 4, 2)
    single = run_filter(kf, system.prior(), zs[:, 2])
    close(smoothed.mean[:, 2], rts_smoother(kf.motion, single.belief, single.prior).mean)


def test_ekf_ukf_track_a_turning_target():
    """Mildly nonlinear tracking: both filters stay consistent and close to each other."""
    g = torch.Generator().manual_seed(0)
    motion = NonlinearCoordinatedTurn(dt=1.0, q=0.01, q_omega=1e-6)
    sensor = RangeBearing(5, torch.diag(torch.tensor([4.0, 1e-6])), origin=(-500.0, -500.0))
    x = torch.tensor([0.0, 10.0, 0.0, 5.0, 0.02]).expand(200, 5)
    truth, zs = [], []
    for _ in range(40):
        x = motion(x) + torch.randn(200, 5, generator=g) @ psd_sqrt(motion.Q).T
        truth.append(x)
        zs.append(sensor(x) + torch.randn(200, 2, generator=g) @ torch.linalg.cholesky(sensor.R).T)
    truth, zs = torch.stack(truth), torch.stack(zs)
    prior = GaussianBelief(torch.tensor([0.0, 10.0, 0.0, 5.0, 0.02]).expand(200, 5),
                           torch.diag(torch.tensor([1.0, 1.0, 1.0, 1.0, 1e-4])))
    ekf = run_filter(ExtendedKalmanFilter(motion, sensor), prior, zs)
    ukf = run_filter(UnscentedKalmanFilter(motion, sensor), prior, zs)
    for traj in (ekf, ukf):
        err = traj.belief.mean - truth
        nees = torch.einsum("...i,...ij,...j->...", err, torch.linalg.inv(traj.belief.cov), err)
        assert 2.5 < nees[-10:].mean().item() < 10.0  # chi2(5) mean is 5
    pos_gap = (ekf.belief.mean[..., [0, 2]] - ukf.belief.mean[..., [0, 2]]).norm(dim=-1).mean()
    assert pos_gap.item() < 1.0


def test_range_bearing_closed_form_jacobian_equals_autograd_and_is_differentiable():
    """``RangeBearing.jacobian`` is written out (issue 31); equal to forward-mode autograd of ``h`` on a
    batch, for any position components and origin, and differentiable in the state and the origin."""
    from torchmm import RangeBearing
    from torchmm.models.base import forward_jacobian

    gen = torch.Generator().manual_seed(3)
    for indices in ((0, 2), (3, 1)):
        origin = torch.tensor([-30.0, 12.0], dtype=torch.float64, requires_grad=True)
        sensor = RangeBearing(5, torch.eye(2, dtype=torch.float64), position_indices=indices, origin=origin)
        x = 50 * torch.randn(4, 3, 5, generator=gen, dtype=torch.float64)
        H = sensor.jacobian(x)
        assert H.shape == (4, 3, 2, 5)
        torch.testing.assert_close(H, forward_jacobian(sensor, x), rtol=1e-14, atol=1e-16)
        others = [k for k in range(5) if k not in indices]
        assert (H[..., others] == 0).all()
        x0 = x[0, 0].clone().requires_grad_(True)
        assert torch.autograd.gradcheck(lambda s, o: RangeBearing(5, torch.eye(2, dtype=torch.float64),
                                                                  position_indices=indices, origin=o).jacobian(s),
                                        (x0, origin), eps=1e-6, atol=1e-8)

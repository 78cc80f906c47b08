"""Faults from docs/specification.md §6: missing data, near-singular covariances, float32, all filter kinds."""

from __future__ import annotations

import logging
from functools import partial

import numpy as np
import pytest
import torch

from tests.conftest import BATCH_SHAPES, random_system
from torchmm import (
    IMM,
    ConstantVelocity,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    LinearMotion,
    PositionMeasurement,
    UnscentedKalmanFilter,
    run_filter,
)

close = partial(torch.testing.assert_close, rtol=1e-9, atol=1e-9)
KINDS = {"kf": KalmanFilter, "ekf": ExtendedKalmanFilter, "ukf": UnscentedKalmanFilter}


@pytest.mark.parametrize("kind", KINDS)
def test_missing_measurements_are_skipped_by_every_filter(kind):
    rng = np.random.default_rng(1)
    system = random_system(3, 2, rng)
    filt = KINDS[kind](system.motion(), system.measurement())
    prior = filt.predict(system.prior().expand(3))
    z = torch.tensor([[0.5, -0.2], [float("nan"), float("nan")], [0.3, float("nan")]])
    out = filt.update(prior, z)
    close(out.belief.mean[1], prior.mean[1])
    close(out.belief.cov[1], prior.cov[1])
    assert out.log_likelihood[1].item() == 0.0
    reduced = KINDS[kind](system.motion(), LinearMeasurement(torch.tensor(system.H[:1]),
                                                             torch.tensor(system.R[:1, :1])))
    ref = reduced.update(prior[2], z[2, :1])
    close(out.belief.mean[2], ref.belief.mean)
    close(out.log_likelihood[2], ref.log_likelihood)
    assert bool(torch.isfinite(out.belief.mean).all() and torch.isfinite(out.belief.cov).all())


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
@pytest.mark.parametrize("batch_shape", BATCH_SHAPES, ids=str)
def test_nonlinear_filter_shapes(kind, batch_shape):
    rng = np.random.default_rng(0)
    system = random_system(3, 2, rng)
    filt = KINDS[kind](system.motion(), system.measurement())
    prior = GaussianBelief(torch.zeros(*batch_shape, 3), torch.eye(3))
    traj = run_filter(filt, prior, torch.randn(4, *batch_shape, 2))
    assert traj.belief.mean.shape == (4, *batch_shape, 3)
    assert traj.belief.cov.shape == (4, *batch_shape, 3, 3)
    assert traj.log_likelihood.shape == (4, *batch_shape)
    assert traj.innovation_cov.shape == (4, *batch_shape, 2, 2)


@pytest.mark.parametrize("m", [1, 2])
def test_singular_innovation_covariance_stays_finite_closed_form(m):
    """R = 0 and a prior with zero variance in the measured direction: S = 0."""
    H = torch.eye(m, 3)
    kf = KalmanFilter(LinearMotion(torch.eye(3), torch.zeros(3, 3)), LinearMeasurement(H, torch.zeros(m, m)))
    prior = GaussianBelief(torch.zeros(3), torch.diag(torch.tensor([0.0, 0.0, 1.0])))
    out = kf.update(prior, torch.ones(m))
    assert bool(torch.isfinite(out.belief.mean).all() and torch.isfinite(out.belief.cov).all())
    assert bool(torch.isfinite(out.log_likelihood))


def test_singular_innovation_covariance_is_regularised_flagged_and_reported(caplog):
    """m > 2 goes through cholesky_ex: a failed factorisation is repaired (jitter, then the diagonal),
    the run is flagged in extras['singular'] and run_filter reports the count once."""
    H = torch.eye(3, 4)
    kf = KalmanFilter(LinearMotion(torch.eye(4), torch.zeros(4, 4)), LinearMeasurement(H, torch.zeros(3, 3)))
    prior = GaussianBelief(torch.zeros(2, 4), torch.diag(torch.tensor([1.0, 0.0, 1.0, 1.0])).expand(2, 4, 4))
    out = kf.update(prior, torch.ones(2, 3))
    assert out.extras["singular"].tolist() == [True, True]
    assert bool(torch.isfinite(out.belief.mean).all() and torch.isfinite(out.belief.cov).all())
    healthy = kf.update(GaussianBelief(torch.zeros(2, 4), torch.eye(4).expand(2, 4, 4)), torch.ones(2, 3))
    assert healthy.extras["singular"].tolist() == [False, False]
    with caplog.at_level(logging.WARNING, logger="torchmm"):
        run_filter(kf, prior, torch.ones(3, 2, 3))
    assert "not numerically positive definite" in caplog.text


def test_imm_float32_stays_finite_over_a_long_run():
    torch.set_default_dtype(torch.float32)
    g = torch.Generator().manual_seed(0)
    motion = ConstantVelocity(1, q=0.1, acceleration=[[2.0], [0.0], [-2.0]], dtype=torch.float32)
    sensor = PositionMeasurement(2, [0], torch.tensor(100.0), dtype=torch.float32)
    transition = torch.tensor([[0.95, 0.025, 0.025], [0.025, 0.95, 0.025], [0.025, 0.025, 0.95]])
    from torchmm.simulate import simulate_jump_system, simulate_measurements

    x0 = GaussianBelief(torch.zeros(2), torch.eye(2) * 10.0)
    sim = simulate_jump_system(motion, transition, x0, 1000, (50,), generator=g)
    z = simulate_measurements(sensor, sim.states, generator=g)
    assert z.dtype == torch.float32
    imm = IMM(KalmanFilter(motion, sensor), transition)
    traj = run_filter(imm, imm.initial_belief(x0.expand(50)), z)
    assert traj.belief.mode_log_probs.dtype == torch.float32
    for t in (traj.belief.mode_log_probs, traj.estimate().mean, traj.estimate().cov, traj.log_likelihood):
        assert bool(torch.isfinite(t).all())
    err = (traj.estimate().mean - sim.states)[..., 0].abs()
    assert err.mean().item() < 20.0  # tracks: sensor noise sigma is 10

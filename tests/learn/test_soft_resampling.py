"""Soft resampling: proper weighting (unbiased), alpha limits, finite gradients, bad input."""

from __future__ import annotations

import math

import pytest
import torch

from torchmm import ParticleBelief
from torchmm.beliefs.ops import normalize_log_probs
from torchmm.learn import soft_resample, soft_resample_where_needed


def _belief(generator, batch=(3,), num=50, n=2):
    particles = torch.randn(*batch, num, n, generator=generator)
    log_w = 2.0 * torch.randn(*batch, num, generator=generator)
    return ParticleBelief(particles, log_w)


@pytest.mark.parametrize("alpha", [0.0, 0.3, 0.7])
@pytest.mark.parametrize("scheme", ["systematic", "multinomial"])
def test_soft_resampling_is_properly_weighted(alpha, scheme, generator):
    """E[sum_j w~_j g(x_j)] = sum_i w_i g(x_i): check the mean over many independent draws."""
    base = _belief(generator, batch=(), num=20)
    reps = 4000
    many = ParticleBelief(base.particles.expand(reps, 20, 2), base.log_weights.expand(reps, 20))
    out = soft_resample(many, alpha, scheme, generator=generator)
    w = normalize_log_probs(base.log_weights).exp()
    g = base.particles[..., 0] ** 2 + base.particles[..., 1]  # a test function of the state
    exact = (w * g).sum()
    estimates = (out.log_weights.exp() * (out.particles[..., 0] ** 2 + out.particles[..., 1])).sum(-1)
    # self-normalised weights: unbiased up to O(1/N); within 6 standard errors plus an O(1/N) allowance
    se = estimates.std() / math.sqrt(reps)
    assert abs(estimates.mean() - exact) < 6 * se + 0.05 * exact.abs(), (estimates.mean(), exact)
    torch.testing.assert_close(out.log_weights.logsumexp(-1), torch.zeros(reps))


def test_alpha_one_is_ordinary_resampling_and_alpha_zero_keeps_weights_uniform_ancestors(generator):
    b = _belief(generator)
    hard = soft_resample(b, 1.0, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(hard.log_weights, torch.full_like(hard.log_weights, -math.log(50)))
    soft0 = soft_resample(b, 0.0, "systematic", generator=torch.Generator().manual_seed(0))
    # uniform systematic draws with N = Np pick every particle once: the belief is unchanged
    torch.testing.assert_close(soft0.particles, b.particles)
    torch.testing.assert_close(soft0.log_weights, normalize_log_probs(b.log_weights))


def test_gradients_flow_through_soft_but_not_hard_resampling(generator):
    b = _belief(generator)
    log_w = b.log_weights.clone().requires_grad_()
    particles = b.particles.clone().requires_grad_()
    out = soft_resample(ParticleBelief(particles, log_w), 0.5, generator=generator)
    loss = out.estimate().mean.square().sum()
    loss.backward()
    assert log_w.grad is not None and bool(torch.isfinite(log_w.grad).all()) and log_w.grad.abs().sum() > 0
    assert bool(torch.isfinite(particles.grad).all())
    # alpha = 1: weights reset to 1/N, so the estimate carries no gradient to the old weights
    hard = soft_resample(ParticleBelief(particles, log_w), 1.0, generator=generator)
    (grad,) = torch.autograd.grad(hard.estimate().mean.sum(), log_w, allow_unused=True)
    assert grad is None or bool((grad == 0).all())


def test_where_needed_only_touches_degenerate_elements(generator):
    b = _belief(generator, batch=(4,))
    log_w = b.log_weights.clone()
    log_w[0] = 0.0  # uniform: ESS = Np, never resampled
    b = ParticleBelief(b.particles, log_w)
    out, mask, ess = soft_resample_where_needed(b, 0.9, 0.5, generator=generator)
    assert not mask[0] and bool(mask[1:].all())
    torch.testing.assert_close(out.particles[0], b.particles[0])
    torch.testing.assert_close(ess[0], torch.tensor(50.0))


def test_bad_arguments(generator):
    b = _belief(generator)
    with pytest.raises(ValueError, match="alpha"):
        soft_resample(b, 1.5)
    with pytest.raises(ValueError, match="scheme"):
        soft_resample(b, 0.5, "roulette")
    with pytest.raises(ValueError, match="threshold"):
        soft_resample_where_needed(b, -1.0)


def test_soft_resampling_particle_filter_tracks_the_kalman_filter_and_is_trainable():
    from torchmm import GaussianBelief, KalmanFilter, LinearMotion, PositionMeasurement, run_filter
    from torchmm.learn import SoftResamplingParticleFilter
    from torchmm.models import learnable_noise

    g = torch.Generator().manual_seed(7)
    prior = GaussianBelief(torch.zeros(6, 2), torch.eye(2))
    z = torch.randn(15, 6, 1, generator=g).cumsum(0)
    # full-rank process noise: the particle filter factorises a singular Q by an eigendecomposition
    # whose square root has an infinite derivative at the zero eigenvalue (NaN gradients)
    F, Q = torch.tensor([[1.0, 1.0], [0.0, 1.0]]), torch.tensor([[0.2, 0.1], [0.1, 0.5]])
    kf = KalmanFilter(LinearMotion(F, Q), PositionMeasurement(2, [0], 1.0))
    motion = learnable_noise(LinearMotion(F, Q), "Q", "cholesky")
    pf = SoftResamplingParticleFilter(motion, PositionMeasurement(2, [0], 1.0), alpha=0.5,
                                      ess_threshold=0.5, generator=g)
    exact = run_filter(kf, prior, z)
    traj = run_filter(pf, pf.initial_belief(prior, 4000), z)
    assert bool(traj.extras["resampled"].any())  # the soft step really ran
    # the particle estimate of the posterior mean and of log p(z_1:T) match the exact KF
    torch.testing.assert_close(traj.estimate().mean, exact.estimate().mean, atol=0.15, rtol=0)
    torch.testing.assert_close(traj.total_log_likelihood(), exact.total_log_likelihood(), atol=0.3, rtol=0)
    # gradients of the particle log-likelihood flow through the soft resampling steps
    (-traj.total_log_likelihood().sum()).backward()
    grad = motion.parametrizations.Q.original.grad
    assert grad is not None and bool(torch.isfinite(grad).all()) and grad.abs().sum() > 0


def test_soft_resampling_particle_filter_takes_the_call_generator_and_sensors():
    """run_filter / step with generator= and sensors= (the parent's interface): reproducible, the
    call's stream equals the constructor's when seeded alike, the global stream is not used, and a
    per-step sensor equals a filter built with that sensor."""
    from torchmm import GaussianBelief, run_filter
    from torchmm.learn import SoftResamplingParticleFilter
    from torchmm.models import ConstantVelocity, PositionMeasurement

    z = 3.0 * torch.randn(12, 4, 1, generator=torch.Generator().manual_seed(0))
    prior = GaussianBelief(torch.zeros(4, 2), torch.eye(2).expand(4, 2, 2))

    def run(sensor_r=1.0, generator=None, ctor_generator=None, sensors=None):
        pf = SoftResamplingParticleFilter(ConstantVelocity(1), PositionMeasurement(2, [0], sensor_r),
                                          alpha=0.5, ess_threshold=0.9, generator=ctor_generator)
        b0 = pf.initial_belief(prior, 100, generator=generator)
        return run_filter(pf, b0, z, sensors=sensors, generator=generator)

    torch.manual_seed(1)
    a = run(generator=torch.Generator().manual_seed(42))
    torch.manual_seed(2)  # a different global stream: no effect
    b = run(generator=torch.Generator().manual_seed(42))
    assert bool(a.extras["resampled"].any())  # the soft step ran (and drew ancestors)
    torch.testing.assert_close(a.log_likelihood, b.log_likelihood, rtol=0, atol=0)
    torch.testing.assert_close(a.belief.particles, b.belief.particles, rtol=0, atol=0)
    c = run(ctor_generator=torch.Generator().manual_seed(42))
    torch.testing.assert_close(a.log_likelihood, c.log_likelihood, rtol=0, atol=0)
    d = run(generator=torch.Generator().manual_seed(43))
    assert not torch.equal(a.log_likelihood, d.log_likelihood)
    # one step with generator=
    pf = SoftResamplingParticleFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0), alpha=0.5,
                                      ess_threshold=2.0)
    b0 = pf.initial_belief(prior, 50, generator=torch.Generator().manual_seed(5))
    s1 = pf.step(b0, z[0], generator=torch.Generator().manual_seed(6))
    s2 = pf.step(b0, z[0], generator=torch.Generator().manual_seed(6))
    torch.testing.assert_close(s1.belief.particles, s2.belief.particles, rtol=0, atol=0)
    # sensors: every step's sensor R = 2 equals a filter built with R = 2
    r2 = PositionMeasurement(2, [0], 2.0)
    e = run(generator=torch.Generator().manual_seed(42), sensors=[r2] * 12)
    f = run(sensor_r=2.0, generator=torch.Generator().manual_seed(42))
    torch.testing.assert_close(e.log_likelihood, f.log_likelihood, rtol=0, atol=0)
    assert not torch.equal(e.log_likelihood, a.log_likelihood)

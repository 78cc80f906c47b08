"""Particle filters: missing data versus model failures (docs/robustness.md, "Missing data is a
non-finite *measurement*; a non-finite *prediction* is a failure").

The state-dependent-noise path (``MeasurementModel.log_likelihood``) against the shared-``R`` path and a
SciPy reference; a state-dependent ``R(x)`` that is not positive definite in one run; ``+inf`` particle
likelihoods (a user model's point mass) in the bootstrap and the multiple-model particle filters."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchmm.multimodel.particle as mmpf_module
from torchmm import run_filter
from torchmm.beliefs import ParticleBelief
from torchmm.filters.particle import ParticleFilter
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.models.linear import LinearMeasurement, LinearMotion
from torchmm.multimodel.particle import MultipleModelParticleFilter

INF, NAN = math.inf, math.nan
R2 = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=torch.float64)


class StateNoise(LinearMeasurement):
    """``R(x) = diag(x_0, 1)`` (its leading ``m x m`` block): not positive definite where ``x_0 <= 0``."""

    def noise_cov(self, x=None):
        if x is None:
            return super().noise_cov()
        m = self.meas_dim
        return torch.diag_embed(torch.stack([x[..., 0], torch.ones_like(x[..., 0])], -1)[..., :m])


class NaNSecond(LinearMeasurement):
    """``h(x) = x`` with its second component NaN where ``x_1 > 0`` (a model that fails there); ``R``
    the shared one, also as ``R(x)``."""

    def forward(self, x):
        h = super().forward(x)
        return torch.cat([h[..., :1], torch.where(x[..., 1:] > 0, NAN, h[..., 1:])], -1)

    def noise_cov(self, x=None):
        return super().noise_cov()


def _filters(measurement, **options):
    motion = LinearMotion(torch.eye(2, dtype=torch.float64), 0.3 * torch.eye(2, dtype=torch.float64))
    return [ParticleFilter(motion, measurement, ess_threshold=0.0, state_dependent_noise=sdn, **options)
            for sdn in (False, True)]


def _prior(runs: int, num: int = 60, seed: int = 0) -> ParticleBelief:
    g = torch.Generator().manual_seed(seed)
    particles = torch.randn(runs, num, 2, generator=g, dtype=torch.float64)
    return ParticleBelief(particles, torch.log_softmax(torch.randn(runs, num, generator=g, dtype=torch.float64), -1))


def _scipy_loglik(z: np.ndarray, h: np.ndarray, R: np.ndarray) -> np.ndarray:
    """log N(z_obs; h_obs, R_obs) per particle over the finite components of ``z`` (0 without any)."""
    stats = pytest.importorskip("scipy.stats")
    obs = np.isfinite(z)
    if not obs.any():
        return np.zeros(len(h))
    return stats.multivariate_normal(np.zeros(obs.sum()), R[np.ix_(obs, obs)]).logpdf(z[obs] - h[:, obs]).reshape(-1)


def test_state_dependent_noise_takes_missingness_from_the_data_as_the_shared_path():
    """``+-inf`` and NaN components of z are missing in both paths: the same log-likelihoods and weights
    as the shared-R path and as SciPy's marginal density. Before, ``z = [0.3, +inf]`` gave -inf and
    'degenerate' with ``state_dependent_noise=True`` (the residual, not z, decided missingness) and
    ``[inf, inf]`` left every weight -inf."""
    sensor = LinearMeasurement(torch.eye(2, dtype=torch.float64), R2)
    z = torch.tensor([[0.3, -0.2], [0.3, INF], [INF, INF], [NAN, 0.1], [-INF, NAN]], dtype=torch.float64)
    prior = _prior(len(z))
    shared, own = (f.update(prior, z) for f in _filters(sensor))
    for out in (shared, own):
        assert not out.extras["failed"].any() and not out.extras["degenerate"].any()
        for b in range(len(z)):
            ll = _scipy_loglik(z[b].numpy(), prior.particles[b].numpy(), R2.numpy())
            want = np.logaddexp.reduce(prior.log_weights[b].numpy() + ll)
            np.testing.assert_allclose(out.log_likelihood[b].item(), want if np.isfinite(z[b].numpy()).any() else 0.0,
                                       rtol=1e-12, atol=1e-12)
        assert torch.isfinite(out.belief.log_weights).all()
    torch.testing.assert_close(own.log_likelihood, shared.log_likelihood, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(own.belief.log_weights, shared.belief.log_weights, rtol=1e-12, atol=1e-12)
    assert (own.log_likelihood[2] == 0) and torch.equal(own.belief.log_weights[2], prior.log_weights[2])


def test_a_nan_prediction_fails_the_run_in_both_paths_unless_its_component_is_missing():
    """``h(x)`` NaN in component 1 for some particles: with that component measured, the run fails (NaN
    log-likelihood, those particles weightless) in both paths; with it missing, nothing fails and the
    weights are SciPy's marginal. Before, the state-dependent path scored the NaN component as missing
    (likelihood 1): failed False and 27 % of the weight on NaN particles."""
    sensor = NaNSecond(torch.eye(2, dtype=torch.float64), R2)
    prior = _prior(3)
    bad = prior.particles[..., 1] > 0
    z = torch.tensor([[0.3, 0.1], [0.3, NAN], [0.3, -INF]], dtype=torch.float64)
    for out in (f.update(prior, z) for f in _filters(sensor)):
        assert out.extras["failed"].tolist() == [True, False, False]
        assert math.isnan(out.log_likelihood[0]) and torch.isfinite(out.log_likelihood[1:]).all()
        assert (out.belief.log_weights[0][bad[0]] == -INF).all()
        for b in (1, 2):
            ll = _scipy_loglik(z[b].numpy(), prior.particles[b].numpy(), R2.numpy())
            want = torch.log_softmax(prior.log_weights[b] + torch.from_numpy(ll), -1)
            torch.testing.assert_close(out.belief.log_weights[b], want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("measured", [[0, 1], [0]], ids=["2d", "1d"])
def test_a_state_dependent_noise_not_positive_definite_fails_its_run_only(measured, caplog):
    """``R(x)`` not positive definite for run 0's particles: that run fails (NaN log-likelihood), the
    others are bit for bit the same runs updated alone, and ``run_filter`` goes on and counts it. Before,
    ``torch.linalg.cholesky`` raised a ``LinAlgError`` that aborted the batch."""
    H = torch.eye(2, dtype=torch.float64)[measured]
    sensor = StateNoise(H, torch.eye(len(measured), dtype=torch.float64))
    pf = _filters(sensor)[1]
    prior = _prior(3)
    particles = prior.particles.clone()
    particles[0, :, 0] = -particles[0, :, 0].abs()  # R(x) indefinite (x_0 < 0)
    particles[1:, :, 0] = particles[1:, :, 0].abs() + 5.0  # (positive also after two predictions)
    prior = ParticleBelief(particles, prior.log_weights)
    z = torch.full((3, len(measured)), 0.2, dtype=torch.float64)
    out = pf.update(prior, z)
    assert out.extras["failed"].tolist() == [True, False, False] and math.isnan(out.log_likelihood[0])
    alone = pf.update(ParticleBelief(particles[1:], prior.log_weights[1:]), z[1:])
    assert torch.equal(out.log_likelihood[1:], alone.log_likelihood)
    assert torch.equal(out.belief.log_weights[1:], alone.belief.log_weights)
    # the healthy runs against SciPy (R(x) per particle)
    stats = pytest.importorskip("scipy.stats")
    for b in (1, 2):
        m = len(measured)
        ll = [stats.multivariate_normal(particles[b, i, measured].numpy(), np.diag([particles[b, i, 0].item(), 1.0])[:m, :m]
                                        ).logpdf(z[b].numpy()) for i in range(particles.shape[1])]
        want = np.logaddexp.reduce(prior.log_weights[b].numpy() + np.array(ll))
        np.testing.assert_allclose(out.log_likelihood[b].item(), want, rtol=1e-12)
    g = torch.Generator().manual_seed(1)
    with caplog.at_level("WARNING", logger="torchmm"):
        traj = run_filter(pf, prior, z.expand(2, *z.shape), generator=g)
    assert traj.extras["failed"][:, 0].all() and not traj.extras["failed"][:, 1:].any()
    assert "2 of 6 updates failed" in caplog.text and "R(x) not positive definite" in caplog.text


class PointMass(LinearMeasurement):
    """A user likelihood: the Gaussian one plus ``bonus (Np, B)`` (``+inf``: a point mass on a particle)."""

    bonus: torch.Tensor

    def log_likelihood(self, z, x):
        return super().log_likelihood(z, x) + self.bonus


def test_a_positive_infinite_particle_likelihood_is_a_failure_not_a_degenerate_update(caplog):
    """``+inf`` for one particle of run 0: failed, NaN log-likelihood, that particle weightless, the
    other runs unchanged; never '+inf evidence, degenerate' (before: log-likelihood +inf, prior weights
    kept, ``extras['degenerate']`` True)."""
    motion = LinearMotion(torch.eye(1, dtype=torch.float64), 0.3 * torch.eye(1, dtype=torch.float64))
    sensor = PointMass(torch.eye(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64))
    pf = ParticleFilter(motion, sensor, ess_threshold=0.0, state_dependent_noise=True)
    g = torch.Generator().manual_seed(0)
    prior = ParticleBelief(torch.randn(3, 20, 1, generator=g, dtype=torch.float64),
                           torch.full((3, 20), -math.log(20), dtype=torch.float64))
    z = torch.full((3, 1), 0.4, dtype=torch.float64)
    sensor.bonus = torch.zeros(20, 3, dtype=torch.float64)
    plain = pf.update(prior, z)
    sensor.bonus = sensor.bonus.clone()
    sensor.bonus[4, 0] = INF
    out = pf.update(prior, z)
    assert out.extras["failed"].tolist() == [True, False, False] and not out.extras["degenerate"].any()
    assert math.isnan(out.log_likelihood[0]) and out.belief.log_weights[0, 4] == -INF
    want = torch.log_softmax(plain.belief.log_weights[0].index_fill(0, torch.tensor([4]), -INF), -1)
    torch.testing.assert_close(out.belief.log_weights[0], want, rtol=1e-12, atol=0)
    assert torch.equal(out.log_likelihood[1:], plain.log_likelihood[1:])
    assert torch.equal(out.belief.log_weights[1:], plain.belief.log_weights[1:])
    with caplog.at_level("WARNING", logger="torchmm"):
        run_filter(pf, prior, z[None], generator=g)
    assert "1 of 3 updates failed" in caplog.text and "+inf" in caplog.text
    assert "every weight vanish" not in caplog.text
    # reweight (ParticlePDA's entry) directly: the same rule
    loglik = torch.tensor([[0.0, -1.0, INF, -2.0], [-1.0] * 4], dtype=torch.float64)
    belief = ParticleBelief(prior.particles[:2, :4], torch.full((2, 4), -math.log(4), dtype=torch.float64))
    _, evidence, extras = pf.reweight(belief, loglik, torch.tensor([True, True]))
    assert extras["failed"].tolist() == [True, False] and math.isnan(evidence[0])
    assert not extras["degenerate"].any() and math.isfinite(evidence[1])


def test_multiple_model_pf_fails_a_run_with_a_positive_infinite_particle_likelihood(monkeypatch):
    """The multiple-model PF's weighting (the eager path: innovation statistics on) treats ``+inf`` as the
    bootstrap filter does: failed, NaN log-likelihood, not degenerate (before: +inf, degenerate)."""
    bank = ConstantVelocity(1, q=0.5, acceleration=torch.tensor([[0.5], [-0.5]], dtype=torch.float64),
                            dtype=torch.float64)
    sensor = PositionMeasurement(2, [0], torch.tensor(1.0, dtype=torch.float64), dtype=torch.float64)
    transition = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=torch.float64)
    f = MultipleModelParticleFilter(bank, sensor, transition, 16, innovation_stats=True)
    prior = f.initial_belief(_gaussian(3), generator=torch.Generator().manual_seed(2))
    z = torch.full((3, 1), 0.2, dtype=torch.float64)
    plain = f.step(prior, z, generator=torch.Generator().manual_seed(4))
    original = mmpf_module.particle_log_likelihood

    def with_point_mass(*args, **kwargs):
        loglik, predicted = original(*args, **kwargs)
        return loglik.index_put((torch.tensor(0), torch.tensor(1), torch.tensor(3)), torch.tensor(INF,
                                dtype=loglik.dtype)), predicted

    monkeypatch.setattr(mmpf_module, "particle_log_likelihood", with_point_mass)
    out = f.step(prior, z, generator=torch.Generator().manual_seed(4))
    assert out.extras["failed"].tolist() == [True, False, False] and not out.extras["degenerate"].any()
    assert math.isnan(out.log_likelihood[0])
    assert torch.equal(out.log_likelihood[1:], plain.log_likelihood[1:])


def _gaussian(runs: int):
    from torchmm import GaussianBelief
    return GaussianBelief(torch.zeros(runs, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64).expand(runs, 2, 2))

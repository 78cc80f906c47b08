"""PDA for particle filters (torchmm.association.ParticlePDA): the weights against a NumPy
computation of the per-particle scan likelihood, the Kalman PDA's posterior mean (no gate) within
Monte Carlo error, run_filter and no host read."""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.stats import multivariate_normal

from torchmm import GaussianBelief, KalmanFilter, ParticleFilter, run_filter
from torchmm.association import PDA, ParticlePDA
from torchmm.models import ConstantVelocity, PositionMeasurement

R = torch.tensor([[4.0, 0.5], [0.5, 2.0]], dtype=torch.float64)


def _models():
    return ConstantVelocity(2, dt=1.0, q=0.5, noise="continuous", dtype=torch.float64), PositionMeasurement(4, [0, 2], R)


def test_weights_are_the_per_particle_scan_likelihood():
    motion, sensor = _models()
    pf = ParticleFilter(motion, sensor, ess_threshold=0.0, generator=torch.Generator().manual_seed(1))
    ppda = ParticlePDA(pf, detection_probability=0.8, clutter_density=1e-3)
    prior = pf.initial_belief(GaussianBelief(torch.zeros(2, 4, dtype=torch.float64),
                                             4 * torch.eye(4, dtype=torch.float64)), 300)
    z = torch.tensor([[[1.0, -0.5], [3.0, 2.0], [math.nan, math.nan]],
                      [[math.nan, math.nan], [math.nan, math.nan], [math.nan, math.nan]]], dtype=torch.float64)
    out = ppda.update(prior, z)
    for b in range(2):
        x = prior.particles[b].numpy()
        w0 = np.exp(prior.log_weights[b].numpy())
        w0 /= w0.sum()
        like = np.full(300, 1 - 0.8)
        for zk in z[b].numpy():
            if np.isfinite(zk).all():
                like += 0.8 * np.array([multivariate_normal(xp[[0, 2]], R.numpy()).pdf(zk) for xp in x]) / 1e-3
        post = w0 * like
        np.testing.assert_allclose(np.exp(out.belief.log_weights[b].numpy()), post / post.sum(), rtol=1e-10, atol=1e-14)
        assert abs(float(out.log_likelihood[b]) - math.log(post.sum())) < 1e-10
    assert abs(float(out.log_likelihood[1]) - math.log(0.2)) < 1e-12  # nothing detected: 1 - P_D


def test_the_posterior_mean_is_the_kalman_pdas_within_monte_carlo_error():
    """One scan from a Gaussian prior on a linear-Gaussian model: the importance-weighted particle mean
    against the exact PDA mixture (Kalman, no gate), within 5 standard errors of the weighted mean."""
    motion, sensor = _models()
    Np = 40000
    pf = ParticleFilter(motion, sensor, ess_threshold=0.0, generator=torch.Generator().manual_seed(2))
    prior = GaussianBelief(torch.tensor([0.0, 1.0, 0.0, -1.0], dtype=torch.float64), 6 * torch.eye(4, dtype=torch.float64))
    z = torch.tensor([[0.5, 0.3], [2.0, -3.0], [8.0, 8.0]], dtype=torch.float64)
    options = {"detection_probability": 0.9, "clutter_density": 2e-3}
    out = ParticlePDA(pf, **options).update(pf.initial_belief(prior, Np), z)
    want = PDA(KalmanFilter(motion, sensor), gate_probability=1.0, **options).update(prior, z)
    w = out.belief.log_weights.softmax(-1)
    mean = (w.unsqueeze(-1) * out.belief.particles).sum(0)
    var = (w.unsqueeze(-1) * (out.belief.particles - mean) ** 2).sum(0)
    se = (var * (w ** 2).sum()).sqrt()  # the weighted mean's standard error (effective sample size)
    assert ((mean - want.belief.mean).abs() < 5 * se).all(), (mean, want.belief.mean, se)
    assert float((out.log_likelihood - want.log_likelihood).abs()) < 0.05


def test_through_run_filter_and_without_host_reads():
    from torchmm.runtime import no_host_sync

    motion, sensor = _models()
    pf = ParticleFilter(motion, sensor, generator=torch.Generator().manual_seed(3))
    ppda = ParticlePDA(pf, detection_probability=0.9, clutter_density=1e-3)
    belief = pf.initial_belief(GaussianBelief(torch.zeros(3, 4, dtype=torch.float64), 4 * torch.eye(4, dtype=torch.float64)),
                               200)
    z = torch.randn(6, 3, 4, 2, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 2
    z[2, 1] = math.nan  # an empty scan
    out = run_filter(ppda, belief, z)
    assert out.belief.particles.shape == (6, 3, 200, 4) and torch.isfinite(out.log_likelihood).all()
    assert abs(float(out.log_likelihood[2, 1]) - math.log(0.1)) < 1e-12  # nothing detected: 1 - P_D
    b = pf.predict(belief)
    with no_host_sync("the particle PDA update"):
        ppda.update(b, z[0])


def test_an_imm_of_particle_pdas_is_the_imm_pdaf_within_monte_carlo_error():
    """``IMM(ParticlePDA(ParticleFilter(bank)))``: one scan (IMM interaction, prediction, the scan) from a
    Gaussian prior against the IMM-PDAF over Kalman filters without a gate: the mode probabilities,
    the log-likelihood and the mixed mean within Monte Carlo error (40,000 particles a mode)."""
    from torchmm import IMM

    bank = ConstantVelocity(2, dt=1.0, q=0.5, acceleration=[[0.0, 0.0], [6.0, 0.0], [-6.0, 0.0]], noise="continuous",
                            dtype=torch.float64)
    _, sensor = _models()
    Pi = torch.full((3, 3), 0.05, dtype=torch.float64) + 0.85 * torch.eye(3, dtype=torch.float64)
    options = {"detection_probability": 0.9, "clutter_density": 2e-3}
    prior = GaussianBelief(torch.tensor([0.0, 1.0, 0.0, -1.0], dtype=torch.float64), torch.eye(4, dtype=torch.float64))
    z = torch.tensor([[[4.2, -1.0], [8.0, 8.0], [math.nan, math.nan]]], dtype=torch.float64)
    kalman = IMM(PDA(KalmanFilter(bank, sensor), gate_probability=1.0, **options), Pi)
    want = run_filter(kalman, kalman.initial_belief(prior), z, record=None)
    for seed in (5, 6):
        gen = torch.Generator().manual_seed(seed)
        pf = ParticleFilter(bank, sensor, num_particles=40000, ess_threshold=0.0, generator=gen)
        imm = IMM(ParticlePDA(pf, **options), Pi)
        got = run_filter(imm, imm.initial_belief(prior, generator=gen), z, record=None)
        modes, expected = got.belief.mode_log_probs.exp()[0], want.belief.mode_log_probs.exp()[0]
        assert float((modes - expected).abs().max()) < 0.01, (modes, expected)  # about 0.29 / 0.67 / 0.03
        assert float((got.log_likelihood - want.log_likelihood).abs().max()) < 0.02
        mean, ref = got.belief.estimate().mean[0], want.belief.estimate().mean[0]
        assert float((mean - ref).abs().max()) < 0.05, (mean, ref)

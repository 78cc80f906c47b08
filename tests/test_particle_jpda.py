"""JPDA for particle filters (torchmm.association.ParticleJPDA, the Monte Carlo JPDAF): a NumPy
enumeration of every joint event with per-particle likelihoods, one track is the ParticlePDA, the
Kalman JPDA's marginals and posteriors within Monte Carlo error, LBP against exact, run_filter."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from torchmm import GaussianBelief, KalmanFilter, ParticleFilter, run_filter
from torchmm.association import JPDA, ParticleJPDA, ParticlePDA
from torchmm.models import ConstantVelocity, PositionMeasurement

DT = torch.float64
R = torch.tensor([[4.0, 0.5], [0.5, 2.0]], dtype=DT)
OPTS = {"detection_probability": 0.85, "clutter_density": 2e-3}


def _models():
    return ConstantVelocity(2, dt=1.0, q=0.5, noise="continuous", dtype=DT), PositionMeasurement(4, [0, 2], R)


def _reference(particles, log_weights, scan, pd, lam):
    """Every joint event (each detection to one track or clutter, each track at most one), NumPy."""
    N, Np, _ = particles.shape
    dets = [j for j, zj in enumerate(scan) if np.isfinite(zj).all()]
    w = np.exp(log_weights - log_weights.max(-1, keepdims=True))
    w /= w.sum(-1, keepdims=True)
    p = np.zeros((N, len(scan), Np))  # p(z_j | x_p) for track i
    for i in range(N):
        for j in dets:
            p[i, j] = [multivariate_normal(x[[0, 2]], R.numpy()).pdf(scan[j]) for x in particles[i]]
    l = (w[:, None, :] * p).sum(-1)  # (N, D)
    beta, total = np.zeros((N, 1 + len(scan))), 0.0
    for choice in itertools.product([None, *range(N)], repeat=len(dets)):  # the track of each detection
        taken = [c for c in choice if c is not None]
        if len(taken) != len(set(taken)):
            continue
        weight = 1.0
        for i in range(N):
            weight *= 1 - pd if i not in taken else 1.0
        for j, c in zip(dets, choice):
            if c is not None:
                weight *= pd * l[c, j] / lam
        total += weight
        for i in range(N):
            if i not in taken:
                beta[i, 0] += weight
        for j, c in zip(dets, choice):
            if c is not None:
                beta[c, 1 + j] += weight
    beta /= total
    post = np.zeros((N, Np))
    for i in range(N):
        like = np.full(Np, beta[i, 0])
        for j in dets:
            like += beta[i, 1 + j] * p[i, j] / l[i, j]
        post[i] = w[i] * like / (w[i] * like).sum()
    return beta, post, math.log(total)


def test_equals_an_enumeration_of_every_joint_event():
    motion, sensor = _models()
    pf = ParticleFilter(motion, sensor, ess_threshold=0.0, generator=torch.Generator().manual_seed(1))
    prior = pf.initial_belief(GaussianBelief(torch.tensor([[0.0, 1.0, 0.0, 0.0], [3.0, 0.0, 1.0, 0.0],
                                                           [-2.0, 0.0, 4.0, 0.0]], dtype=DT),
                                             3 * torch.eye(4, dtype=DT)), 60)
    scan = torch.tensor([[0.5, 0.2], [2.0, 1.5], [math.nan, math.nan], [-1.0, 3.0], [30.0, 0.0]], dtype=DT)
    out = ParticleJPDA(pf, **OPTS).update(prior, scan)
    beta, post, log_total = _reference(prior.particles.numpy(), prior.log_weights.numpy(), scan.numpy(),
                                       OPTS["detection_probability"], OPTS["clutter_density"])
    np.testing.assert_allclose(out.extras["association"].numpy(), beta, atol=1e-10)
    np.testing.assert_allclose(out.belief.log_weights.softmax(-1).numpy(), post, atol=1e-12, rtol=1e-9)
    np.testing.assert_allclose(out.log_likelihood.numpy(), log_total, atol=1e-10)
    assert 0.2 < beta[0, 1] < 0.99 and 0.2 < beta[1, 2] < 0.99  # tracks near detections take them, not surely


def test_one_track_is_the_particle_pda():
    motion, sensor = _models()
    pf = ParticleFilter(motion, sensor, ess_threshold=0.0, generator=torch.Generator().manual_seed(2))
    prior = pf.initial_belief(GaussianBelief(torch.zeros(3, 1, 4, dtype=DT), 4 * torch.eye(4, dtype=DT)), 200)
    z = torch.randn(3, 4, 2, generator=torch.Generator().manual_seed(3), dtype=DT) * 2
    z[1, 2:] = math.nan
    joint = ParticleJPDA(pf, **OPTS).update(prior, z)
    alone = ParticlePDA(pf, **OPTS).update(prior[:, 0], z)
    torch.testing.assert_close(joint.belief.log_weights[:, 0].softmax(-1), alone.belief.log_weights.softmax(-1),
                               rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(joint.log_likelihood[:, 0], alone.log_likelihood, rtol=0, atol=1e-12)


@pytest.mark.parametrize("method", ["exact", "lbp"])
def test_an_impossible_scan_keeps_every_track_as_jpda_and_the_particle_pda_do(method):
    """P_D = 1 with fewer detections than tracks: no joint event has weight, so the scan's likelihood is 0
    and each track keeps its particles (not a failed run). Run 0: two tracks, one detection; run 1: the
    same tracks and a detection each (possible: the enumeration's numbers). One track without a detection
    is the ParticlePDA's answer (log-likelihood -inf, weights unchanged)."""
    motion, sensor = _models()
    pf = ParticleFilter(motion, sensor, ess_threshold=0.0, generator=torch.Generator().manual_seed(4))
    prior = pf.initial_belief(GaussianBelief(torch.tensor([[0.0, 1.0, 0.0, 0.0], [3.0, 0.0, 1.0, 0.0]], dtype=DT),
                                             3 * torch.eye(4, dtype=DT)).expand(2, 2), 50)
    scan = torch.tensor([[[0.5, 0.2], [math.nan, math.nan]], [[0.5, 0.2], [2.0, 1.5]]], dtype=DT)
    opts = {"detection_probability": 1.0, "clutter_density": 2e-3}
    out = ParticleJPDA(pf, method=method, **opts).update(prior, scan)
    assert torch.isneginf(out.log_likelihood[0]).all() and not out.extras["failed"].any()
    torch.testing.assert_close(out.belief.log_weights[0].softmax(-1), prior.log_weights[0].softmax(-1),
                               rtol=0, atol=1e-15)
    assert torch.equal(out.extras["association"][0], torch.tensor([[1.0, 0, 0], [1.0, 0, 0]], dtype=DT))
    assert torch.isfinite(out.log_likelihood[1]).all()
    if method == "exact":
        beta, post, log_total = _reference(prior.particles[1].numpy(), prior.log_weights[1].numpy(),
                                           scan[1].numpy(), 1.0, opts["clutter_density"])
        np.testing.assert_allclose(out.extras["association"][1].numpy(), beta, atol=1e-10)
        np.testing.assert_allclose(out.log_likelihood[1].numpy(), log_total, atol=1e-10)
    one = prior[:, :1]
    nothing = torch.full((2, 1, 2), math.nan, dtype=DT)
    joint = ParticleJPDA(pf, method=method, **opts).update(one, nothing)
    alone = ParticlePDA(pf, **opts).update(one[:, 0], nothing)
    assert torch.isneginf(alone.log_likelihood).all() and torch.isneginf(joint.log_likelihood).all()
    assert not joint.extras["failed"].any() and not alone.extras["failed"].any()
    torch.testing.assert_close(joint.belief.log_weights[:, 0].softmax(-1), alone.belief.log_weights.softmax(-1),
                               rtol=0, atol=1e-15)


def test_the_kalman_jpda_within_monte_carlo_error():
    """Two tracks 3 m apart, one scan from Gaussian priors on a linear-Gaussian model: the marginals
    and posterior means of the Kalman JPDA without a gate, within Monte Carlo error (40,000
    particles a track)."""
    motion, sensor = _models()
    means = torch.tensor([[0.0, 1.0, 0.0, 0.0], [3.0, -1.0, 0.5, 0.0]], dtype=DT)
    prior = GaussianBelief(means, 2 * torch.eye(4, dtype=DT))
    scan = torch.tensor([[1.0, 0.3], [2.2, 0.1], [9.0, -6.0]], dtype=DT)
    want = JPDA(KalmanFilter(motion, sensor), gate_probability=1.0, **OPTS).update(prior, scan)
    pf = ParticleFilter(motion, sensor, ess_threshold=0.0, generator=torch.Generator().manual_seed(4))
    out = ParticleJPDA(pf, **OPTS).update(pf.initial_belief(prior, 40000), scan)
    beta, expected = out.extras["association"], want.extras["association"]
    assert float((beta - expected).abs().max()) < 0.01, (beta, expected)
    w = out.belief.log_weights.softmax(-1)
    mean = (w.unsqueeze(-1) * out.belief.particles).sum(-2)
    var = (w.unsqueeze(-1) * (out.belief.particles - mean.unsqueeze(-2)) ** 2).sum(-2)
    se = (var * (w**2).sum(-1, keepdim=True)).sqrt()
    assert ((mean - want.belief.mean).abs() < 5 * se).all(), (mean, want.belief.mean, se)
    assert float((out.log_likelihood - want.log_likelihood).abs().max()) < 0.05


def test_lbp_is_close_to_exact_for_separated_tracks():
    motion, sensor = _models()
    pf = ParticleFilter(motion, sensor, ess_threshold=0.0, generator=torch.Generator().manual_seed(5))
    prior = pf.initial_belief(GaussianBelief(torch.tensor([[0.0, 0, 0, 0], [40.0, 0, 0, 0], [0.0, 0, 40, 0]],
                                                          dtype=DT), 2 * torch.eye(4, dtype=DT)), 300)
    scan = torch.tensor([[0.5, 0.2], [40.5, -1.0], [1.0, 39.0], [20.0, 20.0]], dtype=DT)
    exact = ParticleJPDA(pf, **OPTS).update(prior, scan)
    lbp = ParticleJPDA(pf, method="lbp", **OPTS).update(prior, scan)
    torch.testing.assert_close(lbp.extras["association"], exact.extras["association"], rtol=0, atol=1e-7)


def test_through_run_filter_without_host_reads_and_errors():
    from torchmm.runtime import no_host_sync

    motion, sensor = _models()
    pf = ParticleFilter(motion, sensor, generator=torch.Generator().manual_seed(6))
    jpda = ParticleJPDA(pf, **OPTS)
    belief = pf.initial_belief(GaussianBelief(torch.tensor([[0.0, 0, 0, 0], [5.0, 0, 0, 0]], dtype=DT)
                                              .expand(3, 2, 4), 4 * torch.eye(4, dtype=DT)), 100)
    z = torch.randn(5, 3, 4, 2, generator=torch.Generator().manual_seed(7), dtype=DT) * 3
    z[2, 1] = math.nan  # an empty scan
    out = run_filter(jpda, belief, z)
    assert out.belief.particles.shape == (5, 3, 2, 100, 4) and torch.isfinite(out.log_likelihood).all()
    assert torch.allclose(out.log_likelihood[2, 1], torch.tensor(2 * math.log(0.15), dtype=DT))  # both missed
    with no_host_sync("the particle JPDA's step"):
        jpda.step(belief, z[0])
    with pytest.raises(ValueError, match="belief: 3 tracks a run exceed max_targets=2"):
        ParticleJPDA(pf, max_targets=2, **OPTS).update(pf.initial_belief(
            GaussianBelief(torch.zeros(3, 4, dtype=DT), torch.eye(4, dtype=DT)), 10), z[0, 0])
    with pytest.raises(TypeError, match="belief: ParticleJPDA needs a ParticleBelief"):
        jpda.update(GaussianBelief(torch.zeros(2, 4, dtype=DT), torch.eye(4, dtype=DT)), z[0, 0])
    with pytest.raises(ValueError, match="z: expected a scan"):
        jpda.update(belief, torch.zeros(3, 4, 3, dtype=DT))

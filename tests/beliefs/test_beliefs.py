"""Belief value objects: batch ops round-trip, moment matching, particle statistics."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import BATCH_SHAPES, assert_symmetric_psd, random_psd
from torchmm import GaussianBelief, ModeBelief, ParticleBelief
from torchmm.beliefs import cat, mix_gaussians, normalize_log_probs, psd_sqrt, stack

close = partial(torch.testing.assert_close, rtol=1e-10, atol=1e-10)


def _random_gaussian(batch_shape, n, seed=0):
    rng = np.random.default_rng(seed)
    size = int(np.prod(batch_shape)) if batch_shape else 1
    covs = np.array([random_psd(n, rng) for _ in range(size)]).reshape(*batch_shape, n, n)
    return GaussianBelief(torch.tensor(rng.normal(size=(*batch_shape, n))), torch.tensor(covs))


@pytest.mark.parametrize("batch_shape", BATCH_SHAPES, ids=str)
@pytest.mark.parametrize("n", [1, 2, 3])
def test_gaussian_batch_shape_and_round_trips(batch_shape, n):
    b = _random_gaussian(batch_shape, n)
    assert b.batch_shape == torch.Size(batch_shape)
    assert b.state_dim == n
    flat = b.reshape(-1)
    assert flat.batch_shape == (int(np.prod(batch_shape)) if batch_shape else 1,)
    back = flat.reshape(batch_shape)
    close(back.mean, b.mean)
    close(back.cov, b.cov)
    s = stack([b, b, b], dim=0)
    assert s.batch_shape == (3, *batch_shape)
    close(s[1].cov, b.cov)
    u = b.unsqueeze(-1).expand(*batch_shape, 4)
    assert u.batch_shape == (*batch_shape, 4)
    close(u.select(-1, 2).mean, b.mean)


def test_stack_and_cat_along_last_batch_axis():
    a, b = _random_gaussian((3,), 2, 1), _random_gaussian((3,), 2, 2)
    s = stack([a, b], dim=-1)
    assert s.batch_shape == (3, 2)
    close(s.select(-1, 1).cov, b.cov)
    c = cat([a, b], dim=0)
    assert c.batch_shape == (6,)
    close(c[3:].mean, b.mean)
    t = s.transpose_batch(0, 1)
    assert t.batch_shape == (2, 3)
    close(t[1].mean, b.mean)


def test_shared_covariance_broadcasts():
    b = GaussianBelief(torch.zeros(5, 2), torch.eye(2))
    assert b.batch_shape == (5,)
    assert b.materialize().cov.shape == (5, 2, 2)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), K=st.integers(1, 5), n=st.integers(1, 4))
def test_collapse_preserves_mixture_moments(seed, K, n):
    rng = np.random.default_rng(seed)
    comps = _random_gaussian((K,), n, seed)
    w = torch.tensor(rng.dirichlet(np.ones(K)))
    out = comps.collapse(w)
    # E[x] and E[x x^T] of the mixture, computed directly
    mean = (w[:, None] * comps.mean).sum(0)
    second = (w[:, None, None] * (comps.cov + comps.mean[:, :, None] * comps.mean[:, None, :])).sum(0)
    close(out.mean, mean)
    close(out.cov, second - torch.outer(mean, mean))
    assert_symmetric_psd(out.cov)


def test_mix_gaussians_columns():
    comps = _random_gaussian((2, 3), 2)  # batch 2, K=3
    weights = torch.tensor([[0.2, 0.5], [0.3, 0.25], [0.5, 0.25]]).expand(2, 3, 2)
    mean, cov = mix_gaussians(comps.mean, comps.cov, weights)
    assert mean.shape == (2, 2, 2) and cov.shape == (2, 2, 2, 2)
    for j in range(2):
        ref = comps.collapse(weights[..., j])
        close(mean[:, j], ref.mean)
        close(cov[:, j], ref.cov)


def test_mode_belief_estimate_and_probs():
    comps = _random_gaussian((4, 3), 2)
    log_probs = normalize_log_probs(torch.randn(4, 3))
    belief = ModeBelief(log_probs, comps)
    assert belief.batch_shape == (4,)
    assert belief.num_modes == 3
    close(belief.mode_probs.sum(-1), torch.ones(4))
    est = belief.estimate()
    close(est.mean, (belief.mode_probs[..., None] * comps.mean).sum(-2))
    sub = belief[1:3]
    assert sub.batch_shape == (2,) and sub.components.batch_shape == (2, 3)


def test_particle_statistics():
    g = torch.Generator().manual_seed(0)
    particles = torch.randn(2, 1000, 3, generator=g)
    log_w = torch.randn(2, 1000, generator=g)
    b = ParticleBelief(particles, log_w)
    w = torch.softmax(log_w, -1)
    est = b.estimate()
    close(est.mean, (w[..., None] * particles).sum(-2))
    diff = particles - est.mean[:, None]
    close(est.cov, torch.einsum("bp,bpi,bpj->bij", w, diff, diff))
    close(b.effective_sample_size(), 1 / (w**2).sum(-1))
    uniform = ParticleBelief(particles, torch.zeros(2, 1000))
    close(uniform.effective_sample_size(), torch.full((2,), 1000.0))


def test_particle_mix_is_the_exact_mixture():
    g = torch.Generator().manual_seed(1)
    b = ParticleBelief(torch.randn(2, 3, 50, 2, generator=g), torch.randn(2, 3, 50, generator=g))
    w = torch.softmax(torch.randn(2, 3, 4, generator=g), dim=-2)
    mixed = b.mix(w)
    assert mixed.particles.shape == (2, 4, 150, 2)
    assert mixed.batch_shape == (2, 4)
    # the mixture mean equals the weighted component means
    comp = b.estimate()
    expected = torch.einsum("bkj,bkn->bjn", w, comp.mean)
    close(mixed.estimate().mean, expected)


def test_normalize_log_probs_handles_all_minus_inf():
    x = torch.tensor([[0.0, 1.0, 2.0], [-torch.inf, -torch.inf, -torch.inf]])
    out = normalize_log_probs(x)
    close(out[0].exp().sum(), torch.tensor(1.0))
    close(out[1].exp(), torch.full((3,), 1 / 3))


def test_psd_sqrt_of_singular_covariance():
    G = torch.tensor([[0.5], [1.0]])
    Q = G @ G.T
    L = psd_sqrt(Q)
    close(L @ L.T, Q)
    L = psd_sqrt(torch.eye(2) * 4)
    close(L, 2 * torch.eye(2))


def test_psd_sqrt_device_form_reads_nothing_and_factors_singular_matrices():
    """The device form (no eigendecomposition, no host read): a square root of positive definite,
    singular (rank 1 to d - 1, ``G G^T``) and indefinite-by-rounding matrices, the Cholesky factor
    where Cholesky succeeds, and a NaN factor for a non-finite matrix only."""
    from torchmm.linalg import pivot_clamped_cholesky
    from torchmm.runtime import no_host_sync

    gen = torch.Generator().manual_seed(5)
    d = 4
    mats = []
    for rank in range(1, d + 1):
        G = torch.randn(6, d, rank, generator=gen, dtype=torch.float64) * 3
        mats.append(G @ G.mT)
    A = torch.cat(mats)  # (24, 4, 4): ranks 1, 2, 3, 4
    A[0] = A[0] - 1e-15 * torch.eye(d, dtype=torch.float64) * A[0].diagonal().max()  # indefinite by rounding
    A[1, 2, 2] = float("nan")
    with no_host_sync("psd_sqrt's device form"):
        L = psd_sqrt(A)
    finite = torch.ones(24, dtype=torch.bool)
    finite[1] = False
    assert torch.isnan(L[1]).all() and torch.isfinite(L[finite]).all()
    scale = A[finite].diagonal(dim1=-2, dim2=-1).amax(-1)[:, None, None]
    assert ((L[finite] @ L[finite].mT - A[finite]).abs() / scale).max() < 1e-12
    assert torch.equal(L[finite], L[finite].tril())
    full = mats[-1]  # rank d: positive definite, Cholesky succeeds, so it is the factor
    torch.testing.assert_close(L[-6:], torch.linalg.cholesky(full), rtol=0, atol=0)
    torch.testing.assert_close(pivot_clamped_cholesky(full), torch.linalg.cholesky(full), rtol=1e-12, atol=1e-12)
    Lc = psd_sqrt(A[finite])  # the CPU form (an eigendecomposition): another root of the same matrices
    torch.testing.assert_close(Lc @ Lc.mT, L[finite] @ L[finite].mT, rtol=0, atol=1e-12 * float(scale.max()))


def test_gaussian_log_prob():
    from scipy.stats import multivariate_normal

    b = _random_gaussian((), 3, seed=4)
    x = torch.tensor([0.3, -0.2, 1.0])
    close(b.log_prob(x), torch.tensor(multivariate_normal(b.mean.numpy(), b.cov.numpy()).logpdf(x.numpy())))

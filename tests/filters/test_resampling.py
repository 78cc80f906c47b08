"""Resampling schemes: valid indices, unbiased counts, scheme-specific count bounds, ESS gating."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchmm.beliefs import ParticleBelief
from torchmm.filters.resampling import (
    RESAMPLING_SCHEMES,
    apply_indices,
    effective_sample_size,
    resample,
    resample_where_needed,
)

SCHEMES = sorted(RESAMPLING_SCHEMES)


def _weights(num: int, seed: int = 0) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    w = rng.gamma(0.7, size=num)
    w[3] = 0.0  # a zero-weight particle is never chosen
    return torch.tensor(w / w.sum())


def _counts(indices: torch.Tensor, num: int) -> torch.Tensor:
    counts = torch.zeros(*indices.shape[:-1], num, dtype=torch.float64)
    return counts.scatter_add_(-1, indices, torch.ones_like(indices, dtype=torch.float64))


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("batch", [(), (4,), (3, 2)], ids=str)
def test_indices_shape_dtype_range(scheme, batch, generator):
    log_w = torch.randn(*batch, 17, generator=generator)
    idx = resample(log_w, scheme, generator=generator)
    assert idx.shape == (*batch, 17) and idx.dtype == torch.int64
    assert int(idx.min()) >= 0 and int(idx.max()) < 17
    idx = resample(log_w, scheme, 40, generator=generator)
    assert idx.shape == (*batch, 40)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_unbiased_counts_within_monte_carlo_error(scheme):
    """E[N_i] = N w_i: mean counts over 20 000 repetitions within 5 standard errors."""
    num, reps = 40, 20_000
    w = _weights(num)
    log_w = w.log().expand(reps, num)
    g = torch.Generator().manual_seed(7)
    counts = _counts(resample(log_w, scheme, generator=g), num)  # (reps, num)
    mean, std = counts.mean(0), counts.std(0)
    expected = num * w
    assert torch.all(counts[:, 3] == 0)
    big = expected > 0.2  # z-tests on rare particles are unreliable (docs/baselines.md §8)
    se = std[big] / math.sqrt(reps)
    z = (mean[big] - expected[big]) / se.clamp_min(1e-12)
    assert float(z.abs().max()) < 5.0, (scheme, float(z.abs().max()))
    assert torch.allclose(counts.sum(-1), torch.full((reps,), float(num)))


def test_systematic_and_stratified_bounds_residual_floor():
    num, reps = 50, 4000
    w = _weights(num, seed=3)
    log_w = w.log().expand(reps, num)
    g = torch.Generator().manual_seed(11)
    expected = num * w
    sys_counts = _counts(resample(log_w, "systematic", generator=g), num)
    assert torch.all(sys_counts >= torch.floor(expected) - 1e-9)
    assert torch.all(sys_counts <= torch.ceil(expected) + 1e-9)
    strat = _counts(resample(log_w, "stratified", generator=g), num)
    assert float((strat - expected).abs().max()) < 2.0
    resid = _counts(resample(log_w, "residual", generator=g), num)
    assert torch.all(resid >= torch.floor(expected) - 1e-9)
    # variance ordering the theory guarantees: residual and stratified <= multinomial
    multi = _counts(resample(log_w, "multinomial", generator=g), num)
    assert resid.var(0).mean() < multi.var(0).mean()
    assert strat.var(0).mean() < multi.var(0).mean()


def test_residual_with_exact_copies_is_deterministic(generator):
    log_w = torch.tensor([0.5, 0.25, 0.25]).log()
    idx = resample(log_w, "residual", 4, generator=generator)
    assert idx.tolist() == [0, 0, 1, 2]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
def test_residual_at_uniform_weights_copies_every_particle(dtype):
    """Uniform weights are N w_i = 1 up to a rounding of exp(log w - logsumexp): every particle is copied
    once (no residual draw), at every N, offset and dtype (1 - 1 ulp once floored to 0 copies: 826 of the N
    in 2..2000 in float64, and all of N = 1000 in float32, which made residual resampling multinomial)."""
    g = torch.Generator().manual_seed(0)
    for num in [*range(2, 130), 1000, 4097, 100_000]:
        for offset in (0.0, -3.7, 123.4):
            idx = resample(torch.full((num,), offset, dtype=dtype), "residual", generator=g)
            assert torch.equal(idx, torch.arange(num)), (num, offset)
    # twice as many draws: two copies each
    idx = resample(torch.zeros(9, dtype=dtype), "residual", 18, generator=g)
    assert torch.equal(idx, torch.arange(9).repeat_interleave(2))


def test_fixed_generator_reproducible():
    log_w = torch.randn(5, 30, generator=torch.Generator().manual_seed(0))
    for scheme in SCHEMES:
        a = resample(log_w, scheme, generator=torch.Generator().manual_seed(3))
        b = resample(log_w, scheme, generator=torch.Generator().manual_seed(3))
        assert torch.equal(a, b)


def test_effective_sample_size_matches_definition(generator):
    log_w = torch.randn(6, 25, generator=generator) * 2 + 30.0  # unnormalised, large offset
    w = torch.softmax(log_w, -1)
    torch.testing.assert_close(effective_sample_size(log_w), 1 / (w**2).sum(-1))
    ess = effective_sample_size(torch.full((2, 4), -float("inf")))
    assert torch.equal(ess, torch.zeros(2))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_equal_weights_have_an_ess_of_exactly_np_so_threshold_one_keeps_them(dtype):
    """Equal weights (uniform ``-log Np``, as after resampling, or any common value) have ESS exactly
    ``Np`` for every ``Np`` up to 400 and in both dtypes, so ``ess_threshold=1`` does not resample them and a
    step without a datum keeps the particles (docs/robustness.md). Before, ``exp(2 lse(l) - lse(2 l))``
    gave 4.999999999999999 for ``Np = 5`` (float64) and ``ess < 1.0 * Np`` resampled the uniform set."""
    from torchmm.filters.particle import ParticleFilter
    from torchmm.models.linear import LinearMeasurement, LinearMotion

    sizes = torch.arange(2, 401)
    ess = torch.stack([effective_sample_size(torch.full((int(n),), -math.log(int(n)), dtype=dtype)) for n in sizes])
    assert torch.equal(ess, sizes.to(dtype))
    assert float(effective_sample_size(torch.full((7,), 123.4, dtype=dtype))) == 7.0
    belief = ParticleBelief(torch.randn(3, 5, 1, dtype=dtype), torch.full((3, 5), -math.log(5), dtype=dtype))
    kept, mask, _ = resample_where_needed(belief, 1.0, generator=torch.Generator().manual_seed(0))
    assert not mask.any() and torch.equal(kept.particles, belief.particles)
    eye = torch.eye(1, dtype=dtype)
    pf = ParticleFilter(LinearMotion(eye, eye), LinearMeasurement(eye, eye), ess_threshold=1.0)
    out = pf.update(belief, torch.tensor([[math.nan], [0.1], [math.nan]], dtype=dtype),
                    generator=torch.Generator().manual_seed(1))
    assert out.extras["resampled"].tolist() == [False, True, False]
    assert torch.equal(out.belief.particles[0], belief.particles[0])
    assert torch.equal(out.belief.log_weights[2], belief.log_weights[2])


def test_apply_indices_and_ess_gating(generator):
    particles = torch.randn(3, 10, 2, generator=generator)
    log_w = torch.zeros(3, 10)
    log_w[1] = torch.linspace(0, 30, 10)  # degenerate: ESS ~ 1
    belief = ParticleBelief(particles, log_w)
    new, mask, ess = resample_where_needed(belief, 0.5, generator=generator)
    assert mask.tolist() == [False, True, False]
    assert torch.equal(new.particles[0], particles[0]) and torch.equal(new.log_weights[2], log_w[2])
    torch.testing.assert_close(new.log_weights[1], torch.full((10,), -math.log(10)))
    assert torch.all(new.particles[1] == particles[1, -1])  # all mass on the last particle
    assert ess.shape == (3,)
    gathered = apply_indices(belief, torch.tensor([[0, 0], [9, 1], [2, 3]]))
    assert gathered.particles.shape == (3, 2, 2)
    torch.testing.assert_close(gathered.particles[1, 0], particles[1, 9])


def test_bad_input_raises():
    with pytest.raises(ValueError, match="scheme"):
        resample(torch.zeros(4), "bogus")
    with pytest.raises(ValueError, match="num_samples"):
        resample(torch.zeros(4), "systematic", 0)
    with pytest.raises(ValueError, match="log_weights"):
        resample(torch.zeros(4, dtype=torch.int64), "systematic")
    with pytest.raises(ValueError, match="threshold"):
        resample_where_needed(ParticleBelief(torch.zeros(2, 1), torch.zeros(2)), -1.0)


def test_float32_runs(generator):
    log_w = torch.randn(4, 100, generator=generator).float()
    for scheme in SCHEMES:
        idx = resample(log_w, scheme, generator=generator)
        assert int(idx.max()) < 100


@pytest.mark.parametrize("threads", [1, 2])
def test_searchsorted_rows_equals_torch_searchsorted(threads):
    from torchmm.filters.resampling import searchsorted_rows

    g = torch.Generator().manual_seed(0)
    w = torch.rand(3, 4, 5000, generator=g, dtype=torch.float64) ** 6
    w[..., ::7] = 0.0  # zero-weight particles: runs of equal CDF entries
    cdf = torch.cumsum(w, -1)
    cdf = cdf / cdf[..., -1:]
    cdf[..., -1] = 1.0
    u = torch.rand(3, 4, 12000, generator=g, dtype=torch.float64)  # > 2^17 queries: the threaded path
    u[..., :10] = cdf[..., 100:110]  # queries exactly on CDF entries
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        got = searchsorted_rows(cdf, u)
    finally:
        torch.set_num_threads(previous)
    assert got.shape == u.shape and got.dtype == torch.int64
    assert torch.equal(got, torch.searchsorted(cdf, u, right=True))
    # never a zero-weight particle
    chosen = torch.gather(w, -1, got.clamp_max(4999))
    assert bool((chosen > 0).all())
    # float32 rows, and the torch fallback for non-finite data, agree as well
    assert torch.equal(searchsorted_rows(cdf.float(), u.float()),
                       torch.searchsorted(cdf.float(), u.float(), right=True))
    bad = u.clone()
    bad[0, 0, 0] = float("inf")
    assert torch.equal(searchsorted_rows(cdf, bad), torch.searchsorted(cdf, bad, right=True))
    with pytest.raises(ValueError, match="values"):
        searchsorted_rows(cdf, u[:2])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_systematic_search_never_returns_an_index_past_the_particles(dtype):
    """The largest uniform below 1 in float32 made ``num - u0`` round to ``num - 1``, so the last
    entry was counted and the index was ``K`` (an out-of-range gather in benchmarks/gpu.py's PF)."""
    from torchmm.filters.resampling import systematic_search

    K = num = 100
    weights = torch.rand(K, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    weights[-2:] = 0.0  # two trailing zero-weight particles: never selected either
    cdf = (weights.cumsum(0) / weights.sum()).to(dtype).unsqueeze(0)
    cdf[0, -3:] = 1.0
    for u0 in (1 - torch.finfo(dtype).eps / 2, 0.5, 0.0):
        index = systematic_search(cdf, torch.tensor([[u0]], dtype=dtype), num)
        assert int(index.max()) <= K - 3, (u0, index.max())
        if u0 != 1 - torch.finfo(dtype).eps / 2:  # where the grid itself does not round: plain searchsorted
            want = torch.searchsorted(cdf[0], (torch.arange(num, dtype=dtype) + u0) / num, right=True)
            torch.testing.assert_close(index, want.unsqueeze(0))

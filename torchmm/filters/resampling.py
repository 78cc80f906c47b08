r"""Resampling schemes and effective sample size, as pure functions on log-weights.

Every scheme takes unnormalised log-weights ``(*B, Np)`` and returns ancestor **indices**
``(*B, N)`` (``N = Np`` unless ``num_samples`` says otherwise), drawn independently for every batch
element with an explicit ``torch.Generator``. :func:`apply_indices` turns indices into a resampled
:class:`~torchmm.beliefs.ParticleBelief`; :func:`resample_where_needed` resamples only the batch
elements whose effective sample size fell below a threshold (``torch.where``, so shapes stay static).

Selection is by the inverse CDF (docs/baselines.md §8): ``c = cumsum(w)`` with ``c[-1] = 1``
forced, ``index = searchsorted(c, u, right=True)`` (zero-weight particles are never selected).

* multinomial: ``u_j`` i.i.d. ``U(0, 1)``; counts ``~ Multinomial(N, w)``.
* stratified: ``u_j = (j + U_j) / N``; ``|N_i - N w_i| < 2``.
* systematic: ``u_j = (j + U) / N`` (one ``U`` per batch element); ``N_i`` in
  ``{floor(N w_i), ceil(N w_i)}``. The points form a grid, so the search is a count
  (:func:`systematic_search`, ``O(Np + N)``).
* residual (Liu and Chen 1998): ``floor(N w_i)`` deterministic copies, the remaining
  ``R = N - sum floor(N w_i)`` drawn multinomially from ``(N w_i - floor(N w_i)) / R``.

All four are unbiased: ``E[N_i] = N w_i``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from torchmm.beliefs.ops import effective_sample_size as ess_of_log_weights, normalize_log_probs
from torchmm.beliefs.particle import ParticleBelief
from torchmm.runtime import host_reads_ok
from torchmm.validation import broadcast_shape

__all__ = [
    "RESAMPLING_SCHEMES",
    "apply_indices",
    "effective_sample_size",
    "inverse_cdf",
    "multinomial_resample",
    "resample",
    "resample_where_needed",
    "residual_resample",
    "searchsorted_rows",
    "stratified_resample",
    "systematic_resample",
    "systematic_search",
]


def effective_sample_size(log_weights: Tensor) -> Tensor:
    r"""Kong-Liu-Wong effective sample size ``1 / sum w_i^2`` from unnormalised log-weights
    (:func:`torchmm.beliefs.ops.effective_sample_size`: exactly ``Np`` for equal weights, so
    ``ess_threshold=1`` never resamples a uniform set); an all ``-inf`` slice gives 0.

    Shapes:
        log_weights: ``(*B, Np)`` -> ``(*B,)``

    Examples:
        >>> effective_sample_size(torch.zeros(3, 10))
        tensor([10., 10., 10.])
        >>> float(effective_sample_size(torch.full((5,), -math.log(5))))
        5.0
    """
    return ess_of_log_weights(log_weights)


def _cdf(log_weights: Tensor) -> Tensor:
    """Normalised cumulative weights with the last entry forced to exactly 1. ``(*B, Np)``."""
    weights = normalize_log_probs(log_weights).exp()
    cdf = torch.cumsum(weights, dim=-1)
    cdf = cdf / cdf[..., -1:]
    return torch.cat([cdf[..., :-1], torch.ones_like(cdf[..., -1:])], dim=-1)


_POOL: list = []


def _np_searchsorted(keys: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """``np.searchsorted(keys, queries, side="right")``, the queries split over torch's intra-op
    thread count (NumPy releases the GIL while searching)."""
    threads = torch.get_num_threads()
    if threads <= 1 or queries.size < 1 << 17:
        return np.searchsorted(keys, queries, side="right")
    if not _POOL or _POOL[0]._max_workers != threads:
        from concurrent.futures import ThreadPoolExecutor

        _POOL[:] = [ThreadPoolExecutor(threads, thread_name_prefix="torchmm-search")]
    out = np.empty(queries.shape, dtype=np.intp)
    bounds = np.linspace(0, queries.size, threads + 1).astype(int)

    def work(j):
        out[bounds[j]:bounds[j + 1]] = np.searchsorted(keys, queries[bounds[j]:bounds[j + 1]], side="right")

    list(_POOL[0].map(work, range(threads)))  # chunks of one flat search, not a loop over runs
    return out


def searchsorted_rows(sorted_seq: Tensor, values: Tensor) -> Tensor:
    """``torch.searchsorted(sorted_seq, values, right=True)`` for equally batched rows.

    On CPU (float inputs, finite) this runs NumPy's ``searchsorted`` once over all rows laid end to
    end as integer keys ``row * stride + floor((x - lo) * 2^k)``, about twice as fast as torch's
    kernel here (NumPy narrows the search for sorted queries). The keys are monotone in ``x``
    (equal entries stay equal, so zero-weight particles are never selected); they resolve
    differences down to ``2^-k`` of the data range, with ``k >= 40`` (typically ~50), else, and on
    other devices, torch's kernel is used.

    Shapes:
        sorted_seq: ``(*B, K)`` non-decreasing rows; values: ``(*B, Q)`` -> ``(*B, Q)`` int64
    """
    if sorted_seq.shape[:-1] != values.shape[:-1]:
        raise ValueError(f"values: batch {tuple(values.shape[:-1])} differs from sorted_seq {tuple(sorted_seq.shape[:-1])}")
    K, Q = sorted_seq.shape[-1], values.shape[-1]
    if (not host_reads_ok(sorted_seq) or not sorted_seq.is_floating_point() or sorted_seq.numel() == 0
            or values.numel() == 0):
        return torch.searchsorted(sorted_seq.contiguous(), values.contiguous(), right=True)
    seq = sorted_seq.detach().reshape(-1, K).double()
    val = values.detach().reshape(-1, Q).double()
    vmin, vmax = torch.aminmax(val)
    lo = min(float(seq[:, 0].min()), float(vmin), 0.0)  # 0 for CDFs: no shift needed
    hi = max(float(seq[:, -1].max()), float(vmax))
    span = hi - lo
    rows = seq.shape[0]
    if not math.isfinite(span):
        return torch.searchsorted(sorted_seq.contiguous(), values.contiguous(), right=True)
    k = math.floor(62 - math.log2(rows) - math.log2(span + 1.0))
    if k < 40:
        return torch.searchsorted(sorted_seq.contiguous(), values.contiguous(), right=True)
    scale = 2.0**min(k, 60)
    stride = math.floor(span * scale) + 1
    offset = torch.arange(rows, dtype=torch.int64).mul_(stride).unsqueeze(-1)

    def keys(x):  # x - lo >= 0, so the truncating cast is the floor
        shifted = x * scale if lo == 0.0 else (x - lo).mul_(scale)
        return shifted.long().add_(offset)

    key_seq, key_val = keys(seq), keys(val)
    flat = _np_searchsorted(key_seq.numpy().ravel(), key_val.numpy().ravel())
    index = torch.from_numpy(flat).view(rows, Q).sub_(torch.arange(rows, dtype=torch.int64).mul_(K).unsqueeze(-1))
    return index.view(values.shape)


def inverse_cdf(log_weights: Tensor, u: Tensor) -> Tensor:
    """Indices ``searchsorted(cdf, u, right=True)`` for points ``u`` in ``[0, 1)``.

    Shapes:
        log_weights: ``(*B, Np)``; u: ``(*B, N)`` -> ``(*B, N)`` (int64)
    """
    cdf = _cdf(log_weights)
    batch = broadcast_shape(cdf.shape[:-1], u.shape[:-1])
    cdf = cdf.expand(*batch, cdf.shape[-1]).contiguous()
    u = u.expand(*batch, u.shape[-1]).contiguous()
    index = searchsorted_rows(cdf, u)
    return index.clamp_max(cdf.shape[-1] - 1)


def _check(log_weights: Tensor, num_samples: int | None) -> int:
    if not isinstance(log_weights, Tensor) or log_weights.dim() < 1 or log_weights.shape[-1] < 1:
        raise ValueError("log_weights: expected a tensor of shape (*B, Np) with Np >= 1")
    if not log_weights.is_floating_point():
        raise ValueError(f"log_weights: expected a floating-point tensor, got {log_weights.dtype}")
    n = log_weights.shape[-1] if num_samples is None else int(num_samples)
    if n < 1:
        raise ValueError(f"num_samples: must be >= 1, got {num_samples}")
    return n


def _uniform(shape, like: Tensor, generator: torch.Generator | None) -> Tensor:
    return torch.rand(shape, dtype=like.dtype, device=like.device, generator=generator)


def multinomial_resample(log_weights: Tensor, num_samples: int | None = None, *,
                         generator: torch.Generator | None = None) -> Tensor:
    """Multinomial resampling: ``N`` i.i.d. draws from the weights.

    Shapes:
        log_weights: ``(*B, Np)`` -> indices ``(*B, N)``

    Examples:
        >>> g = torch.Generator().manual_seed(0)
        >>> multinomial_resample(torch.tensor([0.0, -float("inf")]), 3, generator=g)
        tensor([0, 0, 0])
    """
    n = _check(log_weights, num_samples)
    u = _uniform((*log_weights.shape[:-1], n), log_weights, generator)
    return inverse_cdf(log_weights, u)


def stratified_resample(log_weights: Tensor, num_samples: int | None = None, *,
                        generator: torch.Generator | None = None) -> Tensor:
    """Stratified resampling: one uniform in each stratum ``[j/N, (j+1)/N)``.

    Shapes:
        log_weights: ``(*B, Np)`` -> indices ``(*B, N)`` (non-decreasing)
    """
    n = _check(log_weights, num_samples)
    offsets = torch.arange(n, dtype=log_weights.dtype, device=log_weights.device)
    u = (offsets + _uniform((*log_weights.shape[:-1], n), log_weights, generator)) / n
    return inverse_cdf(log_weights, u)


def systematic_search(cdf: Tensor, u0: Tensor, num: int) -> Tensor:
    """``searchsorted(cdf, (arange(num) + u0) / num, right=True)`` by counting, ``O(K + num)``.

    The systematic points form a regular grid, so the number of CDF entries ``<= (q + u0) / num``
    is the number of entries whose grid position ``ceil(num * c - u0)`` is at most ``q``: one
    scatter-add of the ``K`` positions and a cumulative sum replace ``num`` binary searches.

    With ``c`` in ``[0, 1]`` the positions lie in ``[0, num]`` without clamping, and the entries
    equal to 1 (the last one, at least) sit at ``num``, past every point, so the counts stay below
    ``K``. They are put there explicitly: in float32 ``num - u0`` rounds to ``num - 1`` for ``u0``
    within ``num * 2^-24`` of 1, which would count the last entry too (an index ``K``).

    Shapes:
        cdf: ``(*B, K)`` non-decreasing in ``[0, 1]``, last entry exactly 1; u0: ``(*B, 1)`` in
        ``[0, 1)`` -> ``(*B, num)``
    """
    pos = (cdf * num).sub_(u0).ceil_().long().masked_fill_(cdf >= 1, num)
    counts = torch.zeros((*cdf.shape[:-1], num + 1), dtype=torch.int64, device=cdf.device)
    counts.scatter_add_(-1, pos, torch.ones((), dtype=torch.int64, device=cdf.device).expand_as(pos))
    return torch.cumsum(counts[..., :num], dim=-1)


def systematic_resample(log_weights: Tensor, num_samples: int | None = None, *,
                        generator: torch.Generator | None = None) -> Tensor:
    """Systematic resampling: ``u_j = (j + U) / N`` with one uniform per batch element.

    Shapes:
        log_weights: ``(*B, Np)`` -> indices ``(*B, N)`` (non-decreasing)

    Examples:
        >>> systematic_resample(torch.tensor([0.5, 0.25, 0.25]).log(), 4).tolist()
        [0, 0, 1, 2]
    """
    n = _check(log_weights, num_samples)
    return systematic_search(_cdf(log_weights), _uniform((*log_weights.shape[:-1], 1), log_weights, generator), n)


def residual_resample(log_weights: Tensor, num_samples: int | None = None, *,
                      generator: torch.Generator | None = None) -> Tensor:
    """Residual resampling: deterministic ``floor(N w_i)`` copies plus a multinomial residual.

    ``N w_i`` within the rounding of normalising ``log_weights`` (``16 eps (1 + log Np)`` relative) of
    an integer counts as that integer, so uniform weights give ``N / Np`` exact copies of each particle
    when ``Np`` divides ``N``.

    The number of deterministic copies differs between batch elements; output slot ``s`` takes
    the deterministic copy number ``s`` where ``s < sum floor(N w)``, else a residual draw, so the
    output shape is static.

    Shapes:
        log_weights: ``(*B, Np)`` -> indices ``(*B, N)``
    """
    n = _check(log_weights, num_samples)
    weights = normalize_log_probs(log_weights).exp()
    scaled = n * weights
    # N w_i that is an integer up to the rounding of exp(log w - logsumexp) (relative error up to about
    # 5 eps log Np: at uniform weights, 1/Np * Np is 1 - 1 ulp for 826 of the Np in 2..2000) counts as that
    # integer: otherwise uniform weights would draw no deterministic copy at all, and residual resampling
    # would be multinomial
    eps = torch.finfo(weights.dtype).eps * 16 * (1 + math.log(weights.shape[-1]))
    copies = torch.floor(scaled * (1 + eps))
    residual = (scaled - copies).clamp_min(0)
    cum_copies = torch.cumsum(copies, dim=-1)  # (*B, Np), last = number of deterministic copies
    slots = torch.arange(n, dtype=weights.dtype, device=weights.device).expand(*weights.shape[:-1], n)
    deterministic = torch.searchsorted(cum_copies.contiguous(), slots.contiguous(), right=True)
    deterministic = deterministic.clamp_max(weights.shape[-1] - 1)
    # residual weights: a row without residual mass (all copies exact) is never used below
    has_residual = residual.sum(-1, keepdim=True) > 0
    residual_log = torch.where(has_residual, residual.log(), torch.zeros_like(residual))
    drawn = multinomial_resample(residual_log, n, generator=generator)
    return torch.where(slots < cum_copies[..., -1:], deterministic, drawn)


#: name -> scheme, for configs (``resampling="systematic"``)
RESAMPLING_SCHEMES: dict[str, Callable[..., Tensor]] = {
    "multinomial": multinomial_resample,
    "residual": residual_resample,
    "stratified": stratified_resample,
    "systematic": systematic_resample,
}


def resample(log_weights: Tensor, scheme: str = "systematic", num_samples: int | None = None, *,
             generator: torch.Generator | None = None) -> Tensor:
    """Ancestor indices by a named scheme (one of :data:`RESAMPLING_SCHEMES`).

    Shapes:
        log_weights: ``(*B, Np)`` -> indices ``(*B, N)``
    """
    try:
        fn = RESAMPLING_SCHEMES[scheme]
    except KeyError:
        raise ValueError(f"scheme: expected one of {sorted(RESAMPLING_SCHEMES)}, got {scheme!r}") from None
    return fn(log_weights, num_samples, generator=generator)


def apply_indices(belief: ParticleBelief, indices: Tensor) -> ParticleBelief:
    """The resampled belief: particles gathered at ``indices``, uniform log-weights ``-log N``.

    Shapes:
        belief: particles ``(*B, Np, n)``; indices ``(*B, N)`` -> particles ``(*B, N, n)``
    """
    particles = belief.particles
    batch = broadcast_shape(particles.shape[:-2], indices.shape[:-1])
    particles = particles.expand(*batch, *particles.shape[-2:])
    indices = indices.expand(*batch, indices.shape[-1])
    gathered = torch.gather(particles, -2, indices.unsqueeze(-1).expand(*indices.shape, particles.shape[-1]))
    log_w = torch.full(indices.shape, -math.log(indices.shape[-1]), dtype=particles.dtype,
                       device=particles.device)
    return ParticleBelief(gathered, log_w)


def resample_where_needed(belief: ParticleBelief, threshold: float = 0.5, scheme: str = "systematic", *,
                          generator: torch.Generator | None = None) -> tuple[ParticleBelief, Tensor, Tensor]:
    """Resample the batch elements whose ESS is below ``threshold * Np``; keep the others.

    ``threshold = 0`` never resamples (and draws no random numbers), ``threshold > 1`` always (the
    ESS never exceeds ``Np``). Otherwise every element is resampled internally and the result
    chosen per element with ``torch.where``, so shapes and the random stream are independent of
    which elements needed it.

    Returns:
        ``(belief, resampled, ess)``: the new belief, a bool mask ``(*B,)``, the ESS before
        resampling ``(*B,)``.

    Shapes:
        belief: particles ``(*B, Np, n)``, log_weights ``(*B, Np)`` -> same shapes
    """
    if threshold < 0:
        raise ValueError(f"threshold: must be >= 0, got {threshold}")
    ess = effective_sample_size(belief.log_weights)
    num = belief.num_particles
    if threshold == 0:  # an option, not data: never resample, draw nothing
        return belief, torch.zeros(ess.shape, dtype=torch.bool, device=ess.device), ess
    mask = ess < threshold * num
    new = apply_indices(belief, resample(belief.log_weights, scheme, num, generator=generator))
    particles = torch.where(mask[..., None, None], new.particles, belief.particles)
    log_w = torch.where(mask[..., None], new.log_weights, belief.log_weights)
    return ParticleBelief(particles, log_w), mask, ess

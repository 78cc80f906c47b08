r"""Model-set policies of paper 003 (25)-(34): exact minimum entropy and the challenge match.

Both select, per run and step, the active models of a variable-structure estimator: as
``policy(joint_log_weights (*B, M, Np), generator)`` on a multiple-model particle filter's joint
weights (:class:`~torchmm.multimodel.mevsmm.MinimumEntropyVSMM`), or as
``policy.select(posterior, generator)`` over any bank
(:class:`~torchmm.multimodel.VariableStructureIMM`; the entropy then uses the beliefs' own
``entropy()``: Shannon for particle weights, differential for Gaussians).

**Exact myopic selection** (25)-(31), :class:`ExactMinimumEntropy`. With joint normalised weights
``w_{jl}`` (model ``j``, particle ``l``), per-model masses ``W_j = sum_l w_{jl}`` and within-model
entropies ``h_j = -sum_l (w_{jl}/W_j) log(w_{jl}/W_j)``, the entropy of the weights restricted to
and renormalised on a set ``S`` is (reading "joint", see docs/reproduction-003.md)

.. math::
    H(S) = \log W_S - \frac{1}{W_S}\sum_{j\in S} W_j(\log W_j - h_j),\qquad W_S = \sum_{j\in S} W_j,

so the entropies of *all* ``2^M - 1`` non-empty subsets are one subset-indicator matrix times
two per-model sums, evaluated in chunks of subsets (bounded memory). The literal reading of (26)
(``omega`` of (28) times ``p(m_j | S)`` of (29)) gives ``H(S) = sum_j p_j^2 (h_j - 2 log p_j)`` with
``p_j = W_j / W_S`` and is available as ``entropy="literal"``. Since
``H(S) = H(p) + sum_j p_j h_j >= min_j h_j``, the "joint" minimum is always attained by a single
model (the one whose belief is most concentrated): over all subsets (no ``family``) the "joint"
search takes the least ``h_j`` directly, in ``O(M)`` instead of ``O(2^M)``, with the enumeration's
conventions (:func:`min_entropy_set`); the enumeration runs for the literal reading and for a
``family`` (``family=subset_masks(M)`` enumerates every subset).

**Challenge match** (32)-(34) and section 3.4.3, :class:`ChallengeMatch` (:mod:`torchmm.multimodel.challenge`): the ``N`` heaviest of the
``M Np`` particles are found by the randomised tournament of the paper (vectorised over runs) or
exactly by ``topk``; a model stays in the set if it has at least ``Thre`` of the ``N`` winners.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from torchmm.beliefs import ModeBelief
from torchmm.beliefs.ops import normalize_log_probs
from torchmm.contract import Choice, Indices, Int, Of, entry_point
from torchmm.multimodel.challenge import ChallengeMatch, challenge_match  # (re-exported: both policies here)
from torchmm.validation import as_int

__all__ = [
    "ChallengeMatch",
    "ENTROPY_READINGS",
    "ExactMinimumEntropy",
    "challenge_match",
    "min_entropy_set",
    "min_entropy_subset",
    "model_statistics",
    "subset_entropies",
    "subset_masks",
]

ENTROPY_READINGS = ("joint", "literal")


# ------------------------------------------------------------------------------------------------
# exact subset entropies
# ------------------------------------------------------------------------------------------------
def model_statistics(log_weights: Tensor) -> tuple[Tensor, Tensor]:
    """Per-model log-masses ``log W_j`` and within-model entropies ``h_j`` of joint log-weights.

    A model with no mass (all ``-inf``) gets ``log W_j = -inf`` and ``h_j = 0``.

    Shapes:
        log_weights: ``(*B, M, Np)`` (any normalisation) -> ``(*B, M)``, ``(*B, M)``
    """
    log_mass = torch.logsumexp(log_weights, dim=-1)
    within = normalize_log_probs(log_weights)
    p = within.exp()
    h = -(torch.where(p > 0, p * within, torch.zeros_like(p))).sum(-1)
    h = torch.where(torch.isfinite(log_mass), h, torch.zeros_like(h))
    return log_mass, h


def _scaled_stats(log_weights: Tensor, entropy: str) -> Tensor:
    """Per-model sufficient statistics ``(*B, M, s)`` for :func:`_entropy_from_sums`."""
    if entropy not in ENTROPY_READINGS:
        raise ValueError(f"entropy: expected one of {ENTROPY_READINGS}, got {entropy!r}")
    return _stats_from(*model_statistics(log_weights), entropy)


def _stats_from(log_mass: Tensor, h: Tensor, entropy: str) -> Tensor:
    """The sufficient statistics from per-model log-masses and within-model entropies ``(*B, M)``."""
    top = log_mass.amax(-1, keepdim=True)
    top = torch.where(torch.isfinite(top), top, 0.0)
    log_scaled = log_mass - top  # <= 0, max 0
    mass = log_scaled.exp()
    safe_log = torch.where(mass > 0, log_scaled, 0.0)
    if entropy == "joint":
        return torch.stack([mass, mass * (safe_log - h)], dim=-1)
    sq = mass.square()
    return torch.stack([mass, sq * (h - 2 * safe_log), sq], dim=-1)


def _entropy_from_sums(sums: Tensor, entropy: str) -> Tensor:
    """Entropies from subset sums ``(..., s)``; subsets without (representable) mass -> ``+inf``."""
    mass = sums[..., 0]
    ok = mass > 0
    safe = torch.where(ok, mass, 1.0)  # (a Python scalar: no filled tensor, the same values)
    if entropy == "joint":
        value = safe.log() - sums[..., 1] / safe
    else:
        value = (sums[..., 1] + 2 * safe.log() * sums[..., 2]) / safe.square()
    return torch.where(ok, value, math.inf)


def subset_masks(num_models: int, start: int = 1, stop: int | None = None, *, device=None) -> Tensor:
    """Indicator rows of the subsets with binary codes ``start .. stop-1`` (bit ``j`` = model ``j``).

    Shapes:
        -> ``(stop - start, M)`` bool
    """
    stop = (1 << num_models) if stop is None else stop
    codes = torch.arange(start, stop, dtype=torch.int64, device=device)
    bits = torch.arange(num_models, dtype=torch.int64, device=device)
    return ((codes.unsqueeze(-1) >> bits) & 1).bool()


def subset_entropies(log_weights: Tensor, subsets: Tensor, entropy: str = "joint") -> Tensor:
    """Entropy (26) of the particle weights restricted to each candidate set.

    Shapes:
        log_weights: ``(*B, M, Np)`` joint log-weights; subsets: ``(K, M)`` bool -> ``(*B, K)``
    """
    stats = _scaled_stats(log_weights, entropy)  # (*B, M, s)
    subsets = _check_subsets(subsets, log_weights.shape[-2])
    sums = torch.einsum("km,...ms->...ks", subsets.to(stats.dtype), stats)
    return _entropy_from_sums(sums, entropy)


def _check_subsets(subsets, num_models: int, name: str = "family") -> Tensor:
    subsets = torch.as_tensor(subsets)
    if subsets.dim() != 2 or subsets.shape[-1] != num_models:
        raise ValueError(f"{name}: expected a (K, {num_models}) indicator matrix, got {tuple(subsets.shape)}")
    subsets = subsets.bool()
    if not bool(subsets.any(-1).all()):
        raise ValueError(f"{name}: every candidate set must contain at least one model")
    return subsets


def min_entropy_subset(log_weights: Tensor, family: Tensor | None = None, *, chunk_size: int = 16384,
                       entropy: str = "joint") -> tuple[Tensor, Tensor]:
    """The minimum-entropy candidate set (30) per batch element.

    ``family=None`` searches all ``2^M - 1`` non-empty subsets (binary code ``c``, bit ``j`` = model
    ``j``): for the "joint" reading the minimum is the single model of least within-model entropy
    (module docstring; no enumeration, any ``M``); for the literal one the subsets are evaluated about
    ``chunk_size`` at a time (memory ``~ chunk_size * prod(B) * 3 * 8`` bytes, ``M <= 30``): the
    per-subset sums are those of the low and high halves of the code, each an indicator matrix times
    the per-model sums. Otherwise the rows of ``family`` are the candidates. Ties go to the first
    candidate (lowest code / row).

    Returns:
        ``(active, entropy)``: the selected set ``(*B, M)`` bool and its entropy ``(*B,)``.

    Shapes:
        log_weights: ``(*B, M, Np)``; family: ``(K, M)`` bool -> ``(*B, M)``, ``(*B,)``

    Examples:
        >>> lw = torch.log(torch.tensor([[[0.3, 0.1], [0.3, 0.3]]]))
        >>> active, h = min_entropy_subset(lw)
        >>> active.tolist()
        [[True, False]]
    """
    if entropy == "joint" and family is None:
        return _most_concentrated(*model_statistics(log_weights))
    return _min_entropy(_scaled_stats(log_weights, entropy), family, chunk_size, entropy)


def min_entropy_set(log_mass: Tensor, within_entropy: Tensor, family: Tensor | None = None, *,
                    chunk_size: int = 16384, entropy: str = "joint") -> tuple[Tensor, Tensor]:
    """:func:`min_entropy_subset` from per-model statistics: any mode filter's beliefs.

    ``log_mass`` are the models' (log) posterior probabilities, ``within_entropy`` the entropies of
    their beliefs (the weights' Shannon entropy for particles, the differential entropy
    ``(1/2) log det(2 pi e P)`` for Gaussians: :meth:`~torchmm.beliefs.GaussianBelief.entropy`).
    With ``family=None`` and the "joint" reading the minimum is found without enumerating the subsets
    (:func:`min_entropy_subset`): the set is the model of least entropy among those of representable
    mass (``exp(log W_j - max log W) > 0``), ties to the lowest index, and its value is that
    entropy; a NaN statistic or a ``-inf`` minimum keeps every model, as the enumeration does.

    Shapes:
        log_mass, within_entropy: ``(*B, M)``; family ``(K, M)`` bool -> ``(*B, M)``, ``(*B,)``
    """
    if entropy not in ENTROPY_READINGS:
        raise ValueError(f"entropy: expected one of {ENTROPY_READINGS}, got {entropy!r}")
    h = torch.where(torch.isfinite(log_mass), within_entropy, 0.0)
    if entropy == "joint" and family is None:
        active, value = _most_concentrated(log_mass, h)
    else:
        active, value = _min_entropy(_stats_from(log_mass, h, entropy), family, chunk_size, entropy)
    # the set in the memory order of log_mass (a batch-last kernel's view stays batch-last: the policy's
    # renormalisations that follow then run over it 2x faster)
    return torch.empty_like(log_mass, dtype=torch.bool).copy_(active), value


def _most_concentrated(log_mass: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    """The "joint" minimum over all non-empty subsets without enumerating them:
    ``H(S) = H(p) + sum_{j in S} p_j h_j >= min_{j in S} h_j``, with equality for a single model, so the
    minimum is the singleton of least ``h_j`` among the models of representable mass (docs/reproduction-003.md).

    The enumeration's conventions hold: a model's mass is representable where ``exp(log W_j - max log W)
    > 0``; ties go to the lowest index (the lowest code); a NaN statistic in a run (a NaN ``h_j``, or
    an infinite one of a model without representable mass, whose ``W_j h_j`` is then ``0 * inf``) or a
    minimum of ``-inf`` keeps every model, as no finite minimum does. The value is ``h_j`` itself
    (the enumeration's ``log W_j - (W_j log W_j - W_j h_j) / W_j`` is it, to rounding).

    Shapes:
        log_mass, h: ``(*B, M)`` (``h`` 0 where ``log_mass`` is not finite) -> ``(*B, M)`` bool, ``(*B,)``
    """
    top = log_mass.amax(-1, keepdim=True)
    top = torch.where(torch.isfinite(top), top, 0.0)
    representable = (log_mass - top).exp() > 0
    value = torch.where(representable, h, h * 0.0 + math.inf)  # (h * 0: NaN where h is not finite)
    best, index = value.min(-1)
    active = index.unsqueeze(-1) == torch.arange(log_mass.shape[-1], device=log_mass.device)
    # (a NaN or -inf minimum, or no model of representable mass: keep all, as the enumeration does)
    return active | ~torch.isfinite(best).unsqueeze(-1), best


def _min_entropy(stats: Tensor, family, chunk_size: int, entropy: str) -> tuple[Tensor, Tensor]:
    num_models = stats.shape[-2]
    if chunk_size < 1:
        raise ValueError(f"chunk_size: must be >= 1, got {chunk_size}")
    batch = stats.shape[:-2]
    flat = stats.reshape(batch.numel(), num_models, stats.shape[-1])  # (Bf, M, s)
    operand = flat.permute(1, 0, 2).reshape(num_models, -1)  # (M, Bf * s)
    if family is None:
        if num_models > 30:
            raise ValueError(f"family: all subsets of {num_models} models are too many; give a family")
        total = (1 << num_models) - 1
    else:
        family = _check_subsets(family, num_models).to(stats.device)
        total = family.shape[0]
    best = torch.full((flat.shape[0],), math.inf, dtype=stats.dtype, device=stats.device)
    best_index = torch.zeros(flat.shape[0], dtype=torch.int64, device=stats.device)
    if family is None:
        # all subsets: code = (high << a) | low, so a subset's sums are the sums of its low-half
        # and high-half members: two small indicator matrices times the per-model sums, combined
        # by broadcasting (one add per subset and statistic instead of M multiply-adds)
        a = (num_models + 1) // 2
        low = subset_masks(a, 0, device=stats.device).to(stats.dtype) @ operand[:a]  # (2^a, Bf*s)
        high_masks = subset_masks(num_models - a, 0, device=stats.device).to(stats.dtype)
        high = high_masks @ operand[a:]  # (2^b, Bf*s)
        rows_per_chunk = max(1, chunk_size // low.shape[0])
        for start in range(0, high.shape[0], rows_per_chunk):
            stop = min(start + rows_per_chunk, high.shape[0])
            sums = (high[start:stop, None] + low[None]).view(stop - start, low.shape[0], flat.shape[0],
                                                             stats.shape[-1])
            values = _entropy_from_sums(sums, entropy).flatten(0, 1)  # (chunk, Bf); code 0 -> +inf
            chunk_best, chunk_arg = values.min(0)
            better = chunk_best < best
            best = torch.where(better, chunk_best, best)
            best_index = torch.where(better, chunk_arg + start * low.shape[0], best_index)
        best_index = best_index - 1  # codes start at 1 below
    else:
        for start in range(0, total, chunk_size):
            stop = min(start + chunk_size, total)
            rows = family[start:stop]
            sums = (rows.to(stats.dtype) @ operand).view(stop - start, flat.shape[0], stats.shape[-1])
            values = _entropy_from_sums(sums, entropy)  # (K_c, Bf)
            chunk_best, chunk_arg = values.min(0)
            better = chunk_best < best
            best = torch.where(better, chunk_best, best)
            best_index = torch.where(better, chunk_arg + start, best_index)
    if family is None:
        bits = torch.arange(num_models, device=stats.device)
        active = (((best_index + 1).unsqueeze(-1) >> bits) & 1).bool()
    else:
        active = family[best_index]
    # no candidate with representable mass (cannot happen with a finite weight): keep all
    active = torch.where(torch.isfinite(best).unsqueeze(-1), active, torch.ones_like(active))
    return active.view(*batch, num_models), best.view(batch)


# ------------------------------------------------------------------------------------------------
# selection policies
# ------------------------------------------------------------------------------------------------
class ExactMinimumEntropy:
    """Select the minimum-entropy set (30) among all non-empty subsets or a given ``family`` (over all
    subsets, the "joint" reading's minimum is a single model and is found without enumerating them:
    :func:`min_entropy_subset`).

    Args:
        family: ``(K, M)`` bool candidate sets, or a list (any sequence: a tuple, a config's list) of lists
            of model indices; None = all. :class:`~torchmm.multimodel.VariableStructureIMM` refuses an index
            past its bank's ``M`` when it is built.
        chunk_size: subsets evaluated at once.
        entropy: ``"joint"`` (default; entropy of the renormalised weights on the set) or
            ``"literal"`` (the product of (28) and (29) as printed).
    """

    @entry_point(family=Of((Sequence, Tensor), optional=True,
                           what="a list of model-index lists or a (K, M) bool mask"),
                 chunk_size=Int(1),
                 entropy=Choice(*ENTROPY_READINGS))
    def __init__(self, family=None, *, chunk_size: int = 16384, entropy: str = "joint"):
        if isinstance(family, Tensor):
            if family.dtype != torch.bool or family.dim() != 2:
                raise TypeError("family: expected a (K, M) bool mask or a list of model-index lists, got a "
                                f"tensor of dtype {family.dtype} and shape {tuple(family.shape)}")
        elif family is not None:
            # any sequence of index sequences (a list, a tuple, a config's ListConfig), kept as lists of ints
            if isinstance(family, (str, bytes)) or not family:
                raise TypeError("family: expected a (K, M) bool mask or a non-empty list of "
                                f"model-index lists, got {family!r}")
            family = [[int(i) for i in Indices().check(members, f"family[{k}]")]
                      for k, members in enumerate(family)]
        self.family, self.chunk_size, self.entropy = family, as_int(chunk_size, "chunk_size", minimum=1), entropy

    def check_bank(self, bank, name: str = "policy") -> None:
        """Refuse a ``family`` whose sets name a model past the bank's ``M`` (or a mask of another width):
        ``ValueError`` naming ``name.family``; called once by
        :class:`~torchmm.multimodel.VariableStructureIMM` when it is built."""
        if self.family is not None:
            self._make_family(bank.num_modes, "cpu", f"{name}.family")

    def _family(self, num_models: int, device) -> Tensor | None:
        if self.family is None:
            return None
        cache = self.__dict__.setdefault("_families", {})  # (a host-to-device copy once, not every step)
        key = (num_models, str(device))
        if key not in cache:
            cache[key] = self._make_family(num_models, device)
        return cache[key]

    def _make_family(self, num_models: int, device, name: str = "family") -> Tensor:
        fam = self.family
        if isinstance(fam, list):
            rows = torch.zeros(len(fam), num_models, dtype=torch.bool)
            for k, members in enumerate(fam):
                bad = [i for i in members if not 0 <= i < num_models]
                if bad:
                    raise ValueError(f"{name}: entry {k} ({members}) has model index {bad[0]}, out of range "
                                     f"for the bank's {num_models} models (0..{num_models - 1})")
                rows[k, members] = True
            fam = rows
        return _check_subsets(fam, num_models, name).to(device)

    def __call__(self, log_weights: Tensor, generator=None) -> tuple[Tensor, dict]:
        family = self._family(log_weights.shape[-2], log_weights.device)
        active, value = min_entropy_subset(log_weights, family, chunk_size=self.chunk_size, entropy=self.entropy)
        return active, {"entropy": value}

    def select(self, belief: ModeBelief, generator=None) -> tuple[Tensor, dict]:
        """The policy over any bank: the models' posterior probabilities and their beliefs' entropies
        (:func:`min_entropy_set`). ``belief``: the posterior over all models, batch ``(*B,)``."""
        comps = belief.components
        if not hasattr(comps, "entropy"):
            raise TypeError(f"ExactMinimumEntropy: the mode filters' belief {type(comps).__name__} defines no entropy()")
        family = self._family(belief.num_modes, belief.mode_log_probs.device)
        active, value = min_entropy_set(belief.mode_log_probs, comps.entropy(), family, chunk_size=self.chunk_size,
                                        entropy=self.entropy)
        return active, {"entropy": value}

r"""Distances between sets of points (multi-target tracking): GOSPA and OSPA, batched over runs and steps.

**GOSPA** (Rahmathullah, García-Fernández & Svensson, FUSION 2017; ``alpha = 2``), of an estimated
set ``Y`` against the true set ``X`` with cut-off ``c`` and order ``p``:

.. math::
    d_p^{(c)}(X, Y) = \Bigl(\min_\gamma \sum_{(i, j) \in \gamma} d(x_i, y_j)^p
        + \tfrac{c^p}{2}\bigl(|X| + |Y| - 2|\gamma|\bigr)\Bigr)^{1/p}

over the partial assignments ``gamma`` of truths to estimates with ``d < c``; it splits into the
*localisation* ``sum d^p`` of the assigned pairs, the *missed* ``c^p/2`` per unassigned truth and the
*false* ``c^p/2`` per unassigned estimate (each in units of distance to the ``p``, as Stone Soup's
``GOSPAMetric`` reports them; ``distance`` is the ``p``-th root of their sum).

**OSPA** (Schuhmacher, Vo & Vo, IEEE TSP 56(8), 2008): for ``|X| = m <= |Y| = n`` (else swapped),
``(1/n (min_pi sum_i min(d, c)^p + c^p (n - m)))^{1/p}``, 0 for two empty sets.

Both solve one minimum-cost assignment per set pair, all pairs of a batch at once
(:func:`torchmm.assignment.linear_assignment`), of the ``N x K`` matrix ``min(d, c)^p - c^p`` (``<= 0``,
0 for a pair with an absent point): GOSPA^p is ``c^p/2 (|X| + |Y|)`` plus the least sum of it (an
assigned pair at distance ``c`` or more costs what a missed and a false point cost), and OSPA's pairing
of the smaller set minimises it too. The figures are then summed from the pairs the assignment makes
(``d^p`` of the pairs closer than ``c``), not from the shifted costs, so no ``c^p`` cancels. The
Euclidean distance of the points' coordinates; pass the components to compare (e.g. positions).

**Any order p.** Everything is computed on ``u = min(d, c) / c`` in ``[0, 1]``: the assignment of
``u^p - 1``, and the distance as ``c m (sum (u / m)^p + ...)^(1/p)`` with ``m`` the largest term's
``u`` (log-sum-exp's rescaling for a p-norm), so no ``c^p`` is formed and no ``d^p`` overflows: at
``p = 250`` and ``c = 30`` (``c^p = 1e369``) the distance is a number, not an ``OverflowError``. Where a
pair's ``u^p`` or the pairs' sum of them is below ``2^-20`` (at large ``p`` every pair well within ``c``:
its ``u^p - 1`` rounds to ``-1``), the pairs are assigned again with as many pairs on ``(u / s)^p``, no
``-1`` beside them, ``s`` a lower bound of the best pairs' largest ``u`` and the first pairs' largest,
and the smallest sum kept. The parts ``localisation``, ``missed``, ``false`` are in units of distance to
the ``p``: ``inf`` beyond the float range (tests/test_set_metrics_large_p.py: against every assignment
summed in 2000 digits, ``p`` up to 250; docs/tracking.md).

Sets are padded tensors with a presence mask: ``truth (*B, N, d)`` with ``truth_present (*B, N)``,
``estimates (*B, K, d)`` with ``estimate_present (*B, K)`` (default: every row present). Absent rows
are ignored whatever they hold (NaN padding is fine). The two sets' non-finite rows differ, each as
the library's simulators and estimators write them:

* a *truth* row with a non-finite coordinate is a target that does not exist then (the convention of
  :func:`~torchmm.simulate.simulate_detections`' states: not yet born, or dead): it is absent, as if
  ``truth_present`` were False there;
* an *estimate* row marked present with a non-finite coordinate is a diverged estimate: at distance
  ``c`` from every point, so scored as a false point (and the target it should have covered as
  missed), never hidden.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.assignment import linear_assignment
from torchmm.contract import Labels, Mask, Real, Sets, entry_point, unchecked
from torchmm.runtime import host_reads_ok
from torchmm.validation import broadcast_shape

__all__ = ["gospa", "gospa_switching", "ospa"]


def _prepare(estimates: Tensor, truth: Tensor, estimate_present, truth_present, c: float):
    """Broadcast sets and masks; the cut-off distances ``(*B, N, K)``."""
    if estimates.dim() < 2:
        raise ValueError(f"estimates: expected a padded set (*B, K, d), got shape {tuple(estimates.shape)}")
    if truth.dim() < 2:
        raise ValueError(f"truth: expected a padded set (*B, N, d), got shape {tuple(truth.shape)}")
    if estimates.shape[-1] != truth.shape[-1]:
        raise ValueError(f"truth: points of dimension {truth.shape[-1]}, the estimates' are {estimates.shape[-1]}")
    dtype = torch.promote_types(estimates.dtype, truth.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    estimates, truth = estimates.to(dtype), truth.to(dtype)
    try:
        batch = broadcast_shape(estimates.shape[:-2], truth.shape[:-2])
    except RuntimeError:
        raise ValueError(f"truth: batch {tuple(truth.shape[:-2])} does not broadcast with the estimates' "
                         f"{tuple(estimates.shape[:-2])}") from None
    K, N = estimates.shape[-2], truth.shape[-2]
    masks = []
    for mask, size, name in ((estimate_present, K, "estimate_present"), (truth_present, N, "truth_present")):
        if mask is None:
            mask = torch.ones(size, dtype=torch.bool, device=estimates.device)
        if mask.dim() < 1 or mask.shape[-1] != size:
            raise ValueError(f"{name}: expected (*B, {size}) (one flag per row of its set), got {tuple(mask.shape)}")
        try:
            batch = broadcast_shape(batch, mask.shape[:-1])
        except RuntimeError:
            raise ValueError(f"{name}: batch {tuple(mask.shape[:-1])} does not broadcast with the sets' "
                             f"{tuple(batch)}") from None
        masks.append(mask)
    est_present = masks[0].expand(*batch, K)
    # a true point with a non-finite coordinate: a target that does not exist then (absent)
    tru_present = masks[1].expand(*batch, N) & torch.isfinite(truth).all(-1).expand(*batch, N)
    diff = truth.expand(*batch, N, truth.shape[-1]).unsqueeze(-2) - estimates.expand(*batch, K, truth.shape[-1]).unsqueeze(-3)
    distance = diff.square().sum(-1).sqrt()  # (*B, N, K)
    distance = torch.where(torch.isfinite(distance), distance.clamp(max=c), torch.full_like(distance, c))
    return distance, est_present, tru_present


#: a term u^p below this (units of c^p) keeps fewer than 32 bits in the cost u^p - 1, and a sum of u^p
#: below it fewer than 32 bits beside the costs' -1s: there the assignment of u^p - 1 is checked against a
#: rescaled one
_RESOLVED = 2.0**-20


def _pairs(assigned: Tensor, u: Tensor, both: Tensor) -> tuple[Tensor, Tensor]:
    """The rows ``assigned (*B, N)`` pairs with a present point (``both (*B, N, K)``) and their
    ``u (*B, N)``."""
    if not u.shape[-1]:
        return torch.zeros_like(assigned, dtype=torch.bool), torch.zeros(assigned.shape, dtype=u.dtype,
                                                                          device=u.device)
    pick = assigned.clamp(0, u.shape[-1] - 1).unsqueeze(-1)
    return (assigned >= 0) & both.gather(-1, pick).squeeze(-1), u.gather(-1, pick).squeeze(-1)


def _objective(up: Tensor, pairs: Tensor, p: float, rest: Tensor, weight: float) -> tuple[Tensor, Tensor]:
    """``sum u^p`` over ``pairs (*B, N)`` (``up`` their ``u``) plus ``weight`` for each of ``rest (*B,)``
    unpaired points, as ``(m, G)`` with the sum ``m^p G``: ``m`` the largest term's ``u``
    (``weight^(1/p)`` for an unpaired point), so ``G`` lies in ``[1, points]`` and nothing overflows or
    vanishes (``m = G = 0``: an empty sum)."""
    zero = torch.zeros((), dtype=up.dtype, device=up.device)
    top = torch.where(pairs, up, zero).amax(-1) if up.shape[-1] else zero.expand(up.shape[:-1])
    m = torch.where(rest > 0, top.clamp(min=weight ** (1.0 / p)), top)
    safe = torch.where(m > 0, m, torch.ones_like(m))
    terms = torch.where(pairs, (up / safe.unsqueeze(-1)).pow(p), zero).sum(-1)
    unpaired = rest.to(up.dtype) * torch.exp(math.log(weight) - p * torch.log(safe))  # (m^p >= weight)
    G = terms + torch.where(rest > 0, unpaired, zero)
    return m, torch.where(m > 0, G, zero)


def _log_objective(m: Tensor, G: Tensor, p: float) -> Tensor:
    """``log(m^p G)``, to compare two assignments (``-inf`` for an empty sum)."""
    positive = m > 0
    one = torch.ones_like(m)
    logs = p * torch.where(positive, m, one).log() + torch.where(positive, G, one).log()
    return torch.where(positive, logs, -math.inf)


def _rescaled_assignment(u: Tensor, allowed: Tensor, p: float, count: Tensor, scale: Tensor) -> Tensor:
    """The assignment ``(R, N)`` of exactly ``count (R,)`` pairs, each ``allowed``, of the least sum of
    ``(u / scale)^p`` (no ``-1`` beside them: their relative precision kept): ``N - count`` dummy columns
    of cost 0 take the other rows; a pair not allowed, or a dummy past them, costs more than any sum of
    the others (terms above that cap, far beyond the optimum's, are capped)."""
    R, N, K = u.shape
    cap = torch.finfo(u.dtype).max / (4.0 * (N + 1))
    zero = torch.zeros((), dtype=u.dtype, device=u.device)
    scaled = (u / scale[:, None, None]).pow(p).clamp(max=cap)
    free = torch.arange(N, device=u.device) < (N - count).unsqueeze(-1)  # (R, N): the dummies of cost 0
    dummy = torch.where(free, zero, 2.0 * cap)
    cost = torch.cat([torch.where(allowed, scaled, 2.0 * cap), dummy.unsqueeze(-2).expand(R, N, N)], -1)
    assigned = unchecked(linear_assignment)(cost)
    return torch.where(assigned < K, assigned, -1)


def _best_assignment(u: Tensor, both: Tensor, allowed: Tensor, p: float, pieces, weight: float) -> Tensor:
    """The assignment ``(R, N)`` of the set pairs' ``u (R, N, K)`` (``both``: two present points; ``allowed``:
    the pairs that may count) minimising ``sum u^p`` over the pairs it makes plus ``weight`` per unpaired
    point (``pieces(assigned, index) -> (pairs, u of them, unpaired points)``, ``index`` the set pairs or
    None for all): the assignment of ``u^p - 1`` (0 for an absent point), exact to about ``n eps`` of the
    objective; where a term or the sum of its pairs' ``u^p`` is below ``_RESOLVED`` (lost beside the
    ``-1``s), also :func:`_rescaled_assignment` with as many pairs, scaled by a lower bound of the optimum's
    largest term (the ``count``-th least of the rows' least ``u``) and by the first one's largest, and the
    one of the smallest sum of ``u^p`` kept; on the CPU for those set pairs only (a host read)."""
    zero = torch.zeros((), dtype=u.dtype, device=u.device)
    first = unchecked(linear_assignment)(torch.where(both, u.pow(p) - 1, zero))
    if not u.numel():
        return first

    def keys(assigned: Tensor, index):  # the pairs, the log of their sum of u^p, the largest u
        pairs, up, _ = pieces(assigned, index)
        log_pairs = _log_objective(*_objective(up, pairs, p, torch.zeros_like(pairs[..., 0]), weight), p)
        return pairs.sum(-1), log_pairs, torch.where(pairs, up, zero).amax(-1)

    pairs, up, rest = pieces(first, None)
    terms = torch.where(pairs, up.pow(p), zero)  # (underflow is harmless here: compared with _RESOLVED)
    count = pairs.sum(-1)
    small = (pairs & (terms < _RESOLVED)).any(-1)
    unresolved = (count > 0) & (((rest == 0) & (terms.sum(-1) < _RESOLVED)) | small)
    if host_reads_ok(u):
        if not bool(unresolved.any()):
            return first
        index = unresolved.nonzero(as_tuple=True)[0]
    else:
        index = torch.arange(u.shape[0], device=u.device)
    uu, ok, n = u[index], allowed[index], count[index]
    least = torch.where(ok, uu, math.inf).amin(-1).sort(-1).values  # (the rows' least u, ascending)
    lower = least.gather(-1, (n - 1).clamp(min=0).unsqueeze(-1)).squeeze(-1)
    _, best_key, top = keys(first[index], index)
    best = first[index]
    for scale in (lower, top):
        scale = torch.where((scale > 0) & torch.isfinite(scale), scale, torch.ones_like(scale))
        second = _rescaled_assignment(uu, ok, p, n, scale)
        count2, log_pairs2, _ = keys(second, index)
        better = (count2 == n) & (log_pairs2 < best_key)
        best = torch.where(better.unsqueeze(-1), second, best)
        best_key = torch.where(better, log_pairs2, best_key)
    if host_reads_ok(u):
        first = first.clone()
        first[index] = best
        return first
    return torch.where(unresolved.unsqueeze(-1), best, first)


@entry_point(estimates=Sets(missing=None, mask="estimate_present"),
             truth=Sets(missing=math.nan, mask="truth_present"), c=Real(positive=True), p=Real(minimum=1.0),
             estimate_present=Mask(optional=True), truth_present=Mask(optional=True))
def gospa(estimates: Tensor, truth: Tensor, *, c: float, p: float = 2.0, estimate_present: Tensor | None = None,
          truth_present: Tensor | None = None) -> dict[str, Tensor]:
    r"""GOSPA (``alpha = 2``) between estimated and true point sets, for every set pair of a batch.

    Args:
        estimates: ``(*B, K, d)`` estimated points (e.g. track positions), padded (a present row with a
            non-finite coordinate: a diverged estimate, at distance ``c`` from everything).
        truth: ``(*B, N, d)`` true points, padded (its batch broadcasts with the estimates'); a row with
            a non-finite coordinate is a target that does not exist (absent, as ``truth_present`` False).
        c: the cut-off distance (> 0): a pair at least ``c`` apart counts as a missed and a false point.
        p: the order (>= 1); default 2.
        estimate_present, truth_present: ``(*B, K)`` / ``(*B, N)`` bool, which rows are points (default
            all).

    Returns:
        ``{"distance", "localisation", "missed", "false"}``, each ``(*B,)`` (the last three in units of
        distance to the ``p``, ``inf`` beyond the float range; ``distance = (localisation + missed +
        false)^(1/p)``, computed without them), and ``"assigned"``
        ``(*B, N)`` long: the estimate assigned to each true point (-1: missed).

    Examples:
        >>> truth = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
        >>> estimates = torch.tensor([[0.0, 1.0], [50.0, 50.0], [10.0, 2.0]])
        >>> out = gospa(estimates, truth, c=5.0)
        >>> [round(float(out[k]), 3) for k in ("localisation", "missed", "false")], out["assigned"].tolist()
        ([5.0, 0.0, 12.5], [0, 2])
    """
    c, p = float(c), float(p)
    distance, est_present, tru_present = _prepare(estimates, truth, estimate_present, truth_present, c)
    dtype = distance.dtype
    zero = torch.zeros((), dtype=dtype, device=distance.device)
    u = distance / c  # in [0, 1] (cut at c)
    both = tru_present.unsqueeze(-1) & est_present.unsqueeze(-2)
    points = tru_present.sum(-1) + est_present.sum(-1)

    # GOSPA^p / c^p = min over partial assignments of sum u^p + (|X| + |Y| - 2 |gamma|) / 2 over the pairs
    # closer than c: one assignment of the N x K matrix u^p - 1 (<= 0; 0 for an absent point)
    *batch, N, K = u.shape
    R = math.prod(batch)  # (spelled out: reshape(-1, ...) is ambiguous for a set of no point)
    flat_u, flat_both, flat_points = u.reshape(R, N, K), both.reshape(R, N, K), points.reshape(R)

    def pieces(assigned: Tensor, index):  # the pairs closer than c, their u, the unpaired points
        uu, bb, n = ((flat_u, flat_both, flat_points) if index is None
                     else (flat_u[index], flat_both[index], flat_points[index]))
        paired, up = _pairs(assigned, uu, bb)
        matched = paired & (up < 1)
        return matched, up, n - 2 * matched.sum(-1)

    assigned = _best_assignment(flat_u, flat_both, flat_both & (flat_u < 1), p, pieces, 0.5)
    assigned = assigned.reshape(*batch, N)
    paired, up = _pairs(assigned, u, both)
    matched = paired & (up < 1)
    count = matched.sum(-1)
    m, G = _objective(up, matched, p, points - 2 * count, 0.5)
    d = _pairs(assigned, distance, both)[1]
    localisation = torch.where(matched, d.pow(p), zero).sum(-1)  # (the parts: inf beyond the float range)
    half = torch.full((), c, dtype=dtype, device=distance.device).pow(p) / 2
    missed, false = ((tru_present.sum(-1) - count).to(dtype), (est_present.sum(-1) - count).to(dtype))
    missed = torch.where(missed > 0, half * missed, zero)  # (not inf * 0)
    false = torch.where(false > 0, half * false, zero)
    return {"distance": c * m * G.pow(1.0 / p), "localisation": localisation, "missed": missed,
            "false": false, "assigned": torch.where(matched, assigned, -1)}


@entry_point(labels=Labels(minimum=-1), penalty=Real(minimum=0.0), p=Real(minimum=1.0),
             truth_present=Mask(optional=True))
def gospa_switching(labels: Tensor, *, penalty: float, p: float = 2.0, truth_present: Tensor | None = None) -> Tensor:
    r"""GOSPA's track-switching term over time (Rahmathullah, Garcia-Fernandez & Svensson 2016, Sec. V; as
    Stone Soup's ``GOSPAMetric(switching_penalty=...)`` and MATLAB's ``trackGOSPAMetric`` compute it).

    A target's track is the label of the estimate GOSPA assigns to it (-1: none). From the first step it
    has a track, each change of it costs a *half switch* (0.5) when it gains or loses its track and a full
    one (1) when it moves from one track to another; a step where the target does not exist
    (``truth_present`` False) changes nothing. At step ``k`` the term is
    ``penalty * (sum of the targets' switch costs at k)^(1/p)``, and the GOSPA with switching is
    ``(d_k^2 + term_k^2)^(1/2)`` (``alpha = 2``; Stone Soup's combination).

    Args:
        labels: ``(T, *B, N)`` integer: the label of the track assigned to each target (``gospa``'s
            ``assigned`` mapped through the estimates' labels), -1 where none.
        penalty: the switching penalty (>= 0; Stone Soup's ``switching_penalty``).
        p: GOSPA's order (>= 1).
        truth_present: ``(T, *B, N)`` bool: which targets exist at each step (default all).

    Returns:
        ``(T, *B)`` the switching term at each step (0 at the first).

    Examples:
        >>> labels = torch.tensor([[0], [0], [1], [-1], [1]])  # a target's track: 0, 0, 1, none, 1
        >>> gospa_switching(labels, penalty=2.0, p=1.0).tolist()
        [0.0, 0.0, 2.0, 1.0, 1.0]
    """
    labels = labels.long()
    if labels.dim() < 2:
        raise ValueError(f"labels: expected (T, *B, N), got shape {tuple(labels.shape)}")
    present = torch.ones_like(labels, dtype=torch.bool) if truth_present is None else truth_present
    try:
        present = present.expand(labels.shape)
    except RuntimeError:
        raise ValueError(f"truth_present: shape {tuple(present.shape)} does not match labels' "
                         f"{tuple(labels.shape)}") from None
    dtype = torch.get_default_dtype()
    last = torch.full_like(labels[0], -1)  # the last track of each target (-1: none)
    seen = torch.zeros_like(labels[0], dtype=torch.bool)  # the target has had a track
    out = []
    for k in range(labels.shape[0]):  # (over time only)
        now, here = labels[k], present[k]
        changed = here & seen & (now != last)
        cost = 0.5 * changed.to(dtype) + 0.5 * (changed & (now >= 0) & (last >= 0)).to(dtype)
        out.append(float(penalty) * cost.sum(-1).pow(1.0 / float(p)))
        record = here & (seen | (now >= 0))
        last = torch.where(record, now, last)
        seen = seen | (here & (now >= 0))
    return torch.stack(out)


@entry_point(estimates=Sets(missing=None, mask="estimate_present"),
             truth=Sets(missing=math.nan, mask="truth_present"), c=Real(positive=True), p=Real(minimum=1.0),
             estimate_present=Mask(optional=True), truth_present=Mask(optional=True))
def ospa(estimates: Tensor, truth: Tensor, *, c: float, p: float = 2.0, estimate_present: Tensor | None = None,
         truth_present: Tensor | None = None) -> Tensor:
    r"""OSPA between estimated and true point sets, for every set pair of a batch.

    Args and shapes as :func:`gospa`.

    Returns:
        ``(*B,)``: the OSPA distance (0 where both sets are empty, ``c`` where exactly one is).

    Examples:
        >>> truth = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
        >>> estimates = torch.tensor([[0.0, 1.0], [10.0, 2.0], [50.0, 50.0]])
        >>> round(float(ospa(estimates, truth, c=5.0, p=1.0)), 6)  # (1 + 2 + 5) / 3
        2.666667
    """
    c, p = float(c), float(p)
    distance, est_present, tru_present = _prepare(estimates, truth, estimate_present, truth_present, c)
    u = distance / c  # in [0, 1] (cut at c)
    both = tru_present.unsqueeze(-1) & est_present.unsqueeze(-2)
    size = torch.maximum(tru_present.sum(-1), est_present.sum(-1))

    # min over the pairings of the smaller set of sum u^p (u cut at 1), each point of the larger one left
    # over costing 1: one assignment of u^p - 1 (<= 0; 0 for an absent point)
    *batch, N, K = u.shape
    R = math.prod(batch)  # (spelled out: reshape(-1, ...) is ambiguous for a set of no point)
    flat_u, flat_both, flat_size = u.reshape(R, N, K), both.reshape(R, N, K), size.reshape(R)

    def pieces(assigned: Tensor, index):  # the pairs, their u (cut at 1), the points of the larger set left
        uu, bb, n = ((flat_u, flat_both, flat_size) if index is None
                     else (flat_u[index], flat_both[index], flat_size[index]))
        paired, up = _pairs(assigned, uu, bb)
        return paired, up, n - paired.sum(-1)

    pairs, up, rest = pieces(_best_assignment(flat_u, flat_both, flat_both, p, pieces, 1.0), None)
    m, G = _objective(up, pairs, p, rest, 1.0)
    m, G = m.reshape(batch), G.reshape(batch)
    zero = torch.zeros((), dtype=u.dtype, device=u.device)
    return torch.where(size > 0, c * m * (G / size.clamp_min(1).to(u.dtype)).pow(1.0 / p), zero)

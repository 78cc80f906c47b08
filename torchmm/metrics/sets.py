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
        distance to the ``p``; ``distance = (localisation + missed + false)^(1/p)``), and ``"assigned"``
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
    *batch, N, K = distance.shape
    half = c**p / 2
    zero = torch.zeros((), dtype=distance.dtype, device=distance.device)
    # GOSPA^p = c^p/2 (|X| + |Y|) + min over partial assignments of sum (d^p - c^p) over pairs closer than c:
    # one assignment of the N x K matrix min(d^p - c^p, 0) (0 for an absent point: never an assigned pair)
    both = tru_present.unsqueeze(-1) & est_present.unsqueeze(-2)
    gain = torch.where(both, distance.pow(p) - c**p, zero)
    assigned = unchecked(linear_assignment)(gain)  # (*B, N): an estimate per truth, -1 where none (N > K)
    pick = assigned.clamp(0, max(K - 1, 0))
    if K:
        d = distance.gather(-1, pick.unsqueeze(-1)).squeeze(-1)
        matched = (assigned >= 0) & tru_present & est_present.gather(-1, pick) & (d < c)
        localisation = torch.where(matched, d.pow(p), zero).sum(-1)
    else:
        matched = torch.zeros_like(tru_present)
        localisation = torch.zeros(batch, dtype=distance.dtype, device=distance.device)
    count = matched.sum(-1)
    missed = half * (tru_present.sum(-1) - count).to(distance.dtype)
    false = half * (est_present.sum(-1) - count).to(distance.dtype)
    return {"distance": (localisation + missed + false).pow(1.0 / p), "localisation": localisation,
            "missed": missed, "false": false, "assigned": torch.where(matched, assigned, -1)}


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
    *batch, N, K = distance.shape
    zero = torch.zeros((), dtype=distance.dtype, device=distance.device)
    # min over the pairings of the smaller set of sum min(d, c)^p: one assignment of min(d, c)^p - c^p
    # (<= 0; 0 for an absent point); the figure from the pairs it makes, the rest at c^p each
    both = tru_present.unsqueeze(-1) & est_present.unsqueeze(-2)
    assigned = unchecked(linear_assignment)(torch.where(both, distance.pow(p) - c**p, zero))
    pick = assigned.clamp(0, max(K - 1, 0))
    if K:
        paired = (assigned >= 0) & tru_present & est_present.gather(-1, pick)
        d = distance.gather(-1, pick.unsqueeze(-1)).squeeze(-1)
        local = torch.where(paired, d.pow(p), zero).sum(-1)
        pairs = paired.sum(-1)
    else:
        local = torch.zeros(batch, dtype=distance.dtype, device=distance.device)
        pairs = torch.zeros(batch, dtype=torch.long, device=distance.device)
    size = torch.maximum(tru_present.sum(-1), est_present.sum(-1))
    total = local + c**p * (size - pairs).to(distance.dtype)
    return torch.where(size > 0, (total / size.clamp_min(1).to(total.dtype)).pow(1.0 / p), zero)

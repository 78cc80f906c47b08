r"""Joint probabilistic data association (JPDA; Fortmann, Bar-Shalom & Scheffe, IEEE J. Oceanic Eng.
8(3), 1983) over any Gaussian filter of the contract: ``N`` tracks of a run share each scan.

Every track's update is run for every detection at once and gated as in :mod:`torchmm.association.pda`.
With ``w_ij = P_D N(nu_ij; 0, S_i) / lambda`` for detection ``j`` validated by track ``i`` (0 otherwise)
and ``m = 1 - P_D P_G`` for a missed detection, a *joint event* assigns each track at most one
detection and each detection at most one track; its weight is the product of its tracks' ``w_ij``
(assigned) and ``m`` (missed). The association probability ``beta_ij`` is the total weight of the
events that give detection ``j`` to track ``i``, over the total ``Z`` of all events; each track's
posterior is the PDA collapse with its ``beta_i0 .. beta_iD``.

``method="exact"`` sums over every joint event with a dynamic programme over the detections whose
state is the set of tracks already assigned (``2^N`` states): a forward pass, and a backward pass
that forms the marginals, in the log domain. Cost ``O(D' N 2^N)`` a run and scan, memory ``O(D'
2^N)``, ``D'`` the detections validated by some track (on the CPU the others are dropped first; on
other devices ``D' = D``, without a host read). Exact, for up to ``max_targets`` (default 12) tracks.

``method="lbp"`` approximates the marginals by loopy belief propagation between tracks and
detections (Williams & Lau, IEEE TAES 50(4), 2014): messages ``mu_ij = w_ij / (m + sum_{j' != j} w_ij'
nu_j'i)`` and ``nu_ji = 1 / (1 + sum_{i' != i} mu_i'j)``, then ``beta_ij ∝ w_ij nu_ji``, ``beta_i0 ∝ m``.
Cost ``O(iterations N D)`` a run and scan; exact when no detection is validated by two tracks. With
``m = 0`` (``P_D P_G = 1``: every track takes a detection) the messages are their ``m -> 0`` limit (a track
left one detection sends it ``mu = inf``); where tracks share detections that limit can be far more confident
than the exact marginals (two tracks, two detections, ``w = [[1, 0.5], [0.5, 1]]``: 1 against 0.8;
tests/test_sure_detection.py).

``method="kbest"`` sums over the ``k`` most likely joint events only (Murty's k best assignments of the
``N x (D + N)`` costs ``-log w_ij`` and, on track ``i``'s own column ``D + i``, ``-log m``:
:func:`torchmm.assignment.k_best_assignments`), for many targets: ``beta_ij`` and ``Z`` as above over
those events (``Z`` a lower bound of the exact one; with ``k`` at least the number of events, exact JPDA).
Cost a Murty round per event; the event weights are differentiable in the ``w_ij`` (the events are
chosen without gradient).

The log-likelihood of a scan is ``log Z`` (``method="exact"``, ``"kbest"``): the joint target hypothesis against "every
detection is clutter" (with one track, the PDA's). With ``"lbp"`` it is the sum over tracks of each
track's PDA log-likelihood, which equals ``log Z`` when no detection is validated by two tracks; with
``m = 0`` it is ``-inf`` where no joint event has weight (fewer detections than tracks, say), as ``log Z`` is.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.assignment import k_best_assignments, linear_assignment
from torchmm.association.pda import (
    DetectionSets,
    check_detections,
    check_gaussian,
    detection_hypotheses,
    missed_hypothesis,
    missed_log_weight,
    mix_hypotheses,
    set_association,
)
from torchmm.beliefs import GaussianBelief
from torchmm.contract import Choice, Int, Of, Real, Sets, entry_point, unchecked
from torchmm.filters.base import Filter, StepOutput
from torchmm.runtime import host_reads_ok
from torchmm.validation import check_filter_dtype

__all__ = ["GNN", "JPDA", "jpda_marginals"]


def flat_runs(t: Tensor, event: int) -> Tensor:
    """``t (*R, ...)`` with its leading axes (all but the last ``event``) as one, ``(prod R, ...)``: a
    reshape with the sizes spelled out, valid when some size is 0 (``reshape(-1, ...)`` is ambiguous
    for a tensor of no elements: an empty scan, no runs)."""
    return t.reshape(math.prod(t.shape[:t.dim() - event]), *t.shape[t.dim() - event:])


def exact_marginals(log_w: Tensor, log_missed: float | Tensor) -> tuple[Tensor, Tensor]:
    """Exact JPDA marginals. ``log_w (R, N, D)`` -> ``log beta (R, N, 1 + D)`` (missed first), ``log Z (R,)``.
    ``log_missed``: one number, or ``(R, N)`` a weight per track (JIPDA: ``1 - P_D P_G chi_i``).

    The dynamic programme over detections ``j`` with state ``S`` (the tracks assigned already), on
    ``(R, 2^N)`` tables indexed by the bits of ``S``: viewed as ``(R, 2^(N-1-i), 2, 2^i)``, the middle
    axis is track ``i``'s bit, so assigning track ``i`` moves its 0-slice to its 1-slice (no gather).
    Linear domain, the weights relative to a missed detection, each table rescaled to a maximum of 1
    per run with its log-scale kept.
    """
    R, N, D = log_w.shape
    dtype, device = log_w.dtype, log_w.device
    K = 1 << N
    tiny = torch.finfo(dtype).tiny
    if isinstance(log_missed, Tensor):  # per track: M(S) = prod_{i not in S} m_i, rescaled to a maximum of 1
        bits = (torch.arange(K, device=device).unsqueeze(-1) >> torch.arange(N, device=device)) & 1 == 1
        zero = torch.zeros((), dtype=dtype, device=device)
        log_M = torch.where(bits, zero, log_missed.unsqueeze(-2)).sum(-1)  # (R, K)
        offset = log_M.amax(-1)
        w, M = log_w.exp(), (log_M - offset.unsqueeze(-1)).exp()
    elif log_missed > -math.inf:  # w / m: a missed track weighs 1; Z = m^N sum_S F_D(S)
        w, offset = (log_w - log_missed).exp(), N * log_missed
        M = torch.ones(K, dtype=dtype, device=device)
    else:  # m = 0: only events that assign every track
        w, offset = log_w.exp(), 0.0
        M = torch.zeros(K, dtype=dtype, device=device)
        M[K - 1:].fill_(1.0)

    def views(t: Tensor, i: int) -> tuple[Tensor, Tensor]:  # S without / with track i
        v = t.view(R, -1, 2, 1 << i)
        return v[:, :, 0, :], v[:, :, 1, :]

    F = torch.zeros(R, K, dtype=dtype, device=device)
    F[:, :1].fill_(1.0)
    log_f = torch.zeros(R, dtype=dtype, device=device)  # F_j = F~_j exp(log_f)
    forward = []
    for j in range(D):  # F_{j+1}(S) = F_j(S) + sum_{i in S} w_ij F_j(S - i)
        forward.append((F, log_f))
        new = F.clone()
        for i in range(N):
            views(new, i)[1].add_(w[:, i, j, None, None] * views(F, i)[0])
        top = new.amax(-1, keepdim=True).clamp_min(tiny)
        F, log_f = new / top, log_f + top[:, 0].log()
    end = F * M
    total = end.sum(-1)
    log_total = total.log()
    log_z = log_total + log_f + offset
    missed = torch.stack([views(end, i)[0].sum((-2, -1)) for i in range(N)], -1).log() - log_total.unsqueeze(-1)
    G = M.expand(R, K)  # G_D(S) = M(S); G_j(S) = G_{j+1}(S) + sum_{i not in S} w_ij G_{j+1}(S + i)
    log_g = torch.zeros(R, dtype=dtype, device=device)
    detected = []
    for j in range(D - 1, -1, -1):
        Fj, log_fj = forward[j]
        pair = torch.stack([(views(Fj, i)[0] * views(G, i)[1]).sum((-2, -1)) for i in range(N)], -1)  # (R, N)
        detected.append((pair * w[:, :, j]).log() + (log_fj + log_g - log_f - log_total).unsqueeze(-1))
        new = G.clone()
        for i in range(N):
            views(new, i)[0].add_(w[:, i, j, None, None] * views(G, i)[1])
        top = new.amax(-1, keepdim=True).clamp_min(tiny)
        G, log_g = new / top, log_g + top[:, 0].log()
    log_detected = torch.stack(detected[::-1], -1) if D else log_w[:, :, :0]
    return torch.cat([missed.unsqueeze(-1), log_detected], -1), log_z


def others_sum(x: Tensor, dim: int) -> Tensor:
    """The sum of ``x >= 0`` along ``dim`` of every entry but each one's own, accurate where one entry dwarfs
    the others or is ``inf`` (``sum - x`` would lose the others or give ``inf - inf``): the sum without one
    largest entry ``M``, plus ``M - x`` for every entry but one equal to ``M``."""
    top, where_top = x.max(dim, keepdim=True)
    index = torch.arange(x.shape[dim], device=x.device).view(-1, *[1] * (x.dim() - 1 - dim % x.dim()))
    first = index == where_top
    rest = torch.where(first, 0.0, x).sum(dim, keepdim=True)  # the sum without one largest entry
    return rest + torch.where(x == top, 0.0, top - x)


def lbp_marginals(log_w: Tensor, log_missed: float | Tensor, iterations: int, tolerance: float,
                  missed_may_vanish: bool | None = None) -> Tensor:
    """Loopy belief propagation (Williams & Lau 2014). ``log_w (R, N, D)`` -> ``log beta (R, N, 1 + D)``.
    ``log_missed``: one number, or ``(R, N)`` a weight per track (JIPDA: ``1 - P_D P_G chi_i``).

    Each track's row ``(m_i, w_i1 .. w_iD)`` is scaled to a largest entry of 1 (the messages do not change).
    A missed weight ``m_i = 0`` (``P_D P_G = 1``: the track must take a detection) is allowed: a track
    left with one detection sends it ``mu = inf``, which tells that detection's other tracks ``nu = 0``
    (the ``m -> 0`` limit of the messages; ``w_ij = 0`` sends ``mu = 0``). Then (``missed_may_vanish``;
    by default where ``log_missed`` is ``-inf`` or a tensor) the sums over the other tracks and detections
    are :func:`others_sum`'s, exact with ``inf`` and dominant terms; otherwise ``sum - own``."""
    R, N, D = log_w.shape
    if missed_may_vanish is None:
        missed_may_vanish = isinstance(log_missed, Tensor) or log_missed == -math.inf
    if not isinstance(log_missed, Tensor):
        log_missed = log_w.new_full((R, N), log_missed)
    scale = torch.maximum(log_w.amax(-1), log_missed) if D else log_missed
    scale = torch.where(torch.isfinite(scale), scale, 0.0)  # (a row of no weight: 0; NaN stays NaN)
    log_w, log_missed = log_w - scale.unsqueeze(-1), log_missed - scale
    w, miss = log_w.exp(), log_missed.exp().unsqueeze(-1)  # (R, N, D), (R, N, 1)
    others = others_sum if missed_may_vanish else (lambda x, dim: x.sum(dim, keepdim=True) - x)
    valid = w > 0
    nu = torch.ones_like(w)  # detection -> track messages
    early = host_reads_ok(w)
    for _ in range(iterations):
        denominator = miss + others(w * nu, -1)
        if missed_may_vanish:  # (0 / 0 -> 0: an unvalidated detection; w / 0 -> inf)
            mu = torch.where(valid, w / torch.where(valid, denominator, 1.0), 0.0)
        else:
            mu = w / denominator  # track -> detection
        new = 1.0 / (1.0 + others(mu, -2))
        if early and bool(((new - nu).abs() <= tolerance * new).all()):
            nu = new
            break
        nu = new
    # normalised in the log domain: a weight of 0 (an unvalidated detection) has log-marginal -inf with
    # gradient 0, where log(num / sum) would give it a NaN gradient
    log_num = torch.cat([log_missed.unsqueeze(-1), log_w + nu.log()], -1)
    return torch.log_softmax(log_num, -1)


def lbp_log_likelihood(log_w: Tensor, log_missed: float | Tensor,
                       missed_may_vanish: bool | None = None) -> Tensor:
    """The loopy-belief-propagation JPDA's log-likelihood ``(R,)`` of ``log_w (R, N, D)``: the sum over
    tracks of each one's PDA log-likelihood ``log(m_i + sum_j w_ij)``. Where a missed weight can vanish
    (``missed_may_vanish``, as for :func:`lbp_marginals`) it is ``-inf`` for a run with no joint event of
    weight (sure tracks that cannot all take a detection: an impossible scan, as the exact method finds
    it), by one batched assignment that takes as few forbidden pairs as it can."""
    R, N, D = log_w.shape
    if missed_may_vanish is None:
        missed_may_vanish = isinstance(log_missed, Tensor) or log_missed == -math.inf
    if not isinstance(log_missed, Tensor):
        log_missed = log_w.new_full((R, N), log_missed)
    log_z = torch.logsumexp(torch.cat([log_missed.unsqueeze(-1), log_w], -1), -1).sum(-1)
    if not missed_may_vanish or N == 0:
        return log_z
    own = torch.eye(N, dtype=torch.bool, device=log_w.device)
    own_miss = own & (log_missed > -math.inf).unsqueeze(-1)
    allowed = torch.cat([log_w > -math.inf, own_miss], -1)  # (R, N, D + N)
    col = unchecked(linear_assignment)((~allowed).to(log_w.dtype))  # (every track a column: N <= D + N)
    some_event = allowed.gather(-1, col.unsqueeze(-1)).all(-2).squeeze(-1)
    return torch.where(some_event | torch.isnan(log_z), log_z, -math.inf)


def kbest_events(log_w: Tensor, log_missed: float | Tensor, k: int) -> tuple[Tensor, Tensor]:
    """The ``k`` most likely joint events of ``log_w (R, N, D)``: ``columns (R, k, N)`` (0: missed,
    ``1 + j``: detection ``j``) and their log-weights ``(R, k)`` (``-inf`` past the last feasible one).
    ``log_missed``: one number or ``(R, N)``. The events are the k best assignments of the ``N x (D + N)``
    costs (track ``i``'s own column ``D + i`` its miss); their log-weights are re-gathered from ``log_w``
    so that they carry its gradient."""
    R, N, D = log_w.shape
    dtype, device = log_w.dtype, log_w.device
    own = torch.eye(N, dtype=torch.bool, device=device)
    log_m = log_missed if isinstance(log_missed, Tensor) else torch.full((R, N), log_missed, dtype=dtype, device=device)
    neg_inf = torch.full((), -math.inf, dtype=dtype, device=device)
    gain = torch.cat([log_w, torch.where(own, log_m.unsqueeze(-1), neg_inf)], -1)  # (R, N, D + N)
    cost = torch.where(torch.isfinite(gain), -gain.detach(), math.inf)
    cost = torch.where(torch.isnan(cost), math.inf, cost)  # (a failed track: no pair; its run is NaN below)
    events, _ = unchecked(k_best_assignments)(cost, k)  # (R, k, N); -1 past the last
    feasible = (events >= 0).all(-1)  # (R, k)
    taken = gain.unsqueeze(1).expand(R, k, N, D + N).gather(-1, events.clamp_min(0).unsqueeze(-1)).squeeze(-1)
    log_e = torch.where(feasible, taken.sum(-1), neg_inf)  # (R, k) each event's log-weight
    log_e = log_e + torch.where(torch.isnan(log_w).any(-1).any(-1), torch.nan, 0.0).unsqueeze(-1)
    columns = torch.where(events >= D, 0, events + 1).clamp_min(0)
    return columns, log_e


def kbest_marginals(log_w: Tensor, log_missed: float | Tensor, k: int) -> tuple[Tensor, Tensor]:
    """JPDA marginals over the ``k`` most likely joint events (:func:`kbest_events`). ``log_w (R, N, D)``
    -> ``log beta (R, N, 1 + D)`` (missed first), ``log Z (R,)`` (over those events; ``-inf`` where none
    has weight, NaN for a failed run)."""
    R, N, D = log_w.shape
    dtype, device = log_w.dtype, log_w.device
    columns, log_e = kbest_events(log_w, log_missed, k)
    log_z = torch.logsumexp(log_e, -1)
    zero = torch.zeros((), dtype=dtype, device=device)
    p = torch.where(torch.isfinite(log_e), (log_e - log_z.unsqueeze(-1)).exp(), zero)
    p = torch.where(torch.isneginf(log_z).unsqueeze(-1), zero, p)
    onehot = (columns.unsqueeze(-1) == torch.arange(1 + D, device=device)).to(dtype)  # (R, k, N, 1 + D)
    return (p[..., None, None] * onehot).sum(1).log(), log_z


@entry_point(log_weights=Sets(axis=-1, missing=-math.inf, floating=True), missed=Real(minimum=0.0),
             method=Choice("exact", "lbp", "kbest"), iterations=Int(1), tolerance=Real(minimum=0.0), k=Int(1))
def jpda_marginals(log_weights: Tensor, missed: float, *, method: str = "exact", iterations: int = 100,
                   tolerance: float = 1e-13, k: int = 100) -> tuple[Tensor, Tensor | None]:
    r"""JPDA association probabilities from single-target log-weights.

    Args:
        log_weights: ``(*B, N, D)`` ``log w_ij``, floating point (an integer tensor is a ``TypeError``;
            ``-inf``: detection ``j`` not validated by track ``i``; ``D = 0``: no detection, the same
            marginals ``beta_i0`` and ``Z`` as ``D`` columns of ``-inf``).
        missed: ``m``, the weight of a missed detection (``1 - P_D P_G``; 0: every track is detected).
        method: ``"exact"`` (every joint event), ``"lbp"`` (loopy belief propagation) or ``"kbest"``
            (the ``k`` most likely joint events).
        iterations, tolerance: the belief propagation's most iterations and relative tolerance (on
            the CPU it stops when every message moved less; elsewhere it runs every iteration).
        k: the events of ``"kbest"``.

    Returns:
        ``log beta (*B, N, 1 + D)`` (missed first; each track's sum to one) and ``log Z (*B,)``
        (``None`` for ``"lbp"``; for ``"kbest"`` over its events).

    Examples:
        >>> log_w = torch.tensor([[[0.0, -1.0], [-1.0, 0.0]]])  # two tracks, two detections
        >>> log_beta, log_z = jpda_marginals(log_w, 0.1)
        >>> log_beta.exp().sum(-1)
        tensor([[1.0000, 1.0000]])
    """
    if log_weights.dim() < 2:
        raise ValueError(f"log_weights: expected (*B, N, D), got shape {tuple(log_weights.shape)}")
    *batch, N, D = log_weights.shape
    flat = flat_runs(log_weights, 2)
    log_missed = math.log(missed) if missed > 0 else -math.inf
    if method == "lbp":
        return lbp_marginals(flat, log_missed, iterations, tolerance).reshape(*batch, N, 1 + D), None
    if method == "kbest":
        log_beta, log_z = kbest_marginals(flat, log_missed, k)
        return log_beta.reshape(*batch, N, 1 + D), log_z.reshape(batch)
    log_beta, log_z = exact_marginals(flat, log_missed)
    return log_beta.reshape(*batch, N, 1 + D), log_z.reshape(batch)


def check_scan(assoc, batch: torch.Size, z: Tensor, dtype: torch.dtype) -> Tensor:
    """A joint association's checks: the belief's ``batch`` ends with the run's tracks (at most
    ``max_targets`` for the exact method) and ``z (*B, D, m)`` (real; ``D`` may be 0) broadcasts to the
    runs; returns ``z`` expanded to ``(*runs, D, m)`` in ``dtype``."""
    name = type(assoc).__name__
    if len(batch) < 1:
        raise ValueError(f"belief: {name} needs a batch whose last axis holds the tracks, (*B, N); got none")
    *runs, N = batch
    if assoc.method == "exact" and N > assoc.max_targets:
        raise ValueError(f"belief: {N} tracks a run exceed max_targets={assoc.max_targets} of the exact JPDA "
                         f"(cost 2^N); use method='lbp' or raise max_targets")
    return check_detections(z, assoc.detections_dim, torch.Size(runs), dtype, tracks=batch)


class JPDA(DetectionSets):
    r"""Joint probabilistic data association over a Gaussian filter: the belief's last batch axis holds
    a run's ``N`` tracks, which share each scan (the module docstring gives the equations).

    Args:
        filter: a filter whose belief is a :class:`~torchmm.GaussianBelief` (Kalman, extended or
            unscented), or an IMM over such filters: the IMM-JPDAF (Blom & Bloem, IEEE TAC 45(2),
            2000), as for :class:`~torchmm.association.PDA`; its ``predict`` is used as it is, its
            ``update`` once per track and detection.
        detection_probability: ``P_D`` in (0, 1].
        clutter_density: ``lambda`` > 0, false detections per unit volume of measurement space.
        gate_probability: ``P_G`` in (0, 1] (default 0.99; 1: no gate).
        method: ``"exact"`` (default; every joint event, up to ``max_targets`` tracks), ``"lbp"``
            (loopy belief propagation, any number) or ``"kbest"`` (the ``k`` most likely joint events,
            any number: Murty's k best assignments).
        max_targets: the most tracks ``"exact"`` takes (its cost grows as ``2^N``).
        iterations, tolerance: the belief propagation's (``"lbp"``).
        k: the joint events of ``"kbest"`` (default 100; at least the number of events: exact JPDA).

    Shapes:
        belief: :class:`~torchmm.GaussianBelief` (or the IMM's ``ModeBelief``) with batch ``(*B, N)``;
        ``z``: ``(*B, D, m)``, one scan per run (a row with a non-finite entry is no detection).
        ``log_likelihood`` ``(*B, N)``: the run's ``log Z`` for each of its tracks. ``extras``: ``"association"`` ``(*B, N, 1 + D)`` the
        ``beta_i0 .. beta_iD`` (missed first), ``"validated"`` ``(*B, N, D)`` bool, ``"failed"``
        ``(*B, N)`` bool: the run's update was not finite (a track's NaN prediction fails every track
        of its run, the association being joint), its weights and posteriors NaN.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> jpda = JPDA(KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0)),
        ...             detection_probability=0.9, clutter_density=0.01)
        >>> tracks = GaussianBelief(torch.tensor([[0.0, 0.0], [3.0, 0.0]]), torch.eye(2))  # N = 2
        >>> scan = torch.tensor([[0.2], [2.5], [float("nan")]])  # D = 3
        >>> out = jpda.update(tracks, scan)
        >>> out.belief.mean.shape, out.extras["association"].shape
        (torch.Size([2, 2]), torch.Size([2, 4]))
    """

    joint = True

    @entry_point(filter=Of(Filter), detection_probability=Real(0.0, 1.0), clutter_density=Real(positive=True),
                 gate_probability=Real(0.0, 1.0), method=Choice("exact", "lbp", "kbest"), max_targets=Int(1),
                 iterations=Int(1), tolerance=Real(minimum=0.0), k=Int(1))
    def __init__(self, filter: Filter, *, detection_probability: float, clutter_density: float,
                 gate_probability: float = 0.99, method: str = "exact", max_targets: int = 12,
                 iterations: int = 100, tolerance: float = 1e-13, k: int = 100):
        super().__init__()
        set_association(self, filter, detection_probability, clutter_density, gate_probability)
        self.method, self.max_targets = method, int(max_targets)
        self.iterations, self.tolerance = int(iterations), float(tolerance)
        self.k = int(k)

    def update(self, belief: GaussianBelief, z: Tensor) -> StepOutput:
        hyp, validated, log_w, S, singular = self._scan(belief, z)
        weights, log_z = self._weights(log_w, validated, missed_log_weight(self))
        return self._finish(belief, hyp, validated, weights, log_z, S, singular)

    def _scan(self, belief: GaussianBelief, z: Tensor) -> tuple[StepOutput, Tensor, Tensor, Tensor, Tensor]:
        """Checks; every track's update for every detection (batch ``(D, *B, N)``), ``validated`` and the
        log-weights ``log(P_D N / lambda)`` ``(*B, N, D)``, the tracks' innovation covariances and
        ``singular (*B, N)`` (:func:`~torchmm.association.pda.detection_hypotheses`)."""
        check_gaussian(belief, type(self).__name__)
        z = check_scan(self, belief.batch_shape, z, belief.dtype)
        check_filter_dtype(self.filter, belief, "belief")
        *runs, N = belief.batch_shape
        D, m = z.shape[-2:]
        hyp, validated, log_detected, S, singular = detection_hypotheses(
            self, belief, z.unsqueeze(-3).expand(*runs, N, D, m))
        return hyp, validated.movedim(0, -1), log_detected.movedim(0, -1), S, singular

    def _finish(self, belief, hyp: StepOutput, validated: Tensor, weights: Tensor, log_z: Tensor, S: Tensor,
                singular: Tensor) -> StepOutput:
        """The collapse with ``weights (*B, N, 1 + D)``; an impossible scan keeps the priors, a failed
        run (a NaN ``log_z``, or a track of it ``singular``: no gate) is NaN."""
        *runs, N, D = validated.shape
        log_z = torch.where(singular.any(-1), torch.nan, log_z)  # one track without a gate fails the joint event
        # an impossible scan (no joint event has weight): likelihood 0, every track keeps its prior
        impossible = torch.isneginf(log_z)[..., None, None]
        weights = torch.where(impossible, (torch.arange(D + 1, device=weights.device) == 0).to(weights.dtype), weights)
        failed = torch.isnan(log_z)[..., None].expand(*runs, N)
        weights = torch.where(failed.unsqueeze(-1), torch.nan, weights)
        posterior, combined = mix_hypotheses(missed_hypothesis(self, belief, hyp), hyp, weights)
        return StepOutput(posterior, belief, log_z[..., None].expand(*runs, N), combined, S,
                          {"association": weights, "validated": validated, "failed": failed})

    def _weights(self, log_w: Tensor, validated: Tensor, log_missed: float) -> tuple[Tensor, Tensor]:
        """The association weights ``(*B, N, 1 + D)`` and the run's log-likelihood ``(*B,)``."""
        *runs, N, D = log_w.shape
        if self.method == "exact":
            log_beta, log_z = self._exact(log_w, validated, log_missed)
        elif self.method == "kbest":
            log_beta, log_z = kbest_marginals(flat_runs(log_w, 2), log_missed, self.k)
            log_beta, log_z = log_beta.reshape(*runs, N, 1 + D), log_z.reshape(runs)
        else:
            log_beta = lbp_marginals(flat_runs(log_w, 2), log_missed, self.iterations,
                                      self.tolerance).reshape(*runs, N, 1 + D)
            log_z = lbp_log_likelihood(flat_runs(log_w, 2), log_missed).reshape(runs)
        return log_beta.exp(), log_z

    def _exact(self, log_w: Tensor, validated: Tensor, log_missed: float) -> tuple[Tensor, Tensor]:
        """The exact marginals; on the CPU over the detections some track validated only (a host read)."""
        *runs, N, D = log_w.shape
        flat = flat_runs(log_w, 2)
        if not host_reads_ok(log_w) or D == 0 or flat.shape[0] == 0:
            log_beta, log_z = exact_marginals(flat, log_missed)
            return log_beta.reshape(*runs, N, 1 + D), log_z.reshape(runs)
        used = flat_runs(validated, 2).any(-2)  # (R, D)
        order = torch.argsort((~used).to(torch.int8), dim=-1, stable=True)  # the used detections first
        keep = int(used.sum(-1).max())
        index = order[:, :keep].unsqueeze(-2).expand(-1, N, keep)
        log_beta_kept, log_z = exact_marginals(flat.gather(-1, index), log_missed)
        log_beta = torch.full((flat.shape[0], N, 1 + D), -math.inf, dtype=log_w.dtype, device=log_w.device)
        log_beta[..., :1] = log_beta_kept[..., :1]
        log_beta[..., 1:] = log_beta[..., 1:].scatter(-1, index, log_beta_kept[..., 1:])
        return log_beta.reshape(*runs, N, 1 + D), log_z.reshape(runs)


class GNN(JPDA):
    r"""Global nearest neighbour: each scan, the single most likely joint event (each track at most one
    detection, each detection at most one track; the largest product of the ``w_ij`` of
    :class:`JPDA` and ``m`` for the tracks left without one), and every track updated with its
    detection alone (or not at all). The best event is one batched assignment
    (:func:`torchmm.assignment.linear_assignment`) of the ``N x (D + N)`` costs ``-log w_ij`` and, on
    track ``i``'s own column ``D + i``, ``-log m``; gated-out pairs are forbidden.

    Args:
        filter, detection_probability, clutter_density, gate_probability: as for :class:`JPDA`.

    The shapes are :class:`JPDA`'s. ``extras["association"]`` is one-hot (``1`` at the detection taken, or at 0 for none), and
    the log-likelihood, the same for every track of a run, is the best event's ``log`` weight against
    "all clutter" (``-inf`` where none has weight).

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> gnn = GNN(KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0)),
        ...           detection_probability=0.9, clutter_density=0.01)
        >>> tracks = GaussianBelief(torch.tensor([[0.0, 0.0], [3.0, 0.0]]), torch.eye(2))
        >>> out = gnn.update(tracks, torch.tensor([[0.2], [2.5], [float("nan")]]))
        >>> out.extras["association"].argmax(-1)  # track 0 took detection 1, track 1 detection 2
        tensor([1, 2])
    """

    @entry_point(filter=Of(Filter), detection_probability=Real(0.0, 1.0), clutter_density=Real(positive=True),
                 gate_probability=Real(0.0, 1.0))
    def __init__(self, filter: Filter, *, detection_probability: float, clutter_density: float,
                 gate_probability: float = 0.99):
        super().__init__(filter, detection_probability=detection_probability, clutter_density=clutter_density,
                         gate_probability=gate_probability)
        self.method = "assignment"  # (no exact programme: no limit on the tracks)

    def _weights(self, log_w: Tensor, validated: Tensor, log_missed: float) -> tuple[Tensor, Tensor]:
        *runs, N, D = log_w.shape
        dtype, device = log_w.dtype, log_w.device
        own = torch.eye(N, dtype=torch.bool, device=device)
        log_m = torch.full((), log_missed, dtype=dtype, device=device)
        neg_inf = torch.full((), -math.inf, dtype=dtype, device=device)
        gain = torch.cat([log_w, torch.where(own, log_m, neg_inf).expand(*runs, N, N)], -1)  # (*B, N, D + N)
        allowed = torch.isfinite(gain)
        # forbidden pairs cost more than any whole assignment of allowed ones (a finite matrix to solve)
        finite = torch.where(allowed, gain, torch.zeros((), dtype=dtype, device=device))
        big = (finite.abs().amax((-2, -1), keepdim=True) + 1) * (2 * N + 1)
        cost = torch.where(allowed, -gain, big).nan_to_num(nan=0.0)
        col = unchecked(linear_assignment)(cost)  # (*B, N): every track a column (N <= D + N)
        taken = allowed.gather(-1, col.unsqueeze(-1)).squeeze(-1) & (col < D)  # a detection in its gate
        index = torch.where(taken, col + 1, torch.zeros_like(col))  # 0: missed
        weights = (torch.arange(D + 1, device=device) == index.unsqueeze(-1)).to(dtype)
        chosen = torch.where(taken, log_w.gather(-1, col.clamp(max=max(D - 1, 0)).unsqueeze(-1)).squeeze(-1)
                             if D else log_m.expand(*runs, N), log_m)
        log_z = chosen.sum(-1) + torch.where(torch.isnan(log_w).any(-1).any(-1), torch.nan, 0.0)
        return weights, log_z

r"""Multiple hypothesis tracking that starts, confirms and deletes its own tracks (Reid, IEEE TAC 24(6), 1979:
new targets and false alarms as hypotheses), in the hypothesis-oriented form of :class:`~torchmm.association.MHT`
over a fixed table of ``K`` track slots per hypothesis (docs/tracking.md, "MHT that starts its own tracks").

Each scan, in every hypothesis, a detection is a track's, a **new target's** or clutter. With the track
weights ``w_ij = P_D N(nu_ij; 0, S_i) / lambda`` of :class:`~torchmm.association.JPDA` (``lambda`` the clutter
density), a track's miss ``m_i = 1 - P_D P_G``, and a new target's weight ``b = beta_NT / lambda``
(``beta_NT``, ``birth_density``: the density of new targets' first detections a scan, a unit volume), a joint
event weighs the product of its ``w_ij``, its tracks' misses and ``b`` for each new target (clutter: 1).
These events are Murty's k best assignments of the tracks and one "new target" row per detection (row
``K + j`` takes detection ``j`` alone, weight ``b``, or nothing, weight 1) against the detections
(:func:`~torchmm.assignment.k_best_assignments`); the ``H`` best children are kept as in ``MHT``. A free
slot takes no detection and pays no miss.

In each child, a new target's track starts in a free slot (its detections matched to the free slots by
rank, as :class:`~torchmm.association.ManagedTracks` does; past the ``K`` slots a new target is dropped) from
``initiate(z)``, with a new label (each hypothesis counts its labels up from 0); an IMM's new track starts
every mode from it with ``mode_probs``. A track is **confirmed** once ``M`` of its first ``N`` scans
(``m_of_n``) gave it a detection in its hypothesis, and kept confirmed; one unconfirmed after ``N`` scans,
or missed ``max_misses`` scans running, is deleted (its slot freed). The estimate is the best hypothesis's
slots (:meth:`TrackHypotheses.best`: a :class:`~torchmm.association.TrackTable`, its confirmed tracks with
their labels).

The scan's log-likelihood is ``log sum exp`` over the children of every kept hypothesis (against "all
clutter"). Special case (tests/test_mht_tracks.py): with no birth (``birth_density`` tiny) and the table
started from the tracks, it is :class:`~torchmm.association.MHT` (1e-12).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, ClassVar

import torch
import torch.utils._pytree as pytree
from torch import Tensor

from torchmm.association.jpda import kbest_events
from torchmm.association.mht import (
    MHT,
    HypothesisBelief,
    prepend_missed,
    children,
    normalise,
    pick_options,
    prune,
    shift_history,
    take_hypothesis,
)
from torchmm.association.pda import missed_hypothesis, missed_log_weight
from torchmm.association.tracks import ModeTrackTable, TrackTable
from torchmm.beliefs import GaussianBelief, ModeBelief, register_belief, where
from torchmm.contract import BeliefArg, DType, Device, Finite, Int, Of, Real, Shape, entry_point
from torchmm.filters.base import Filter, StepOutput
from torchmm.validation import check_filter_dtype, check_probabilities

__all__ = ["ManagedMHT", "TrackHypotheses"]


@register_belief
@dataclasses.dataclass(frozen=True)
class TrackHypotheses(HypothesisBelief):
    """``H`` global hypotheses of a run's ``K`` track slots and each slot's record.

    Shapes:
        log_weights ``(*B, H)``, history ``(*B, H, L, K)``, tracks (batch ``(*B, H * K)``) as
        :class:`~torchmm.association.HypothesisBelief`'s; alive / firm ``(*B, H, K)`` bool, label / age /
        hits / misses ``(*B, H, K)`` long, next_label ``(*B, H)`` long
    """

    alive: Tensor
    label: Tensor
    next_label: Tensor
    age: Tensor
    hits: Tensor
    misses: Tensor
    firm: Tensor
    score: Tensor
    peak: Tensor

    event_dims: ClassVar[dict[str, int]] = {"log_weights": 1, "history": 3, "alive": 2, "label": 2, "next_label": 1,
                                            "age": 2, "hits": 2, "misses": 2, "firm": 2, "score": 2, "peak": 2}

    def best_scores(self) -> Tensor:
        """``(*B, K)``: the best hypothesis's tracks' scores (log-likelihood ratios; 0 in a free slot)."""
        best = self.log_weights.argmax(-1)
        return torch.where(take_hypothesis(self.alive, best), take_hypothesis(self.score, best), 0.0)

    def best(self) -> TrackTable | ModeTrackTable:
        """The best hypothesis's slots as a track table, batch ``(*B, K)`` (a free slot: existence 0)."""
        best = self.log_weights.argmax(-1)  # (*B,)

        def pick(t: Tensor, e: int = 0) -> Tensor:
            return take_hypothesis(t, best)
        state = self.by_hypothesis().map_tensors(pick)
        alive = pick(self.alive)
        K = alive.shape[-1]
        log_e = torch.where(alive, 0.0, -math.inf).to(self.log_weights.dtype)
        record = (pick(self.age), pick(self.hits), pick(self.misses), pick(self.firm) & alive)
        next_label = pick(self.next_label).unsqueeze(-1).expand(*best.shape, K)
        label = torch.where(alive, pick(self.label), -1)
        if isinstance(state, ModeBelief):
            return ModeTrackTable(state.mode_log_probs, state.components, log_e, label, next_label, *record)
        return TrackTable(state.mean, state.cov, log_e, label, next_label, *record)

    def estimate(self) -> GaussianBelief:
        """The best hypothesis's slots' estimates, batch ``(*B, K)`` (free slots hold their last state)."""
        return self.best().estimate()


class ManagedMHT(MHT):
    r"""MHT with track initiation, confirmation and deletion (the module docstring's equations).

    Args:
        filter, detection_probability, clutter_density, gate_probability, hypotheses, k, n_scan: as for
            :class:`~torchmm.association.MHT` (``k`` default ``hypotheses``).
        capacity: ``K``, the track slots of a hypothesis.
        initiate: ``z (*B, D, m) -> GaussianBelief (*B, D, n)``, a new track's state from its detection
            (:func:`~torchmm.association.position_initiator`).
        birth_density: ``beta_NT`` > 0, new targets' first detections per unit volume a scan.
        m_of_n: ``(M, N)`` confirmation (default ``(2, 3)``; None: by score alone); max_misses: deletion
            after this many misses running (default 3; None: none).
        confirm_score: the track-oriented rule (MATLAB's ``trackerTOMHT``): a track is confirmed once its
            score (its log-likelihood ratio: ``log b`` at birth, then ``log w_ij`` of its detections and
            ``log m`` of its misses) reaches this; delete_drop: deleted once its score falls this far below
            its peak (default None: neither).
        mode_probs: an IMM's new track's mode probabilities (default equal).

    Shapes:
        belief: :class:`TrackHypotheses` (:meth:`initial_belief`: every slot free); ``z``: ``(*B, D, m)``.
        ``log_likelihood`` ``(*B,)``; ``extras``: ``"association"`` ``(*B, K, 1 + D)`` the best
        hypothesis's slots' detections (one-hot, missed first; a new track's its first detection),
        ``"failed"`` ``(*B,)``, ``"unstarted"`` ``(*B,)`` the best hypothesis's new targets left without a
        free slot (new targets take the free slots in detection order; capacity binds where above 0).

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> from torchmm.association import position_initiator
        >>> cv, sensor = ConstantVelocity(1, dtype=torch.float64), PositionMeasurement(2, [0], 1.0, dtype=torch.float64)
        >>> mht = ManagedMHT(KalmanFilter(cv, sensor),
        ...                  detection_probability=0.9, clutter_density=0.01, birth_density=0.001,
        ...                  hypotheses=4, capacity=3, initiate=position_initiator(2, [0], 1.0, 4.0))
        >>> b = mht.initial_belief((5,))  # 5 runs, no track
        >>> for z in ([[0.0], [7.0]], [[1.0], [7.1]], [[2.1], [7.0]]):
        ...     b = mht.step(b, torch.tensor(z, dtype=torch.float64).expand(5, 2, 1)).belief
        >>> b.best().confirmed().sum(-1)  # two tracks in every run, confirmed (2 of 3)
        tensor([2, 2, 2, 2, 2])
    """

    @entry_point(filter=Of(Filter), detection_probability=Real(0.0, 1.0), clutter_density=Real(positive=True),
                 gate_probability=Real(0.0, 1.0), hypotheses=Int(1), k=Int(1, optional=True), n_scan=Int(0),
                 capacity=Int(1), initiate=Of(object), birth_density=Real(positive=True),
                 m_of_n=Of((tuple, list), what="two integers (M, N)", optional=True), max_misses=Int(1, optional=True),
                 mode_probs=Finite(optional=True), confirm_score=Real(optional=True),
                 delete_drop=Real(positive=True, optional=True))
    def __init__(self, filter: Filter, *, detection_probability: float, clutter_density: float,
                 capacity: int, initiate: Callable, birth_density: float, gate_probability: float = 0.99,
                 hypotheses: int = 10, k: int | None = None, n_scan: int = 3, m_of_n=(2, 3),
                 max_misses: int | None = 3, mode_probs=None, confirm_score: float | None = None,
                 delete_drop: float | None = None):
        super().__init__(filter, detection_probability=detection_probability, clutter_density=clutter_density,
                         gate_probability=gate_probability, hypotheses=hypotheses, k=k, n_scan=n_scan)
        if not callable(initiate):
            raise TypeError(f"initiate: expected a function z -> GaussianBelief, got {type(initiate).__name__}")
        if m_of_n is None and confirm_score is None:
            raise ValueError("m_of_n: None needs confirm_score (a track is confirmed by one of the two rules)")
        if m_of_n is not None and (len(m_of_n) != 2 or not all(isinstance(v, int) and not isinstance(v, bool)
                                                              for v in m_of_n) or not 1 <= m_of_n[0] <= m_of_n[1]):
            raise ValueError(f"m_of_n: expected two integers (M, N) with 1 <= M <= N, got {m_of_n}")
        self.capacity, self.initiate = int(capacity), initiate
        self.birth_density = float(birth_density)
        self.m_of_n = None if m_of_n is None else (int(m_of_n[0]), int(m_of_n[1]))
        self.confirm_score = None if confirm_score is None else float(confirm_score)
        self.delete_drop = None if delete_drop is None else float(delete_drop)
        self.birth_log_weight = math.log(self.birth_density / self.clutter_density)
        self.max_misses = None if max_misses is None else int(max_misses)
        M = getattr(filter, "num_modes", None)
        self.num_modes = M
        if mode_probs is not None and M is None:
            raise ValueError(f"mode_probs: the filter ({type(filter).__name__}) has no modes")
        probs = None if M is None else (torch.full((M,), 1.0 / M, dtype=torch.float64) if mode_probs is None else
                                        check_probabilities(mode_probs, "mode_probs", M, dtype=torch.float64))
        if probs is not None and probs.shape != (M,):
            raise ValueError(f"mode_probs: expected the {M} modes' probabilities (M,), got {tuple(probs.shape)}")
        self.mode_log_probs = None if probs is None else probs.log()

    @property
    def _firm_at_birth(self) -> bool:
        return (self.m_of_n is not None and self.m_of_n[0] <= 1) or (
            self.confirm_score is not None and self.birth_log_weight >= self.confirm_score)

    def _started(self, state: GaussianBelief):
        """A new track's state: the Gaussian, or over an IMM every mode from it with ``mode_probs``."""
        if self.num_modes is None:
            return state
        batch = state.batch_shape
        probs = self.mode_log_probs.to(state.device, state.dtype).expand(*batch, self.num_modes)
        return ModeBelief(probs, state.unsqueeze(-1).expand(*batch, self.num_modes))

    @entry_point(batch_shape=Shape(), tracks=BeliefArg(optional=True, check=False), dtype=DType(), device=Device())
    def initial_belief(self, batch_shape=(), *, tracks: GaussianBelief | None = None, dtype=torch.float64,
                       device=None) -> TrackHypotheses:
        """One hypothesis (the others empty) of ``capacity`` slots, runs ``batch_shape``: every slot free,
        or, given ``tracks`` (a :class:`~torchmm.GaussianBelief` with batch ``(*B, N)``, ``N <= capacity``,
        its runs then the batch), the first ``N`` slots holding them, confirmed, labelled ``0 .. N - 1``."""
        n, K, H, L = self.state_dim, self.capacity, self.hypotheses, self.n_scan + 1
        if tracks is not None:
            if not isinstance(tracks, GaussianBelief) or len(tracks.batch_shape) < 1:
                raise TypeError("tracks: expected a GaussianBelief with batch (*B, N), the tracks last")
            check_filter_dtype(self, tracks, "tracks")
            tracks = tracks.validate("tracks")
            *runs, N = tracks.batch_shape
            if N > K:
                raise ValueError(f"tracks: {N} tracks, the table has {K} slots (capacity)")
            dtype, device = tracks.dtype, tracks.device
        else:
            runs, N = list(batch_shape), 0
        shape = (*runs, H, K)
        mean = torch.zeros(*shape, n, dtype=dtype, device=device)
        cov = torch.eye(n, dtype=dtype, device=device).expand(*shape, n, n).clone()
        if N:
            mean[..., :N, :] = tracks.mean.expand(*runs, N, n).unsqueeze(-3)
            cov[..., :N, :, :] = tracks.cov.expand(*runs, N, n, n).unsqueeze(-4)
        state = self._started(GaussianBelief(mean.reshape(*runs, H * K, n), cov.reshape(*runs, H * K, n, n)))
        log_w = torch.full((*runs, H), -math.inf, dtype=dtype, device=device)
        log_w[..., 0] = 0.0
        zero = torch.zeros(shape, dtype=torch.long, device=device)
        held = (torch.arange(K, device=device) < N).expand(shape)
        return TrackHypotheses(log_w, torch.zeros((*runs, H, L, K), dtype=torch.long, device=device), state,
                               held, torch.where(held, torch.arange(K, device=device), -1), zero[..., 0] + N,
                               zero + held.long(), zero + held.long(), zero, held, zero.to(dtype), zero.to(dtype))

    def update(self, belief: TrackHypotheses, z: Tensor) -> StepOutput:
        if not isinstance(belief, TrackHypotheses):
            raise TypeError(f"belief: ManagedMHT takes its TrackHypotheses (ManagedMHT.initial_belief), got "
                            f"{type(belief).__name__}")
        z, tracks, hyp, log_w, singular = self._scan_hypotheses(belief, z)  # log_w (*B, H, K, D)
        runs, H, K, D = log_w.shape[:-3], *log_w.shape[-3:]
        dtype = belief.log_weights.dtype
        alive = belief.alive
        neg_inf = torch.full((), -math.inf, dtype=dtype, device=z.device)
        log_w = torch.where(alive.unsqueeze(-1), log_w, neg_inf)  # a free slot takes nothing, misses nothing
        log_m = torch.where(alive, missed_log_weight(self), 0.0).to(dtype)
        present = torch.isfinite(z).all(-1)  # (*B, D)
        own = torch.eye(D, dtype=torch.bool, device=z.device) & present.unsqueeze(-2)  # (*B, D, D): row j, column j
        birth = torch.where(own, self.birth_log_weight, neg_inf)
        gains = torch.cat([log_w, birth.unsqueeze(-3).expand(*runs, H, D, D)], -2)  # (*B, H, K + D, D)
        misses = torch.cat([log_m, torch.zeros(*runs, H, D, dtype=dtype, device=z.device)], -1)
        R = math.prod(runs) * H
        columns, log_e = kbest_events(gains.reshape(R, K + D, D), misses.reshape(R, K + D), self.k)
        log_like, child_w, parent, chosen = children(belief.log_weights, columns, log_e, self.k)
        failed = (singular & alive).reshape(*runs, -1).any(-1) | torch.isnan(log_like)
        slot, new = chosen[..., :K], chosen[..., K:] > 0  # (*B, H, K) the slots' options; (*B, H, D) new targets
        options = pytree.tree_map(prepend_missed, missed_hypothesis(self, tracks, hyp), hyp.belief)
        updated = pytree.tree_map(lambda t: pick_options(t, parent, slot), options)  # (*B, H * K)

        def parents(t: Tensor) -> Tensor:  # a record (*B, H, ...) of each child's parent
            p = parent.reshape(*parent.shape, *([1] * (t.dim() - parent.dim())))
            return t.gather(len(runs), p.expand(*parent.shape, *t.shape[len(runs) + 1:]))
        was, label, next_label = parents(alive), parents(belief.label), parents(belief.next_label)
        hit = (slot > 0) & was
        age = torch.where(was, parents(belief.age) + 1, 0)
        window = self.m_of_n[1] if self.m_of_n is not None else 0
        hits = parents(belief.hits) + (hit & (age <= window)).long()
        misses_run = torch.where(hit, 0, parents(belief.misses) + was.long())
        # each track's score: its parent's plus its own log-weight in the event (log m_i missed, log w_ij)
        own_gain = parents(torch.cat([log_m.unsqueeze(-1), log_w], -1)).gather(-1, slot.unsqueeze(-1)).squeeze(-1)
        score = torch.where(was, parents(belief.score) + own_gain, 0.0)
        peak = torch.maximum(parents(belief.peak), score)
        firm = parents(belief.firm)
        kept = was
        if self.m_of_n is not None:
            firm = firm | (hits >= self.m_of_n[0])
            kept = kept & (firm | (age < window))  # unconfirmed after N scans: deleted
        if self.confirm_score is not None:
            firm = firm | (score >= self.confirm_score)
        if self.max_misses is not None:
            kept = kept & (misses_run < self.max_misses)
        if self.delete_drop is not None:
            kept = kept & (peak - score <= self.delete_drop)
        # new targets into the free slots, matched by rank
        free = ~kept
        free_rank = torch.cumsum(free.long(), -1)
        match = free.unsqueeze(-1) & new.unsqueeze(-2) & (
            free_rank.unsqueeze(-1) == torch.cumsum(new.long(), -1).unsqueeze(-2))  # (*B, H, K, D)
        born = match.any(-1)
        pick = match.to(dtype)
        started = self.initiate(torch.where(present.unsqueeze(-1), z, 0.0))  # (*B, D, n)
        mean = pick @ started.mean.unsqueeze(-3)
        cov = torch.einsum("...kd,...dij->...kij", pick, started.cov.expand(*runs, D, *started.cov.shape[-2:])
                           .unsqueeze(-4))
        state = updated.map_tensors(lambda t, e: t.reshape(*runs, H, K, *t.shape[t.dim() - e:]))
        state = where(born, self._started(GaussianBelief(mean, cov)), state)
        state = state.map_tensors(lambda t, e: t.reshape(*runs, H * K, *t.shape[t.dim() - e:]))
        first = (pick * torch.arange(1, D + 1, dtype=dtype, device=z.device)).sum(-1).long()  # 1 + j of a birth
        history = shift_history(belief.history, parent, torch.where(born, first, torch.where(kept, slot, 0)))
        one, zero = torch.ones((), dtype=torch.long, device=z.device), torch.zeros((), dtype=torch.long, device=z.device)
        out = TrackHypotheses(
            normalise(prune(child_w, history, self.n_scan), failed), history, state, kept | born,
            torch.where(born, next_label.unsqueeze(-1) + free_rank - 1, torch.where(kept, label, -1)),
            next_label + born.sum(-1), torch.where(born, one, torch.where(kept, age, zero)),
            torch.where(born, one, torch.where(kept, hits, zero)), torch.where(born | ~kept, zero, misses_run),
            torch.where(born, self._firm_at_birth, firm & kept),
            torch.where(born, self.birth_log_weight, torch.where(kept, score, 0.0)),
            torch.where(born, self.birth_log_weight, torch.where(kept, peak, 0.0)))
        best = torch.where(born, first, torch.where(kept, slot, 0))[..., 0, :]  # the best child's, (*B, K)
        association = (best.unsqueeze(-1) == torch.arange(1 + D, device=z.device)).to(dtype)
        unstarted = (new.sum(-1) - born.sum(-1))[..., 0]  # (*B,): the best child's new targets without a slot
        return StepOutput(out, belief, torch.where(failed, torch.nan, log_like), None, None,
                          {"association": association, "failed": failed, "unstarted": unstarted})

r"""Track management by target existence: initiation, confirmation and deletion in a fixed table of
track slots per run (docs/tracking.md, "Track management").

Every scan, :class:`ManagedTracks`:

1. associates the table's tracks jointly with existence (the wrapped :class:`JIPDA`); a free slot has
   existence 0, so it takes no detection and weighs nothing;
2. **deletes** the tracks whose existence fell below ``delete`` (their slot is freed);
3. **initiates** a track from every detection that the tracks leave unexplained (``1 - sum_i beta_ij``
   above ``unexplained``), in the run's free slots, in detection order: the state from ``initiate(z)``,
   existence ``birth_existence`` and a new label (the run's labels count up from 0 and are never
   reused), as many as there are free slots: the first ones in detection order. The step's
   ``extras["unstarted"]`` ``(*B,)`` counts the unexplained detections left without a slot (capacity
   binds where it is above 0).

A track is **confirmed** while its existence is at least ``confirm`` (``belief.confirmed(...)``); its
label stays the same for the life of the track. Everything is batched over runs and slots, without a
host read (the slots a run gives to its new tracks are matched by rank: the k-th unexplained
detection to the k-th free slot).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, ClassVar

import torch
from torch import Tensor

from torchmm.association.ipda import JIPDA
from torchmm.association.pda import check_scans
from torchmm.beliefs import (
    Belief,
    ExistenceBelief,
    GaussianBelief,
    ModeBelief,
    ModeExistenceBelief,
    register_belief,
    where,
)
from torchmm.beliefs.existence import check_existence_belief
from torchmm.contract import DType, Device, Finite, Indices, Int, Of, Real, Shape, entry_point
from torchmm.filters.base import Filter, StepOutput
from torchmm.validation import check_covariance, check_probabilities

__all__ = ["ManagedTracks", "ModeTrackTable", "TrackTable", "position_initiator"]


@register_belief
@dataclass(frozen=True)
class TrackTable(Belief):
    """A run's track slots: each slot's state given existence, ``log P(exists)`` (``-inf``: a free
    slot), its label (-1 when free) and the run's next label (the same in every slot of a run).

    The track's record: ``age`` (scans since it started, 1 at its first), ``hits`` (scans with a
    detection in its gate among its first ``N`` for an M-of-N rule, all of them otherwise), ``misses``
    (consecutive scans without one) and ``firm`` (confirmed by the manager's rule; an M-of-N
    confirmation is kept for the track's life).

    Shapes:
        mean ``(*B, K, n)``, cov ``(*B, K, n, n)``, log_existence ``(*B, K)``, label ``(*B, K)`` long,
        next_label ``(*B, K)`` long, age / hits / misses ``(*B, K)`` long, firm ``(*B, K)`` bool
    """

    mean: Tensor
    cov: Tensor
    log_existence: Tensor
    label: Tensor
    next_label: Tensor
    age: Tensor
    hits: Tensor
    misses: Tensor
    firm: Tensor

    event_dims: ClassVar[dict[str, int]] = {"mean": 1, "cov": 2, "log_existence": 0, "label": 0, "next_label": 0,
                                            "age": 0, "hits": 0, "misses": 0, "firm": 0}

    @property
    def existence(self) -> Tensor:
        return self.log_existence.exp()

    @property
    def tracks(self) -> ExistenceBelief:
        """The slots as the JIPDA's tracks."""
        return ExistenceBelief(self.mean, self.cov, self.log_existence)

    @property
    def state(self) -> GaussianBelief:
        """Every slot's state given existence."""
        return GaussianBelief(self.mean, self.cov)

    def validate(self, name: str = "belief") -> TrackTable:
        """Finite means, PSD covariances, log-existences in ``[-inf, 0]``."""
        check_existence_belief(self, name)
        return self

    def confirmed(self, threshold: float | None = None) -> Tensor:
        """``(*B, K)`` bool: the slots holding a confirmed track: by the manager's rule (``firm``), or,
        given a ``threshold``, those whose existence is at least ``threshold``."""
        if threshold is None:
            return self.firm & (self.log_existence > -math.inf)
        return self.log_existence >= math.log(threshold)

    def estimate(self) -> GaussianBelief:
        """Every slot's state given existence (free slots hold their last state; see ``label``)."""
        return GaussianBelief(self.mean, self.cov)


@register_belief
@dataclass(frozen=True)
class ModeTrackTable(Belief):
    """:class:`TrackTable` over an IMM (IMM-JIPDA): each slot's mode log-probabilities and per-mode
    components given existence, ``log P(exists)``, its label and the run's next label.

    Shapes:
        mode_log_probs ``(*B, K, M)``, components: a belief with batch ``(*B, K, M)``, log_existence
        ``(*B, K)``, label ``(*B, K)`` long, next_label ``(*B, K)`` long, age / hits / misses / firm as
        :class:`TrackTable`'s
    """

    mode_log_probs: Tensor
    components: Belief
    log_existence: Tensor
    label: Tensor
    next_label: Tensor
    age: Tensor
    hits: Tensor
    misses: Tensor
    firm: Tensor

    event_dims: ClassVar[dict[str, int]] = {"mode_log_probs": 1, "log_existence": 0, "label": 0, "next_label": 0,
                                            "age": 0, "hits": 0, "misses": 0, "firm": 0}

    existence = TrackTable.existence
    validate = TrackTable.validate
    confirmed = TrackTable.confirmed

    @property
    def tracks(self) -> ModeExistenceBelief:
        """The slots as the IMM-JIPDA's tracks."""
        return ModeExistenceBelief(self.mode_log_probs, self.components, self.log_existence)

    @property
    def state(self) -> ModeBelief:
        """Every slot's mode belief given existence."""
        return ModeBelief(self.mode_log_probs, self.components)

    def estimate(self) -> GaussianBelief:
        """Every slot's moment-matched state given existence (free slots hold their last state)."""
        return self.state.estimate()


def _table(state, log_existence: Tensor, label: Tensor, next_label: Tensor, record) -> TrackTable | ModeTrackTable:
    """A table from the slots' state and the rest; ``record``: ``(age, hits, misses, firm)``."""
    if isinstance(state, ModeBelief):
        return ModeTrackTable(state.mode_log_probs, state.components, log_existence, label, next_label, *record)
    return TrackTable(state.mean, state.cov, log_existence, label, next_label, *record)


def _record(table) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    return table.age, table.hits, table.misses, table.firm


@entry_point(state_dim=Int(1), indices=Indices(), noise_cov=Finite(), unobserved_variance=Real(minimum=0.0, optional=True),
             max_speed=Real(positive=True, optional=True))
def position_initiator(state_dim: int, indices, noise_cov, unobserved_variance: float | None = None, *,
                       max_speed: float | None = None) -> Callable:
    """``initiate(z)`` for a sensor that measures state components ``indices`` directly (e.g.
    ``PositionMeasurement``): the state ``z`` at ``indices`` and 0 elsewhere, the covariance
    ``noise_cov`` at ``indices`` and ``unobserved_variance`` on the diagonal elsewhere (velocities).
    ``noise_cov``: an ``(m, m)`` matrix, a vector (its diagonal) or a number ``r`` (``r I``, as
    ``PositionMeasurement`` reads it).

    **A velocity bound** (``max_speed=v`` instead of ``unobserved_variance``): each unmeasured component
    uniform on ``[-v, v]``, its variance ``v^2 / 3`` (one-point initiation; the gate of the track's next
    update then holds what a speed up to about ``v`` reaches). The next update is the **two-point**
    initiation: with a diffuse velocity (a large variance) the updated velocity is the difference of the
    two detections over the period, to ``R / variance`` (tests/test_tracks.py).

    Raises (at the call, naming the argument): an index outside the ``state_dim`` components or given
    twice (``indices``); a ``noise_cov`` that does not expand to ``(m, m)`` or is not a covariance
    (symmetric, positive semi-definite: every track it started would fail).

    Shapes: ``z (*B, m)`` -> a :class:`~torchmm.GaussianBelief` ``(*B, n)``."""
    if (unobserved_variance is None) == (max_speed is None):
        raise TypeError("unobserved_variance: give it or max_speed (a velocity bound), one of the two")
    if max_speed is not None:
        unobserved_variance = float(max_speed) ** 2 / 3.0
    idx = [int(i) for i in indices]
    m = len(idx)
    for i in idx:
        if i >= state_dim:
            raise ValueError(f"indices: entry {i} is outside the state's {state_dim} components (0 .. {state_dim - 1})")
    repeated = next((i for k, i in enumerate(idx) if i in idx[:k]), None)
    if repeated is not None:
        raise ValueError(f"indices: {repeated} is given twice (each measured component once)")
    H = torch.zeros(m, state_dim, dtype=torch.float64)
    H[torch.arange(m), torch.tensor(idx)] = 1.0
    try:
        R = torch.as_tensor(noise_cov, dtype=torch.float64)
        # a number is r I, as PositionMeasurement reads it (issue 44: it was expanded to a matrix of r's, every
        # new track's measured components fully correlated); a vector is the diagonal
        R = R * torch.eye(m, dtype=torch.float64) if R.dim() == 0 else torch.diag(R) if R.dim() == 1 else R
        R = R.expand(m, m)
    except RuntimeError:
        raise ValueError(f"noise_cov: expected a number or a ({m}, {m}) matrix for the {m} indices, got shape "
                         f"{tuple(torch.as_tensor(noise_cov).shape)}") from None
    check_covariance(R, "noise_cov")
    cov = H.mT @ R @ H + torch.diag((1.0 - H.sum(0)) * float(unobserved_variance))
    made: dict = {}  # (dtype, device) -> (H, cov): copied to a device once, not at every scan

    def initiate(z: Tensor) -> GaussianBelief:
        key = (z.dtype, str(z.device))
        if key not in made:
            made[key] = (H.to(z.device, z.dtype), cov.to(z.device, z.dtype))
        Hd, Pd = made[key]
        return GaussianBelief(z @ Hd, Pd.expand(*z.shape[:-1], state_dim, state_dim))
    return initiate


class ManagedTracks(Filter):
    """Track initiation, confirmation and deletion over a :class:`JIPDA` (the module docstring).

    Args:
        association: the :class:`~torchmm.association.JIPDA` that updates the tracks.
        capacity: ``K``, the track slots per run (the exact JIPDA takes up to its ``max_targets``: more
            is refused here).
        initiate: ``z (*B, D, m) -> GaussianBelief (*B, D, n)``, a new track's state from a detection
            (:func:`position_initiator` for sensors that measure positions).
        birth_existence: a new track's existence, in (0, 1] (default 0.1; 0 is refused: a slot of
            existence 0 is a free slot, so a track born so would be no track).
        unexplained: a detection starts a track when the tracks explain it with probability below
            ``1 - unexplained`` (default 0.5).
        delete: a track is deleted when its existence falls below this (default 0.01; 0: never by
            existence).
        confirm: without ``m_of_n``, a track is confirmed (``firm``) while its existence is at least
            this (default 0.9).
        m_of_n: ``(M, N)``: the M-of-N rule instead: a track is confirmed once ``M`` of its first ``N``
            scans (the one that started it included) had a detection in its gate, and kept confirmed
            for life; a track still unconfirmed after ``N`` scans is deleted.
        max_misses: a track is deleted after this many consecutive scans without a detection in its
            gate (default None: no such rule).

    Shapes:
        belief: :class:`TrackTable` with batch ``(*B, K)`` (:meth:`initial_belief`: all slots free);
        ``z``: ``(*B, D, m)``. ``extras``: JIPDA's and ``"born"`` ``(*B, K)`` bool (a track started in
        the slot at this scan).
    """

    @entry_point(association=Of(JIPDA), capacity=Int(1), initiate=Of(object), birth_existence=Real(0.0, 1.0, positive=True),
                 unexplained=Real(0.0, 1.0), delete=Real(0.0, 1.0), confirm=Real(0.0, 1.0),
                 m_of_n=Of((tuple, list), what="two integers (M, N)", optional=True), max_misses=Int(1, optional=True),
                 mode_probs=Finite(optional=True))
    def __init__(self, association: JIPDA, *, capacity: int, initiate: Callable, birth_existence: float = 0.1,
                 unexplained: float = 0.5, delete: float = 0.01, confirm: float = 0.9, m_of_n=None,
                 max_misses: int | None = None, mode_probs=None):
        super().__init__()
        if not callable(initiate):
            raise TypeError(f"initiate: expected a function z -> GaussianBelief, got {type(initiate).__name__}")
        if m_of_n is not None:
            if len(m_of_n) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) for v in m_of_n) or \
                    not 1 <= m_of_n[0] <= m_of_n[1]:
                raise ValueError(f"m_of_n: expected two integers (M, N) with 1 <= M <= N, got {m_of_n}")
            m_of_n = (int(m_of_n[0]), int(m_of_n[1]))
        if confirm <= 0:
            raise ValueError(f"confirm: expected an existence in (0, 1], got {confirm}")
        if association.method == "exact" and capacity > association.max_targets:
            raise ValueError(f"capacity: {capacity} slots exceed max_targets={association.max_targets} of the exact "
                             "JIPDA (every slot is a track of its joint events, cost 2^K); use method='lbp' or raise "
                             "max_targets")
        self.association = association
        self.capacity = int(capacity)
        self.initiate = initiate
        self.birth_existence, self.unexplained, self.delete = float(birth_existence), float(unexplained), float(delete)
        self.confirm, self.m_of_n = float(confirm), m_of_n
        self.max_misses = None if max_misses is None else int(max_misses)
        M = getattr(association.filter, "num_modes", None)  # an IMM under the JIPDA: the tracks are mode beliefs
        self.num_modes = M
        if mode_probs is not None:
            if M is None:
                raise ValueError(f"mode_probs: the JIPDA's filter ({type(association.filter).__name__}) has no modes")
            probs = check_probabilities(mode_probs, "mode_probs", M, dtype=torch.float64)
            if probs.shape != (M,):
                raise ValueError(f"mode_probs: expected the {M} modes' probabilities (M,), got shape "
                                 f"{tuple(probs.shape)}")
            self.mode_log_probs = probs.log()
        else:
            self.mode_log_probs = None if M is None else torch.full((M,), -math.log(M), dtype=torch.float64)
        self._made: dict = {}  # (dtype, device) -> the new tracks' mode log-probabilities, copied once

    measurement_rank = 2

    @property
    def state_dim(self) -> int | None:
        return self.association.state_dim

    @property
    def meas_dim(self) -> None:
        return None

    def informative(self, z: Tensor) -> Tensor:
        return torch.ones(z.shape[:-2], dtype=torch.bool, device=z.device)

    def check_measurements(self, measurements: Tensor, batch: torch.Size, name: str = "measurements", *,
                           time: bool = True) -> None:
        """The scans ``(T, *B, D, m)`` against the table's runs (its batch ``(*B, K)``, the slots last):
        :func:`~torchmm.association.pda.check_scans`."""
        check_scans(measurements, self.association.detections_dim, batch, name, time=time, joint=True)

    def check_bank_member(self, name: str, num_modes: int) -> None:
        """Not a mode filter: the table's slots are its last batch axis (manage an IMM-JIPDA instead:
        ``ManagedTracks(JIPDA(IMM(...)), ...)``)."""
        raise TypeError(f"{name}: ManagedTracks cannot be a mode filter (the modes would be taken for its slots); "
                        "manage the tracks of a JIPDA over the multiple-model filter: ManagedTracks(JIPDA(IMM(...)), "
                        "...)")

    @entry_point(batch_shape=Shape(), dtype=DType(), device=Device())
    def initial_belief(self, batch_shape=(), *, dtype=torch.float64, device=None) -> TrackTable | ModeTrackTable:
        """An empty table: ``capacity`` free slots per run, batch ``(*batch_shape, K)`` (a
        :class:`ModeTrackTable` over an IMM).

        Args:
            batch_shape: the runs, a shape (``(runs,)``; ``()``: one run); a bare integer is refused.
            dtype: a floating dtype (default float64; None: the default dtype); device: where."""
        n, K = self.state_dim, self.capacity
        shape = (*tuple(batch_shape), K)
        state = self._started(GaussianBelief(torch.zeros(*shape, n, dtype=dtype, device=device),
                                             torch.eye(n, dtype=dtype, device=device).expand(*shape, n, n)))
        zero = torch.zeros(shape, dtype=torch.long, device=device)
        return _table(state, torch.full(shape, -math.inf, dtype=dtype, device=device),
                      torch.full(shape, -1, dtype=torch.long, device=device), zero,
                      (zero, zero, zero, torch.zeros(shape, dtype=torch.bool, device=device)))

    def _started(self, state: GaussianBelief):
        """A new track's state: the Gaussian itself, or over an IMM every mode from it with ``mode_probs``."""
        if self.num_modes is None:
            return state
        key = (state.dtype, str(state.device))
        if key not in self._made:
            self._made[key] = self.mode_log_probs.to(state.device, state.dtype)
        M, batch = self.num_modes, state.batch_shape
        return ModeBelief(self._made[key].expand(*batch, M), state.unsqueeze(-1).expand(*batch, M))

    def _check(self, belief) -> None:
        kind = TrackTable if self.num_modes is None else ModeTrackTable
        if not isinstance(belief, kind):
            raise TypeError(f"belief: ManagedTracks over {type(self.association.filter).__name__} needs a "
                            f"{kind.__name__} (ManagedTracks.initial_belief), got {type(belief).__name__}")

    def predict(self, belief: TrackTable | ModeTrackTable, *, u: Tensor | None = None) -> TrackTable | ModeTrackTable:
        self._check(belief)
        p = self.association.predict(belief.tracks, u=u)
        return _table(p.state, p.log_existence, belief.label, belief.next_label, _record(belief))

    def update(self, belief: TrackTable | ModeTrackTable, z: Tensor) -> StepOutput:
        self._check(belief)
        out = self.association.update(belief.tracks, z)
        post = out.belief
        *runs, K = post.log_existence.shape
        D = z.shape[-2]
        z = z.to(post.dtype).expand(*runs, D, z.shape[-1])
        neg_inf = torch.full((), -math.inf, dtype=post.dtype, device=post.device)
        # the tracks' record: a scan older, a hit when a detection fell in the gate
        held = belief.log_existence > -math.inf  # the slots that held a track at this scan
        hit = out.extras["validated"].any(-1) & held  # (*B, K)
        age = torch.where(held, belief.age + 1, 0)
        counted = hit if self.m_of_n is None else hit & (age <= self.m_of_n[1])
        hits = belief.hits + counted.long()
        misses = torch.where(hit, 0, belief.misses + held.long())
        # 2. confirmation and deletion
        alive = post.log_existence >= math.log(self.delete) if self.delete > 0 else post.log_existence > -math.inf
        if self.m_of_n is None:
            firm = post.log_existence >= math.log(self.confirm)
        else:
            firm = belief.firm | (hits >= self.m_of_n[0])
            alive = alive & (firm | (age < self.m_of_n[1]))  # unconfirmed after N scans: deleted
        if self.max_misses is not None:
            alive = alive & (misses < self.max_misses)
        log_e = torch.where(alive, post.log_existence, neg_inf)
        label = torch.where(alive, belief.label, -1)
        # 3. initiation: unexplained detections into free slots, matched by rank
        explained = out.extras["association"][..., 1:].nan_to_num(0.0).sum(-2)  # (*B, D)
        present = torch.isfinite(z).all(-1)
        candidate = present & (explained < 1.0 - self.unexplained)
        free = ~alive
        free_rank = torch.cumsum(free.long(), -1)  # 1-based among the free slots
        cand_rank = torch.cumsum(candidate.long(), -1)
        match = free.unsqueeze(-1) & candidate.unsqueeze(-2) & (free_rank.unsqueeze(-1) == cand_rank.unsqueeze(-2))
        born = match.any(-1)  # (*B, K)
        pick = match.to(post.dtype)  # (*B, K, D): one-hot where born
        new = self.initiate(torch.where(present.unsqueeze(-1), z, 0.0))  # (*B, D, n)
        new_mean = pick @ new.mean
        new_cov = torch.einsum("...kd,...dij->...kij", pick, new.cov.expand(*runs, D, *new.cov.shape[-2:]))
        state = where(born, self._started(GaussianBelief(new_mean, new_cov)), post.state)
        birth = torch.full((), math.log(self.birth_existence),
                           dtype=post.dtype, device=post.device)
        log_e = torch.where(born, birth, log_e)
        label = torch.where(born, belief.next_label + free_rank - 1, label)
        next_label = belief.next_label + born.sum(-1, keepdim=True)
        # a new track's record: its first scan, one hit (its detection)
        one = torch.ones((), dtype=torch.long, device=age.device)
        zero = torch.zeros((), dtype=torch.long, device=age.device)
        firm_at_birth = self.birth_existence >= self.confirm if self.m_of_n is None else self.m_of_n[0] <= 1
        record = (torch.where(born, one, torch.where(alive, age, zero)),
                  torch.where(born, one, torch.where(alive, hits, zero)),
                  torch.where(born | ~alive, zero, misses),
                  torch.where(born, firm_at_birth, firm & alive))
        extras = dict(out.extras)
        extras["born"] = born
        extras["unstarted"] = candidate.sum(-1) - born.sum(-1)  # (*B,): no free slot left for them
        table = _table(state, log_e, label, next_label.expand(*runs, K), record)
        return StepOutput(table, belief, out.log_likelihood, out.innovation, out.innovation_cov, extras)

r"""Multiple hypothesis tracking (Reid, IEEE TAC 24(6), 1979) over any Gaussian filter, in its
hypothesis-oriented form with Murty's k best assignments (Cox & Hingorani, IEEE TPAMI 18(2), 1996) and
N-scan pruning, batched over runs: ``H`` global hypotheses a run, each a full set of the run's ``N``
tracks with its own association history.

Each scan, every track of every hypothesis is updated with every detection at once and gated, giving
``w_ij = P_D N(nu_ij; 0, S_i) / lambda`` and ``m = 1 - P_D P_G`` as in :class:`~torchmm.association.JPDA`.
A hypothesis ``h`` of log-weight ``l_h`` has joint events ``e`` (each track at most one detection, each
detection at most one track) of weight ``w_e``, the product of its ``w_ij`` and ``m``; its ``k`` best
events are Murty's k best assignments of the ``N x (D + N)`` costs ``-log w_ij`` (track ``i``'s own column
``D + i`` its miss; :func:`torchmm.assignment.k_best_assignments`). The children ``(h, e)`` weigh
``l_h + log w_e``; the ``H`` best are kept and normalised; each child's tracks are its parent's, each
updated with its detection of ``e`` alone (or not at all). **N-scan pruning** (N-scan-back, as in Blackman,
IEEE AES Magazine 19(1), 2004): after the ``H`` best are kept, a hypothesis whose assignment ``n_scan``
scans back differs from the best hypothesis's is dropped, so the decisions ``n_scan`` and more scans back
are the best hypothesis's and the survivors differ on the last ``n_scan`` scans at most (``n_scan = 1``:
on the current scan's assignment). The literature's ``N = 0`` (every decision fixed at once) is GNN,
here ``hypotheses=1, k=1``; ``n_scan = 0`` here is no pruning. Fewer than ``H`` hypotheses may survive
a scan (the pruning follows the cut to ``H``).

The scan's log-likelihood is ``log sum_(h, e) exp(l_h + log w_e)`` over the parents' ``k`` events (the
joint target hypotheses against "all clutter"; with every hypothesis and event kept, the exact marginal
likelihood of the scan given the previous ones). The estimate (``belief.estimate()``) is the best
hypothesis's tracks, batch ``(*B, N)``, each track keeping its label (its index).

Special cases (tests/test_mht.py): ``hypotheses=1, k=1`` is GNN (the best event every scan); one scan
with every hypothesis kept gives PDA's / JPDA's ``log Z`` and, mixed over the hypotheses, their posterior.

This is the hypothesis-oriented form: fixed-size tensors of ``H`` hypotheses a run, no track trees. The
track-oriented form (track trees scored by the filters' likelihoods, global hypotheses re-solved each
scan) computes the same best hypotheses where both keep them; it is not built.
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import torch
import torch.utils._pytree as pytree
from torch import Tensor

from torchmm.association.jpda import JPDA, kbest_events
from torchmm.association.pda import check_detections, missed_hypothesis, missed_log_weight
from torchmm.beliefs import Belief, GaussianBelief
from torchmm.beliefs.base import register_belief
from torchmm.contract import Int, Of, Real, entry_point
from torchmm.filters.base import Filter, StepOutput

__all__ = ["MHT", "HypothesisBelief"]


@register_belief
@dataclasses.dataclass(frozen=True)
class HypothesisBelief(Belief):
    """``H`` global hypotheses of a run's ``N`` tracks.

    Shapes:
        log_weights: ``(*B, H)`` normalised (``-inf``: an empty or pruned slot)
        history: ``(*B, H, L, N)`` long, each hypothesis's last ``L = n_scan + 1`` assignments, oldest
            first (0 missed, ``1 + j`` detection ``j``, ``-1`` before the first scan)
        tracks: a belief with batch ``(*B, H * N)`` (hypothesis-major)
    """

    log_weights: Tensor
    history: Tensor
    tracks: Belief

    event_dims: ClassVar[dict[str, int]] = {"log_weights": 1, "history": 3}

    def validate(self, name: str = "belief") -> HypothesisBelief:
        """Log-weights normalised (``-inf`` allowed: an empty slot; no NaN or ``+inf``), the history's
        shape, and the tracks valid."""
        lw = self.log_weights.detach()
        if bool(torch.isnan(lw).any()) or bool((lw == math.inf).any()):
            raise ValueError(f"{name}.log_weights: contains NaN or +inf")
        if lw.numel() and bool(((torch.logsumexp(lw, -1).exp() - 1).abs() > 1e-6).any()):
            raise ValueError(f"{name}.log_weights: the hypotheses' probabilities must sum to 1")
        if self.history.shape[:-2] != lw.shape:
            raise ValueError(f"{name}.history: expected (*B, H, L, N) for log_weights {tuple(lw.shape)}")
        self.tracks.validate(f"{name}.tracks")
        return self

    @property
    def num_hypotheses(self) -> int:
        return self.log_weights.shape[-1]

    def by_hypothesis(self) -> Belief:
        """The tracks with batch ``(*B, H, N)``."""
        H = self.num_hypotheses
        N = self.history.shape[-1]
        lead = self.log_weights.dim() - 1

        def split(t: Tensor, e: int) -> Tensor:
            return t.reshape(*t.shape[:lead], H, N, *t.shape[t.dim() - e:])
        return self.tracks.map_tensors(split)

    def estimate(self):
        """The best hypothesis's tracks' estimates, batch ``(*B, N)``."""
        best = self.log_weights.argmax(-1)  # (*B,)
        return self.by_hypothesis().estimate().map_tensors(lambda t, e: take_hypothesis(t, best))


class MHT(JPDA):
    r"""Multiple hypothesis tracking over a Gaussian filter (or an IMM over Gaussian filters: IMM-MHT), the
    module docstring's equations.

    Args:
        filter, detection_probability, clutter_density, gate_probability: as for :class:`JPDA`.
        hypotheses: ``H``, the global hypotheses kept a run (default 10).
        k: the best joint events of each hypothesis a scan (default ``hypotheses``).
        n_scan: the N-scan pruning depth: the decisions ``n_scan`` scans back are fixed, the hypotheses
            may differ on the last ``n_scan`` scans (default 3; 0: no pruning; the module docstring).

    Shapes:
        belief: :class:`HypothesisBelief` (from :meth:`initial_belief` of the tracks, batch ``(*B, N)``);
        ``z``: ``(*B, D, m)``. ``log_likelihood`` ``(*B,)``. ``extras``: ``"association"``
        ``(*B, N, 1 + D)`` the best hypothesis's (one-hot; missed first), ``"failed"`` ``(*B,)``.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> mht = MHT(KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0)),
        ...           detection_probability=0.9, clutter_density=0.01, hypotheses=4)
        >>> b0 = mht.initial_belief(GaussianBelief(torch.tensor([[0.0, 0.0], [3.0, 0.0]]), torch.eye(2)))
        >>> out = mht.update(mht.predict(b0), torch.tensor([[0.2], [2.5], [float("nan")]]))
        >>> out.belief.estimate().mean.shape, out.belief.log_weights.exp().sum().round()
        (torch.Size([2, 2]), tensor(1.))
    """

    joint = False  # (the belief's batch is the runs; the tracks are inside the hypotheses)

    @entry_point(filter=Of(Filter), detection_probability=Real(0.0, 1.0), clutter_density=Real(positive=True),
                 gate_probability=Real(0.0, 1.0), hypotheses=Int(1), k=Int(1, optional=True), n_scan=Int(0))
    def __init__(self, filter: Filter, *, detection_probability: float, clutter_density: float,
                 gate_probability: float = 0.99, hypotheses: int = 10, k: int | None = None, n_scan: int = 3):
        super().__init__(filter, detection_probability=detection_probability, clutter_density=clutter_density,
                         gate_probability=gate_probability, method="kbest", k=int(k or hypotheses))
        self.hypotheses, self.n_scan = int(hypotheses), int(n_scan)

    def check_bank_member(self, name: str, num_modes: int) -> None:
        raise TypeError(f"{name}: MHT cannot be a mode filter; track with MHT(IMM(...), ...) instead")

    def initial_belief(self, belief, **kwargs) -> HypothesisBelief:
        """One hypothesis (the others empty) holding ``belief``: the wrapped filter's start of the
        tracks, batch ``(*B, N)`` (e.g. ``imm.initial_belief(prior)`` for IMM tracks)."""
        if isinstance(belief, HypothesisBelief):
            return belief
        # the wrapped filter's start of the tracks (an IMM's ModeBelief from a Gaussian one), or its own
        tracks = self.filter.initial_belief(belief, **kwargs) if isinstance(belief, GaussianBelief) else belief
        batch = tracks.batch_shape
        if len(batch) < 1:
            raise ValueError("belief: MHT needs tracks with a batch (*B, N), the tracks last")
        *runs, N = batch
        H, L = self.hypotheses, self.n_scan + 1  # (the decisions n_scan scans back and every later one)
        dtype, device = tracks.dtype, tracks.device
        log_w = torch.full((*runs, H), -math.inf, dtype=dtype, device=device)
        log_w[..., 0] = 0.0
        history = torch.full((*runs, H, L, N), -1, dtype=torch.long, device=device)

        def copies(t: Tensor, e: int) -> Tensor:
            t = t.expand(*runs, N, *t.shape[t.dim() - e:])
            return t.unsqueeze(len(runs)).expand(*runs, H, N, *t.shape[len(runs) + 1:]).reshape(
                *runs, H * N, *t.shape[len(runs) + 1:])
        return HypothesisBelief(log_w, history, tracks.map_tensors(copies))

    def predict(self, belief: HypothesisBelief, *, u: Tensor | None = None) -> HypothesisBelief:
        return dataclasses.replace(belief, tracks=self.filter.predict(belief.tracks, u=u))

    def _scan_hypotheses(self, belief: HypothesisBelief, z: Tensor):
        """The scan ``z`` checked, every hypothesis's tracks ``(*B, H, N)`` and their update for every
        detection at once (:meth:`JPDA._scan`): ``(z, tracks, hyp, log_w (*B, H, N, D), singular (*B, H, N))``."""
        runs = belief.log_weights.shape[:-1]
        H, N = belief.num_hypotheses, belief.history.shape[-1]
        z = check_detections(z, self.detections_dim, torch.Size(runs), belief.log_weights.dtype,
                             tracks=torch.Size((*runs, N)))
        tracks = belief.by_hypothesis()  # (*B, H, N)
        D, m = z.shape[-2:]
        hyp, _, log_w, _, singular = self._scan(tracks, z.unsqueeze(-3).expand(*runs, H, D, m))
        return z, tracks, hyp, log_w, singular

    def update(self, belief: HypothesisBelief, z: Tensor) -> StepOutput:
        if not isinstance(belief, HypothesisBelief):
            raise TypeError(f"belief: MHT takes its HypothesisBelief (MHT.initial_belief of the tracks), got "
                            f"{type(belief).__name__}")
        z, tracks, hyp, log_w, singular = self._scan_hypotheses(belief, z)
        runs, H, N, D = log_w.shape[:-3], *log_w.shape[-3:]
        R = math.prod(runs) * H
        columns, log_e = kbest_events(log_w.reshape(R, N, D), missed_log_weight(self), self.k)  # (R, k, N), (R, k)
        log_like, log_w, parent, chosen = children(belief.log_weights, columns, log_e, self.k)
        failed = singular.reshape(*runs, -1).any(-1) | torch.isnan(log_like)
        # the children's tracks: each its parent's track updated with its detection (option 1 + j) or missed (0)
        options = pytree.tree_map(prepend_missed, missed_hypothesis(self, tracks, hyp), hyp.belief)  # (1 + D, *B, H, N)
        new_tracks = pytree.tree_map(lambda t: pick_options(t, parent, chosen), options)
        history = shift_history(belief.history, parent, chosen)
        log_w = normalise(prune(log_w, history, self.n_scan), failed)
        out = HypothesisBelief(log_w, history, new_tracks)
        association = (chosen[..., 0, :].unsqueeze(-1) == torch.arange(1 + D, device=z.device)).to(log_w.dtype)
        return StepOutput(out, belief, torch.where(failed, torch.nan, log_like), None, None,
                          {"association": association, "failed": failed})


def take_hypothesis(t: Tensor, index: Tensor) -> Tensor:
    """Each run's hypothesis ``index (*B,)`` of ``t (*B, H, ...)`` -> ``(*B, ...)``."""
    lead = index.dim()
    at = index.reshape(*index.shape, 1, *([1] * (t.dim() - lead - 1)))
    return t.gather(lead, at.expand(*t.shape[:lead], 1, *t.shape[lead + 1:])).squeeze(lead)


def children(log_weights: Tensor, columns: Tensor, log_e: Tensor, k: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The ``H`` best children ``(h, e)`` of ``H`` parents of log-weights ``(*B, H)`` and their ``k`` events
    each (``columns (R, k, W)``, ``log_e (R, k)``, ``R = prod(B) H``): the scan's log-likelihood ``(*B,)``
    (over every child), the children's unnormalised log-weights ``(*B, H)`` (best first), their parents
    ``(*B, H)`` and their events' columns ``(*B, H, W)``."""
    *runs, H = log_weights.shape
    W = columns.shape[-1]
    every = (log_weights.unsqueeze(-1) + log_e.reshape(*runs, H, k)).reshape(*runs, H * k)
    top, index = every.nan_to_num(nan=-math.inf).topk(H, dim=-1)  # (*B, H), the best children first
    chosen = columns.reshape(*runs, H * k, W).gather(-2, index.unsqueeze(-1).expand(*runs, H, W))
    return torch.logsumexp(every, -1), top, index // k, chosen


def pick_options(t: Tensor, parent: Tensor, chosen: Tensor) -> Tensor:
    """Each child's tracks from its parent's options: ``t (1 + D, *B, H, N, *E)`` (option 0 missed,
    ``1 + j`` detection ``j``), ``parent (*B, H)``, ``chosen (*B, H, N)`` -> ``(*B, H * N, *E)``."""
    *runs, H, N = chosen.shape
    lead = len(runs)
    e = t.dim() - (1 + lead + 2)
    t = t.movedim(0, lead + 2)  # (*B, H, N, 1 + D, *E)
    shape = t.shape
    t = t.gather(lead, parent.reshape(*runs, H, 1, 1, *([1] * e)).expand(*runs, H, *shape[lead + 1:]))
    t = t.gather(lead + 2, chosen.reshape(*runs, H, N, 1, *([1] * e)).expand(*runs, H, N, 1, *shape[lead + 3:]))
    return t.squeeze(lead + 2).reshape(*runs, H * N, *shape[lead + 3:])


def shift_history(history: Tensor, parent: Tensor, chosen: Tensor) -> Tensor:
    """The children's histories ``(*B, H, L, N)``: the parent's, shifted, with ``chosen (*B, H, N)`` last."""
    *runs, H = parent.shape
    history = history.gather(-3, parent.reshape(*runs, H, 1, 1).expand(*runs, H, *history.shape[-2:]))
    return torch.cat([history[..., 1:, :], chosen.unsqueeze(-2)], -2)


def prune(log_w: Tensor, history: Tensor, n_scan: int) -> Tensor:
    """N-scan pruning: a hypothesis whose assignments ``n_scan`` scans back differ from the best one's
    gets weight 0 (``-inf``), so the survivors differ on the last ``n_scan`` scans at most; ``n_scan = 0``:
    none. ``history (*B, H, n_scan + 1, N)``: its first entry is the scan ``n_scan`` back."""
    if n_scan <= 0:
        return log_w
    best = log_w.argmax(-1, keepdim=True)
    oldest = history[..., -1 - n_scan, :]  # (*B, H, N): the scan n_scan back
    agree = (oldest == oldest.gather(-2, best.unsqueeze(-1).expand(*oldest.shape[:-2], 1, oldest.shape[-1]))).all(-1)
    return torch.where(agree, log_w, -math.inf)


def normalise(log_w: Tensor, failed: Tensor) -> Tensor:
    """The hypotheses' log-weights normalised, NaN in a failed run."""
    log_w = log_w - torch.logsumexp(log_w, -1, keepdim=True)
    return torch.where(failed.unsqueeze(-1), torch.nan, log_w)


def prepend_missed(missed: Tensor, detections: Tensor) -> Tensor:
    """The missed hypothesis ``(*B, ...)`` in front of the detections' ``(D, *B, ...)``."""
    full = torch.broadcast_shapes(missed.shape, detections.shape[1:])
    return torch.cat([missed.expand(full).unsqueeze(0), detections.expand(detections.shape[0], *full)], 0)

"""What :func:`~torchmm.learn.estimate` estimates (split from :mod:`torchmm.learn.estimation` by concern, issue
47): the declaration of one tensor's estimation (:class:`Param`: its kind, fixed entries, shared groups,
bounds), the map from the free vector to the tensor and back (:class:`Block`), the tensors found by name in a
filter or a start belief (:func:`blocks`, :class:`StartFields`, :func:`resolve`), the estimates written back
(:func:`write_back`), and the dry run of a fit's set-up (:func:`estimated_entries`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor, nn

from torchmm.beliefs import Belief
from torchmm.contract import Choice, Finite, Of, Real, Text, Unchecked, entry_point
from torchmm.models.transition import ModeTransition

__all__ = ["KINDS", "START", "Block", "Param", "StartFields", "blocks", "estimated_entries", "resolve", "stationary",
           "write_back"]


#: the kinds of :class:`Param`
KINDS = ("free", "variance", "covariance", "stochastic", "probabilities")


class Param:
    """How one tensor of a filter is estimated (:func:`estimate`).

    Args:
        kind: ``"free"`` (default): every entry a real number, between ``lower`` and ``upper`` if
            given (``lower + exp(u)``, ``upper - exp(u)`` or ``lower + (upper - lower) sigmoid(u)``);
            ``"variance"``: the diagonal of each (last two axes) matrix positive (``exp(u)``), the other
            entries fixed (0 for a diagonal covariance); ``"covariance"``: each matrix positive definite,
            ``L L^T`` with ``L`` lower triangular and its diagonal ``exp(u)``; ``"stochastic"``: each row
            (last axis) a probability vector, ``softmax`` over its free entries with the last free entry
            as the reference (``M - 1`` values a row), its zero entries and ``fixed`` entries kept (the
            free ones share the rest of the row's mass: a row left with one free entry holds it at that
            rest, neither estimated nor reported); ``"probabilities"``: the last axis a probability
            vector, as one row of ``"stochastic"``.
        fixed: a boolean mask of the tensor's shape (or broadcastable to it): entries held at their
            current values. ``"covariance"`` takes none.
        groups: an integer tensor of the tensor's shape: entries with the same non-negative number
            share one value (``-1``: an entry of its own). ``"free"`` and ``"variance"`` only. E.g. for a
            bank's stacked ``H (M, m, n)``, ``groups[j, 0, 1] = 0`` for every regime ``j`` shares
            ``H[:, 0, 1]`` across the regimes.
        lower, upper: bounds of ``"free"`` entries (floats; ``None``: unbounded).
        label: the name the entries are reported under (default: the tensor's name in the filter).

    Examples:
        >>> Param("stochastic")
        Param('stochastic')
        >>> Param(lower=0.0, label="const")
        Param('free', lower=0.0, label='const')
    """

    @entry_point(kind=Choice(*KINDS), fixed=Unchecked("a boolean mask, checked by estimate against the tensor"),
                 groups=Unchecked("an integer tensor, checked by estimate against the tensor"),
                 lower=Real(optional=True), upper=Real(optional=True),
                 label=Text(optional=True))
    def __init__(self, kind: str = "free", *, fixed: Any = None, groups: Any = None, lower: float | None = None,
                 upper: float | None = None, label: str | None = None):
        if kind != "free" and (lower is not None or upper is not None):
            raise ValueError(f"lower: bounds are for kind 'free' entries, not {kind!r}")
        if lower is not None and upper is not None and not lower < upper:
            raise ValueError(f"upper: must exceed lower ({lower}), got {upper}")
        if groups is not None and kind not in ("free", "variance"):
            raise ValueError(f"groups: shared entries are for kinds 'free' and 'variance', not {kind!r}")
        if fixed is not None and kind == "covariance":
            raise ValueError("fixed: a 'covariance' (Cholesky) tensor has no fixed entries; use 'variance' for a "
                             "diagonal one")
        self.kind, self.fixed, self.groups, self.lower, self.upper, self.label = kind, fixed, groups, lower, upper, label

    def __repr__(self) -> str:
        extra = "".join(f", {k}={v!r}" for k, v in (("lower", self.lower), ("upper", self.upper),
                                                     ("label", self.label)) if v is not None)
        extra += "".join(f", {k}=..." for k in ("fixed", "groups") if getattr(self, k) is not None)
        return f"Param({self.kind!r}{extra})"


@entry_point(matrix=Finite(square=True))
def stationary(matrix: Tensor) -> Tensor:
    """The stationary (ergodic) distribution ``pi = pi P`` of row-stochastic ``(*P, M, M)`` matrices,
    ``(*P, M)``, solved exactly and differentiable in ``matrix`` (an estimated transition matrix's start
    probabilities, statsmodels' default). Needs an irreducible chain (a unique solution).

    Examples:
        >>> stationary(torch.tensor([[0.9, 0.1], [0.2, 0.8]]))
        tensor([0.6667, 0.3333])
    """
    if not isinstance(matrix, Tensor) or not matrix.is_floating_point() or matrix.dim() < 2 \
            or matrix.shape[-1] != matrix.shape[-2]:
        raise ValueError(f"matrix: expected row-stochastic (*P, M, M) floating-point matrices, got "
                         f"{tuple(matrix.shape) if isinstance(matrix, Tensor) else type(matrix).__name__}")
    M = matrix.shape[-1]
    eye = torch.eye(M, dtype=matrix.dtype, device=matrix.device)
    A = torch.cat([(matrix.mT - eye)[..., :-1, :], torch.ones_like(matrix[..., :1, :])], dim=-2)
    b = torch.zeros(matrix.shape[:-1], dtype=matrix.dtype, device=matrix.device)
    b[..., -1] = 1.0
    return torch.linalg.solve(A, b)


def _index(shape: torch.Size, flat: int) -> str:
    """``flat``'s multi-index in ``shape`` as ``[i,j]`` (``""`` for a scalar)."""
    idx = []
    for size in reversed(shape):
        idx.append(flat % size)
        flat //= size
    return "[" + ",".join(str(i) for i in reversed(idx)) + "]" if shape else ""


class Block:
    """One estimated tensor: its free values ``u`` (float64) and the map ``u -> tensor``."""

    def __init__(self, name: str, value: Tensor, param: Param):
        self.name, self.param, self.kind = name, param, param.kind
        self.label = param.label or name
        self.value = value.detach()
        self.shape, self.dtype, self.device = value.shape, value.dtype, value.device
        v = self.value.to(torch.float64).cpu()
        size = v.numel()
        fixed = torch.zeros(self.shape, dtype=torch.bool)
        if param.fixed is not None:
            try:
                fixed = torch.as_tensor(param.fixed, dtype=torch.bool).expand(self.shape).clone()
            except (RuntimeError, TypeError, ValueError):
                raise ValueError(f"parameters[{name!r}]: fixed: expected a boolean mask of shape {tuple(self.shape)}"
                                 ) from None
        if self.kind in ("variance", "covariance") and (v.dim() < 2 or v.shape[-1] != v.shape[-2]):
            raise ValueError(f"parameters[{name!r}]: a {self.kind!r} needs square matrices (*P, d, d), got shape "
                             f"{tuple(self.shape)}")
        if self.kind in ("stochastic", "probabilities") and v.dim() < (2 if self.kind == "stochastic" else 1):
            raise ValueError(f"parameters[{name!r}]: {self.kind!r} needs {'rows (*P, M, M)' if self.kind == 'stochastic' else 'a last axis of probabilities'}, got shape {tuple(self.shape)}")
        if self.kind == "variance":
            diag = torch.zeros(self.shape, dtype=torch.bool)
            diag.diagonal(dim1=-2, dim2=-1).fill_(True)
            fixed = fixed | ~diag
            if bool((v.diagonal(dim1=-2, dim2=-1) <= 0).any()):
                raise ValueError(f"parameters[{name!r}]: a 'variance' starts from a positive diagonal")
            off = torch.nonzero((v != 0) & ~diag)
            if len(off):  # (held there, the diagonal's estimate would be that of another model; and an
                # indefinite matrix a few steps away)
                where = "[" + ",".join(map(str, off[0].tolist())) + "]"
                raise ValueError(f"parameters[{name!r}]: a 'variance' estimates a diagonal matrix (its "
                                 f"off-diagonal entries 0), but the start has {len(off)} non-zero "
                                 f"off-diagonal entr{'y' if len(off) == 1 else 'ies'} ({where} = "
                                 f"{float(v[tuple(off[0])]):.6g}): kind 'covariance' estimates the full "
                                 "matrix; or start from a diagonal one")
        if self.kind in ("stochastic", "probabilities"):
            if bool((v < 0).any()) or not torch.allclose(v.sum(-1), torch.ones(()).double(), atol=1e-9):
                raise ValueError(f"parameters[{name!r}]: {self.kind!r} starts from probabilities (each "
                                 f"{'row' if self.kind == 'stochastic' else 'last axis'} non-negative, summing to 1)")
            fixed = fixed | (v == 0)  # zeros stay zeros
        groups = torch.full(self.shape, -1, dtype=torch.long)
        if param.groups is not None:
            try:
                groups = torch.as_tensor(param.groups).expand(self.shape).to(torch.long).clone()
            except (RuntimeError, TypeError, ValueError):
                raise ValueError(f"parameters[{name!r}]: groups: expected an integer tensor of shape "
                                 f"{tuple(self.shape)}") from None
        self.fixed = fixed
        flat_fixed, flat_groups = fixed.reshape(-1), groups.reshape(-1)
        if self.kind == "covariance":
            d = self.shape[-1]
            tril = torch.tril(torch.ones(d, d, dtype=torch.bool)).expand(self.shape)
            self.reported = torch.nonzero(tril.reshape(-1))[:, 0]  # the lower triangle's entries
            L, info = torch.linalg.cholesky_ex(v)
            if bool((info != 0).any()) or not bool(torch.isfinite(L).all()):
                raise ValueError(f"parameters[{name!r}]: a 'covariance' starts from a positive definite "
                                 "matrix (its Cholesky factor L L^T); this one is singular or indefinite "
                                 "(kind 'variance' estimates a diagonal one, or start from a positive "
                                 "definite one)")
            start = torch.where(torch.eye(d, dtype=torch.bool), L.diagonal(dim1=-2, dim2=-1).log().diag_embed(), L)
            self.u0 = start.reshape(-1)[self.reported]
            self.slot = None
        elif self.kind in ("stochastic", "probabilities"):
            rows = v.reshape(-1, self.shape[-1])
            free = ~fixed.reshape(-1, self.shape[-1])
            self.rows_free = free
            ref = torch.full((rows.shape[0],), -1, dtype=torch.long)
            for r in range(rows.shape[0]):  # (once, at construction)
                idx = torch.nonzero(free[r])[:, 0]
                if len(idx):
                    ref[r] = idx[-1]
            self.ref = ref
            logits = torch.zeros_like(rows)
            entries = []
            for r in range(rows.shape[0]):
                if ref[r] < 0:
                    continue
                for j in torch.nonzero(free[r])[:, 0].tolist():
                    if j != int(ref[r]):
                        entries.append(r * rows.shape[1] + j)
                        logits[r, j] = rows[r, j].log() - rows[r, ref[r]].log()
            self.entries = torch.tensor(entries, dtype=torch.long)
            self.u0 = logits.reshape(-1)[self.entries] if entries else torch.zeros(0, dtype=torch.float64)
            # a row's free entries, where it has two or more (a row with one free entry holds it at the rest
            # of its mass: nothing of it is estimated, so nothing is reported)
            self.reported = torch.nonzero((free & (free.sum(-1, keepdim=True) > 1)).reshape(-1))[:, 0]
            self.fixed_mass = torch.where(free, 0.0, rows).sum(-1)  # each row's fixed probability
            if bool((self.fixed_mass > 1 + 1e-12).any()):
                raise ValueError(f"parameters[{name!r}]: the fixed entries of a row sum to more than 1")
        else:  # free, variance: one value per free entry, or per group
            slot = torch.full((size,), -1, dtype=torch.long)
            reps, first_of_group = [], {}
            for i in range(size):  # (once, at construction)
                if bool(flat_fixed[i]):
                    continue
                g = int(flat_groups[i])
                if g >= 0 and g in first_of_group:
                    slot[i] = first_of_group[g]
                    continue
                slot[i] = len(reps)
                reps.append(i)
                if g >= 0:
                    first_of_group[g] = slot[i].item()
            self.slot, self.reported = slot, torch.tensor(reps, dtype=torch.long)
            start = v.reshape(-1)[self.reported]
            self.u0 = self._inverse(start)
        if self.u0.numel() == 0:
            zeros = " (a probability's zeros stay zero: start from positive ones)" \
                if self.kind in ("stochastic", "probabilities") else ""
            raise ValueError(f"parameters[{name!r}]: every entry is fixed{zeros}: nothing to estimate")

    # -- the free entries' transforms (kind free and variance) -----------------------------------------
    def _inverse(self, x: Tensor) -> Tensor:
        lo, hi = self.param.lower, self.param.upper
        if self.kind == "variance":
            return x.log()
        if lo is not None and hi is not None:
            if bool(((x <= lo) | (x >= hi)).any()):
                raise ValueError(f"parameters[{self.name!r}]: the start lies outside its bounds ({lo}, {hi})")
            p = (x - lo) / (hi - lo)
            return p.log() - (-p).log1p()
        if lo is not None:
            if bool((x <= lo).any()):
                raise ValueError(f"parameters[{self.name!r}]: the start is not above its lower bound {lo}")
            return (x - lo).log()
        if hi is not None:
            if bool((x >= hi).any()):
                raise ValueError(f"parameters[{self.name!r}]: the start is not below its upper bound {hi}")
            return (hi - x).log()
        return x.clone()

    def _forward(self, u: Tensor) -> Tensor:
        lo, hi = self.param.lower, self.param.upper
        if self.kind == "variance":
            return u.exp()
        if lo is not None and hi is not None:
            return lo + (hi - lo) * torch.sigmoid(u)
        if lo is not None:
            return lo + u.exp()
        if hi is not None:
            return hi - u.exp()
        return u

    def build(self, u: Tensor) -> Tensor:
        """The tensor at free values ``u`` (float64, differentiable), in the filter's dtype and device."""
        base = self.value.to(torch.float64).cpu()
        if self.kind == "covariance":
            d = self.shape[-1]
            flat = torch.zeros(base.numel(), dtype=u.dtype).index_put((self.reported,), u)
            raw = flat.view(self.shape)
            eye = torch.eye(d, dtype=torch.bool)
            L = torch.where(eye, raw.diagonal(dim1=-2, dim2=-1).exp().diag_embed(), torch.tril(raw, -1))
            out = L @ L.mT
        elif self.kind in ("stochastic", "probabilities"):
            rows = base.reshape(-1, self.shape[-1])
            logits = torch.zeros(rows.numel(), dtype=u.dtype).index_put((self.entries,), u).view(rows.shape)
            logits = torch.where(self.rows_free, logits, -math.inf)
            soft = torch.softmax(logits, -1).nan_to_num(0.0)  # (a row without free entries: all fixed)
            out = torch.where(self.rows_free, (1 - self.fixed_mass).unsqueeze(-1) * soft, rows).view(self.shape)
        else:
            values = self._forward(u)
            flat = base.reshape(-1)
            gathered = values[self.slot.clamp_min(0)]
            out = torch.where(self.slot >= 0, gathered, flat).view(self.shape)
        return out.to(dtype=self.dtype, device=self.device)

    def natural(self, u: Tensor) -> Tensor:
        """The reported entries at ``u`` (float64): each free entry (one per group), each free
        probability, the lower triangle of a covariance."""
        return self.build(u).to(torch.float64).cpu().reshape(-1)[self.reported]

    def names(self) -> list[str]:
        return [f"{self.label}{_index(self.shape, int(i))}" for i in self.reported]


START = "belief0."


def blocks(filter: nn.Module, parameters: Mapping[str, Any], start: StartFields | None = None) -> list[Block]:
    """The estimated tensors of ``parameters`` (``{name: Param or kind}``), checked against the filter
    (and, for names ``belief0.<field>``, against the start belief's fields ``start``)."""
    if not parameters:
        raise ValueError("parameters: empty (name the tensors to estimate)")
    blocks = []
    for name, param in parameters.items():
        if not isinstance(name, str):
            raise TypeError(f"parameters: keys are tensor names (strings), got {name!r}")
        if isinstance(param, str):
            if param not in KINDS:
                raise ValueError(f"parameters[{name!r}]: expected a Param or one of {', '.join(KINDS)}, got {param!r}")
            param = Param(param)
        elif not isinstance(param, Param):
            raise TypeError(f"parameters[{name!r}]: expected a Param or a kind, got {type(param).__name__}")
        if name.startswith(START):
            if start is None:
                raise ValueError(f"parameters[{name!r}]: names a field of the start belief, but belief0 is a "
                                 "function (estimate a start belief's fields by giving the belief itself)")
            if name.endswith(".mode_log_probs"):
                raise ValueError(f"parameters[{name!r}]: the mode probabilities are estimated as "
                                 f"{name.removesuffix('.mode_log_probs')}.mode_probs (kind 'probabilities')")
            if name.endswith(".mode_probs") and param.kind != "probabilities":
                raise ValueError(f"parameters[{name!r}]: mode probabilities are estimated as 'probabilities', not "
                                 f"{param.kind!r}")
            blocks.append(Block(name, resolve(start, name.removeprefix(START), "belief0"), param))
            continue
        try:
            owner = filter.get_submodule(name.rpartition(".")[0]) if "." in name else filter
        except AttributeError:
            owner = None  # (no such module: _resolve names the tensors there are)
        if isinstance(owner, ModeTransition) and param.kind != "stochastic":
            raise ValueError(f"parameters[{name!r}]: a transition matrix is estimated as 'stochastic' (its rows stay "
                             f"probabilities), not {param.kind!r}")
        blocks.append(Block(name, resolve(filter, name), param))
    return blocks


@entry_point(filter=Of(nn.Module, what="a filter (an nn.Module)"),
             parameters=Of(Mapping, what="a mapping {tensor name: Param or kind}"),
             belief0=Of(Belief, optional=True))
def estimated_entries(filter: nn.Module, parameters: Mapping[str, Param | str],
                      belief0: Belief | None = None) -> list[str]:
    """The entries :func:`estimate` would report for ``parameters`` of ``filter`` (``"<label>[i,j]"``),
    every entry checked as :func:`estimate` checks it (an unknown tensor, a kind that does not fit it, a
    start outside its constraints, every entry fixed: ``ValueError`` naming ``parameters[...]``), without
    evaluating anything: a dry run of a fit's set-up.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import LinearMotion, LinearMeasurement
        >>> kf = KalmanFilter(LinearMotion([[1.0]], [[1.0]]), LinearMeasurement([[1.0]], [[2.0]]))
        >>> estimated_entries(kf, {"motion.Q": "variance", "measurement.R": Param("variance", label="R")})
        ['motion.Q[0,0]', 'R[0,0]']
    """
    return [n for b in blocks(filter, parameters, None if belief0 is None else StartFields(belief0)) for n in b.names()]


class StartFields(nn.Module):
    """A start belief's floating-point fields as buffers (``belief0.mean``, ``belief0.cov``,
    ``belief0.components.mean``, ``belief0.mode_probs`` for the mode log-probabilities), so that
    :func:`estimate` can estimate them by name. A field the belief broadcasts (an expanded view: stride 0
    along an axis) is held once along that axis - one value estimated for every run or mode it is
    broadcast to - and expanded again by :meth:`build`."""

    def __init__(self, belief: Belief):
        super().__init__()
        self._template = belief
        self._layout: dict[str, tuple[str, tuple[int, ...], torch.Size]] = {}
        for f in dataclasses.fields(belief):
            value = getattr(belief, f.name)
            if isinstance(value, Belief):
                self.add_module(f.name, StartFields(value))
            elif isinstance(value, Tensor) and value.is_floating_point():
                keep = tuple(1 if st == 0 and n > 1 else n for n, st in zip(value.shape, value.stride()))
                compact = value[tuple(slice(0, 1) if k == 1 and n > 1 else slice(None)
                                      for k, n in zip(keep, value.shape))]
                squeezed = compact.reshape([n for n, k, full in zip(compact.shape, keep, value.shape)
                                            if not (k == 1 and full > 1)])
                name = "mode_probs" if f.name == "mode_log_probs" else f.name
                self.register_buffer(name, (squeezed.exp() if name != f.name else squeezed).detach().clone())
                self._layout[name] = (f.name, keep, value.shape)

    def build(self) -> Belief:
        """The belief with the buffers' current values (expanded where it broadcasts them)."""
        values = {}
        for f in dataclasses.fields(self._template):
            value = getattr(self._template, f.name)
            if isinstance(value, Belief):
                values[f.name] = getattr(self, f.name).build()
                continue
            values[f.name] = value
            for name, (field_name, keep, full) in self._layout.items():
                if field_name == f.name:
                    t = getattr(self, name).reshape(keep).expand(full)
                    values[f.name] = t.log() if name != field_name else t
        return type(self._template)(**values)


def resolve(filter: nn.Module, name: str, what: str = "filter") -> Tensor:
    named = dict(filter.named_buffers(remove_duplicate=False)) | dict(filter.named_parameters(remove_duplicate=False))
    if name not in named:
        if what == "belief0":
            tensors = [START + n for n in sorted(named)]
            raise ValueError(f"parameters: {START + name!r} is not a field of the start belief (its fields: "
                             f"{', '.join(tensors)})")
        tensors = sorted(named)
        raise ValueError(f"parameters: {name!r} is not a tensor of the filter (its tensors: {', '.join(tensors)})")
    owner, _, attr = name.rpartition(".")
    value = getattr(filter.get_submodule(owner) if owner else filter, attr)
    if not value.is_floating_point():
        raise TypeError(f"parameters[{name!r}]: not a floating-point tensor ({value.dtype})")
    return value


def write_back(filter: nn.Module, name: str, value: Tensor) -> None:
    """The estimate into the filter's tensor ``name``: in place, or as a tensor of its own where the
    model holds the same tensor object under another name too (it would change both)."""
    current = resolve(filter, name)
    tied = [n for n, t in (*filter.named_buffers(remove_duplicate=False),
                           *filter.named_parameters(remove_duplicate=False)) if t is current and n != name]
    if not tied:
        current.copy_(value)
        return
    owner, _, attr = name.rpartition(".")
    module = filter.get_submodule(owner) if owner else filter
    if attr in module._buffers:
        module._buffers[attr] = value.detach().clone()
    else:
        module._parameters[attr] = nn.Parameter(value.detach().clone(), requires_grad=current.requires_grad)

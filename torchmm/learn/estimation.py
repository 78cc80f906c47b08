r"""Maximum-likelihood estimation of any tensor of a filter, with standard errors (issue 45).

:func:`estimate` estimates named tensors of a filter - a bank's stacked ``H``, ``R``, ``F``, ``Q``, offsets,
the transition matrix, the start belief's fields (``belief0.mean``, ``belief0.mode_probs``, ...) -
by maximising the log-likelihood of the data, and reports each estimated entry with its standard
error from the observed information:

* **What is estimated** is declared per tensor by a :class:`Param`: its *kind* (``"free"`` entries on
  the real line or between bounds, ``"variance"`` (positive diagonal), ``"covariance"`` (a full
  positive-definite matrix through its Cholesky factor), ``"stochastic"`` (rows of a transition matrix:
  each row a softmax over its free entries, zeros kept), ``"probabilities"`` (the last axis sums to
  one)), the entries held *fixed*, and *groups* of entries that share one value (e.g. a regression
  coefficient shared by every regime).
* **The free vector** ``theta`` gathers every unconstrained value; each tensor is rebuilt from it at
  every evaluation and put in the filter's place for that evaluation
  (:func:`torch.func.functional_call`), so whatever reads the filter - its steps, the whole-run
  kernels of :class:`~torchmm.learn.Objective` - sees the estimated values. Nothing of the filter is
  changed in place until the end, when the estimates are written back (``write=True``).
* **The optimiser** is ``scipy.optimize.minimize`` (L-BFGS-B by default, statsmodels' choice), with
  the gradient from autograd; the objective is :class:`~torchmm.learn.Objective` (checked once, the
  kernels where they apply).
* **Standard errors**: the observed information ``I = -d^2 log L / d theta^2`` by autograd at the
  optimum (the eager steps: a second derivative through every step), ``Cov(theta) = I^{-1}``, and
  each reported entry ``g(theta)`` by the delta method, ``Cov(g) = J I^{-1} J^T``. At a maximum this
  equals the inverse information in the natural parameters, whatever the parametrisation (the
  Hessians differ by ``J^T H J`` only where the gradient is zero), so the errors are those of
  statsmodels' ``cov_type="approx"`` up to its finite differences. An information that is not
  positive definite (a boundary, a flat direction) gives NaN errors and says so (``Estimate.note``).
* **Criteria**: the log-likelihood, ``k`` (the free values), ``nobs`` (the steps with a measurement),
  AIC ``= -2 log L + 2 k``, BIC ``= -2 log L + k log nobs``, and for a ``"stochastic"`` tensor the
  expected durations ``1 / (1 - p_ii)`` with their delta-method errors.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from torchmm.beliefs import Belief
from torchmm.contract import Choice, Data, Finite, Flag, Int, Of, Real, Text, Unchecked, entry_point
from torchmm.filters.base import Filter
from torchmm.models.transition import ModeTransition
from torchmm.runtime import one_thread_when_small

__all__ = ["KINDS", "Estimate", "Param", "estimate", "estimated_entries", "stationary"]

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
            free ones share the rest of the row's mass); ``"probabilities"``: the last axis a probability
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


class _Block:
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
            L = torch.linalg.cholesky(v)
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
            self.reported = torch.nonzero(free.reshape(-1))[:, 0]
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


@dataclass
class Estimate:
    """What :func:`estimate` found.

    Attributes:
        names: the reported entries, ``"<label>[i,j]"``; ``estimates``, ``se``: their values and
            standard errors (NaN where the information is not positive definite); ``z = estimate / se``.
        cov: the covariance of the reported entries ``(K, K)`` (delta method).
        theta, theta_cov: the free values at the optimum and the inverse information.
        loglik: the log-likelihood at the optimum (the sum over the runs); ``k``: the free values;
        nobs: the steps with a measurement; ``aic``, ``bic``.
        durations: ``[(name, 1 / (1 - p_ii), se)]`` for each ``"stochastic"`` tensor's diagonal.
        converged, iterations, evaluations, message, seconds: the optimiser's.
        note: why the errors are NaN, if they are.
        belief0: the start belief with its estimated fields (``"belief0.<field>"`` parameters; the given
            belief where none is estimated; None for a start function).
    """

    names: list[str]
    estimates: list[float]
    se: list[float]
    cov: Tensor
    theta: Tensor
    theta_cov: Tensor
    loglik: float
    k: int
    nobs: int
    converged: bool
    iterations: int
    evaluations: int
    message: str
    seconds: float
    method: str
    durations: list[tuple[str, float, float]] = field(default_factory=list)
    note: str = ""
    belief0: Belief | None = None

    @property
    def z(self) -> list[float]:
        return [e / s if s and math.isfinite(s) and s > 0 else math.nan for e, s in zip(self.estimates, self.se)]

    @property
    def aic(self) -> float:
        return -2 * self.loglik + 2 * self.k

    @property
    def bic(self) -> float:
        return -2 * self.loglik + self.k * math.log(max(self.nobs, 1))

    def rows(self) -> list[list]:
        """``[name, estimate, se, z]`` per reported entry (the ``learned`` table)."""
        return [[n, e, s, z] for n, e, s, z in zip(self.names, self.estimates, self.se, self.z)]

    def __getitem__(self, name: str) -> tuple[float, float]:
        """``(estimate, se)`` of a reported entry by name."""
        try:
            i = self.names.index(name)
        except ValueError:
            raise KeyError(f"{name!r} is not a reported entry ({', '.join(self.names)})") from None
        return self.estimates[i], self.se[i]


START = "belief0."


def _blocks(filter: nn.Module, parameters: Mapping[str, Any], start: _Start | None = None) -> list[_Block]:
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
            blocks.append(_Block(name, _resolve(start, name.removeprefix(START), "belief0"), param))
            continue
        try:
            owner = filter.get_submodule(name.rpartition(".")[0]) if "." in name else filter
        except AttributeError:
            owner = None  # (no such module: _resolve names the tensors there are)
        if isinstance(owner, ModeTransition) and param.kind != "stochastic":
            raise ValueError(f"parameters[{name!r}]: a transition matrix is estimated as 'stochastic' (its rows stay "
                             f"probabilities), not {param.kind!r}")
        blocks.append(_Block(name, _resolve(filter, name), param))
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
    return [n for b in _blocks(filter, parameters, None if belief0 is None else _Start(belief0)) for n in b.names()]


class _Call(nn.Module):
    """The objective as a module's forward, so that :func:`torch.func.functional_call` puts the
    estimated tensors in the filter's place for one evaluation."""

    def __init__(self, filter: nn.Module, fn: Callable[[], Tensor], start: _Start | None = None):
        super().__init__()
        self.filter = filter
        self.start = start
        self.fn = fn

    def forward(self) -> Tensor:
        return self.fn()


class _Start(nn.Module):
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
                self.add_module(f.name, _Start(value))
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


def _resolve(filter: nn.Module, name: str, what: str = "filter") -> Tensor:
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


def _write(filter: nn.Module, name: str, value: Tensor) -> None:
    """The estimate into the filter's tensor ``name``: in place, or as a tensor of its own where the
    model holds the same tensor object under another name too (it would change both)."""
    current = _resolve(filter, name)
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


def _nobs(measurements: Tensor, burn: int, batch_dims: int) -> int:
    """The steps with a measurement after ``burn``, summed over the runs."""
    finite = torch.isfinite(measurements[burn:])
    return int(finite.reshape(*finite.shape[:1 + batch_dims], -1).any(-1).sum())


@entry_point(filter=Of(Filter), belief0=Of(Belief, callable_ok=True, what="a belief or a function filter -> belief"),
             measurements=Data(),
             parameters=Of(Mapping, what="a mapping {tensor name: Param or kind}"),
             controls=Data(optional=True),
             motions=Of((list, tuple), callable_ok=True, optional=True,
                        what="a sequence of T models, a callable k -> model, or None"),
             update_first=Flag(), burn=Int(0),
             method=Choice("L-BFGS-B", "BFGS", "CG", "TNC", "SLSQP", "trust-constr"),
             se=Flag(), hessian=Choice("differences", "autograd"), tol=Real(positive=True, optional=True),
             maxiter=Int(1, optional=True),
             write=Flag(), progress=Unchecked("None, True, False or a description"))
@one_thread_when_small(lambda filter, belief0, measurements, *args, **kwargs:
                       measurements[0].numel() * max(1, getattr(filter, "num_modes", 1) or 1) * 8)
def estimate(filter: Filter, belief0: Belief | Callable[[Filter], Belief], measurements: Tensor,
        parameters: Mapping[str, Param | str], *, controls: Tensor | None = None, motions: Any = None,
        update_first: bool = False,
        burn: int = 0, method: str = "L-BFGS-B", se: bool = True, hessian: str = "differences",
        tol: float | None = None,
        maxiter: int | None = None, write: bool = True, progress: bool | str | None = None) -> Estimate:
    r"""The maximum-likelihood estimates of ``parameters`` (tensors of ``filter`` by name), with standard
    errors from the observed information (module docstring).

    Args:
        filter: any filter whose log-likelihood :class:`~torchmm.learn.Objective` evaluates.
        belief0: the start belief, or a function ``filter -> belief`` (called at every evaluation, with
            the estimated tensors in place: e.g. the ergodic mode probabilities of the estimated transition
            matrix, :func:`stationary`).
        measurements: ``(T, *B, m)``, NaN missing; the runs ``*B`` share the parameters (their
            log-likelihoods add up).
        parameters: ``{name: Param or kind}``: the tensors of ``filter`` to estimate, by their names in
            ``filter.named_buffers()`` / ``named_parameters()`` (``"transition.value"``,
            ``"bank.filter.measurement.H"``, ...; a wrong name lists them), and the start belief's fields
            as ``"belief0.<field>"`` where ``belief0`` is a belief (``"belief0.mean"``, ``"belief0.cov"``;
            a mode belief's ``"belief0.mode_probs"`` (kind ``"probabilities"``) and
            ``"belief0.components.mean"``): a field the belief broadcasts (an ``expand``-ed view) is one
            value for every run or mode it is broadcast to, a materialised one a value each.
        controls: ``(T, *B, k)`` inputs ``u_k`` of the motion models (e.g. regressors).
        motions: per-step motion models (irregular time stamps: one model per step,
            :func:`~torchmm.run_filter`'s ``motions``), or None. The estimated tensors are the filter's:
            those of the per-step models are fixed (a motion's own tensors are not shared with them).
        update_first: ``belief0`` is the prior of the first measurement.
        burn: the first steps' log-likelihood terms left out.
        method: ``scipy.optimize.minimize``'s (a gradient method).
        se: compute the standard errors from the observed information.
        hessian: how the information is computed: ``"differences"`` (default): central differences of the
            exact (autograd) gradient, ``2 k`` evaluations through the kernels where they apply, step
            ``1e-5 max(1, |theta_i|)`` (agrees with the exact Hessian to about 1e-7 relative,
            tests/learn/test_estimate.py); ``"autograd"``: the exact second derivative through the eager
            steps (no kernel has a second derivative: slower, seconds for a few hundred steps).
        tol, maxiter: the optimiser's tolerance and iteration limit (default for L-BFGS-B: ``ftol=1e-13``,
            ``gtol=1e-8`` in float64, tighter than scipy's, which stops short on a flat likelihood; ``1e-6``
            and ``1e-3`` in float32).
        write: leave the estimates in the filter's tensors (in place, without gradient).
        progress: a bar over the evaluations (None: on a terminal only).

    Returns:
        an :class:`Estimate` (``Estimate.belief0``: the start belief with its estimated fields).

    Raises:
        ValueError / TypeError naming ``parameters`` (an unknown name, a kind that does not fit the
        tensor, a start outside its constraints, every entry fixed) or the other arguments.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import LinearMotion, LinearMeasurement
        >>> one = torch.ones(1, 1, dtype=torch.float64)
        >>> kf = KalmanFilter(LinearMotion(one, one), LinearMeasurement(one, one))
        >>> z = torch.randn(200, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0)).cumsum(0)
        >>> est = estimate(kf, GaussianBelief(torch.zeros(1, dtype=torch.float64), one), z, {"motion.Q": "variance"})
        >>> est.names, est.converged, est.se[0] > 0
        (['motion.Q[0,0]'], True, True)
    """
    from scipy.optimize import minimize
    from tqdm.auto import tqdm

    import torchmm.kernels as kernels
    from torchmm.learn.objective import Objective

    held = _Start(belief0) if isinstance(belief0, Belief) else None
    blocks = _blocks(filter, parameters, held)
    given = belief0 if isinstance(belief0, Belief) else None
    if held is not None and any(b.name.startswith(START) for b in blocks):
        belief0 = lambda f: held.build()  # noqa: E731 (the start's estimated fields in place at each evaluation)
    sizes = [b.u0.numel() for b in blocks]
    theta0 = torch.cat([b.u0 for b in blocks]).to(torch.float64)
    objective = Objective(filter, belief0, measurements, reduction="sum", update_first=update_first,
                          controls=controls, motions=motions, burn=burn)
    call = _Call(filter, objective, held)

    def substitutes(theta: Tensor) -> dict[str, Tensor]:
        return {"start." + b.name.removeprefix(START) if b.name.startswith(START) else f"filter.{b.name}": b.build(u)
                for b, u in zip(blocks, theta.split(sizes))}

    def loss_at(theta: Tensor) -> Tensor:
        # tie_weights=False: a tensor object that the model holds under two names (LinearMotion(I, I): F
        # and Q the same tensor) is substituted under the estimated name only
        return torch.func.functional_call(call, substitutes(theta), (), tie_weights=False)

    estimate.objective = objective  # (the last call's: which kernel ran, objective.kernel / objective.why)
    evaluations = [0]
    bar = tqdm(desc=progress if isinstance(progress, str) else "estimate", disable=None if progress is None
               else not progress, leave=False)

    def loss_and_grad(x):
        theta = torch.from_numpy(x).requires_grad_(True)
        loss = loss_at(theta)
        (grad,) = torch.autograd.grad(loss, theta)
        evaluations[0] += 1
        bar.update(1)
        bar.set_postfix(nll=f"{float(loss.detach()):.6g}")
        return float(loss.detach()), grad.numpy()

    options = {} if maxiter is None else {"maxiter": int(maxiter)}
    if tol is None and method == "L-BFGS-B":  # to the optimum, not near it (likelihoods are cheap; scipy's
        # default ftol stops ~1e-4 short in flat directions); float32 likelihoods are only so precise
        single = measurements.dtype == torch.float32
        options.update(ftol=1e-6 if single else 1e-13, gtol=1e-3 if single else 1e-8)
    tic = time.perf_counter()
    try:
        result = minimize(loss_and_grad, theta0.numpy(), jac=True, method=method, tol=tol, options=options)
    finally:
        bar.close()
    theta = torch.from_numpy(result.x).to(torch.float64)
    with torch.no_grad():
        loglik = -float(loss_at(theta))
    natural = torch.cat([b.natural(u) for b, u in zip(blocks, theta.split(sizes))])
    names = [n for b in blocks for n in b.names()]
    K = len(names)
    cov = torch.full((K, K), math.nan, dtype=torch.float64)
    theta_cov = torch.full((len(theta), len(theta)), math.nan, dtype=torch.float64)
    note = ""
    if se:
        if hessian == "autograd":
            with kernels.switched_off(*kernels.names()):  # the eager steps: a second derivative through them
                eager = _Call(filter, Objective(filter, belief0, measurements, reduction="sum",
                                                update_first=update_first, controls=controls, motions=motions,
                                                burn=burn), held)
                H = torch.autograd.functional.hessian(
                    lambda t: torch.func.functional_call(eager, substitutes(t), (), tie_weights=False), theta)
        else:  # central differences of the exact gradient (2 k evaluations, the kernels where they apply)
            H = torch.empty(len(theta), len(theta), dtype=torch.float64)
            for i in range(len(theta)):
                h = 1e-5 * max(1.0, abs(float(theta[i])))
                step = torch.zeros_like(theta)
                step[i] = h
                up = torch.from_numpy(loss_and_grad((theta + step).numpy())[1])
                down = torch.from_numpy(loss_and_grad((theta - step).numpy())[1])
                H[i] = (up - down) / (2 * h)
        hessian = 0.5 * (H + H.mT)
        L, info = torch.linalg.cholesky_ex(hessian)
        if int(info) == 0:
            theta_cov = torch.cholesky_inverse(L)
            J = torch.autograd.functional.jacobian(
                lambda t: torch.cat([b.natural(u) for b, u in zip(blocks, t.split(sizes))]), theta)
            cov = J @ theta_cov @ J.mT
        else:
            note = ("the observed information is not positive definite at the optimum (a parameter on a boundary, "
                    "or one the data do not identify): no standard errors")
    errors = cov.diagonal().clamp_min(0).sqrt()
    durations = []
    for b, u in zip(blocks, theta.split(sizes)):
        if b.kind != "stochastic":
            continue
        M = b.shape[-1]

        def duration(t, b=b):
            P = b.build(t).to(torch.float64).cpu().reshape(-1, M, M)
            return (1 / (1 - P.diagonal(dim1=-2, dim2=-1))).reshape(-1)
        start = sum(sizes[:blocks.index(b)])
        d = duration(u)
        if se and not note:
            Jd = torch.autograd.functional.jacobian(duration, u)
            cov_u = theta_cov[start:start + u.numel(), start:start + u.numel()]
            d_se = (Jd @ cov_u @ Jd.mT).diagonal().clamp_min(0).sqrt()
        else:
            d_se = torch.full_like(d, math.nan)
        rows = d.numel() // M
        for i in range(d.numel()):
            where = f"[{i // M},{i % M}]" if rows > 1 else f"[{i}]"
            durations.append((f"duration of {b.label}{where}", float(d[i]), float(d_se[i])))
    with torch.no_grad():
        for b, u in zip(blocks, theta.split(sizes)):
            if b.name.startswith(START):
                _write(held, b.name.removeprefix(START), b.build(u))
            elif write:
                _write(filter, b.name, b.build(u))
        start_belief = held.build() if held is not None and given is not belief0 else given
    batch_dims = measurements.dim() - 2
    return Estimate(names=names, estimates=natural.tolist(), se=errors.tolist(), cov=cov, theta=theta,
                    theta_cov=theta_cov, loglik=loglik, k=len(theta), nobs=_nobs(measurements, burn, batch_dims),
                    converged=bool(result.success), iterations=int(getattr(result, "nit", 0)),
                    evaluations=evaluations[0], message=str(result.message), seconds=time.perf_counter() - tic,
                    method=method, durations=durations, note=note, belief0=start_belief)

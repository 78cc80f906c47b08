"""The batch-last kernels' Gaussian algebra, written once (issue 47: free functions each kernel composes, not
methods of one class): a model matrix's entries classified once (:class:`Coef`, :func:`coefficients`) and
combined with the fewest operations (:func:`combine`); on per-entry tensors (``X[a]``, the upper triangle
``C[a][c]``, each ``(..., *B)``, the batch last) the regularised Cholesky factor of torchmm.linalg.cholesky
(:func:`factor`), the triangular solves, the mixing and collapse of Gaussian mixtures and the sandwich ``F C
F^T + Q``. The IMM / GPB1 step (:mod:`~torchmm.kernels.batch_last.imm`), GPB2's pairs, the unscented modes,
the two-filter smoother and IMM-TF's transfer compose them."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.beliefs.ops import live_log

__all__ = ["ONE", "ZERO", "Coef", "cholesky_entries", "coefficients", "collapse_entries", "collapse_modes", "combine",
           "factor", "log_normalized", "mix_entries", "mixing", "mode_update", "moments", "sandwich", "solve_lower",
           "solve_lower_transposed", "stack_upper", "sum_terms"]


class Coef:
    """One entry of a model matrix, classified once at the entry point: exactly zero or one in every
    mode (its products are skipped: bit-identical, as ``x * 0 = 0`` and ``x * 1 = x`` are exact), one
    number shared by the modes (a 0-dim tensor), or a tensor ``(1 or M, 1, ...)``. Entries of
    parameters that require gradients are always tensors (a skipped zero would lose its gradient)."""

    __slots__ = ("kind", "value")

    def __init__(self, kind: str, value=None):
        self.kind, self.value = kind, value


ZERO, ONE = Coef("zero"), Coef("one")


def coefficients(t: Tensor, M: int, event: int, batch_dims: int) -> list:
    """A parameter ``([1 or M,] *event)`` as nested lists (``event`` deep) of :class:`Coef`."""
    if t.dim() == event:
        t = t.unsqueeze(0)
    front = t.movedim(0, -1)  # (*event, P)
    front = front.reshape(*front.shape, *([1] * batch_dims))  # (*event, P, 1...)
    traced = t.requires_grad and torch.is_grad_enabled()
    entries = front.flatten(0, event - 1).unbind(0) if event > 1 else front.unbind(0)
    if traced:
        flat = [Coef("tensor", entry) for entry in entries]
    else:
        # every entry's kind in one pass and one host read, at the entry point: 0 zero in every mode,
        # 1 one in every mode, 2 one number shared by the modes, 3 per mode
        values = t.detach().flatten(1)  # (P, entries)
        first = values[0]
        kind = torch.where((values == 0).all(0), 0, torch.where((values == 1).all(0), 1,
                           torch.where((values == first).all(0), 2, 3))).tolist()
        # 0-dim copies (an operation with a Python number costs more dispatch than with a tensor)
        shared = first.clone().unbind(0)
        flat = [ZERO if k == 0 else ONE if k == 1 else Coef("scalar", shared[e]) if k == 2
                else Coef("tensor", entries[e]) for e, k in enumerate(kind)]
    if event == 1:
        return flat
    cols = t.shape[-1]
    return [flat[a * cols:(a + 1) * cols] for a in range(t.shape[-2])]


def sum_terms(terms: list) -> Tensor:
    """``terms[0] + terms[1] + ...``, in that order."""
    acc = terms[0]
    for t in terms[1:]:
        acc = acc + t
    return acc


def combine(terms, const: Coef = ZERO, like: Tensor | None = None) -> Tensor:
    """``sum_e coef_e * t_e + const`` with the fewest operations (zero terms skipped, ones added,
    shared scalars and per-mode tensors through ``addcmul``).

    ``like``: a tensor to take the shape from when every term is zero."""
    acc = None
    for coef, t in terms:
        if coef.kind == "zero":
            continue
        if acc is None:
            acc = t if coef.kind == "one" else t * coef.value
        elif coef.kind == "one":
            acc = acc + t
        else:  # a shared scalar (0-dim) or a per-mode tensor
            acc = torch.addcmul(acc, t, coef.value)
    if acc is None:
        acc = torch.zeros_like(like)
    if const.kind == "zero":
        return acc
    return acc + (1.0 if const.kind == "one" else const.value)


def stack_upper(C: list) -> Tensor:
    """The upper triangle ``C[a][c]`` (``a <= c``) of per-entry tensors as one symmetric ``(n, n, ...)``."""
    n = len(C)
    return torch.stack([C[min(a, c)][max(a, c)] for a in range(n) for c in range(n)]).unflatten(0, (n, n))


def factor(S: list, with_flag: bool = False):
    """:func:`torchmm.linalg.cholesky`'s regularised factor of the per-entry symmetric ``S`` (upper
    triangle ``S[a][c]``, ``a <= c``, of any size ``len(S)``), the same formulas entry by entry: for
    sizes up to 2 its closed form (pivots clamped at ``eps max|S_aa|``, ``tiny`` for size 1);
    beyond, the Cholesky factor where every pivot is positive, elsewhere the factor of
    ``S + sqrt(eps) s I`` (``s = max |S_aa|``), and where that fails too ``diag(sqrt(max(S_aa, eps
    s)))`` - ``cholesky_ex``'s retry, without reading a value on the host. Returns the lower
    triangle ``L[a][c]`` (``c <= a``) and, with ``with_flag``, where ``S`` was regularised
    (:func:`~torchmm.linalg.cholesky`'s flag)."""
    n = len(S)
    tiny = torch.finfo(S[0][0].dtype).tiny
    if n == 1:
        L = [[S[0][0].clamp_min(tiny).sqrt()]]
        return (L, ~(S[0][0] > tiny)) if with_flag else L
    if n == 2:
        a, b, c = S[0][0], S[0][1], S[1][1]
        scale = torch.maximum(a.abs(), c.abs()) * torch.finfo(a.dtype).eps + tiny
        l11 = a.clamp_min(0).maximum(scale).sqrt()
        l21 = b / l11
        pivot = c - l21 * l21
        L = [[l11, None], [l21, pivot.maximum(scale).sqrt()]]
        return (L, ~((a > scale) & (pivot > scale))) if with_flag else L
    plain, failed = cholesky_entries(S, None)
    scale = S[0][0].abs()
    for a in range(1, n):
        scale = torch.maximum(scale, S[a][a].abs())
    scale = scale.nan_to_num(nan=1.0).clamp_min(tiny)
    jitter = torch.where(failed, scale * torch.finfo(scale.dtype).eps ** 0.5, 0.0)
    retry, failed_again = cholesky_entries(S, jitter)
    floor = torch.finfo(scale.dtype).eps * scale
    L = [[None] * n for _ in range(n)]
    for a in range(n):
        for c in range(a + 1):
            fallback = S[a][a].maximum(floor).sqrt() if a == c else torch.zeros_like(scale)
            L[a][c] = torch.where(failed, torch.where(failed_again, fallback, retry[a][c]), plain[a][c])
    return (L, failed) if with_flag else L

def cholesky_entries(S: list, jitter: Tensor | None) -> tuple[list, Tensor]:
    """The Cholesky factor of ``S (+ jitter I)`` entry by entry (lower ``L[a][c]``) and where a pivot
    is not positive (or NaN): ``cholesky_ex``'s failure."""
    n = len(S)
    L = [[None] * n for _ in range(n)]
    failed = None
    for j in range(n):
        pivot = S[j][j] if jitter is None else S[j][j] + jitter
        for k in range(j):
            pivot = pivot - L[j][k] * L[j][k]
        bad = ~(pivot > 0)
        failed = bad if failed is None else failed | bad
        L[j][j] = pivot.sqrt()
        for i in range(j + 1, n):
            acc = S[j][i]
            for k in range(j):
                acc = acc - L[i][k] * L[j][k]
            L[i][j] = acc / L[j][j]
    return L, failed

def solve_lower(L: list, rhs: list) -> list:
    """``L^{-1} rhs`` by forward substitution, ``rhs[e][c]`` (``len(L)`` rows of any number of columns)."""
    n = len(L)
    out = [None] * n
    for a in range(n):
        row = []
        for c in range(len(rhs[a])):
            acc = rhs[a][c]
            for k in range(a):
                acc = acc - L[a][k] * out[k][c]
            row.append(acc / L[a][a])
        out[a] = row
    return out

def solve_lower_transposed(L: list, rhs: list) -> list:
    """``L^{-T} rhs`` by back substitution, ``rhs[e][c]`` (``len(L)`` rows of any number of columns)."""
    n = len(L)
    out = [None] * n
    for a in range(n - 1, -1, -1):
        row = []
        for c in range(len(rhs[a])):
            acc = rhs[a][c]
            for k in range(a + 1, n):
                acc = acc - L[k][a] * out[k][c]
            row.append(acc / L[a][a])
        out[a] = row
    return out


def mixing(mu: Tensor, matrix: Tensor, tiny: Tensor, collapse: bool = False) -> tuple[Tensor, Tensor]:
    """The interaction of the mode probabilities ``mu (M, *B)`` through ``matrix (i, j, 1...)``: the predicted
    mode probabilities ``c_j = sum_i mu_i pi_ij`` ``(j, *B)`` and the mixing weights ``mu_{i|j} = pi_ij mu_i /
    c_j`` ``(i, j, *B)`` (``c_j`` floored at ``tiny``); ``collapse`` (GPB1): ``mu_i`` ``(i, 1, *B)``, every
    mode starting from the one collapsed posterior. Elementwise, not ``mm``: BLAS would round by the batch
    size, and a run's numbers must not depend on how the runs are chunked
    (tests/experiments/test_run_streams.py)."""
    mu_i = mu.unsqueeze(1)
    joint_ij = mu_i * matrix  # (i, j, *B)
    cbar = joint_ij.sum(0)  # (j, *B)
    return cbar, mu_i if collapse else joint_ij / torch.maximum(cbar, tiny).unsqueeze(0)


def log_normalized(joint: Tensor, norm: Tensor, size: int) -> Tensor:
    """``joint - norm`` as :func:`~torchmm.beliefs.ops.safe_log_normalize` gives it (a NaN, where every term
    was ``-inf`` or one was NaN, is the uniform ``-log(size)``), the group size written out (a traced step's
    tensors have no ``numel``)."""
    return (joint - norm).nan_to_num_(nan=-math.log(size), posinf=math.inf, neginf=-math.inf)


def mode_update(ll: Tensor, cbar: Tensor, anyob: Tensor, lowest: Tensor, zero: Tensor, M: int,
                tiny: Tensor) -> tuple:
    """The IMM's mode posterior ``log mu_j = ell_j + log c_j - logsumexp_l(ell_l + log c_l)`` from the mode
    log-likelihoods and predicted probabilities ``(M, *B)``, as torch.logsumexp and safe_log_normalize compute
    it (all ``-inf``: ``-inf`` and uniform), in fewer passes: ``log c (M, *B)``, ``log mu (M, *B)`` and the
    log-likelihood ``(*B,)`` (exactly ``zero`` where ``anyob`` says no datum; ``lowest``: the dtype's). No
    gradient passes through a ``c_j`` at or below ``tiny`` (the smallest normal number; a mode no run can
    reach: ``log``'s ``1 / c_j`` times its zero adjoint would be NaN in every mode), as the eager steps'
    (:mod:`torchmm.multimodel.interaction`); the values are ``c_j``'s."""
    log_cbar = live_log(cbar, tiny)
    joint = ll + log_cbar
    top = torch.maximum(joint.amax(0), lowest)
    shifted = joint - top
    log_sum = shifted.exp().sum(0).log()
    new_log_mu = log_normalized(shifted, log_sum, M)
    return log_cbar, new_log_mu, torch.where(anyob, top + log_sum, zero)


def moments(X: list, P: list, w: Tensor, n: int) -> tuple[list, list]:
    """Moment-matched mixtures of per-entry beliefs, the means ``X[a]`` and the upper triangle ``P[a][c]``
    (``a <= c``), with weights ``w`` summing to one over the first axis (every shape broadcasting with
    ``w``'s): the means ``sum_i w_i x_i`` and ``sum_i w_i (P_i + d_i d_i^T)``, ``d_i = x_i - x`` (centred),
    each one pass over ``w``'s shape, the first axis summed out (lists as given)."""
    xs = [(w * X[a]).sum(0) for a in range(n)]
    D = [X[a] - xs[a] for a in range(n)]
    wD = [w * D[a] for a in range(n)]
    Cm = [[None] * n for _ in range(n)]
    for a in range(n):
        for c in range(a, n):
            Cm[a][c] = torch.addcmul(w * P[a][c], wD[a], D[c]).sum(0)
    return xs, Cm


def mix_entries(X: list, P: list, w: Tensor, n: int) -> tuple[list, list]:
    """The IMM's mixing of per-entry beliefs ``X[a]``, ``P[a][c]`` ``(i, *B)`` with weights ``w (i, j, *B)``
    (:func:`mixing`): the :func:`moments` over ``i`` of every ``j``, the means ``(j, *B)`` and the upper
    triangle ``(j, *B)``. (By index, not iteration: a traced step's arguments are proxies.)"""
    return moments([X[a].unsqueeze(1) for a in range(n)],
                   [[P[a][c].unsqueeze(1) if c >= a else None for c in range(n)] for a in range(n)], w, n)


def sandwich(F: list, Cs: list, Q: list, like: Tensor) -> list:
    """``F C F^T + Q`` (upper triangle) of per-entry ``F[a][e]`` (:class:`Coef`), ``C`` (upper
    triangle) and ``Q[a][c]`` (:class:`Coef`); ``like``: the shape of an all-zero entry."""
    n = len(F)  # (F: nested lists of Coef; Cs may be traced)
    sym = lambda T, a, c: T[min(a, c)][max(a, c)]  # noqa: E731
    A = [[combine([(F[a][e], sym(Cs, e, c)) for e in range(n)], ZERO, like) for c in range(n)]
         for a in range(n)]  # F C
    Pp = [[None] * n for _ in range(n)]
    for a in range(n):
        for c in range(a, n):
            Pp[a][c] = combine([(F[c][e], A[a][e]) for e in range(n)], Q[a][c], like)
    return Pp


def collapse_modes(X: Tensor, P: Tensor, mu: Tensor) -> tuple[Tensor, Tensor]:
    """The moment-matched collapse over the modes (the estimate), ``(n, *B)`` and ``(n, n, *B)``
    (exactly symmetric), of ``X (n, M, *B)``, ``P (n, n, M, *B)`` with weights ``mu (M, *B)``."""
    est = (mu * X).sum(1)
    spread = X - est.unsqueeze(1)
    return est, (mu * (P + spread.unsqueeze(1) * spread.unsqueeze(0))).sum(2)


def collapse_entries(xu: list, Cu: list, mu: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """:func:`collapse_modes` of the per-entry layout: the means ``xu[a] (M, *B)`` and the upper
    triangle ``Cu[a][c] (M, *B)`` (:func:`moments` over the modes), stacked ``(n, *B)`` and ``(n, n, *B)``."""
    est, est_cov = moments(xu, Cu, mu, n)
    return torch.stack(est), stack_upper(est_cov)

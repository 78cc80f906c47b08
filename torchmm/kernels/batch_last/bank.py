r"""The model algebra of a bank of linear Kalman modes in the batch-last layout (issue 47: one algebra that the
kernels compose): every mode's prediction ``F m + b``, ``F C F^T + Q``, the update one measurement component
after the other (a diagonal ``R``) and the record of the innovations, on per-entry tensors (``x[a]``, the upper
triangle ``C[a][c]``, any shapes broadcasting with the modes' ``(M, *B)``). The IMM and GPB1
(:class:`~torchmm.kernels.batch_last.imm.BatchLastIMM`), GPB2's pairs, IMM-TF's transfer and the two-filter
smoother run it; the extended and unscented banks (:class:`~torchmm.kernels.batch_last.nonlinear.NonlinearBank`)
answer the same three calls."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.kernels.batch_last.algebra import ZERO, coefficients, combine, sandwich

__all__ = ["LinearBank"]

_LOG_2PI = math.log(2 * math.pi)


class LinearBank:
    """The linear Kalman modes of a description (module docstring): its matrices classified entry by entry once
    (:func:`~torchmm.kernels.batch_last.algebra.coefficients`: exactly 0 or 1 in every mode, one number shared
    by the modes, a tensor per mode).

    Args:
        model: a :class:`~torchmm.kernels.linear.LinearGaussian` description with a diagonal ``R``.
        M: the number of modes; batch_dims: ``len(B)``; like: a tensor of the run's dtype and device.
    """

    #: its steps can run as a traced graph (:mod:`~torchmm.kernels.batch_last.traced`): no Python of the
    #: user's models runs in them
    traceable = True

    def __init__(self, model, M: int, batch_dims: int, like: Tensor):
        d = batch_dims
        self.n, self.m = model.F.shape[-1], model.H.shape[-2]
        self.F = coefficients(model.F, M, 2, d)
        self.Q = coefficients(model.Q, M, 2, d)
        self.b = coefficients(model.b, M, 1, d)
        self.H = coefficients(model.H, M, 2, d)
        self.r = coefficients(model.R.diagonal(dim1=-2, dim2=-1), M, 1, d)
        R = model.R
        self.R_front = (R if R.dim() == 3 else R.unsqueeze(0)).movedim(0, -1).reshape(
            self.m, self.m, -1, *([1] * d))  # (m, m, P, 1...), for the recorded S only
        self.tiny = torch.finfo(like.dtype).tiny
        # constants as 0-dim tensors (an operation with a Python number costs more dispatch)
        self.tiny_t = torch.full((), self.tiny, dtype=like.dtype, device=like.device)
        self.log_2pi = torch.full((), _LOG_2PI, dtype=like.dtype, device=like.device)

    def predict(self, xs: list, Cs: list, like: Tensor) -> tuple[list, list]:
        """Every mode's prediction of per-entry beliefs (any shapes broadcasting with the modes' ``(M, *B)``):
        ``F m + b``, ``F C F^T + Q`` (upper triangle). ``like``: the shape of an all-zero entry."""
        n, F, b = self.n, self.F, self.b
        xp = [combine([(F[a][e], xs[e]) for e in range(n)], b[a], like) for a in range(n)]
        return xp, sandwich(F, Cs, self.Q, like)

    def update(self, xp: list, Pp: list, zc: Tensor, ob: Tensor, nhob: Tensor, like: Tensor, flags: bool) -> tuple:
        """The Kalman update of per-entry beliefs ``xp[a]``, ``Pp[a][c]`` (``a <= c``, any broadcastable
        shapes ``(..., *B)``), one measurement component after the other (diagonal ``R``): ``s = h P h^T +
        r``, ``K = P h^T / s``, ``P+ = P - K (P h^T)^T``, ``s`` clamped at the smallest normal number; a
        missing component has ``ob = 0``, ``zc = 0`` and is skipped exactly. ``like``: a tensor of the
        result's shape for an all-zero sum. Returns the posterior ``xu``, ``Cu``, the log-likelihood, the
        singular flags (None unless ``flags``) and the first component's ``s``."""
        n, m, tiny = self.n, self.m, self.tiny
        H, r = self.H, self.r
        upper = [(a, c) for a in range(n) for c in range(a, n)]
        sym = lambda T, a, c: T[min(a, c)][max(a, c)]  # noqa: E731
        xu, Cu = xp, Pp
        ll = singular = s_first = None
        for k in range(m):
            g = [combine([(H[k][c], sym(Cu, a, c)) for c in range(n)], ZERO, like) for a in range(n)]  # P h^T
            s_raw = combine([(H[k][a], g[a]) for a in range(n)], r[k], like)
            nu = zc[k] - combine([(H[k][a], xu[a]) for a in range(n)], ZERO, like)
            s = torch.maximum(s_raw, self.tiny_t)
            ratio = ob[k] / s
            gain = [g[a] * ratio for a in range(n)]
            xu = [torch.addcmul(xu[a], gain[a], nu) for a in range(n)]
            new = [[None] * n for _ in range(n)]
            for a, c in upper:
                new[a][c] = torch.addcmul(Cu[a][c], gain[a], g[c], value=-1.0)
            Cu = new
            term = torch.addcdiv(s.log().add_(self.log_2pi), nu * nu, s).mul_(nhob[k])
            ll = term if ll is None else ll + term
            if flags:
                flag = (s_raw <= tiny) & (ob[k] > 0)
                singular = flag if singular is None else singular | flag
            if k == 0:
                s_first = s_raw
        return xu, Cu, ll, singular, s_first

    def innovation(self, zraw, xp, Pp, s_first) -> tuple[Tensor, Tensor]:
        """The step's record of ``z - H x-`` ``(m, M, *B)`` (non-finite where missing) and
        ``S = H P- H^T + R`` ``(m, m, M, *B)`` (``s_first``: :meth:`update`'s)."""
        m, n, H = self.m, self.n, self.H
        nu = torch.stack([zraw[k] - combine([(H[k][a], xp[a]) for a in range(n)], ZERO, xp[0]) for k in range(m)])
        if m == 1:
            return nu, s_first.unsqueeze(0).unsqueeze(0)
        sym = lambda T, a, c: T[min(a, c)][max(a, c)]  # noqa: E731
        HP = [[combine([(H[k][e], sym(Pp, e, c)) for e in range(n)], ZERO, xp[0]) for c in range(n)]
              for k in range(m)]
        S = torch.stack([torch.stack([combine([(H[j][c], HP[k][c]) for c in range(n)], ZERO, xp[0])
                                      for j in range(m)]) for k in range(m)])
        return nu, S + self.R_front

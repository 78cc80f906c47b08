r"""The objective as ``scipy.optimize.minimize`` sees it in :func:`~torchmm.learn.estimate` (split from
:mod:`torchmm.learn.estimation` by concern): a point where the log-likelihood or its gradient is not finite
is answered as a failed step, never passed on as a number; and the checks of the optimiser's answer.

A parametrisation can leave the model's domain: a ``"variance"`` or bounded ``"free"`` entry that makes a
covariance indefinite (``Param(lower=-0.5)`` on a variance), an overflow far out. There the loss is
``inf`` or ``NaN``. Passed on, neither is handled by scipy's L-BFGS-B: its line search (More-Thuente)
interpolates between the trial values, ``inf`` makes the step ``NaN``, and it returns to the last
iterate and reports ``CONVERGENCE`` at a point whose gradient is not zero (measured, docs/estimation.md);
``NaN`` derails the search (``ABNORMAL``, with the iterates thrown to the infinities); a large finite
value with a zero gradient does as ``inf`` does (the cubic through the two ends puts the next trial at the
last iterate, whose relative reduction of 0 passes ``ftol``).

:class:`Guarded` answers such a point ``x`` with the parabola through the last iterate ``x_k`` (value
``f_k``, gradient ``g_k``) that rises by ``s = |g_k . d|`` over ``d = x - x_k``: the value ``f_k + s``,
above ``f_k``, so no sufficient-decrease test accepts it, and the gradient ``3 s d / |d|^2``, the slope of
that parabola at ``x``. The line search's interpolation then puts its next trial a quarter of the way from
``x_k`` to ``x`` (the parabola's minimum): it backtracks into the domain, as it does from any too-long
step. The start must be finite (a ``ValueError`` otherwise: there is nothing to step back to).

A fit the optimiser did not call converged (``maxiter`` reached, a line search that found no decrease)
gets standard errors only where it is a maximum for them: where one Newton step ``H^{-1} g`` from it moves
no free value by more than :data:`NEWTON_RATIO` (1 %) of that value's standard error
(:func:`newton_ratio`), the distance to the maximum is negligible against the errors (e.g. a fit started at
the optimum with ``maxiter=1``); otherwise the errors are NaN, said so.

A free value that no datum touches (the start mean of a series without a finite measurement) leaves the
log-likelihood unchanged: its gradient is exactly 0 at every point and its row of the information too, which
is then singular. :func:`untouched` finds such values (:attr:`Guarded.touched`: a gradient not 0 at some
evaluation; and the Hessian's row and column exactly 0); :func:`~torchmm.learn.estimate` holds them out of
the information and of ``k`` and reports them NaN, named in its note.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

__all__ = ["NEWTON_RATIO", "Guarded", "newton_ratio", "untouched"]

#: the largest Newton step, in standard errors of each free value, at which a fit that did not converge
#: still reports its standard errors (:func:`~torchmm.learn.estimate`)
NEWTON_RATIO = 0.01


def newton_ratio(hessian: Tensor, gradient: Tensor) -> float:
    """``max_i |(H^{-1} g)_i| / sqrt((H^{-1})_{ii})``: one Newton step from a point, in standard errors of
    each free value (``hessian`` ``(P, P)`` of the negative log-likelihood, ``gradient`` ``(P,)``); ``inf``
    where ``hessian`` is not positive definite or either is not finite."""
    H, g = hessian.to(torch.float64), gradient.to(torch.float64)
    L, info = torch.linalg.cholesky_ex(H)
    if int(info) != 0 or not bool(torch.isfinite(L).all()) or not bool(torch.isfinite(g).all()):
        return math.inf
    step = torch.cholesky_solve(g.unsqueeze(-1), L).squeeze(-1)
    se = torch.cholesky_inverse(L).diagonal().sqrt()
    return float((step.abs() / se).max()) if len(g) else 0.0


def untouched(touched: np.ndarray, hessian: Tensor | None = None) -> Tensor:
    """``(P,)`` bool: the free values no datum touches: a gradient exactly 0 at every evaluation
    (``touched`` ``(P,)``: :attr:`Guarded.touched`) and, where given, a row and a column of ``hessian``
    ``(P, P)`` exactly 0."""
    idle = ~torch.from_numpy(np.asarray(touched, dtype=bool))
    if hessian is not None:
        idle &= (hessian == 0).all(-1) & (hessian == 0).all(-2)
    return idle


class Guarded:
    """``fun(x) -> (loss, gradient)`` (NumPy float64) for ``scipy.optimize.minimize(jac=True)`` with its
    non-finite answers replaced by a failed step (module docstring); pass :meth:`callback` as
    ``minimize``'s ``callback`` so that it knows the iterates.

    Attributes:
        start: ``(x0, loss, gradient)`` of the first evaluation; best: the same of the lowest finite loss
            evaluated; failed: the evaluations that were not finite (answered as failed steps); touched:
            ``(P,)`` bool, the free values whose gradient was not 0 at some finite evaluation.
    """

    def __init__(self, fun: Callable[[np.ndarray], tuple[float, np.ndarray]]):
        self.fun = fun
        self.start = self.best = self.anchor = None
        self.failed = 0
        self.touched = None
        self._since: dict[bytes, tuple] = {}  # the finite evaluations since the last iterate

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        loss, grad = self.fun(x)
        if math.isfinite(loss) and bool(np.isfinite(grad).all()):
            point = (np.array(x, dtype=np.float64), float(loss), np.array(grad, dtype=np.float64))
            if self.start is None:
                self.start = self.anchor = point
            if self.best is None or loss < self.best[1]:
                self.best = point
            self._since[point[0].tobytes()] = point
            self.touched = (point[2] != 0) | (False if self.touched is None else self.touched)
            return loss, grad
        if self.start is None:
            raise ValueError(f"parameters: the log-likelihood at the start values is {-loss} (its gradient "
                             f"{'finite' if np.isfinite(grad).all() else 'not finite'}): start from values "
                             "where the model's likelihood and its gradient are finite")
        self.failed += 1
        xk, fk, gk = self.anchor
        d = np.asarray(x, dtype=np.float64) - xk
        dd = float(d @ d)
        if dd == 0.0:  # (the iterate itself was finite: only a non-deterministic loss gets here)
            return fk + max(1.0, abs(fk)), np.zeros_like(gk)
        # the rise: the slope along d, at least a relative 1e-8 of the loss (a stationary iterate still
        # rejects the step)
        s = max(abs(float(gk @ d)), 1e-8 * max(1.0, abs(fk)))
        return fk + s, (3.0 * s / dd) * d

    def callback(self, xk, *_) -> None:
        """``minimize``'s callback: ``xk`` is the new iterate, the anchor of the next failed steps (the lowest
        finite evaluation where ``xk`` was not one of them)."""
        x = np.asarray(getattr(xk, "x", xk), dtype=np.float64)
        self.anchor = self._since.get(x.tobytes(), self.best)
        self._since = {self.anchor[0].tobytes(): self.anchor}

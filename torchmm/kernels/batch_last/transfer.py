r"""IMM-TF and IF-TF (:class:`~torchmm.multimodel.TransferIMM`, paper 000) over linear Kalman modes in the
batch-last layout (issue 31, goal 3).

:func:`~torchmm.run_filter` runs a ``TransferIMM`` (with or without its influence gate) over one
:class:`~torchmm.KalmanFilter` with mode-bank linear models, a diagonal ``R`` and ``R_S`` and a state of
at most six components through this kernel (:class:`BatchLastTransferKernel`, registered as
``"batch_last_transfer"``), for any record. It is the batch-last IMM kernel's step
(:mod:`torchmm.kernels.batch_last.imm`, one tensor ``(M, *B)`` per entry) with the transfer of
:meth:`TransferIMM.step <torchmm.multimodel.TransferIMM.step>`, in the same order:

1. the IMM's mixing, prediction and update with ``y_k`` (the plain posterior and ``Lambda_j``);
2. the source filter's posterior: the prediction updated with ``y_{S,k}`` (noise ``R_S``);
3. the transfer smoothing (13)-(14) from the reference at ``k-1`` (the combined estimate, or each
   mode's mixed start): ``G^T = (F P F^T + Q)^{-1} F P`` by the regularised factor of
   :func:`torchmm.linalg.cholesky` (closed form for ``n <= 2``, entry by entry beyond), the smoothed
   mean ``x + G (m - f(x))`` (and, for the record, its covariance ``P + G (D - P^-) G^T``);
4. the transferred knowledge ``u_S = H (F m_s + b)``, the correction (20)-(21) with it where the
   source datum is present, the update (22)-(23) with ``y_k``;
5. the mode probabilities from ``Lambda_j`` (or the corrected likelihoods); the influence value (33)
   at the transferred output, ``-(H (x - x*))^T R^{-1}`` with ``x*`` the gate mode's update of
   ``N(x^-, W)`` with ``y_k``; IF-TF's gate; the components (and, with the corrected likelihoods, the
   mode probabilities and the log-likelihood): the transferred ones where the transfer is used, else
   the plain IMM step's.

Every ``extras`` entry of the eager step is returned, in its order (the influence is computed only
where a gate or the extras need it). Equal to the eager steps to rounding
(tests/multimodel/test_batch_last_transfer.py).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import ModeBelief
from torchmm.typing import StepOutput
from torchmm.kernels.batch_last.algebra import (
    ZERO,
    collapse_entries,
    combine,
    factor,
    mix_entries,
    mixing,
    mode_update,
    solve_lower,
    solve_lower_transposed,
    stack_upper,
    sum_terms,
)
from torchmm.kernels.batch_last.bank import LinearBank
from torchmm.kernels.batch_last.frame import Frame
from torchmm.kernels.batch_last.imm import LARGE_BATCH, LARGE_STATE, MAX_STATE
from torchmm.kernels.batch_last.plan import planned, why_not
from torchmm.models.streams import split_streams

__all__ = ["TRANSFER", "TRANSFER_LARGE", "BatchLastTransfer", "BatchLastTransferKernel", "LargeStateTransfer"]


class BatchLastTransfer(Frame):
    """One IMM-TF step in the batch-last layout (module docstring): the :class:`~torchmm.kernels.batch_last.frame.Frame`
    of the kernel (the state one tensor per entry), the linear bank of the modes
    (:class:`~torchmm.kernels.batch_last.bank.LinearBank`) and the source sensor's (``H_S``, ``r_S``).

    Args:
        description: the filter's :class:`~torchmm.multimodel.transfer.TransferGaussian`.
        M, batch_dims, like: as :class:`~torchmm.kernels.batch_last.imm.BatchLastIMM`.
    """

    kind = "IMM-TF"

    def __init__(self, description, M: int, batch_dims: int, like: Tensor):
        self.bank = bank = LinearBank(description.model, M, batch_dims, like)
        super().__init__(description.model, M, bank.n, bank.m, batch_dims, like)
        source = description.model._replace(H=description.H_S, R=description.R_S)
        self.source = LinearBank(source, M, batch_dims, like)  # (its update only)
        self.combined = description.smoothing_reference == "combined"
        self.corrected = description.mode_likelihood == "corrected"
        self.gate = description.gate  # None: IMM-TF (the influence is still a diagnostic, mode 0's)
        self.gate_mode = 0 if self.gate is None else self.gate.mode
        self.process_weight = self.gate is not None and self.gate.weight == "process"

    def prepare_streams(self, y: Tensor, ys: Tensor) -> None:
        """Once per run: the target data (:meth:`prepare`) and the source data ``(T, *B, m_S)`` as
        ``(T, m_S, *B)`` with 0 where missing, its masks, and ``gamma_k`` (every component present)."""
        self.prepare(y)
        z = ys.movedim(-1, 1)
        observed = torch.isfinite(z)
        ob = observed.to(z.dtype)
        present = observed.all(1)  # gamma_k (T, *B)
        self.source_data = list(zip(torch.where(observed, z, 0.0).unbind(0), ob.unbind(0), ob.mul(-0.5).unbind(0),
                                    present.unbind(0), present.to(z.dtype).unbind(0)))

    def _factor_solve(self, S: list, rhs: list) -> list:
        """``S^{-1} rhs`` for the per-entry symmetric ``S`` (upper triangle) and ``rhs[a][c]`` (a full
        ``n x n``): :func:`~torchmm.linalg.cholesky_solve` of :func:`torchmm.linalg.cholesky`'s factor
        (:meth:`factor`), its two substitutions entry by entry."""
        L = factor(S)
        return solve_lower_transposed(L, solve_lower(L, rhs))

    def core(self, X: list, C: list, mu: Tensor, zc: Tensor, ob: Tensor, nhob: Tensor, anyob: Tensor, zraw: Tensor,
             szc: Tensor, sob: Tensor, snhob: Tensor, present: Tensor, present_f: Tensor) -> tuple:
        """The IMM-TF step's arithmetic (module docstring).

        Shapes:
            X, C: the state (per-entry ``(M, *B)``); mu ``(M, *B)``; the target's data as the IMM's core
            (``(m, *B)``, anyob ``(*B,)``), the source's ``(m_S, *B)`` and ``gamma_k`` ``(*B,)`` (bool and
            float) -> the next ``X, C``, ``log mu``, ``mu``, the log-likelihood ``(*B,)``, then (None where
            not needed) the posterior ``(n, M, *B)``, ``(n, n, M, *B)``, the prior and ``log c``, the
            innovations and their covariances (``estimate_only``: the estimate in these two).
        """
        n, omitted, bank = self.n, self.omitted, self.bank
        F, H = bank.F, bank.H
        sym = lambda T, a, c: T[min(a, c)][max(a, c)]  # noqa: E731
        # 1. the IMM: mixing, prediction, update with y_k
        cbar, w = mixing(mu, self.matrix, self.tiny_t)
        xs, Cm = mix_entries(X, C, w, self.n)
        w = None
        xp, Pp = bank.predict(xs, Cm, cbar)
        extras = "extras" not in omitted
        xu, Cu, ll, singular, s_first = bank.update(xp, Pp, zc, ob, nhob, cbar, extras)
        # 2. the source filter's posterior
        ms, Ds, _, _, _ = self.source.update(xp, Pp, szc, sob, snhob, cbar, False)
        # 3. the transfer smoothing from the reference at k-1
        if self.combined:
            est, est_cov = collapse_entries(X, C, mu, self.n)
            rx = [est[a].unsqueeze(0) for a in range(n)]
            rC = [[est_cov[a, c].unsqueeze(0) if c >= a else None for c in range(n)] for a in range(n)]
        else:
            rx, rC = xs, Cm
        mp, Cp = bank.predict(rx, rC, cbar)  # f(x), F P F^T + Q
        FP = [[combine([(F[a][e], sym(rC, e, c)) for e in range(n)], ZERO, cbar) for c in range(n)]
              for a in range(n)]
        gain_t = self._factor_solve(Cp, FP)  # (F P F^T + Q)^{-1} F P = G^T
        dm = [ms[e] - mp[e] for e in range(n)]
        smoothed = [rx[a] + sum_terms([gain_t[e][a] * dm[e] for e in range(n)]) for a in range(n)]
        # 4. u_S = H (F m_s + b) where the source datum is present; the correction and the update
        fm = [combine([(F[a][e], smoothed[e]) for e in range(n)], bank.b[a], cbar) for a in range(n)]
        u_s = [combine([(H[k][a], fm[a]) for a in range(n)], ZERO, cbar) for k in range(self.m)]
        uzc = torch.stack([torch.where(present, u_s[k], 0.0) for k in range(self.m)])
        uob = present_f.expand(self.m, *present_f.shape)
        xc, Cc, _, _, _ = bank.update(xp, Pp, uzc, uob, uob * -0.5, cbar, False)
        xt, Ct, llt, _, _ = bank.update(xc, Cc, zc, ob, nhob, cbar, False)
        # 5. the mode probabilities, the influence (33) and the gate, the components
        def update(lik):  # (the plain likelihoods' too, where a gate rejects a corrected transfer)
            return mode_update(lik, cbar, anyob, self.lowest, self.zero, self.M, self.tiny_t)

        log_cbar, log_mu, total = update(torch.where(present, llt, ll) if self.corrected else ll)
        mu = log_mu.exp()
        used, diagnostics = present, None
        if self.gate is not None or extras:
            value, used = self._influence(xt, Ct, mu, xp, Pp, xu, zc, ob, zraw, present)
            diagnostics = (ll, singular, xs, Cm, value, smoothed, self._smoothed_cov(rC, gain_t, Ds, Cp), u_s)
        if self.corrected and self.gate is not None:
            # a rejected transfer is no transfer: the plain IMM step's mode probabilities and likelihood
            _, plain_log_mu, plain_total = update(ll)
            log_mu, total = torch.where(used, log_mu, plain_log_mu), torch.where(used, total, plain_total)
            mu = log_mu.exp()
        xn = [torch.where(used, xt[a], xu[a]) for a in range(n)]
        Cn = [[torch.where(used, Ct[a][c], Cu[a][c]) if c >= a else None for c in range(n)] for a in range(n)]
        X_out = P_out = Xp = Ppt = nu_out = S_out = None
        if self.estimate_only:
            nu_out, S_out = collapse_entries(xn, Cn, mu, self.n)
        else:
            X_out, P_out = torch.stack(xn), stack_upper(Cn)
            if "prior" not in omitted:
                Xp, Ppt = torch.stack(xp), stack_upper(Pp)
            if "innovation" not in omitted or "innovation_cov" not in omitted:
                nu_out, S_out = bank.innovation(zraw, xp, Pp, s_first)
        return xn, Cn, X_out, P_out, log_mu, mu, total, Xp, Ppt, log_cbar, nu_out, S_out, used, diagnostics

    def _influence(self, xt, Ct, mu, xp, Pp, xu, zc, ob, zraw, present) -> tuple[Tensor, Tensor]:
        """The influence value (33) ``(m, *B)`` at the transferred output and where the transfer is used
        (``gamma_k``, and for IF-TF not harmful): ``L^T = -(H (x - x*))^T R^{-1}`` with ``x*`` the update
        of the gate mode's prediction ``N(x^-, W)`` with ``y_k`` (``W`` its predicted covariance: then
        ``x*`` is that mode's plain posterior; or its process noise)."""
        n, m, j = self.n, self.m, self.gate_mode
        H, r = self.bank.H, self.bank.r
        est, _ = collapse_entries(xt, Ct, mu, self.n)  # the tentative output (27)
        if self.process_weight:  # x*: the update of N(x^-, Q) with y_k
            W = [[combine([], self.bank.Q[a][c], xp[0]) if c >= a else None for c in range(n)] for a in range(n)]
            x_star = self.bank.update(xp, W, zc, ob, ob * -0.5, xp[0], False)[0]
        else:
            x_star = xu
        x_star = [x_star[a][j] for a in range(n)]
        anchor = [xp[a][j] for a in range(n)]
        value, product = [], None
        for k in range(m):
            h = [_at_mode(H[k][a], j) for a in range(n)]  # mode j's row (None: an exact zero)
            shift = _dot(h, [est[a] - x_star[a] for a in range(n)])
            # R^{-1} shift through the factor of the diagonal R, as cholesky_solve(cholesky(R), shift)
            rk = _at_mode(r[k], j)
            root = math.sqrt(rk) if isinstance(rk, float) else self.tiny_t.sqrt() if rk is None else rk.sqrt()
            v = torch.where(ob[k] > 0, -(shift / root / root), 0.0)
            predicted = _dot(h, anchor)
            innovation = torch.where(ob[k] > 0, zraw[k] - predicted, 0.0)
            value.append(v)
            product = v * innovation if product is None else product + v * innovation
        used = present if self.gate is None else present & ~(product > self.gate.threshold)
        return torch.stack(value), used

    def _smoothed_cov(self, rC, gain_t, Ds, Cp) -> list:
        """The transfer smoothing's covariance ``P + G (D - P^-) G^T`` (upper triangle)."""
        n = self.n
        sym = lambda T, a, c: T[min(a, c)][max(a, c)]  # noqa: E731
        diff = [[sym(Ds, e, f) - sym(Cp, e, f) for f in range(n)] for e in range(n)]
        inner = [[sum_terms([diff[e][f] * gain_t[f][c] for f in range(n)]) for c in range(n)] for e in range(n)]
        return [[sym(rC, a, c) + sum_terms([gain_t[e][a] * inner[e][c] for e in range(n)]) if c >= a else None
                 for c in range(n)] for a in range(n)]

    def step(self, state: tuple, z: Tensor) -> tuple[tuple, StepOutput]:
        """One IMM-TF step on the prepared data of the state's step (``z``: held by the kernel)."""
        X, C, mu, k = state
        self._steps_done = k + 1
        (X, C, X_out, P_out, log_mu, mu, total, Xp, Pp, log_cbar, nu, S, used, diagnostics) = self.core(
            X, C, mu, *self.data[k], *self.source_data[k])
        state = (X, C, mu, k + 1)
        extras = None
        if diagnostics is not None and "extras" not in self.omitted:
            extras = self._extras(k, total, log_cbar, used, *diagnostics)
        if self.estimate_only:
            return state, self.estimate_output(nu, S, total)
        prior = None if Xp is None else ModeBelief(self.modes(log_cbar), self.gaussian(Xp, Pp))
        return state, self.output(log_mu, X_out, P_out, prior, total, nu, S, extras)

    def _extras(self, k, total, log_cbar, used, ll, singular, xs, Cm, value, smoothed, smoothed_cov, u_s) -> dict:
        """The eager step's ``extras``, in its order, as batch-first views."""
        modes, present = self.modes, self.source_data[k][3]
        shape = log_cbar.shape
        u = torch.stack([torch.where(present, t.expand(shape), torch.nan) for t in u_s])  # (m, M, *B)
        mean = torch.stack([t.expand(shape) for t in smoothed])
        cov = stack_upper([[None if t is None else t.expand(shape) for t in row] for row in smoothed_cov])
        return {
            **self.failures(modes, ll, singular, total, k),
            "mixed": ModeBelief(modes(log_cbar), self.gaussian(torch.stack(xs), stack_upper(Cm))),
            "influence": value.permute(self._to_front1),
            "transfer_used": used,
            "source_present": present,
            "smoothed": self.gaussian(mean, cov),
            "transferred_knowledge": u.permute(self._to_front_x),
        }


def _at_mode(coef, j: int):
    """Mode ``j``'s value of a :func:`~torchmm.kernels.batch_last.algebra.coefficients` entry: None for an
    exact zero, 1.0, a shared 0-dim tensor, or the ``(1...)`` slice of a per-mode tensor."""
    if coef.kind == "zero":
        return None
    if coef.kind == "one":
        return 1.0
    if coef.kind == "scalar":
        return coef.value
    return coef.value[j if coef.value.shape[0] > 1 else 0]


def _dot(h: list, x: list) -> Tensor:
    """``sum_a h[a] x[a]`` over the entries whose ``h`` is not an exact zero (zeros where all are)."""
    terms = [x[a] * h[a] for a in range(len(h)) if h[a] is not None]
    return sum_terms(terms) if terms else torch.zeros_like(x[0])


class BatchLastTransferKernel:
    """The registered kernel of IMM-TF and IF-TF (module docstring): a filter that describes itself with
    ``transfer_gaussian()``, ``n <= 6``, a run without ``update_first``; any record."""

    name = "batch_last_transfer"
    #: the largest state taken; the smallest batch (runs x modes)
    max_state, min_batch = MAX_STATE, 0

    def plan(self, filter, belief0, measurements, request: kernels.Request):
        if request.update_first:
            return "update_first"
        if request.repeated or request.compile_required:
            return "no prepared evaluation and no compiled step"
        description = kernels.describe(filter, "transfer_gaussian")
        if isinstance(description, str):
            return description
        model = description.model
        gate = description.gate
        if gate is not None and gate.weight == "process":  # once per run, as the eager step's check
            Q = model.Q if model.Q.dim() == 2 else model.Q[gate.mode if model.Q.shape[0] > 1 else 0]
            if bool((torch.linalg.cholesky_ex(Q)[1] != 0).any()):
                return "a gate with weight='process' and a singular Q (the eager steps say so)"
        n, M = model.F.shape[-1], model.transition.shape[-1]
        if n > self.max_state:
            return (f"a state of {n} components (more than {self.max_state}: the factor entry by entry costs n^3 "
                    "operations)")
        if n <= MAX_STATE < self.max_state:
            return f"states of {MAX_STATE + 1} to {self.max_state} components only"
        batch = belief0.mode_log_probs.numel() if isinstance(belief0, ModeBelief) else 0
        if batch < self.min_batch:
            return f"a small batch ({batch} runs x modes < {self.min_batch}: the eager steps are faster)"
        try:
            y, ys = split_streams(measurements)
        except TypeError:
            return "the measurements are not MultiRate(target, source)"
        reason = why_not(model, M, belief0, y) or why_not(model._replace(H=description.H_S, R=description.R_S),
                                                          M, belief0, ys)
        if reason is not None:
            return reason
        like = belief0.mode_log_probs
        kernel = BatchLastTransfer(description, M, like.dim() - 1, like)
        kernel.prepare_streams(y, ys)
        return planned(kernel, belief0, request)


class LargeStateTransfer(BatchLastTransferKernel):
    """IMM-TF's and IF-TF's kernel (:class:`BatchLastTransfer`) for states of ``MAX_STATE + 1`` to
    ``LARGE_STATE`` components, from ``LARGE_BATCH`` runs x modes: below, its entry-by-entry factors are
    bound by dispatch and the eager steps are faster (docs/performance.md). Its choice depends on the
    batch size (``by_size``: studies switch it off)."""

    name = "batch_last_transfer_large"
    by_size = True
    max_state, min_batch = LARGE_STATE, LARGE_BATCH


TRANSFER = BatchLastTransferKernel()  # (registered by torchmm.kernels.TABLE)
TRANSFER_LARGE = LargeStateTransfer()

"""Kim's smoother in one compiled loop (torchmm.smooth.kim_step: the pair RTS steps, the smoothed mode
probabilities and the collapse), and the prepared filter-and-smoother (:func:`filter_and_kim`: the forward
pass of :mod:`~torchmm.kernels.linear_loops`, then Kim's, in one call); the step functions of
:mod:`~torchmm.kernels.loop_algebra`."""

from __future__ import annotations

import math

import numba
import numpy as np

from torchmm.kernels.linear_loops import forward
from torchmm.kernels.loop_algebra import (
    chol_reg,
    copy_modes,
    logsumexp,
    matmul_add,
    mix_moments,
    predict_mode,
    solve_lower,
)


@numba.njit(cache=True)
def filter_and_kim(z, F, b, Q, H, R, Pi, rule, update_first, logmu0, x0, P0, bu, eps, tiny, last, slogmu, sx,
                   sP):
    """:func:`forward` then :func:`kim` in one call (a prepared filter-and-smoother: the forward pass's
    intermediates stay inside; ``last (B,)``: each run's last step, as :func:`kim`). Returns :func:`forward`'s
    counts; the smoothed beliefs go to ``slogmu``, ``sx``, ``sP`` (written only where both counts are 0)."""
    T, B, m = z.shape
    M, n = F.shape[0], F.shape[1]
    dt = z.dtype
    ll = np.empty((T, B), dt)
    logmu = np.empty((T, B, M), dt)
    x = np.empty((T, B, M, n), dt)
    P = np.empty((T, B, M, n, n), dt)
    flags = np.empty((T, B, M), np.int8)
    bad, regularised = forward(z, F, b, Q, H, R, Pi, rule, update_first, logmu0, x0, P0, bu, eps, tiny,
                               ll, logmu, x, P, np.empty_like(x), np.empty_like(P), np.empty_like(logmu),
                               np.empty_like(x), np.empty_like(P), np.empty((T, B, M, m), dt),
                               np.empty((T, B, M, m, m), dt), np.empty_like(logmu), flags)
    if bad + regularised == 0:
        kim(F, b, Q, Pi[0, 0], log_matrix(Pi[0, 0]), logmu, x, P, eps, tiny, last, slogmu, sx, sP)
    return bad, regularised


@numba.njit(cache=True)
def log_matrix(Pi):
    """``log Pi`` entrywise (``-inf`` where 0), for Kim's smoother's log-space steps."""
    out = np.empty(Pi.shape, Pi.dtype)
    for j in range(Pi.shape[0]):
        for i in range(Pi.shape[1]):
            out[j, i] = math.log(Pi[j, i]) if Pi[j, i] > 0.0 else -math.inf
    return out


@numba.njit(cache=True, inline="always")
def _kim_linear(logmu, slogmu_next, Pi, mu, smu, pred, pair, wts, out):
    """Kim's mode probabilities of one step in linear space: the filtered ``mu`` and next smoothed ``smu``
    scaled by their largest (the scales cancel), ``pred_i = sum_j mu_j Pi_ji``, ``pair_ji = mu_j Pi_ji smu_i /
    pred_i`` normalised, the smoothed ``out_j = log sum_i pair_ji`` and ``wts[j, i] = pair_ji / sum_i pair_ji``
    (``1 / M`` where that is 0). False (nothing written) where some log-probability lies 700 or more below
    its step's largest (or is -inf or NaN): the caller then works in log space."""
    M = mu.shape[0]
    top, stop, low, slow = -math.inf, -math.inf, math.inf, math.inf
    for j in range(M):
        top, low = max(top, logmu[j]), min(low, logmu[j])
        stop, slow = max(stop, slogmu_next[j]), min(slow, slogmu_next[j])
    if not (low - top > -700.0 and slow - stop > -700.0):
        return False
    for j in range(M):
        mu[j] = math.exp(logmu[j] - top)
        smu[j] = math.exp(slogmu_next[j] - stop)
    for i in range(M):
        s = 0.0
        for j in range(M):
            s += mu[j] * Pi[j, i]
        pred[i] = smu[i] / s if s > 0.0 else 0.0
    total = 0.0
    for j in range(M):
        for i in range(M):
            pair[j, i] = mu[j] * Pi[j, i] * pred[i]
            total += pair[j, i]
    for j in range(M):
        s = 0.0
        for i in range(M):
            s += pair[j, i]
        for i in range(M):
            wts[j, i] = pair[j, i] / s if s > 0.0 else 1.0 / M
        out[j] = math.log(s / total) if s > 0.0 else -math.inf
    return True


@numba.njit(cache=True)
def kim(F, b, Q, Pi, logPi, logmu, x, P, eps, tiny, last, slogmu, sx, sP):
    """Kim's smoother (torchmm.smooth.kim_step) over every run, backwards from its last filtered
    belief: the pair RTS steps from mode ``j``'s posterior through mode ``i``'s model, the smoothed
    mode probabilities in log space, and the moment-matched collapse over ``i``. ``last (B,)``: each
    run's last step (``T - 1``, or earlier for a run that ends there: ``smooth``'s padding); the steps
    from it on keep their filtered beliefs."""
    T, B, M = logmu.shape
    n = x.shape[3]
    dt = x.dtype
    xp = np.empty((M, M, n), dt)
    Pp = np.empty((M, M, n, n), dt)
    mean = np.empty((M, M, n), dt)
    cov = np.empty((M, M, n, n), dt)
    FP = np.empty((n, n), dt)
    zero = np.zeros(n, dt)
    L = np.empty((n, n), dt)
    G = np.empty((n, n), dt)  # G^T = (P^-)^{-1} C^T
    Y = np.empty((n, n), dt)
    D = np.empty((n, n), dt)
    dv = np.empty(n, dt)
    jp = np.empty((M, M), dt)
    lpred = np.empty(M, dt)
    lpair = np.empty((M, M), dt)
    lmode = np.empty(M, dt)
    wts = np.empty((M, M), dt)
    col = np.empty(M, dt)
    flat = np.empty(M * M, dt)
    mu = np.empty(M, dt)
    smu = np.empty(M, dt)
    for r in range(B):
        for t in range(last[r], T):
            copy_modes(logmu[t, r], x[t, r], P[t, r], slogmu[t, r], sx[t, r], sP[t, r])
        for t in range(last[r] - 1, -1, -1):
            for j in range(M):
                for i in range(M):
                    # x^-_ji = F_i x_j + b_i, P^-_ji = F_i P_j F_i^T + Q_i (the forward pass's prediction),
                    # C_ji = P_j F_i^T = (F_i P_j)^T (P_j symmetric, as the filter stores it)
                    predict_mode(F[i], b[i], zero, Q[i], x[t, r, j], P[t, r, j], xp[j, i], Pp[j, i], FP)
                    chol_reg(Pp[j, i], n, eps, tiny, L)
                    # G^T = L^{-T} L^{-1} C^T, C^T = F_i P_j = FP
                    solve_lower(L, FP, n, Y)
                    for c in range(n):
                        for a in range(n - 1, -1, -1):
                            s = Y[a, c]
                            for q in range(a + 1, n):
                                s -= L[q, a] * G[q, c]
                            G[a, c] = s / L[a, a]
                    # mean_ji = x_j + G (xs_i - x^-_ji); cov_ji = sym(P_j + G (Ps_i - P^-_ji) G^T)
                    for a in range(n):
                        dv[a] = sx[t + 1, r, i, a] - xp[j, i, a]
                    for a in range(n):
                        s = x[t, r, j, a]
                        for q in range(n):
                            s += G[q, a] * dv[q]
                        mean[j, i, a] = s
                    for a in range(n):
                        for c in range(n):
                            s = 0.0
                            for q in range(n):
                                s += G[q, a] * (sP[t + 1, r, i, q, c] - Pp[j, i, q, c])
                            D[a, c] = s
                    matmul_add(D, G, 1.0, P[t, r, j], Y)
                    for a in range(n):
                        for c in range(n):
                            cov[j, i, a, c] = 0.5 * (Y[a, c] + Y[c, a])
            # mode probabilities: in linear space where every log-probability of the step lies within 700 of
            # its step's largest (an exp and a log a mode: the usual case), else in log space (tiny ones keep
            # their logs); both give the weights wts[j, i] of the collapse and the smoothed log-probabilities
            if not _kim_linear(logmu[t, r], slogmu[t + 1, r], Pi, mu, smu, lpred, lpair, wts, slogmu[t, r]):
                for j in range(M):
                    for i in range(M):
                        jp[j, i] = logmu[t, r, j] + logPi[j, i]
                for i in range(M):
                    for j in range(M):
                        col[j] = jp[j, i]
                    lpred[i] = logsumexp(col, M)
                q = 0
                for j in range(M):
                    for i in range(M):
                        ratio = slogmu[t + 1, r, i] - lpred[i]
                        if ratio != ratio:
                            ratio = -math.inf
                        lpair[j, i] = jp[j, i] + ratio
                        flat[q] = lpair[j, i]
                        q += 1
                total = logsumexp(flat, M * M)
                for j in range(M):
                    for i in range(M):
                        lpair[j, i] -= total
                for j in range(M):
                    for i in range(M):
                        col[i] = lpair[j, i]
                    lmode[j] = logsumexp(col, M)
                    slogmu[t, r, j] = lmode[j]
                    for i in range(M):
                        v = lpair[j, i] - lmode[j]
                        if v != v:
                            v = -math.log(M)
                        wts[j, i] = math.exp(v)
            for j in range(M):  # the collapse over i (mix_gaussians)
                mix_moments(wts[j], mean[j], cov[j], sx[t, r, j], sP[t, r, j], dv)

"""The reverse pass of :func:`torchmm.kernels.linear_loops.forward` (the adjoint of the whole run, for
autograd: the inputs' gradients from the outputs'), over the forward pass's saved intermediates; the step
functions of :mod:`~torchmm.kernels.loop_algebra`."""

from __future__ import annotations

import math

import numba
import numpy as np

from torchmm.kernels.loop_algebra import (
    chol_plain,
    copy_modes,
    innovation_cov,
    inverse_from_chol,
    matmul,
    matmul_add,
    matmul_tn,
    mixing_weights,
    triple_entry,
    zero_modes,
)


@numba.njit(cache=True)
def backward(z, F, b, Q, H, R, Pi, rule, update_first, logmu0, x0, P0, bu, tiny,
             logmu, x, P, xp, Pp, logc, xm, Pm, gll, glogmu, gx, gP,
             gF, gb, gQ, gH, gR, gPi, glogmu0, gx0, gP0, gbu):
    """The reverse pass of :func:`forward` (runs without regularised updates): accumulates the
    adjoints of the models and start beliefs from those of the outputs ``ll``, ``logmu``, ``x``, ``P``.
    The adjoints of the symmetric matrices (``Q``, ``R``, ``P0``) are symmetric. ``tiny``: the forward
    pass's floor of the predicted mode probabilities ``c_j``; where it applied (a mode no run can reach:
    ``c_j = 0``), the adjoints through ``c_j`` and the mixing into mode ``j`` are 0, as the floor's
    derivative (tests/kernels/test_unreachable_mode.py)."""
    T, B, m = z.shape
    M, n = F.shape[0], F.shape[1]
    dt = z.dtype
    # carried adjoints of the posterior at step t (outputs' own plus the next step's)
    clm = np.empty(M, dt)
    cx = np.empty((M, n), dt)
    cP = np.empty((M, n, n), dt)
    # adjoints of the previous posterior, built by step t
    plmb = np.empty(M, dt)
    pxb = np.empty((M, n), dt)
    pPb = np.empty((M, n, n), dt)
    abar = np.empty(M, dt)
    xpb = np.empty(n, dt)
    Ppb = np.empty((n, n), dt)
    Abar = np.empty((n, n), dt)
    xmb = np.empty((M, n), dt)
    Pmb = np.empty((M, n, n), dt)
    C = np.empty((n, m), dt)
    Cb = np.empty((n, m), dt)
    S = np.empty((m, m), dt)
    L = np.empty((m, m), dt)
    V = np.empty((m, m), dt)
    Vb = np.empty((m, m), dt)
    Sb = np.empty((m, m), dt)
    W = np.empty((m, m), dt)
    u = np.empty(m, dt)
    ub = np.empty(m, dt)
    nu = np.empty(m, dt)
    nub = np.empty(m, dt)
    obs = np.empty(m, np.bool_)
    idx = np.empty(m, np.int64)
    mu = np.empty(M, dt)
    c = np.empty(M, dt)
    w = np.empty((M, M), dt)
    wb = np.empty((M, M), dt)
    cb = np.empty(M, dt)
    mub = np.empty(M, dt)
    d = np.empty(n, dt)
    tmp = np.empty((n, n), dt)
    step_u, run_u = bu.shape[0] > 1, bu.shape[1] > 1
    step_pi, run_pi = Pi.shape[0] > 1, Pi.shape[1] > 1
    for r in range(B):
        ru = r if run_u else 0
        zero_modes(clm, cx, cP)
        for t in range(T - 1, -1, -1):
            tu = t if step_u else 0
            Pt = Pi[t if step_pi else 0, r if run_pi else 0]  # (the step's transition matrix, its adjoint)
            gPt = gPi[t if step_pi else 0, r if run_pi else 0]
            for j in range(M):
                clm[j] += glogmu[t, r, j]
                for i in range(n):
                    cx[j, i] += gx[t, r, j, i]
                    for k in range(n):
                        cP[j, i, k] += gP[t, r, j, i, k]
            count = 0
            for k in range(m):
                obs[k] = math.isfinite(z[t, r, k])
                if obs[k]:
                    idx[count] = k
                    count += 1
            # -- mode posterior: a_j = ell_j + logc_j, logmu = a - lse, ll = lse (observed) or 0
            total = 0.0
            for j in range(M):
                total += clm[j]
            lbar = gll[t, r] if count > 0 else 0.0
            for j in range(M):
                abar[j] = clm[j] + math.exp(logmu[t, r, j]) * (lbar - total)
            for j in range(M):
                for i in range(n):
                    for k in range(n):
                        Abar[i, k] = 0.5 * (cP[j, i, k] + cP[j, k, i])
                ellb = abar[j]
                for i in range(n):
                    xpb[i] = cx[j, i]
                    for k in range(n):
                        Ppb[i, k] = Abar[i, k]
                if count > 0:
                    mo = count
                    # observed blocks: C_o = Pp H_o^T, S_o = H_o Pp H_o^T + R_oo, V = S_o^{-1}
                    innovation_cov(Pp[t, r, j], H[j], R[j], idx, mo, C, S)
                    for kk in range(mo):
                        s = z[t, r, idx[kk]]
                        for i in range(n):
                            s -= H[j, idx[kk], i] * xp[t, r, j, i]
                        nu[kk] = s
                    chol_plain(S, mo, 0.0, L)
                    inverse_from_chol(L, mo, V, W)
                    for kk in range(mo):
                        s = 0.0
                        for ll_ in range(mo):
                            s += V[kk, ll_] * nu[ll_]
                        u[kk] = s
                    # x+ = xp + C u
                    for i in range(n):
                        for kk in range(mo):
                            Cb[i, kk] = cx[j, i] * u[kk]
                    for kk in range(mo):
                        s = 0.0
                        for i in range(n):
                            s += C[i, kk] * cx[j, i]
                        ub[kk] = s
                    # P+ = sym(Pp - C V C^T): Cb -= 2 Abar C V, Vb = -C^T Abar C
                    for i in range(n):
                        for kk in range(mo):
                            Cb[i, kk] -= 2.0 * triple_entry(Abar, C, V, i, kk, n, mo)
                    for kk in range(mo):
                        for ll_ in range(mo):
                            s = 0.0
                            for i in range(n):
                                for q in range(n):
                                    s += C[i, kk] * Abar[i, q] * C[q, ll_]
                            Vb[kk, ll_] = -s + ub[kk] * nu[ll_] - 0.5 * ellb * nu[kk] * nu[ll_]
                    # u = V nu; ell = -0.5 (nu^T u + logdet S + m log 2 pi)
                    for kk in range(mo):
                        s = 0.0
                        for ll_ in range(mo):
                            s += V[kk, ll_] * ub[ll_]
                        nub[kk] = s - ellb * u[kk]
                    # S_bar = -V Vb V - 0.5 ellb V, symmetrised
                    for kk in range(mo):
                        for ll_ in range(mo):
                            s = 0.0
                            for p in range(mo):
                                s += Vb[kk, p] * V[p, ll_]
                            W[kk, ll_] = s
                    for kk in range(mo):
                        for ll_ in range(mo):
                            s = 0.0
                            for p in range(mo):
                                s += V[kk, p] * W[p, ll_]
                            Sb[kk, ll_] = -s - 0.5 * ellb * V[kk, ll_]
                    for kk in range(mo):
                        for ll_ in range(kk, mo):
                            v = 0.5 * (Sb[kk, ll_] + Sb[ll_, kk])
                            Sb[kk, ll_] = v
                            Sb[ll_, kk] = v
                    # S_o = H_o Pp H_o^T + R_oo
                    for kk in range(mo):
                        for ll_ in range(mo):
                            gR[j, idx[kk], idx[ll_]] += Sb[kk, ll_]
                    for kk in range(mo):  # H_bar += 2 Sb H_o Pp = 2 Sb C^T
                        for i in range(n):
                            s = 0.0
                            for ll_ in range(mo):
                                s += Sb[kk, ll_] * C[i, ll_]
                            gH[j, idx[kk], i] += 2.0 * s
                    for i in range(n):  # Pp_bar += H_o^T Sb H_o
                        for q in range(n):
                            s = 0.0
                            for kk in range(mo):
                                for ll_ in range(mo):
                                    s += H[j, idx[kk], i] * Sb[kk, ll_] * H[j, idx[ll_], q]
                            Ppb[i, q] += s
                    # C_o = Pp H_o^T: Pp_bar += Cb H_o, H_bar += Cb^T Pp
                    for i in range(n):
                        for q in range(n):
                            s = 0.0
                            for kk in range(mo):
                                s += Cb[i, kk] * H[j, idx[kk], q]
                            Ppb[i, q] += s
                    for kk in range(mo):
                        for q in range(n):
                            s = 0.0
                            for i in range(n):
                                s += Cb[i, kk] * Pp[t, r, j, i, q]
                            gH[j, idx[kk], q] += s
                    # nu = z_o - H_o xp
                    for kk in range(mo):
                        for i in range(n):
                            gH[j, idx[kk], i] -= nub[kk] * xp[t, r, j, i]
                            xpb[i] -= H[j, idx[kk], i] * nub[kk]
                for i in range(n):
                    for k in range(i, n):
                        v = 0.5 * (Ppb[i, k] + Ppb[k, i])
                        Ppb[i, k] = v
                        Ppb[k, i] = v
                # -- the prior of mode j
                if t == 0 and update_first:
                    for i in range(n):
                        gx0[r, j, i] += xpb[i]
                        for k in range(n):
                            gP0[r, j, i, k] += Ppb[i, k]
                else:
                    # xp = F xm + b; Pp = F Pm F^T + Q
                    for i in range(n):
                        gb[j, i] += xpb[i]
                        gbu[tu, ru, j, i] += xpb[i]
                        s = 0.0
                        for k in range(n):
                            s += F[j, k, i] * xpb[k]
                        xmb[j, i] = s
                    for i in range(n):
                        for k in range(n):
                            gQ[j, i, k] += Ppb[i, k]
                            gF[j, i, k] += xpb[i] * xm[t, r, j, k]
                    Fj, gFj = F[j], gF[j]
                    matmul(Fj, Pm[t, r, j], tmp)  # F_bar += 2 Ppb F Pm
                    matmul_add(Ppb, tmp, 2.0, gFj, gFj)
                    matmul(Ppb, Fj, tmp)  # Pm_bar = F^T Ppb F
                    matmul_tn(Fj, tmp, Pmb[j])
            # -- the interaction, back to the previous posterior
            if t == 0:
                plm, px, pP = logmu0[r], x0[r], P0[r]
            else:
                plm, px, pP = logmu[t - 1, r], x[t - 1, r], P[t - 1, r]
            zero_modes(plmb, pxb, pPb)
            if t == 0 and update_first:
                for j in range(M):
                    glogmu0[r, j] += abar[j]
            elif rule == 2:
                for j in range(M):
                    plmb[j] += abar[j]
                    for i in range(n):
                        pxb[j, i] += xmb[j, i]
                        for k in range(n):
                            pPb[j, i, k] += Pmb[j, i, k]
            else:
                mixing_weights(plm, Pt, rule, tiny, mu, c, w)  # (floored as in the forward pass)
                for j in range(M):
                    if c[j] <= tiny:  # (the floor applied: no adjoint through mode j's mixing)
                        for q in range(M):
                            wb[q, j] = 0.0
                        continue
                    # the total adjoint of xm_j (its own and through d_ij = x_i - xm_j)
                    for i in range(n):
                        s = 0.0
                        for q in range(M):
                            s += w[q, j] * (px[q, i] - xm[t, r, j, i])
                        d[i] = s
                    for i in range(n):
                        s = 0.0
                        for k in range(n):
                            s += (Pmb[j, i, k] + Pmb[j, k, i]) * d[k]
                        xmb[j, i] -= s
                    for q in range(M):
                        for i in range(n):
                            d[i] = px[q, i] - xm[t, r, j, i]
                        s = 0.0
                        for i in range(n):
                            s += xmb[j, i] * px[q, i]
                            for k in range(n):
                                s += Pmb[j, i, k] * (pP[q, i, k] + d[i] * d[k])
                        wb[q, j] = s
                        for i in range(n):
                            v = w[q, j] * xmb[j, i]
                            for k in range(n):
                                v += w[q, j] * (Pmb[j, i, k] + Pmb[j, k, i]) * d[k]
                                pPb[q, i, k] += w[q, j] * Pmb[j, i, k]
                            pxb[q, i] += v
                for i in range(M):
                    mub[i] = 0.0
                for j in range(M):
                    cb[j] = abar[j] / c[j] if c[j] > tiny else 0.0
                if rule == 0:
                    for j in range(M):
                        if c[j] <= tiny:
                            continue
                        for i in range(M):
                            mub[i] += wb[i, j] * Pt[i, j] / c[j]
                            gPt[i, j] += wb[i, j] * mu[i] / c[j]
                            cb[j] -= wb[i, j] * w[i, j] / c[j]
                else:
                    for j in range(M):
                        for i in range(M):
                            mub[i] += wb[i, j]
                for j in range(M):
                    for i in range(M):
                        mub[i] += cb[j] * Pt[i, j]
                        gPt[i, j] += mu[i] * cb[j]
                for i in range(M):
                    plmb[i] += mub[i] * mu[i]
            if t == 0:
                for j in range(M):
                    glogmu0[r, j] += plmb[j]
                    for i in range(n):
                        gx0[r, j, i] += pxb[j, i]
                        for k in range(n):
                            gP0[r, j, i, k] += 0.5 * (pPb[j, i, k] + pPb[j, k, i])
            else:
                copy_modes(plmb, pxb, pPb, clm, cx, cP)

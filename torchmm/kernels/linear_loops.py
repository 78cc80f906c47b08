"""The Numba loops of :mod:`torchmm.kernels.linear` (imported on first use: importing Numba takes
about 0.2 s).

A linear-Gaussian multiple-model filter over a whole run, one run after another, in one compiled call:
the IMM (``rule = 0``: moment mixing), GPB1 (``1``: collapse) and the static bank (``2``: no
interaction, which with one mode is the Kalman filter), the equations of torchmm/multimodel/imm.py,
torchmm/filters/kalman.py and torchmm.linalg.condition, operation by operation; and the reverse pass
(the adjoint) of the same run, for autograd. Small dense loops: the state, measurement and mode
sizes are a few each, so the cost is arithmetic, not the dispatch of ~40 tensor operations a step.

Array layouts (C-contiguous, float32 or float64): ``z (T, B, m)``; models ``F (M, n, n)``, ``b (M, n)``,
``Q (M, n, n)``, ``H (M, m, n)``, ``R (M, m, m)``, ``Pi (T or 1, B or 1, M, M)`` (a time-varying
transition's matrix of each step and run, or one); start ``logmu0 (B, M)``,
``x0 (B, M, n)``, ``P0 (B, M, n, n)``; the input terms ``bu (T or 1, B or 1, M, n)`` (``G_j u_t`` of
each step, run and mode, added to ``b``: zeros ``(1, 1, M, n)`` without controls); outputs ``ll (T, B)``, ``logmu (T, B, M)``, ``x (T, B, M, n)``,
``P (T, B, M, n, n)`` and the intermediates of the same shapes (``xp``/``Pp`` the mode priors,
``logc`` the predicted mode log-probabilities, ``xm``/``Pm`` the mixed start beliefs, ``innov (T, B, M, m)``,
``S (T, B, M, m, m)``, ``mode_ll (T, B, M)``, ``flags (T, B, M)``: 1 where the innovation covariance
was regularised).
"""

from __future__ import annotations

import math

import numba
import numpy as np

LOG_2PI = math.log(2.0 * math.pi)


@numba.njit(cache=True)
def chol_reg(S, m, eps, tiny, L):
    """``torchmm.linalg.cholesky`` of ``S[:m, :m]`` into ``L``: the same regularisation (closed forms
    for ``m <= 2``, jitter then a diagonal for ``m > 2``). Returns 1 where it regularised."""
    for i in range(m):
        for j in range(m):
            L[i, j] = 0.0
    if m == 1:
        s = S[0, 0]
        L[0, 0] = math.sqrt(s if s > tiny else tiny)
        return 0 if s > tiny else 1
    if m == 2:
        a, bb, c = S[0, 0], S[1, 0], S[1, 1]
        scale = max(abs(a), abs(c)) * eps + tiny
        l11 = math.sqrt(max(max(a, 0.0), scale))
        l21 = bb / l11
        pivot = c - l21 * l21
        l22 = math.sqrt(max(pivot, scale))
        L[0, 0], L[1, 0], L[1, 1] = l11, l21, l22
        return 0 if (a > scale and pivot > scale) else 1
    if _chol(S, m, 0.0, L):
        return 0
    scale = 0.0
    for i in range(m):
        scale = max(scale, abs(S[i, i]))
    if scale != scale:
        scale = 1.0
    scale = max(scale, tiny)
    if _chol(S, m, scale * math.sqrt(eps), L):
        return 1
    for i in range(m):
        for j in range(m):
            L[i, j] = 0.0
        L[i, i] = math.sqrt(max(S[i, i], eps * scale))
    return 1


@numba.njit(cache=True)
def _chol(S, m, jitter, L):
    """Plain Cholesky of ``S + jitter I``; False where a pivot is not positive (LAPACK's failure)."""
    for j in range(m):
        d = S[j, j] + jitter
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return False
        L[j, j] = math.sqrt(d)
        for i in range(j + 1, m):
            s = S[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    return True


@numba.njit(cache=True)
def _logsumexp(a, M):
    top = -math.inf
    for j in range(M):
        if a[j] > top:
            top = a[j]
    if top == -math.inf or top != top:
        return top
    s = 0.0
    for j in range(M):
        s += math.exp(a[j] - top)
    return top + math.log(s)


@numba.njit(cache=True, inline="always")
def _mixing_weights(plm, Pt, rule, tiny, mu, c, w):
    """The interaction's weights from the previous mode log-probabilities ``plm`` and the step's transition
    matrix ``Pt``: ``mu`` the probabilities, ``c_j = sum_i mu_i Pt_ij`` the predicted ones, ``w[i, j]`` the
    mixing weight of mode ``i`` into ``j`` (IMM, ``rule`` 0: ``mu_i Pt_ij / c_j``, ``c_j`` floored at
    ``tiny``) or ``mu_i`` (GPB1's collapse). The forward and the reverse pass share it."""
    M = mu.shape[0]
    for i in range(M):
        mu[i] = math.exp(plm[i])
    for j in range(M):
        s = 0.0
        for i in range(M):
            s += mu[i] * Pt[i, j]
        c[j] = s
    for j in range(M):
        cj = c[j] if c[j] > tiny else tiny
        for i in range(M):
            w[i, j] = mu[i] * Pt[i, j] / cj if rule == 0 else mu[i]


@numba.njit(cache=True, inline="always")
def _predict(F, b, bu, Q, x, P, xp, Pp, FP):
    """One mode's prediction: ``xp = F x + b + bu`` (``bu`` the step's input term ``G u_t``), ``FP = F P``
    and ``Pp = FP F^T + Q``. The filter's forward pass and Kim's smoother share it."""
    n = x.shape[0]
    for i in range(n):
        s = b[i] + bu[i]
        for k in range(n):
            s += F[i, k] * x[k]
        xp[i] = s
    for i in range(n):
        for k in range(n):
            s = 0.0
            for q in range(n):
                s += F[i, q] * P[q, k]
            FP[i, k] = s
    for i in range(n):
        for k in range(n):
            s = 0.0
            for q in range(n):
                s += FP[i, q] * F[k, q]
            Pp[i, k] = s + Q[i, k]


@numba.njit(cache=True)
def forward(z, F, b, Q, H, R, Pi, rule, update_first, logmu0, x0, P0, bu, eps, tiny,
            ll, logmu, x, P, xp, Pp, logc, xm, Pm, innov, Sout, mode_ll, flags):
    """The filter over every run and step (see the module docstring). Returns the numbers of
    non-finite log-likelihoods where a datum was present and of regularised updates (0, 0: none)."""
    T, B, m = z.shape
    M, n = F.shape[0], F.shape[1]
    dt = z.dtype
    mu = np.empty(M, dt)
    c = np.empty(M, dt)
    w = np.empty((M, M), dt)
    a = np.empty(M, dt)
    FP = np.empty((n, n), dt)
    C = np.empty((n, m), dt)
    S = np.empty((m, m), dt)
    L = np.empty((m, m), dt)
    A = np.empty((m, n), dt)
    wv = np.empty(m, dt)
    nu = np.empty(m, dt)
    obs = np.empty(m, np.bool_)
    d = np.empty(n, dt)
    bad = 0
    regularised = 0
    step_u, run_u = bu.shape[0] > 1, bu.shape[1] > 1
    step_pi, run_pi = Pi.shape[0] > 1, Pi.shape[1] > 1
    for r in range(B):
        ru = r if run_u else 0
        for t in range(T):
            tu = t if step_u else 0
            Pt = Pi[t if step_pi else 0, r if run_pi else 0]  # (the step's transition matrix)
            if t == 0:
                plm, px, pP = logmu0[r], x0[r], P0[r]
            else:
                plm, px, pP = logmu[t - 1, r], x[t - 1, r], P[t - 1, r]
            if t == 0 and update_first:
                for j in range(M):
                    logc[t, r, j] = plm[j]
                    for i in range(n):
                        xp[t, r, j, i] = px[j, i]
                        for k in range(n):
                            Pp[t, r, j, i, k] = pP[j, i, k]
            else:
                # -- interaction (torchmm/multimodel/imm.py: MomentMixing, Collapse, NoInteraction)
                if rule == 2:
                    for j in range(M):
                        logc[t, r, j] = plm[j]
                        for i in range(n):
                            xm[t, r, j, i] = px[j, i]
                            for k in range(n):
                                Pm[t, r, j, i, k] = pP[j, i, k]
                else:
                    _mixing_weights(plm, Pt, rule, tiny, mu, c, w)
                    for j in range(M):
                        logc[t, r, j] = math.log(c[j])
                    for j in range(M):
                        for i in range(n):
                            s = 0.0
                            for k in range(M):
                                s += w[k, j] * px[k, i]
                            xm[t, r, j, i] = s
                        for i in range(n):
                            for k in range(n):
                                Pm[t, r, j, i, k] = 0.0
                        for q in range(M):
                            for i in range(n):
                                d[i] = px[q, i] - xm[t, r, j, i]
                            for i in range(n):
                                for k in range(n):
                                    Pm[t, r, j, i, k] += w[q, j] * (pP[q, i, k] + d[i] * d[k])
                # -- prediction: xp = F xm + b (+ the step's input term bu = G u_t), Pp = F Pm F^T + Q
                for j in range(M):
                    _predict(F[j], b[j], bu[tu, ru, j], Q[j], xm[t, r, j], Pm[t, r, j], xp[t, r, j], Pp[t, r, j], FP)
            # -- update of every mode (torchmm.linalg.condition)
            count = 0
            for k in range(m):
                obs[k] = math.isfinite(z[t, r, k])
                if obs[k]:
                    count += 1
            for j in range(M):
                for k in range(m):
                    s = 0.0
                    for i in range(n):
                        s += H[j, k, i] * xp[t, r, j, i]
                    innov[t, r, j, k] = z[t, r, k] - s
                for i in range(n):
                    for k in range(m):
                        s = 0.0
                        for q in range(n):
                            s += Pp[t, r, j, i, q] * H[j, k, q]
                        C[i, k] = s
                for k in range(m):
                    for l in range(m):
                        s = 0.0
                        for i in range(n):
                            s += C[i, k] * H[j, l, i]
                        S[k, l] = s + R[j, k, l]
                        Sout[t, r, j, k, l] = S[k, l]
                flag = 0
                ell = 0.0
                if count == 0:
                    for i in range(n):
                        x[t, r, j, i] = xp[t, r, j, i]
                        for k in range(n):
                            P[t, r, j, i, k] = 0.5 * (Pp[t, r, j, i, k] + Pp[t, r, j, k, i])
                else:
                    for k in range(m):
                        nu[k] = innov[t, r, j, k] if obs[k] else 0.0
                        for l in range(m):
                            if not (obs[k] and obs[l]):
                                S[k, l] = 1.0 if k == l else 0.0
                        if not obs[k]:
                            for i in range(n):
                                C[i, k] = 0.0
                    if m == 1:
                        s_raw = S[0, 0]
                        sv = s_raw if s_raw > tiny else tiny
                        flag = 1 if s_raw <= tiny else 0
                        for i in range(n):
                            x[t, r, j, i] = xp[t, r, j, i] + C[i, 0] / sv * nu[0]
                        for i in range(n):
                            for k in range(n):
                                P[t, r, j, i, k] = 0.5 * ((Pp[t, r, j, i, k] - C[i, 0] / sv * C[k, 0])
                                                          + (Pp[t, r, j, k, i] - C[k, 0] / sv * C[i, 0]))
                        ell = -0.5 * (nu[0] * nu[0] / sv + math.log(sv) + LOG_2PI)
                    else:
                        flag = chol_reg(S, m, eps, tiny, L)
                        # A = L^{-1} C^T, wv = L^{-1} nu (forward substitution)
                        for k in range(m):
                            for i in range(n):
                                s = C[i, k]
                                for l in range(k):
                                    s -= L[k, l] * A[l, i]
                                A[k, i] = s / L[k, k]
                            s = nu[k]
                            for l in range(k):
                                s -= L[k, l] * wv[l]
                            wv[k] = s / L[k, k]
                        quad = 0.0
                        half = 0.0
                        for k in range(m):
                            quad += wv[k] * wv[k]
                            half += math.log(L[k, k])
                        for i in range(n):
                            s = xp[t, r, j, i]
                            for k in range(m):
                                s += A[k, i] * wv[k]
                            x[t, r, j, i] = s
                        for i in range(n):
                            for k in range(i, n):
                                s = 0.0
                                for l in range(m):
                                    s += A[l, i] * A[l, k]
                                v = 0.5 * ((Pp[t, r, j, i, k] - s) + (Pp[t, r, j, k, i] - s))
                                P[t, r, j, i, k] = v
                                P[t, r, j, k, i] = v
                        ell = -0.5 * (quad + count * LOG_2PI) - half
                flags[t, r, j] = flag
                mode_ll[t, r, j] = ell
                a[j] = ell + logc[t, r, j]
            # -- mode probabilities (mode_posterior, safe_log_normalize; one mode: log 1 = 0 exactly)
            if M == 1:
                lse = a[0]
                logmu[t, r, 0] = 0.0
            else:
                lse = _logsumexp(a, M)
                for j in range(M):
                    v = a[j] - lse
                    if v != v:
                        v = -math.log(M)
                    logmu[t, r, j] = v
            ll[t, r] = lse if count > 0 else 0.0
            if count > 0 and not math.isfinite(lse):
                bad += 1
            for j in range(M):
                regularised += flags[t, r, j]
    return bad, regularised


@numba.njit(cache=True)
def backward(z, F, b, Q, H, R, Pi, rule, update_first, logmu0, x0, P0, bu,
             logmu, x, P, xp, Pp, logc, xm, Pm, gll, glogmu, gx, gP,
             gF, gb, gQ, gH, gR, gPi, glogmu0, gx0, gP0, gbu):
    """The reverse pass of :func:`forward` (runs without regularised updates): accumulates the
    adjoints of the models and start beliefs from those of the outputs ``ll``, ``logmu``, ``x``, ``P``.
    The adjoints of the symmetric matrices (``Q``, ``R``, ``P0``) are symmetric."""
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
        for j in range(M):
            clm[j] = 0.0
            for i in range(n):
                cx[j, i] = 0.0
                for k in range(n):
                    cP[j, i, k] = 0.0
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
                    for i in range(n):
                        for kk in range(mo):
                            k = idx[kk]
                            s = 0.0
                            for q in range(n):
                                s += Pp[t, r, j, i, q] * H[j, k, q]
                            C[i, kk] = s
                    for kk in range(mo):
                        for ll_ in range(mo):
                            s = 0.0
                            for i in range(n):
                                s += C[i, kk] * H[j, idx[ll_], i]
                            S[kk, ll_] = s + R[j, idx[kk], idx[ll_]]
                        s = z[t, r, idx[kk]]
                        for i in range(n):
                            s -= H[j, idx[kk], i] * xp[t, r, j, i]
                        nu[kk] = s
                    _chol(S, mo, 0.0, L)
                    _inverse_from_chol(L, mo, V, W)
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
                            s = 0.0
                            for q in range(n):
                                for ll_ in range(mo):
                                    s += Abar[i, q] * C[q, ll_] * V[ll_, kk]
                            Cb[i, kk] -= 2.0 * s
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
                    for i in range(n):  # tmp = F Pm
                        for k in range(n):
                            s = 0.0
                            for q in range(n):
                                s += F[j, i, q] * Pm[t, r, j, q, k]
                            tmp[i, k] = s
                    for i in range(n):  # F_bar += 2 Ppb F Pm
                        for k in range(n):
                            s = 0.0
                            for q in range(n):
                                s += Ppb[i, q] * tmp[q, k]
                            gF[j, i, k] += 2.0 * s
                    for i in range(n):  # Pm_bar = F^T Ppb F
                        for k in range(n):
                            s = 0.0
                            for q in range(n):
                                s += Ppb[i, q] * F[j, q, k]
                            tmp[i, k] = s
                    for i in range(n):
                        for k in range(n):
                            s = 0.0
                            for q in range(n):
                                s += F[j, q, i] * tmp[q, k]
                            Pmb[j, i, k] = s
            # -- the interaction, back to the previous posterior
            if t == 0:
                plm, px, pP = logmu0[r], x0[r], P0[r]
            else:
                plm, px, pP = logmu[t - 1, r], x[t - 1, r], P[t - 1, r]
            for i in range(M):
                plmb[i] = 0.0
                for q in range(n):
                    pxb[i, q] = 0.0
                    for k in range(n):
                        pPb[i, q, k] = 0.0
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
                _mixing_weights(plm, Pt, rule, 0.0, mu, c, w)  # (no floor: the forward pass's c exceeded it)
                for j in range(M):
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
                    cb[j] = abar[j] / c[j]
                if rule == 0:
                    for j in range(M):
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
                for j in range(M):
                    clm[j] = plmb[j]
                    for i in range(n):
                        cx[j, i] = pxb[j, i]
                        for k in range(n):
                            cP[j, i, k] = pPb[j, i, k]


@numba.njit(cache=True)
def _inverse_from_chol(L, m, V, W):
    """``V = (L L^T)^{-1}`` (``W``: workspace, ``W = L^{-1}``)."""
    for i in range(m):
        for j in range(m):
            W[i, j] = 0.0
    for j in range(m):
        W[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, m):
            s = 0.0
            for k in range(j, i):
                s -= L[i, k] * W[k, j]
            W[i, j] = s / L[i, i]
    for i in range(m):
        for j in range(m):
            s = 0.0
            for k in range(max(i, j), m):
                s += W[k, i] * W[k, j]
            V[i, j] = s


@numba.njit(cache=True)
def filter_and_kim(z, F, b, Q, H, R, Pi, rule, update_first, logmu0, x0, P0, bu, eps, tiny, slogmu, sx, sP):
    """:func:`forward` then :func:`kim` in one call (a prepared filter-and-smoother: the forward pass's
    intermediates stay inside). Returns :func:`forward`'s counts; the smoothed beliefs go to ``slogmu``,
    ``sx``, ``sP`` (written only where both counts are 0)."""
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
        kim(F, b, Q, Pi[0, 0], log_matrix(Pi[0, 0]), logmu, x, P, eps, tiny, slogmu, sx, sP)
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
def kim(F, b, Q, Pi, logPi, logmu, x, P, eps, tiny, slogmu, sx, sP):
    """Kim's smoother (torchmm.smooth.kim_step) over every run, backwards from the last filtered
    belief: the pair RTS steps from mode ``j``'s posterior through mode ``i``'s model, the smoothed
    mode probabilities in log space, and the moment-matched collapse over ``i``."""
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
        for j in range(M):
            slogmu[T - 1, r, j] = logmu[T - 1, r, j]
            for i in range(n):
                sx[T - 1, r, j, i] = x[T - 1, r, j, i]
                for k in range(n):
                    sP[T - 1, r, j, i, k] = P[T - 1, r, j, i, k]
        for t in range(T - 2, -1, -1):
            for j in range(M):
                for i in range(M):
                    # x^-_ji = F_i x_j + b_i, P^-_ji = F_i P_j F_i^T + Q_i (the forward pass's prediction),
                    # C_ji = P_j F_i^T = (F_i P_j)^T (P_j symmetric, as the filter stores it)
                    _predict(F[i], b[i], zero, Q[i], x[t, r, j], P[t, r, j], xp[j, i], Pp[j, i], FP)
                    chol_reg(Pp[j, i], n, eps, tiny, L)
                    # G^T = L^{-T} L^{-1} C^T, C^T = F_i P_j = FP
                    for c in range(n):
                        for a in range(n):
                            s = FP[a, c]
                            for q in range(a):
                                s -= L[a, q] * Y[q, c]
                            Y[a, c] = s / L[a, a]
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
                    for a in range(n):
                        for c in range(n):
                            s = 0.0
                            for q in range(n):
                                s += D[a, q] * G[q, c]
                            Y[a, c] = P[t, r, j, a, c] + s
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
                    lpred[i] = _logsumexp(col, M)
                q = 0
                for j in range(M):
                    for i in range(M):
                        ratio = slogmu[t + 1, r, i] - lpred[i]
                        if ratio != ratio:
                            ratio = -math.inf
                        lpair[j, i] = jp[j, i] + ratio
                        flat[q] = lpair[j, i]
                        q += 1
                total = _logsumexp(flat, M * M)
                for j in range(M):
                    for i in range(M):
                        lpair[j, i] -= total
                for j in range(M):
                    for i in range(M):
                        col[i] = lpair[j, i]
                    lmode[j] = _logsumexp(col, M)
                    slogmu[t, r, j] = lmode[j]
                    for i in range(M):
                        v = lpair[j, i] - lmode[j]
                        if v != v:
                            v = -math.log(M)
                        wts[j, i] = math.exp(v)
            # the collapse over i (mix_gaussians)
            for j in range(M):
                for a in range(n):
                    s = 0.0
                    for i in range(M):
                        s += wts[j, i] * mean[j, i, a]
                    sx[t, r, j, a] = s
                for a in range(n):
                    for c in range(n):
                        sP[t, r, j, a, c] = 0.0
                for i in range(M):
                    for a in range(n):
                        dv[a] = mean[j, i, a] - sx[t, r, j, a]
                    for a in range(n):
                        for c in range(n):
                            sP[t, r, j, a, c] += wts[j, i] * (cov[j, i, a, c] + dv[a] * dv[c])

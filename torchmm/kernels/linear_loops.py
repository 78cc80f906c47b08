"""The Numba loops of :mod:`torchmm.kernels.linear` (imported on first use: importing Numba takes
about 0.2 s).

A linear-Gaussian multiple-model filter over a whole run, one run after another, in one compiled call:
the IMM (``rule = 0``: moment mixing), GPB1 (``1``: collapse) and the static bank (``2``: no
interaction, which with one mode is the Kalman filter), the equations of torchmm/multimodel/imm.py,
torchmm/filters/kalman.py and torchmm.linalg.condition, operation by operation (its reverse pass, the
adjoint for autograd: :mod:`~torchmm.kernels.linear_reverse`; Kim's smoother:
:mod:`~torchmm.kernels.linear_kim`; the step functions they share: :mod:`~torchmm.kernels.loop_algebra`). Small dense loops: the state, measurement and mode
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

from torchmm.kernels.loop_algebra import (
    LOG_2PI,
    chol_reg,
    copy_modes,
    innovation_cov,
    logsumexp,
    mix_moments,
    mixing_weights,
    predict_mode,
    solve_lower,
)


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
    every = np.arange(m)  # (every measurement component: the innovation covariance's index)
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
                copy_modes(plm, px, pP, logc[t, r], xp[t, r], Pp[t, r])
            else:
                # -- interaction (torchmm/multimodel/imm.py: MomentMixing, Collapse, NoInteraction)
                if rule == 2:
                    copy_modes(plm, px, pP, logc[t, r], xm[t, r], Pm[t, r])
                else:
                    mixing_weights(plm, Pt, rule, tiny, mu, c, w)
                    for j in range(M):
                        logc[t, r, j] = math.log(c[j])
                        mix_moments(w[:, j], px, pP, xm[t, r, j], Pm[t, r, j], d)
                # -- prediction: xp = F xm + b (+ the step's input term bu = G u_t), Pp = F Pm F^T + Q
                for j in range(M):
                    predict_mode(F[j], b[j], bu[tu, ru, j], Q[j], xm[t, r, j], Pm[t, r, j], xp[t, r, j], Pp[t, r, j], FP)
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
                innovation_cov(Pp[t, r, j], H[j], R[j], every, m, C, S)
                Sout[t, r, j] = S
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
                        solve_lower(L, C.T, m, A)
                        for k in range(m):
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
                lse = logsumexp(a, M)
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

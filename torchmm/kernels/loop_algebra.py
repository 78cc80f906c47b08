"""The step functions the Numba loops of :mod:`torchmm.kernels.linear` share (issue 47: one algebra): the
regularised Cholesky factor (:func:`chol_reg`, torchmm.linalg.cholesky's rules), the interaction's weights,
one mode's prediction, a log-sum-exp and the inverse from a factor. The forward pass
(:mod:`~torchmm.kernels.linear_loops`), its reverse pass (:mod:`~torchmm.kernels.linear_reverse`) and Kim's
smoother (:mod:`~torchmm.kernels.linear_kim`) compose them."""

from __future__ import annotations

import math

import numba

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
    if chol_plain(S, m, 0.0, L):
        return 0
    scale = 0.0
    for i in range(m):
        scale = max(scale, abs(S[i, i]))
    if scale != scale:
        scale = 1.0
    scale = max(scale, tiny)
    if chol_plain(S, m, scale * math.sqrt(eps), L):
        return 1
    for i in range(m):
        for j in range(m):
            L[i, j] = 0.0
        L[i, i] = math.sqrt(max(S[i, i], eps * scale))
    return 1


@numba.njit(cache=True)
def chol_plain(S, m, jitter, L):
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
def logsumexp(a, M):
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
def mixing_weights(plm, Pt, rule, tiny, mu, c, w):
    """The interaction's weights from the previous mode log-probabilities ``plm`` and the step's transition
    matrix ``Pt``: ``mu`` the probabilities, ``c_j = sum_i mu_i Pt_ij`` the predicted ones, ``w[i, j]`` the
    mixing weight of mode ``i`` into ``j`` (IMM, ``rule`` 0: ``mu_i Pt_ij / c_j``, ``c_j`` floored at
    ``tiny``) or ``mu_i`` (GPB1's collapse). The forward and the reverse pass share it."""
    M = mu.shape[0]
    for i in range(M):
        mu[i] = math.exp(plm[i])
    matmul(mu.reshape((1, M)), Pt, c.reshape((1, M)))
    for j in range(M):
        cj = c[j] if c[j] > tiny else tiny
        for i in range(M):
            w[i, j] = mu[i] * Pt[i, j] / cj if rule == 0 else mu[i]


@numba.njit(cache=True, inline="always")
def predict_mode(F, b, bu, Q, x, P, xp, Pp, FP):
    """One mode's prediction: ``xp = F x + b + bu`` (``bu`` the step's input term ``G u_t``), ``FP = F P``
    and ``Pp = FP F^T + Q``. The filter's forward pass and Kim's smoother share it."""
    n = x.shape[0]
    for i in range(n):
        s = b[i] + bu[i]
        for k in range(n):
            s += F[i, k] * x[k]
        xp[i] = s
    matmul(F, P, FP)
    matmul_nt_add(FP, F, Q, Pp)


@numba.njit(cache=True)
def inverse_from_chol(L, m, V, W):
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


@numba.njit(cache=True, inline="always")
def matmul(A, B, out):
    """``out = A B`` (``A (p, q)``, ``B (q, r)``). A transposed view as an argument costs the loops' inner
    steps (docs/performance.md): :func:`matmul_nt_add` and :func:`matmul_tn` index their arguments as they are."""
    for i in range(A.shape[0]):
        for k in range(B.shape[1]):
            s = 0.0
            for q in range(A.shape[1]):
                s += A[i, q] * B[q, k]
            out[i, k] = s


@numba.njit(cache=True, inline="always")
def matmul_add(A, B, alpha, C, out):
    """``out = alpha A B + C``, each entry's sum in float64 before the one rounding to ``out``'s dtype
    (``C`` may be ``out``: an accumulation)."""
    for i in range(A.shape[0]):
        for k in range(B.shape[1]):
            s = 0.0
            for q in range(A.shape[1]):
                s += A[i, q] * B[q, k]
            out[i, k] = alpha * s + C[i, k]


@numba.njit(cache=True, inline="always")
def matmul_nt_add(A, B, C, out):
    """``out = A B^T + C`` (indexing ``B`` as it is: no transposed view in the loops' inner steps)."""
    for i in range(A.shape[0]):
        for k in range(B.shape[0]):
            s = 0.0
            for q in range(A.shape[1]):
                s += A[i, q] * B[k, q]
            out[i, k] = s + C[i, k]


@numba.njit(cache=True, inline="always")
def matmul_tn(A, B, out):
    """``out = A^T B`` (indexing ``A`` as it is)."""
    for i in range(A.shape[1]):
        for k in range(B.shape[1]):
            s = 0.0
            for q in range(A.shape[0]):
                s += A[q, i] * B[q, k]
            out[i, k] = s


@numba.njit(cache=True, inline="always")
def solve_lower(L, Bm, m, out):
    """``out = L^{-1} B`` over the first ``m`` rows (``L`` lower triangular, ``B (m, c)``: forward
    substitution column by column)."""
    for c in range(Bm.shape[1]):
        for a in range(m):
            s = Bm[a, c]
            for q in range(a):
                s -= L[a, q] * out[q, c]
            out[a, c] = s / L[a, a]


@numba.njit(cache=True, inline="always")
def copy_modes(lp, X, C, lp_out, X_out, C_out):
    """``(lp_out, X_out, C_out) = (lp, X, C)``: the modes' log-probabilities ``(M,)``, means ``(M, n)``
    and covariances ``(M, n, n)``."""
    M, n = X.shape
    for j in range(M):
        lp_out[j] = lp[j]
        for i in range(n):
            X_out[j, i] = X[j, i]
            for k in range(n):
                C_out[j, i, k] = C[j, i, k]


@numba.njit(cache=True, inline="always")
def zero_modes(lp, X, C):
    """``lp``, ``X`` and ``C`` (as :func:`copy_modes`' ) set to 0."""
    M, n = X.shape
    for j in range(M):
        lp[j] = 0.0
        for i in range(n):
            X[j, i] = 0.0
            for k in range(n):
                C[j, i, k] = 0.0


@numba.njit(cache=True, inline="always")
def mix_moments(w, X, C, x_out, C_out, d):
    """The moment-matched mixture with weights ``w (K,)`` of the Gaussians ``X (K, n)``, ``C (K, n, n)``:
    ``x_out = sum_q w_q X_q``, ``C_out = sum_q w_q (C_q + (X_q - x_out)(X_q - x_out)^T)`` (``d``: workspace
    ``(n,)``). The IMM's interaction (``w`` a column of the mixing weights) and Kim's collapse share it."""
    K, n = X.shape
    for i in range(n):
        s = 0.0
        for k in range(K):
            s += w[k] * X[k, i]
        x_out[i] = s
    for i in range(n):
        for k in range(n):
            C_out[i, k] = 0.0
    for q in range(K):
        for i in range(n):
            d[i] = X[q, i] - x_out[i]
        for i in range(n):
            for k in range(n):
                C_out[i, k] += w[q] * (C[q, i, k] + d[i] * d[k])


@numba.njit(cache=True, inline="always")
def innovation_cov(Pp, H, R, idx, mo, C, S):
    """The cross covariance ``C = Pp H_o^T (n, mo)`` and the innovation covariance ``S = H_o Pp H_o^T + R_oo
    (mo, mo)`` over the measurement components ``idx[:mo]`` (the observed ones, or all of them)."""
    n = Pp.shape[0]
    for i in range(n):
        for kk in range(mo):
            s = 0.0
            for q in range(n):
                s += Pp[i, q] * H[idx[kk], q]
            C[i, kk] = s
    for kk in range(mo):
        for ll in range(mo):
            s = 0.0
            for i in range(n):
                s += C[i, kk] * H[idx[ll], i]
            S[kk, ll] = s + R[idx[kk], idx[ll]]


@numba.njit(cache=True, inline="always")
def triple_entry(X, Y, Z, i, k, p, r):
    """``(X Y Z)[i, k] = sum_q sum_l X[i, q] Y[q, l] Z[l, k]`` over ``q < p``, ``l < r``, summed in float64
    (the reverse pass's products of three factors)."""
    s = 0.0
    for q in range(p):
        for ll in range(r):
            s += X[i, q] * Y[q, ll] * Z[ll, k]
    return s

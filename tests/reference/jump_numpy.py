"""The exact smoother of a jump-Markov linear-Gaussian system in float64 NumPy, independent of torchmm's
code: every mode sequence enumerated, the joint Gaussian of ``(x_0 .. x_{T-1})`` of each built from the
model (no inverse of ``F``, ``Q`` or the initial covariance: singular ones are fine), conditioned on the
finite measurement components, the sequences weighted by their prior and marginal likelihood.

Conventions as torchmm's multiple-model filters (docs/smoothing.md): the initial belief and ``mu0`` at step
-1, ``P(s_0) = mu0 @ Pi``, the prediction into step ``k`` uses ``controls[k]`` through ``B``.
"""

from __future__ import annotations

import itertools
import math

import numpy as np


def exact(F, b, Q, H, R, Pi, mu0, m0, P0, z, u=None, B=None):
    """The smoothed mean ``(T, n)``, covariance ``(T, n, n)`` and mode probabilities ``(T, M)`` of one run.

    Shapes: F, Q ``(M, n, n)``, b ``(M, n)``, H ``(M, m, n)``, R ``(M, m, m)``, Pi ``(M, M)``, mu0 ``(M,)``,
    m0 ``(n,)``, P0 ``(n, n)``, z ``(T, m)`` (NaN: missing), u ``(T, p)`` and B ``(M, n, p)`` or None.
    """
    F, b, Q, H, R, Pi, mu0, m0, P0, z = (np.asarray(a, dtype=np.float64)
                                         for a in (F, b, Q, H, R, Pi, mu0, m0, P0, z))
    M, n = F.shape[0], F.shape[-1]
    T, m = z.shape
    seqs = np.array(list(itertools.product(range(M), repeat=T)))
    with np.errstate(divide="ignore"):
        log_pi, log_p0 = np.log(Pi), np.log(mu0 @ Pi)
    log_prior = log_p0[seqs[:, 0]] + sum(log_pi[seqs[:, k - 1], seqs[:, k]] for k in range(1, T))
    keep = np.isfinite(log_prior)
    seqs, log_prior = seqs[keep], log_prior[keep]
    S, D = len(seqs), n * (T + 1)
    # x_k = L_k [x_{-1}; w_0; ..; w_{T-1}] + c_k
    Lk = np.zeros((S, n, D))
    Lk[:, :, :n] = np.eye(n)
    ck = np.broadcast_to(m0, (S, n)).copy()
    rows, offsets = [], []
    for k in range(T):
        Fs = F[seqs[:, k]]
        Lk = Fs @ Lk
        Lk[:, :, n * (k + 1):n * (k + 2)] += np.eye(n)
        ck = np.einsum("sij,sj->si", Fs, ck) + b[seqs[:, k]]
        if u is not None:
            ck = ck + np.einsum("sij,j->si", np.asarray(B, dtype=np.float64)[seqs[:, k]], np.asarray(u[k]))
        rows.append(Lk.copy())
        offsets.append(ck.copy())
    L, mu = np.concatenate(rows, 1), np.concatenate(offsets, 1)
    base = np.zeros((S, D, D))
    base[:, :n, :n] = P0
    for k in range(T):
        base[:, n * (k + 1):n * (k + 2), n * (k + 1):n * (k + 2)] = Q[seqs[:, k]]
    Sx = L @ base @ L.transpose(0, 2, 1)
    seen = [(k, i) for k in range(T) for i in range(m) if np.isfinite(z[k, i])]
    ll = np.zeros(S)
    if seen:
        Hb = np.zeros((S, len(seen), T * n))
        Rb = np.zeros((S, len(seen), len(seen)))
        zo = np.array([z[k, i] for k, i in seen])
        for r, (k, i) in enumerate(seen):
            Hb[:, r, k * n:(k + 1) * n] = H[seqs[:, k], i]
            for c, (k2, i2) in enumerate(seen):
                if k2 == k:
                    Rb[:, r, c] = R[seqs[:, k], i, i2]
        Sz = Hb @ Sx @ Hb.transpose(0, 2, 1) + Rb
        K = np.linalg.solve(Sz, Hb @ Sx).transpose(0, 2, 1)
        nu = zo - np.einsum("sij,sj->si", Hb, mu)
        mu = mu + np.einsum("sij,sj->si", K, nu)
        Sx = Sx - K @ Hb @ Sx
        logdet = np.linalg.slogdet(Sz)[1]
        ll = -0.5 * (np.einsum("si,si->s", nu, np.linalg.solve(Sz, nu[..., None])[..., 0]) + logdet
                     + len(seen) * math.log(2 * math.pi))
    lw = log_prior + ll
    w = np.exp(lw - lw.max())
    w /= w.sum()
    means = mu.reshape(S, T, n)
    covs = np.stack([Sx[:, k * n:(k + 1) * n, k * n:(k + 1) * n] for k in range(T)], 1)
    mean = np.einsum("s,stn->tn", w, means)
    d = means - mean
    cov = np.einsum("s,stij->tij", w, covs + d[..., :, None] * d[..., None, :])
    probs = np.stack([np.array([w[seqs[:, k] == j].sum() for j in range(M)]) for k in range(T)])
    return mean, cov, probs

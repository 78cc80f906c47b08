"""Naive float64 NumPy/SciPy reference of GIMMAF (paper 004) for one run: loops over models and
components, linear-space mode probabilities, scipy's truncated normal and special functions.

Written from the equations of docs/reproduction-004.md (readings table), independent of torchmm.
"""

from __future__ import annotations

import numpy as np
from scipy import special, stats


def _tn(loc, scale):
    """Per-component N(loc, scale^2) truncated to [0, inf): mean, variance, entropy (scipy)."""
    a = -loc / scale
    # scipy's entropy is NaN for b = inf (inf * pdf(inf)); 60 standard deviations above is the same law
    d = stats.truncnorm(a, np.maximum(a, 0.0) + 60.0, loc=loc, scale=scale)
    return d.mean(), d.var(), d.entropy()


def _iw_terms(T, dof_q, T0, dof_p, A, n):
    """E_q[ln N(x; x-, P)] - KL(IW(dof_q, T) || IW(dof_p, T0)) with standard-dof inverse Wisharts."""
    def mvdigamma(a):
        return sum(special.digamma(a - 0.5 * i) for i in range(n))

    logdet_T, logdet_T0 = np.linalg.slogdet(T)[1], np.linalg.slogdet(T0)[1]
    e_logdet = logdet_T - n * np.log(2.0) - (mvdigamma(dof_q / 2) if dof_q > n - 1 else 0.0)
    e_log_px = -0.5 * n * np.log(2 * np.pi) - 0.5 * e_logdet - 0.5 * dof_q * np.trace(np.linalg.solve(T, A))
    kl = 0.5 * dof_p * (logdet_T - logdet_T0) + 0.5 * dof_q * (np.trace(np.linalg.solve(T, T0)) - n)
    if dof_q > n - 1:
        kl += 0.5 * (dof_q - dof_p) * mvdigamma(dof_q / 2) - special.multigammaln(dof_q / 2, n)
    if dof_p > n - 1:
        kl += special.multigammaln(dof_p / 2, n)
    return e_log_px - kl


def skew_iw_update(xm, Pn, z, H, r, delta, nu, tau, iterations):
    """One measurement update of the skew-t + inverse-Wishart VB filter; returns x, P, ELBO."""
    n, m = len(xm), len(z)
    T0, t = tau * Pn, n + 1 + tau + 1
    a = nu / 2 + 1
    lam = np.ones(m)
    ku = delta / (delta**2 + r)
    loc = ku * (z - H @ xm)
    sc = np.sqrt(r / (delta**2 + r) / lam)
    Eu, Vu, Hu = _tn(loc, sc)
    x, P = xm.copy(), Pn.copy()
    for _ in range(iterations):
        d = x - xm
        T = T0 + P + np.outer(d, d)
        Ph = T / (t - n - 1)
        S = H @ Ph @ H.T + np.diag(r / lam)
        K = Ph @ H.T @ np.linalg.inv(S)
        x = xm + K @ (z - H @ xm - delta * Eu)
        P = Ph - K @ H @ Ph
        res = z - H @ x
        loc, sc = ku * res, np.sqrt(r / (delta**2 + r) / lam)
        Eu, Vu, Hu = _tn(loc, sc)
        phi = ((res - delta * Eu) ** 2 + np.diag(H @ P @ H.T) + delta**2 * Vu) / r + Vu + Eu**2
        b = (nu + phi) / 2
        lam = a / b
    # ELBO (39)
    d = x - xm
    elbo = _iw_terms(T, t - n - 1, T0, tau, P + np.outer(d, d), n)
    elog = special.digamma(a) - np.log(b)
    e_sq = (z - H @ x - delta * Eu) ** 2 + np.diag(H @ P @ H.T) + delta**2 * Vu
    elbo += np.sum(-0.5 * np.log(2 * np.pi * r) + 0.5 * elog - 0.5 * (a / b) * e_sq / r)
    elbo += np.sum(np.log(2) - 0.5 * np.log(2 * np.pi) + 0.5 * elog - 0.5 * (a / b) * (Vu + Eu**2))
    for ai, bi, nui in zip(np.broadcast_to(a, (m,)), b, np.broadcast_to(nu, (m,))):
        # -KL(q || p) = E_q[ln Ga(lam; nu/2, nu/2)] + H(q)
        elbo += (nui / 2 - 1) * (special.digamma(ai) - np.log(bi)) - (nui / 2) * ai / bi \
            + (nui / 2) * np.log(nui / 2) - special.gammaln(nui / 2) + stats.gamma(ai, scale=1 / bi).entropy()
    elbo += 0.5 * np.linalg.slogdet(2 * np.pi * np.e * P)[1] + np.sum(Hu)
    return x, P, elbo


def gimmaf(Fs, Q, H, r, delta, nu, tau, iterations, Pi, x0, P0, zs):
    """GIMMAF over a sequence ``zs (T, m)`` for one run; returns combined means ``(T, n)`` and mode
    probabilities ``(T, M)``."""
    M = len(Fs)
    mu = np.full(M, 1.0 / M)
    xs = [x0.copy() for _ in range(M)]
    Ps = [P0.copy() for _ in range(M)]
    out_x, out_mu = [], []
    for z in zs:
        c = Pi.T @ mu
        w = (Pi * mu[:, None]) / c[None, :]  # w[i, j] = mu_{i|j}
        mixed = []
        for j in range(M):
            xm = sum(w[i, j] * xs[i] for i in range(M))
            Pm = sum(w[i, j] * (Ps[i] + np.outer(xs[i] - xm, xs[i] - xm)) for i in range(M))
            mixed.append((xm, Pm))
        liks = []
        for j in range(M):
            xp = Fs[j] @ mixed[j][0]
            Pp = Fs[j] @ mixed[j][1] @ Fs[j].T + Q
            xs[j], Ps[j], elbo = skew_iw_update(xp, Pp, z, H, r, delta, nu, tau, iterations)
            liks.append(np.exp(elbo))
        mu = np.array(liks) * c
        mu = mu / mu.sum()
        out_x.append(sum(mu[j] * xs[j] for j in range(M)))
        out_mu.append(mu)
    return np.array(out_x), np.array(out_mu)

"""Naive float64 NumPy references of Bar-Shalom's IMM, GPB1 and GPB2 (one run, loops everywhere).

Written straight from docs/baselines.md §1 in linear space, independent of torchmm's code.
"""

from __future__ import annotations

import numpy as np


def kf_step(x, P, F, b, Q, H, R, z):
    x_pred = F @ x + b
    P_pred = F @ P @ F.T + Q
    S = H @ P_pred @ H.T + R
    nu = z - H @ x_pred
    K = P_pred @ H.T @ np.linalg.solve(S, np.eye(len(S)))
    x_post = x_pred + K @ nu
    P_post = P_pred - K @ S @ K.T
    m = len(z)
    lik = np.exp(-0.5 * nu @ np.linalg.solve(S, nu)) / np.sqrt((2 * np.pi) ** m * np.linalg.det(S))
    return x_post, P_post, lik


def merge(weights, xs, Ps):
    x = sum(w * xi for w, xi in zip(weights, xs))
    P = sum(w * (Pi + np.outer(xi - x, xi - x)) for w, xi, Pi in zip(weights, xs, Ps))
    return x, P


def imm(models, H, R, Pi, x0, P0, mu0, zs):
    """models: list of (F, b, Q). Returns per-step combined means, covs and mode probabilities."""
    M = len(models)
    xs, Ps, mu = [x0.copy()] * M, [P0.copy()] * M, mu0.copy()
    out_x, out_P, out_mu = [], [], []
    for z in zs:
        cbar = Pi.T @ mu
        x_mix, P_mix = [], []
        for j in range(M):
            w = [Pi[i, j] * mu[i] / cbar[j] for i in range(M)]
            xj, Pj = merge(w, xs, Ps)
            x_mix.append(xj)
            P_mix.append(Pj)
        liks = np.zeros(M)
        for j, (F, b, Q) in enumerate(models):
            xs[j], Ps[j], liks[j] = kf_step(x_mix[j], P_mix[j], F, b, Q, H, R, z)
        mu = liks * cbar / np.sum(liks * cbar)
        x, P = merge(mu, xs, Ps)
        out_x.append(x)
        out_P.append(P)
        out_mu.append(mu.copy())
    return np.array(out_x), np.array(out_P), np.array(out_mu)


def gpb1(models, H, R, Pi, x0, P0, mu0, zs):
    M = len(models)
    x, P, mu = x0.copy(), P0.copy(), mu0.copy()
    out_x, out_P, out_mu = [], [], []
    for z in zs:
        cbar = Pi.T @ mu
        xs, Ps, liks = [], [], np.zeros(M)
        for j, (F, b, Q) in enumerate(models):
            xj, Pj, liks[j] = kf_step(x, P, F, b, Q, H, R, z)
            xs.append(xj)
            Ps.append(Pj)
        mu = liks * cbar / np.sum(liks * cbar)
        x, P = merge(mu, xs, Ps)
        out_x.append(x)
        out_P.append(P)
        out_mu.append(mu.copy())
    return np.array(out_x), np.array(out_P), np.array(out_mu)


def gpb2(models, H, R, Pi, x0, P0, mu0, zs):
    M = len(models)
    xs, Ps, mu = [x0.copy()] * M, [P0.copy()] * M, mu0.copy()
    out_x, out_P, out_mu = [], [], []
    for z in zs:
        xij = [[None] * M for _ in range(M)]
        Pij = [[None] * M for _ in range(M)]
        w = np.zeros((M, M))
        for i in range(M):
            for j, (F, b, Q) in enumerate(models):
                xij[i][j], Pij[i][j], lik = kf_step(xs[i], Ps[i], F, b, Q, H, R, z)
                w[i, j] = lik * Pi[i, j] * mu[i]
        mu = w.sum(0) / w.sum()
        new_xs, new_Ps = [], []
        for j in range(M):
            weights = w[:, j] / w[:, j].sum()
            xj, Pj = merge(weights, [xij[i][j] for i in range(M)], [Pij[i][j] for i in range(M)])
            new_xs.append(xj)
            new_Ps.append(Pj)
        xs, Ps = new_xs, new_Ps
        x, P = merge(mu, xs, Ps)
        out_x.append(x)
        out_P.append(P)
        out_mu.append(mu.copy())
    return np.array(out_x), np.array(out_P), np.array(out_mu)

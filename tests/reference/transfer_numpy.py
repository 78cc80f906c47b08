"""Naive float64 NumPy reference of paper 000's IMM-TF (one run, loops everywhere).

Written straight from the paper's equations (13)-(28), independent of torchmm's code, with the
readings recorded in docs/reproduction.md: the smoothing reference is the combined output at k-1,
``Q_k`` in (14) is the mode's process-noise covariance ``G Q G^T``, ``F_j x`` includes the mode's
offset, (21) uses ``K̄`` from ``P^-``, and ``Lambda_j`` is evaluated at the uncorrected prediction.
Without ``y_S`` (NaN) the step is the IMM step of ``mm_numpy.imm``.
"""

from __future__ import annotations

import numpy as np

from tests.reference.mm_numpy import merge


def gaussian(nu, S):
    m = len(nu)
    return np.exp(-0.5 * nu @ np.linalg.solve(S, nu)) / np.sqrt((2 * np.pi) ** m * np.linalg.det(S))


def update(x, P, H, R, z):
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    return x + K @ (z - H @ x), P - K @ H @ P


def imm_tf(models, H, R, Hs, Rs, Pi, x0, P0, mu0, ys, ys_source):
    """models: list of (F, b, Q). ys (T, m); ys_source (T, m_s) with NaN rows when absent."""
    M = len(models)
    xs, Ps, mu = [x0.copy()] * M, [P0.copy()] * M, mu0.copy()
    x_out, P_out = x0.copy(), P0.copy()
    out_x, out_P, out_mu = [], [], []
    for y, y_s in zip(ys, ys_source):
        cbar = Pi.T @ mu  # mu_j^-
        new_xs, new_Ps, liks = [], [], np.zeros(M)
        for j, (F, b, Q) in enumerate(models):
            w = [Pi[i, j] * mu[i] / cbar[j] for i in range(M)]
            x0j, P0j = merge(w, xs, Ps)  # (16)-(17)
            x_pred = F @ x0j + b  # (18)
            P_pred = F @ P0j @ F.T + Q  # (19)
            liks[j] = gaussian(y - H @ x_pred, H @ P_pred @ H.T + R)  # (25)
            if np.all(np.isfinite(y_s)):
                m_k, D_k = update(x_pred, P_pred, Hs, Rs, y_s)  # source filter N(m_k^j, D_k^j)
                A = F @ P_out @ F.T + Q
                L = P_out @ F.T @ np.linalg.inv(A)  # smoothing gain
                m_s = x_out + L @ (m_k - (F @ x_out + b))  # (13)
                u_s = H @ (F @ m_s + b)  # u_S = H_j F_j m_{k-1}^j
                x_bar, P_bar = update(x_pred, P_pred, H, R, u_s)  # (20)-(21)
            else:
                x_bar, P_bar = x_pred, P_pred
            x_post, P_post = update(x_bar, P_bar, H, R, y)  # (22)-(23)
            new_xs.append(x_post)
            new_Ps.append(P_post)
        xs, Ps = new_xs, new_Ps
        mu = liks * cbar / np.sum(liks * cbar)  # (26)
        x_out, P_out = merge(mu, xs, Ps)  # (27)-(28)
        out_x.append(x_out)
        out_P.append(P_out)
        out_mu.append(mu.copy())
    return np.array(out_x), np.array(out_P), np.array(out_mu)


def smoothed_previous(x, P, F, b, Q, Hs, Rs, x_pred, P_pred, y_s):
    """Oracle for (13)-(14) by joint-Gaussian conditioning (no RTS formula).

    ``x_{k-1} ~ N(x, P)``, the source posterior at ``k`` is the prediction ``N(x_pred, P_pred)``
    updated with ``y_s``; the smoothed ``x_{k-1}`` is ``p(x_{k-1} | y_s)`` when the prediction is
    ``F x + b`` with ``F P F^T + Q`` (it must be, for the identity to hold).
    """
    n = len(x)
    # joint of (x_{k-1}, x_k): [[P, P F'], [F P, F P F' + Q]]; y_s = Hs x_k + v
    cross = P @ F.T @ Hs.T  # Cov(x_{k-1}, y_s)
    S = Hs @ (F @ P @ F.T + Q) @ Hs.T + Rs
    gain = cross @ np.linalg.inv(S)
    mean = x + gain @ (y_s - Hs @ (F @ x + b))
    cov = P - gain @ cross.T
    assert np.allclose(x_pred, F @ x + b) and np.allclose(P_pred, F @ P @ F.T + Q)
    return mean, cov.reshape(n, n)

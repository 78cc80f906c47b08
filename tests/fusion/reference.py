"""Batch LMMSE oracle for system (1)-(3) in float64 NumPy, independent of torchmm.fusion.

Builds the exact first and second moments of all states x(0..T-1) and measurements y_i(0..T-1)
(with loops everywhere), then projects: x^(t | Y) = E x + Cov(x, Y) Cov(Y)^{-1} (Y - E Y). Every
local / centralized predictor, filter and smoother and every cross-covariance of estimation errors
follows from the same stacked covariance matrix. Meant for small T.
"""

from __future__ import annotations

import numpy as np


class Oracle:
    def __init__(self, A, Gamma, Qw, C, Ct, h, Qp, Qr0, R, Qv, mu0, P0, T):
        self.A, self.G, self.Qw = (np.asarray(a, float) for a in (A, Gamma, Qw))
        self.C, self.Ct = np.asarray(C, float), np.asarray(Ct, float)
        self.h, self.Qp, self.Qr0 = (np.asarray(a, float) for a in (h, Qp, Qr0))
        self.R, self.Qv = np.asarray(R, float), np.asarray(Qv, float)
        self.mu0, self.P0 = np.asarray(mu0, float), np.asarray(P0, float)
        self.T = T
        n, L, m = self.A.shape[0], self.C.shape[0], self.C.shape[1]
        self.n, self.L, self.m = n, L, m
        Ap = [np.linalg.matrix_power(self.A, k) for k in range(T + 1)]
        # E x(t), Cov(x(t), x(s)), second moments
        mean = [Ap[t] @ self.mu0 for t in range(T)]
        Pt = [self.P0]
        for _ in range(T - 1):
            Pt.append(self.A @ Pt[-1] @ self.A.T + self.G @ self.Qw @ self.G.T)
        covx = np.zeros((T, T, n, n))
        for t in range(T):
            for s in range(T):
                covx[t, s] = Ap[t - s] @ Pt[s] if t >= s else Pt[t] @ Ap[s - t].T
        secx = covx + np.einsum("ta,sb->tsab", mean, mean)
        # r moments: E[r_i(t) r_i(s)] = h^|t-s| Qr(min)
        Qr = [self.Qr0]
        for _ in range(T - 1):
            Qr.append(self.h**2 * Qr[-1] + self.Qp)
        Er = np.zeros((L, T, T))
        for i in range(L):
            for t in range(T):
                for s in range(T):
                    Er[i, t, s] = self.h[i] ** abs(t - s) * Qr[min(t, s)][i]

        # E[x(t) v_j(s)^T] = A^{t-1-s} Gamma R_j for s <= t-1
        def xv(t, s, j):
            return Ap[t - 1 - s] @ self.G @ self.R[j] if s <= t - 1 else np.zeros((n, m))

        # stacked measurement vector index: (t, i) -> block
        Ny = T * L * m
        Ey = np.zeros(Ny)
        Cyy = np.zeros((Ny, Ny))
        Cxy = np.zeros((T, n, Ny))

        def blk(t, i):
            k = (t * L + i) * m
            return slice(k, k + m)

        for t in range(T):
            for i in range(L):
                Ey[blk(t, i)] = self.C[i] @ mean[t]
        for t in range(T):
            for i in range(L):
                for s in range(T):
                    for j in range(L):
                        val = self.C[i] @ covx[t, s] @ self.C[j].T
                        if i == j:
                            val = val + Er[i, t, s] * self.Ct[i] @ secx[t, s] @ self.Ct[j].T
                        val = val + self.C[i] @ xv(t, s, j) + xv(s, t, i).T @ self.C[j].T
                        if t == s:
                            val = val + self.Qv[i, j]
                        Cyy[blk(t, i), blk(s, j)] = val
                for s in range(T):
                    # Cov(x(s), y_i(t)) = covx[s, t] C_i^T + E[x(s) v_i(t)^T]
                    Cxy[s, :, blk(t, i)] = covx[s, t] @ self.C[i].T + xv(s, t, i)
        self.mean, self.covx, self.Ey, self.Cyy, self.Cxy, self.blk = mean, covx, Ey, Cyy, Cxy, blk

    #: optional (T, L, m) bool: which measurement components exist (missing ones are not projected on)
    present = None

    def _index(self, last: int, sensors) -> np.ndarray:
        idx = []
        for t in range(last + 1):
            for i in sensors:
                rows = np.arange(self.blk(t, i).start, self.blk(t, i).stop)
                if self.present is not None:
                    rows = rows[np.asarray(self.present[t, i], bool)]
                idx.append(rows)
        return np.concatenate(idx) if idx else np.zeros(0, int)

    def gain(self, t: int, last: int, sensors):
        """K with x^(t|last) = E x(t) + K (Y - EY) over the sensors' data up to ``last``."""
        idx = self._index(min(last, self.T - 1), sensors)
        if len(idx) == 0:
            return idx, np.zeros((self.n, 0))
        S = self.Cyy[np.ix_(idx, idx)]
        return idx, np.linalg.solve(S, self.Cxy[t][:, idx].T).T

    def estimate(self, y: np.ndarray, t: int, N: int, sensors):
        """``y (T, L, m)`` one run -> x^(t|t+N) from ``sensors``."""
        idx, K = self.gain(t, t + N, sensors)
        Y = y.reshape(-1)
        return self.mean[t] + (K @ (Y[idx] - self.Ey[idx]) if len(idx) else 0.0)

    def error_cov(self, t: int, N: int, si, sj):
        """E[(x - x^_a)(x - x^_b)^T] for the estimators from sensor sets ``si`` and ``sj``."""
        ia, Ka = self.gain(t, t + N, si)
        ib, Kb = self.gain(t, t + N, sj)
        P = self.covx[t, t].copy()
        if len(ia):
            P -= Ka @ self.Cxy[t][:, ia].T
        if len(ib):
            P -= self.Cxy[t][:, ib] @ Kb.T
        if len(ia) and len(ib):
            P += Ka @ self.Cyy[np.ix_(ia, ib)] @ Kb.T
        return P

"""Paper-002 example systems and a small random system for the fusion tests."""

from __future__ import annotations

import math

import numpy as np
import torch

from torchmm.fusion import MultiSensorSystem

from .reference import Oracle


def ups_system(dtype=torch.float64) -> MultiSensorSystem:
    """Example 2 (1 kVA UPS), printed parameters; mu0 = 0 (not printed), Qr0 stationary."""
    A = [[0.9226, -0.6330, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    return MultiSensorSystem.from_correlation(
        A=A, Gamma=[[0.5], [0.0], [0.2]], Qw=[[5.0]],
        C=[[[23.738, 20.287, 0.0]]] * 3, Ct=[[[8.0, 12.0, 3.0]], [[10.0, 8.0, 5.0]], [[8.0, 6.0, 10.0]]],
        h=[0.6, -0.7, 0.8], Qp=[2.0, 3.0, 0.5], d=[[[-0.5]], [[0.4]], [[-1.0]]],
        Q_eta=[[[5.0]], [[15.0]], [[10.0]]], mu0=[0.0, 0.0, 0.0], P0=0.1 * torch.eye(3), dtype=dtype)


def radar_system(dtype=torch.float64, P0=None) -> MultiSensorSystem:
    """Example 1 with the reading h = e^{-T/5} (T = 1)."""
    rho1, rho2, T = 0.4, 0.5, 1.0
    A = [[1, T, 0, 0, 0, 0], [0, 1, 1, 0, 0, 0], [0, 0, rho1, 0, 0, 0],
         [0, 0, 0, 1, T, 0], [0, 0, 0, 0, 1, 1], [0, 0, 0, 0, 0, rho2]]
    e = np.eye(6)
    z = np.zeros(6)
    C = np.stack([np.stack([e[0], e[3]]), np.stack([e[0], z]), np.stack([z, e[3]])])
    q = 1 - math.exp(-2 * T / 5)
    h = math.exp(-T / 5)
    d = np.zeros((3, 2, 6))
    d[1, 0, 3], d[1, 1, 5], d[2, 0, 5], d[2, 1, 3] = 0.1, 0.1, 0.1, 1.0
    Q_eta = np.stack([np.diag([1000.0**2, 0.01**2]), np.diag([900.0**2, 0.02**2]),
                      np.diag([800.0**2, 0.01**2])])
    return MultiSensorSystem.from_correlation(
        A=A, Gamma=np.eye(6), Qw=np.diag([0, 0, (103 / 3) ** 2, 0, 0, 1.1e-8]), C=C, Ct=C,
        h=[h, h, 0.9 * h], Qp=[0.05**2 * q, 0.05**2 * q, 0.04**2 * q], d=d, Q_eta=Q_eta,
        mu0=[100, 400, 0, 1, 1.07e-3, 0], P0=np.zeros((6, 6)) if P0 is None else P0, dtype=dtype)


def random_system(seed: int = 0, n: int = 2, L: int = 3, m: int = 2, p: int = 2, dtype=torch.float64):
    """A random stable system with correlated noises and nonzero mu0."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A *= 0.85 / max(abs(np.linalg.eigvals(A)))
    G = rng.normal(size=(n, p))
    W = rng.normal(size=(p, p))
    Qw = W @ W.T + 0.1 * np.eye(p)
    C = rng.normal(size=(L, m, n))
    Ct = 0.5 * rng.normal(size=(L, m, n))
    d = 0.3 * rng.normal(size=(L, m, p))
    E = rng.normal(size=(L, m, m))
    Q_eta = E @ E.transpose(0, 2, 1) + 0.5 * np.eye(m)
    h = rng.uniform(-0.9, 0.9, size=L)
    Qp = rng.uniform(0.05, 0.5, size=L)
    mu0 = rng.normal(size=n)
    P0 = np.eye(n) * 0.7
    return MultiSensorSystem.from_correlation(A, G, Qw, C, Ct, h, Qp, d, Q_eta, mu0, P0, dtype=dtype)


def oracle(system: MultiSensorSystem, T: int) -> Oracle:
    f = lambda t: t.detach().cpu().numpy()  # noqa: E731
    names = ("A", "Gamma", "Qw", "C", "Ct", "h", "Qp", "Qr0", "R", "Qv", "mu0", "P0")
    return Oracle(*(f(getattr(system, k)) for k in names), T=T)

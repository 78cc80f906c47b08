"""Shared fixtures: float64 by default, seeded generators, random linear-Gaussian systems."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch

from torchmm import GaussianBelief, LinearMeasurement, LinearMotion

BATCH_SHAPES = [(), (4,), (3, 2)]

# The suite's tensors are small: one intra-op thread is fastest and immune to a busy machine (two
# threads spinning against other processes slowed the suite ~10x). Subprocesses get OMP_NUM_THREADS=1
# from the Makefile.
torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _float64_default():
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(1234)


def random_psd(n: int, rng: np.random.Generator, scale: float = 1.0, floor: float = 0.1) -> np.ndarray:
    """A random symmetric positive definite matrix (float64)."""
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T / n + floor * np.eye(n))


@dataclass
class LinearSystem:
    F: np.ndarray
    Q: np.ndarray
    H: np.ndarray
    R: np.ndarray
    offset: np.ndarray
    x0: np.ndarray
    P0: np.ndarray

    def motion(self) -> LinearMotion:
        return LinearMotion(torch.tensor(self.F), torch.tensor(self.Q), offset=torch.tensor(self.offset))

    def measurement(self) -> LinearMeasurement:
        return LinearMeasurement(torch.tensor(self.H), torch.tensor(self.R))

    def prior(self) -> GaussianBelief:
        return GaussianBelief(torch.tensor(self.x0), torch.tensor(self.P0))

    def joint_state_moments(self, steps: int) -> tuple[np.ndarray, np.ndarray]:
        """Exact mean ``(steps n,)`` and covariance of the stacked states ``x_1 .. x_T``.

        ``x_k = F^k x_0 + sum_j F^(k-j) (b + w_j)``, so
        ``Cov(x_k, x_l) = F^k P0 F^l' + sum_{j <= min(k, l)} F^(k-j) Q F^(l-j)'``.
        """
        n = self.F.shape[0]
        powers = [np.eye(n)]
        for _ in range(steps):
            powers.append(self.F @ powers[-1])
        mean_x, means = self.x0.copy(), []
        for _ in range(steps):
            mean_x = self.F @ mean_x + self.offset
            means.append(mean_x)
        cov = np.zeros((steps * n, steps * n))
        for k in range(1, steps + 1):
            for kk in range(1, steps + 1):
                c = powers[k] @ self.P0 @ powers[kk].T
                for j in range(1, min(k, kk) + 1):
                    c = c + powers[k - j] @ self.Q @ powers[kk - j].T
                cov[(k - 1) * n : k * n, (kk - 1) * n : kk * n] = c
        return np.concatenate(means), cov

    def simulate(self, steps: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        n, m = self.F.shape[0], self.H.shape[0]
        x = rng.multivariate_normal(self.x0, self.P0)
        xs, zs = [], []
        for _ in range(steps):
            x = self.F @ x + self.offset + rng.multivariate_normal(np.zeros(n), self.Q)
            xs.append(x)
            zs.append(self.H @ x + rng.multivariate_normal(np.zeros(m), self.R))
        return np.array(xs), np.array(zs)


def random_system(n: int, m: int, rng: np.random.Generator, offset: bool = True) -> LinearSystem:
    F = rng.normal(size=(n, n))
    F = 0.95 * F / max(1.0, np.abs(np.linalg.eigvals(F)).max())  # stable
    return LinearSystem(
        F=F,
        Q=random_psd(n, rng, 0.5),
        H=rng.normal(size=(m, n)),
        R=random_psd(m, rng, 1.0),
        offset=rng.normal(size=n) if offset else np.zeros(n),
        x0=rng.normal(size=n),
        P0=random_psd(n, rng, 2.0),
    )


def random_transition(M: int, rng: np.random.Generator) -> np.ndarray:
    P = rng.uniform(0.05, 1.0, size=(M, M)) + 3 * np.eye(M)
    return P / P.sum(1, keepdims=True)


def assert_symmetric_psd(cov: torch.Tensor, tol: float = 1e-9) -> None:
    torch.testing.assert_close(cov, cov.mT, rtol=0, atol=tol * (1 + cov.abs().max().item()))
    eig = torch.linalg.eigvalsh(cov)
    assert bool((eig >= -tol * (1 + eig.abs().max())).all()), f"not PSD: min eigenvalue {eig.min()}"

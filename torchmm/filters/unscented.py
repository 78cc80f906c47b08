r"""Unscented Kalman filter with pluggable sigma-point strategies.

Sigma points are placed on a *leading* axis, ``(S, *B, n)``, so that model parameters keep
broadcasting against the belief's batch (mode banks work unchanged).

.. math::
    \mathcal X = \mathrm{sigma}(x, P),\quad x^- = \textstyle\sum_s W^m_s f(\mathcal X_s),\quad
    P^- = \textstyle\sum_s W^c_s (f(\mathcal X_s) - x^-)(\cdot)^\top + Q

and for the update, from sigma points of the prior, ``z_pred = sum W^m h(X)``,
``S = sum W^c (h(X) - z_pred)(.)^T + R``, ``C = sum W^c (X - x^-)(h(X) - z_pred)^T``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief, symmetrize
from torchmm.filters.base import Filter, StepOutput
from torchmm.filters.linalg import condition
from torchmm.models.base import MeasurementModel, MotionModel, check_model_pair

__all__ = [
    "CubatureSigmaPoints",
    "JulierSigmaPoints",
    "MerweScaledSigmaPoints",
    "SigmaPointStrategy",
    "UnscentedKalmanFilter",
]


class SigmaPointStrategy:
    """Places ``2n + 1`` (or ``2n``) weighted points matching a mean and covariance."""

    def spread(self, n: int) -> float:
        """Scale ``c`` of the symmetric points ``x +- sqrt(c) L e_i``."""
        raise NotImplementedError

    def weights(self, n: int, dtype, device) -> tuple[Tensor, Tensor]:
        """Mean and covariance weights ``(S,)`` each."""
        raise NotImplementedError

    @property
    def include_center(self) -> bool:
        return True

    def points(self, mean: Tensor, cov: Tensor) -> Tensor:
        """Sigma points. Shapes: ``mean (*B, n)``, ``cov (*B, n, n)`` -> ``(S, *B, n)``."""
        n = mean.shape[-1]
        batch = torch.broadcast_shapes(mean.shape[:-1], cov.shape[:-2])
        chol, info = torch.linalg.cholesky_ex(symmetrize(cov))
        if bool((info != 0).any()):
            eigvals, eigvecs = torch.linalg.eigh(symmetrize(cov))
            chol = eigvecs * eigvals.clamp_min(0).sqrt().unsqueeze(-2)
        chol = chol.expand(*batch, n, n)
        offsets = math.sqrt(self.spread(n)) * chol.movedim(-1, 0)  # (n, *B, n): columns of L
        mean = mean.expand(*batch, n).unsqueeze(0).expand(n, *batch, n)
        parts = [mean + offsets, mean - offsets]
        if self.include_center:
            parts.insert(0, mean[:1])
        return torch.cat(parts, dim=0)


class MerweScaledSigmaPoints(SigmaPointStrategy):
    """Van der Merwe's scaled sigma points (``lambda = alpha^2 (n + kappa) - n``)."""

    def __init__(self, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0):
        if alpha <= 0:
            raise ValueError(f"alpha: must be positive, got {alpha}")
        self.alpha, self.beta, self.kappa = alpha, beta, kappa

    def _lambda(self, n: int) -> float:
        return self.alpha**2 * (n + self.kappa) - n

    def spread(self, n: int) -> float:
        c = n + self._lambda(n)
        if c <= 0:
            raise ValueError(f"alpha, kappa: n + lambda = {c} must be positive")
        return c

    def weights(self, n, dtype, device):
        lam = self._lambda(n)
        c = n + lam
        wm = torch.full((2 * n + 1,), 0.5 / c, dtype=dtype, device=device)
        wc = wm.clone()
        wm[0] = lam / c
        wc[0] = lam / c + (1 - self.alpha**2 + self.beta)
        return wm, wc


class JulierSigmaPoints(SigmaPointStrategy):
    """Julier's original sigma points with weight ``kappa / (n + kappa)`` at the centre."""

    def __init__(self, kappa: float = 0.0):
        self.kappa = kappa

    def spread(self, n: int) -> float:
        if n + self.kappa <= 0:
            raise ValueError(f"kappa: n + kappa = {n + self.kappa} must be positive")
        return n + self.kappa

    def weights(self, n, dtype, device):
        c = n + self.kappa
        w = torch.full((2 * n + 1,), 0.5 / c, dtype=dtype, device=device)
        w[0] = self.kappa / c
        return w, w.clone()


class CubatureSigmaPoints(SigmaPointStrategy):
    """Third-degree spherical-radial cubature points (``2n`` points, equal weights)."""

    @property
    def include_center(self) -> bool:
        return False

    def spread(self, n: int) -> float:
        return float(n)

    def weights(self, n, dtype, device):
        w = torch.full((2 * n,), 0.5 / n, dtype=dtype, device=device)
        return w, w.clone()


def _weighted_moments(points: Tensor, wm: Tensor) -> tuple[Tensor, Tensor]:
    """Mean ``(*B, d)`` and centred deviations ``(S, *B, d)`` of sigma points ``(S, *B, d)``."""
    shape = (-1,) + (1,) * (points.dim() - 1)
    mean = (wm.reshape(shape) * points).sum(0)
    return mean, points - mean


class UnscentedKalmanFilter(Filter):
    """Unscented Kalman filter.

    Args:
        motion: any :class:`~torchmm.models.MotionModel`.
        measurement: any :class:`~torchmm.models.MeasurementModel`.
        sigma_points: a :class:`SigmaPointStrategy`; default :class:`MerweScaledSigmaPoints`.

    Shapes:
        as :class:`~torchmm.filters.ExtendedKalmanFilter`.
    """

    def __init__(self, motion: MotionModel, measurement: MeasurementModel,
                 sigma_points: SigmaPointStrategy | None = None):
        super().__init__()
        check_model_pair(motion, measurement)
        self.motion = motion
        self.measurement = measurement
        self.sigma_points = sigma_points or MerweScaledSigmaPoints()

    def predict(self, belief: GaussianBelief, *, u: Tensor | None = None) -> GaussianBelief:
        n = belief.state_dim
        wm, wc = self.sigma_points.weights(n, belief.dtype, belief.device)
        points = self.sigma_points.points(belief.mean, belief.cov)
        propagated = self.motion(points, u=None if u is None else u.unsqueeze(0))
        mean, dev = _weighted_moments(propagated, wm)
        shape = (-1,) + (1,) * (dev.dim() - 1)
        cov = torch.einsum("s...i,s...j->...ij", wc.reshape(shape) * dev, dev)
        cov = cov + self.motion.noise_cov(belief.mean)
        return GaussianBelief(mean, symmetrize(cov))

    def update(self, belief: GaussianBelief, z: Tensor) -> StepOutput:
        n = belief.state_dim
        wm, wc = self.sigma_points.weights(n, belief.dtype, belief.device)
        points = self.sigma_points.points(belief.mean, belief.cov)
        predicted = self.measurement(points)
        z_pred, z_dev = _weighted_moments(predicted, wm)
        x_dev = points - belief.mean
        shape = (-1,) + (1,) * (z_dev.dim() - 1)
        weighted = wc.reshape(shape) * z_dev
        innovation_cov = torch.einsum("s...i,s...j->...ij", weighted, z_dev)
        innovation_cov = innovation_cov + self.measurement.noise_cov(belief.mean)
        cross_cov = torch.einsum("s...i,s...j->...ij", x_dev, weighted)
        innovation = z - z_pred
        mean, cov, log_likelihood = condition(
            belief.mean, belief.cov, innovation, symmetrize(innovation_cov), cross_cov
        )
        return StepOutput(GaussianBelief(mean, cov), belief, log_likelihood, innovation, innovation_cov)

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

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, psd_sqrt, symmetrize
from torchmm.contract import Flag, Of, Real, entry_point
from torchmm.filters.base import Filter, StepOutput, check_model_batches
from torchmm.kernels.nonlinear import NonlinearGaussian
from torchmm.linalg import check_joseph, condition, flag_failed, use_joseph
from torchmm.models.base import MeasurementModel, MotionModel, check_model_pair, check_output
from torchmm.validation import as_float, broadcast_shape, check_measurement, gaussian_batch

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

    def check(self, n: int) -> None:
        """Raise ``ValueError`` if the rule is not defined for state dimension ``n``."""
        self.spread(n)

    def points(self, mean: Tensor, cov: Tensor) -> Tensor:
        """Sigma points. Shapes: ``mean (*B, n)``, ``cov (*B, n, n)`` -> ``(S, *B, n)``.

        The square root is the Cholesky factor, or for a covariance that is not numerically
        positive definite (singular, or indefinite by rounding) the eigen-factor with negative
        eigenvalues clamped to 0 (:func:`~torchmm.beliefs.psd_sqrt`); a non-finite covariance
        gives non-finite points for that batch element only.
        """
        n = mean.shape[-1]
        batch = broadcast_shape(mean.shape[:-1], cov.shape[:-2])
        chol = psd_sqrt(symmetrize(cov)).expand(*batch, n, n)
        offsets = math.sqrt(self.spread(n)) * chol.movedim(-1, 0)  # (n, *B, n): columns of L
        mean = mean.expand(*batch, n).unsqueeze(0).expand(n, *batch, n)
        parts = [mean + offsets, mean - offsets]
        if self.include_center:
            parts.insert(0, mean[:1])
        return torch.cat(parts, dim=0)


class MerweScaledSigmaPoints(SigmaPointStrategy):
    """Van der Merwe's scaled sigma points (``lambda = alpha^2 (n + kappa) - n``)."""

    @entry_point(alpha=Real(positive=True), beta=Real(), kappa=Real())
    def __init__(self, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0):
        self.alpha = as_float(alpha, "alpha", positive=True)
        self.beta = as_float(beta, "beta")
        self.kappa = as_float(kappa, "kappa")

    def _lambda(self, n: int) -> float:
        return self.alpha**2 * (n + self.kappa) - n

    def spread(self, n: int) -> float:
        c = n + self._lambda(n)
        if not c > 0:
            raise ValueError(f"alpha, kappa: n + lambda = alpha^2 (n + kappa) = {c:g} must be positive for "
                             f"state dimension n = {n} (alpha={self.alpha:g}, kappa={self.kappa:g})")
        return c

    def weights(self, n, dtype, device):
        c = self.spread(n)
        lam = c - n
        wm = torch.full((2 * n + 1,), 0.5 / c, dtype=dtype, device=device)
        wc = wm.clone()
        wm[:1].fill_(lam / c)  # (fill_ with a Python number: no host-to-device copy on a GPU)
        wc[:1].fill_(lam / c + (1 - self.alpha**2 + self.beta))
        return wm, wc


class JulierSigmaPoints(SigmaPointStrategy):
    """Julier's original sigma points with weight ``kappa / (n + kappa)`` at the centre."""

    @entry_point(kappa=Real())
    def __init__(self, kappa: float = 0.0):
        self.kappa = as_float(kappa, "kappa")

    def spread(self, n: int) -> float:
        if not n + self.kappa > 0:
            raise ValueError(f"kappa: n + kappa = {n + self.kappa:g} must be positive for state dimension n = {n}")
        return n + self.kappa

    def weights(self, n, dtype, device):
        c = self.spread(n)
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


@kernels.joins("nonlinear_gaussian")
class UnscentedKalmanFilter(Filter):
    r"""Unscented Kalman filter.

    With ``joseph`` (the default in float32 and below) the covariance update is the sigma-point
    Joseph form

    .. math::
        P^+ = \textstyle\sum_s W^c_s\,(\mathcal X_s - x^- - K(\mathcal Z_s - \hat z))(\cdot)^\top + K R K^\top,

    algebraically ``P^- - K S K^T`` but a sum of PSD terms whenever the covariance weights are
    non-negative (the default points, Julier's with ``kappa >= 0``, cubature), so the posterior
    stays symmetric PSD also in float32 with an accurate sensor (``P^- - K S K^T`` cancels there).

    Args:
        motion: any :class:`~torchmm.models.MotionModel`.
        measurement: any :class:`~torchmm.models.MeasurementModel`.
        sigma_points: a :class:`SigmaPointStrategy`; default :class:`MerweScaledSigmaPoints`
            (checked for the model's state dimension here).
        joseph: ``True`` / ``False`` forces the form; ``None`` (default): Joseph in float32 and
            below, ``P - K S K^T`` in float64.

    Shapes:
        as :class:`~torchmm.filters.ExtendedKalmanFilter` (``extras["singular"]`` and
        ``extras["failed"]`` likewise).
    """

    smoother = "unscented"  # (torchmm.smooth's backward pass: Filter.smoother)

    @entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel),
                 sigma_points=Of(SigmaPointStrategy, optional=True), joseph=Flag(optional=True))
    def __init__(self, motion: MotionModel, measurement: MeasurementModel,
                 sigma_points: SigmaPointStrategy | None = None, *, joseph: bool | None = None):
        super().__init__()
        self.joseph = check_joseph(joseph)
        check_model_pair(motion, measurement)
        if sigma_points is not None and not isinstance(sigma_points, SigmaPointStrategy):
            raise TypeError(f"sigma_points: expected a SigmaPointStrategy, got {type(sigma_points).__name__}")
        self.motion = motion
        self.measurement = measurement
        self.sigma_points = sigma_points or MerweScaledSigmaPoints()
        try:
            self.sigma_points.check(motion.state_dim)
        except ValueError as err:
            raise ValueError(f"sigma_points: {err}") from None

    def nonlinear_gaussian(self):
        """This filter's description for the nonlinear-Gaussian kernel (:mod:`torchmm.kernels.nonlinear`),
        or the reason it has none (a subclass with its own steps, a sigma-point rule with its own
        ``points``)."""
        if not kernels.joined(self, "nonlinear_gaussian"):
            return f"{type(self).__name__} overrides the unscented Kalman filter's steps"
        if type(self.sigma_points).points is not SigmaPointStrategy.points:
            return f"the sigma-point rule {type(self.sigma_points).__name__} places its own points"
        return NonlinearGaussian(self.motion, self.measurement, "unscented", self.sigma_points, self.joseph)

    def predict(self, belief: GaussianBelief, *, u: Tensor | None = None,
                motion: MotionModel | None = None) -> GaussianBelief:
        if motion is not None:
            return self.with_motion(motion).predict(belief, u=u)
        n = belief.state_dim
        batch = gaussian_batch(belief, self.state_dim)
        wm, wc = self.sigma_points.weights(n, belief.dtype, belief.device)
        points = self.sigma_points.points(belief.mean, belief.cov)
        propagated = self.motion(points, u=None if u is None else u.unsqueeze(0))
        propagated = check_output(self.motion, propagated, points, "motion")
        mean, dev = _weighted_moments(propagated, wm)
        shape = (-1,) + (1,) * (dev.dim() - 1)
        cov = torch.einsum("s...i,s...j->...ij", wc.reshape(shape) * dev, dev)
        Q = self.motion.noise_cov(belief.mean)
        cov = cov + check_output(self.motion, Q, belief.mean, "motion", "noise_cov", batch=batch)
        return GaussianBelief(mean, symmetrize(cov))

    def check_parameter_batch(self, batch: torch.Size) -> None:
        """The models' parameter batches against the start belief's ``batch``
        (:func:`~torchmm.filters.base.check_model_batches`)."""
        check_model_batches(self, batch)

    def update(self, belief: GaussianBelief, z: Tensor, *, sensor: MeasurementModel | None = None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z)
        n = belief.state_dim
        batch = gaussian_batch(belief, self.state_dim)
        z = check_measurement(z, self.meas_dim, batch, belief.mean)
        wm, wc = self.sigma_points.weights(n, belief.dtype, belief.device)
        points = self.sigma_points.points(belief.mean, belief.cov)
        predicted = check_output(self.measurement, self.measurement(points), points, "measurement")
        z_pred, z_dev = _weighted_moments(predicted, wm)
        x_dev = points - belief.mean
        shape = (-1,) + (1,) * (z_dev.dim() - 1)
        wc = wc.reshape(shape)
        weighted = wc * z_dev
        R = self.measurement.noise_cov(belief.mean)
        R = check_output(self.measurement, R, belief.mean, "measurement", "noise_cov", batch=batch)
        innovation_cov = torch.einsum("s...i,s...j->...ij", weighted, z_dev) + R
        cross_cov = torch.einsum("s...i,s...j->...ij", x_dev, weighted)
        innovation = z - z_pred

        def joseph(gain: Tensor) -> Tensor:
            # sum_s W_s (dx_s - K dz_s)(dx_s - K dz_s)^T + K R K^T  (= P - K S K^T)
            err = x_dev - (gain @ z_dev.unsqueeze(-1)).squeeze(-1)
            spread = torch.einsum("s...i,s...j->...ij", wc * err, err)
            return spread + gain @ R @ gain.mT

        psd_form = use_joseph(self.joseph, belief.dtype)
        observed = torch.isfinite(z)  # missing = non-finite *data*; a non-finite prediction fails the run
        mean, cov, log_likelihood, singular = condition(
            belief.mean, belief.cov, innovation, symmetrize(innovation_cov), cross_cov,
            posterior_cov=joseph if psd_form else None, with_flag=True, observed=observed,
        )
        if psd_form:  # no datum at all: exactly the prior (the sigma-point sum reproduces P to rounding)
            cov = torch.where(observed.any(-1)[..., None, None], cov, belief.cov)
        return StepOutput(GaussianBelief(mean, cov), belief, log_likelihood, innovation, innovation_cov,
                          {"singular": singular, "failed": flag_failed(log_likelihood)})

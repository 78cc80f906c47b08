r"""Kalman and extended Kalman filters.

.. math::
    x^- = f(x),\quad P^- = F P F^\top + Q \qquad (F = \partial f/\partial x)

    \nu = z - h(x^-),\quad S = H P^- H^\top + R,\quad C = P^- H^\top \qquad (H = \partial h/\partial x)

followed by :func:`torchmm.linalg.condition`. For linear models ``F`` and ``H`` are the
model matrices and this is the Kalman filter; otherwise Jacobians come from autograd.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, symmetrize
from torchmm.contract import Flag, Of, entry_point
from torchmm.filters.base import Filter, StepOutput, check_model_batches
from torchmm.kernels.linear import LinearGaussian
from torchmm.kernels.nonlinear import NonlinearGaussian
from torchmm.linalg import cholesky, condition, flag_failed, half_log_det, solve_lower, sum_last
from torchmm.models.base import MeasurementModel, MotionModel, check_model_pair, check_output
from torchmm.models.linear import LinearMeasurement, LinearMotion, plain_linear
from torchmm.validation import broadcast_shape, check_measurement, gaussian_batch

__all__ = ["ExtendedKalmanFilter", "KalmanFilter"]


@kernels.joins("nonlinear_gaussian", ("step", "predict", "update", "_transition_matrix", "_measurement_matrix"))
class ExtendedKalmanFilter(Filter):
    """Extended Kalman filter over any differentiable motion and measurement models.

    Args:
        motion: a :class:`~torchmm.models.MotionModel` (its ``jacobian`` defaults to autograd).
        measurement: a :class:`~torchmm.models.MeasurementModel`.
        joseph: update the covariance in Joseph form (recommended in float32).

    Shapes:
        belief: :class:`GaussianBelief` with batch ``(*B,)``; ``z``: ``(*B, m)`` (non-finite
        components - NaN, ``+-inf`` - are missing; ``z``'s batch must broadcast to ``*B``);
        ``u``: ``(*B, k)``. Model parameter batches broadcast with ``*B`` (mode banks: ``*B``
        ends with the mode axis). ``extras["singular"]`` ``(*B,)`` bool: the innovation
        covariance was not numerically positive definite and was regularised (see
        :func:`~torchmm.linalg.cholesky`); ``extras["failed"]`` ``(*B,)`` bool: a datum was present but
        the update was not finite (a NaN prediction or innovation covariance, e.g. a model whose
        parameters went NaN): the log-likelihood is NaN there, where missing data would give 0
        (:func:`~torchmm.linalg.flag_failed`, docs/robustness.md).

    Examples:
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> kf = KalmanFilter(ConstantVelocity(1, dt=1.0, q=1.0), PositionMeasurement(2, [0], 100.0))
        >>> prior = GaussianBelief(torch.zeros(5, 2), 10 * torch.eye(2))
        >>> out = kf.step(prior, torch.randn(5, 1))
        >>> out.belief.mean.shape, out.log_likelihood.shape
        (torch.Size([5, 2]), torch.Size([5]))
    """

    smoother = "rts"  # (torchmm.smooth's backward pass: Filter.smoother)

    @entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel), joseph=Flag())
    def __init__(self, motion: MotionModel, measurement: MeasurementModel, *, joseph: bool = False):
        super().__init__()
        check_model_pair(motion, measurement)
        self.motion = motion
        self.measurement = measurement
        self.joseph = joseph

    def _transition_matrix(self, mean: Tensor, u: Tensor | None) -> Tensor:
        return self.motion.jacobian(mean, u=u)

    def _measurement_matrix(self, mean: Tensor) -> Tensor:
        return self.measurement.jacobian(mean)

    def predict(self, belief: GaussianBelief, *, u: Tensor | None = None,
                motion: MotionModel | None = None) -> GaussianBelief:
        if motion is not None:
            return self.with_motion(motion).predict(belief, u=u)
        batch = gaussian_batch(belief, self.state_dim)
        F = self._transition_matrix(belief.mean, u)
        mean = self._checked(self.motion, self.motion(belief.mean, u=u), belief.mean, batch)  # x- = f(x)
        F = self._checked(self.motion, F, belief.mean, batch, "jacobian")
        Q = self._checked(self.motion, self.motion.noise_cov(belief.mean), belief.mean, batch, "noise_cov")
        # P- = F P F' + Q (symmetric up to rounding; the update symmetrises its output)
        cov = F @ belief.cov @ F.mT + Q
        return GaussianBelief(mean, cov)

    def _checked(self, model, out: Tensor, mean: Tensor, batch: torch.Size, kind: str = "forward") -> Tensor:
        """A model's output against the belief (:func:`~torchmm.models.base.check_output`, shapes only)."""
        return check_output(model, out, mean, "motion" if model is self.motion else "measurement", kind,
                            batch=batch)

    def _sensor_terms(self, belief: GaussianBelief, batch: torch.Size) -> tuple[Tensor, Tensor, Tensor]:
        """``h(x-)``, ``H`` and ``R`` at the prior mean, checked (evaluated in the order ``H``, ``R``,
        ``h``)."""
        H = self._measurement_matrix(belief.mean)
        R = self.measurement.noise_cov(belief.mean)
        hx = self._checked(self.measurement, self.measurement(belief.mean), belief.mean, batch)
        H = self._checked(self.measurement, H, belief.mean, batch, "jacobian")
        return hx, H, self._checked(self.measurement, R, belief.mean, batch, "noise_cov")

    def check_parameter_batch(self, batch: torch.Size) -> None:
        """The models' parameter batches against the start belief's ``batch``
        (:func:`~torchmm.filters.base.check_model_batches`)."""
        check_model_batches(self, batch)

    def update(self, belief: GaussianBelief, z: Tensor, *, sensor: MeasurementModel | None = None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z)
        batch = gaussian_batch(belief, self.state_dim)
        z = check_measurement(z, self.meas_dim, batch, belief.mean)
        hx, H, R = self._sensor_terms(belief, batch)
        innovation = z - hx  # nu = z - h(x-)
        cross_cov = belief.cov @ H.mT  # C = P- H'
        # S = H P- H' + R, written (P- H')' H' so that an unbatched H folds into one matmul
        innovation_cov = (cross_cov.mT @ H.mT if H.dim() == 2 else H @ cross_cov) + R
        observed = torch.isfinite(z)  # missing = non-finite *data*; a non-finite prediction fails the run
        mean, cov, log_likelihood, singular = condition(
            belief.mean, belief.cov, innovation, innovation_cov, cross_cov,
            joseph=(H, R) if self.joseph else None, with_flag=True, observed=observed,
        )
        return StepOutput(GaussianBelief(mean, cov), belief, log_likelihood, innovation, innovation_cov,
                          {"singular": singular, "failed": flag_failed(log_likelihood)})

    def nonlinear_gaussian(self):
        """This filter's description for the nonlinear-Gaussian kernel (:mod:`torchmm.kernels.nonlinear`),
        or the reason it has none (a subclass with its own steps or linearisation, the Joseph form)."""
        if not kernels.joined(self, "nonlinear_gaussian"):
            return f"{type(self).__name__} overrides the extended Kalman filter's steps"
        if self.joseph:
            return "the Joseph form"
        return NonlinearGaussian(self.motion, self.measurement, "extended")

    def update_each(self, belief: GaussianBelief, zs: Tensor) -> StepOutput:
        """:meth:`Filter.update_each` with the gain shared: the linearisation, innovation covariance,
        its factor and the posterior covariance once per prior, one triangular solve per measurement.
        Equal to :meth:`update` of each measurement to rounding (a subclass with its own update, or the
        Joseph form, takes the default). ``innovation_cov`` is the one shared ``S``, ``(*B, m, m)``
        (it broadcasts against ``innovation (D, *B, m)``)."""
        if type(self).update is not ExtendedKalmanFilter.update or self.joseph:
            return super().update_each(belief, zs)
        batch = gaussian_batch(belief, self.state_dim)
        zs = check_measurement(zs, self.meas_dim, torch.Size([zs.shape[0] if zs.dim() else 0, *batch]), belief.mean,
                               "zs")
        hx, H, R = self._sensor_terms(belief, batch)
        present = torch.isfinite(zs).all(-1)  # (D, *B): a whole measurement
        innovation = torch.where(present.unsqueeze(-1), zs - hx, torch.nan)
        cross_cov = belief.cov @ H.mT
        innovation_cov = (cross_cov.mT @ H.mT if H.dim() == 2 else H @ cross_cov) + R
        L, singular = cholesky(innovation_cov, with_flag=True)
        V = solve_lower(L, cross_cov.mT)  # (*B, m, n): L^-1 C^T, once
        # (D, *B, m); an absent row's innovation 0 (its result is the prior), a NaN prediction's stays NaN
        w = solve_lower(L, torch.where(present.unsqueeze(-1), innovation, 0.0).unsqueeze(-1)).squeeze(-1)
        mean = torch.where(present.unsqueeze(-1), belief.mean + (V.mT @ w.unsqueeze(-1)).squeeze(-1), belief.mean)
        cov = torch.where(present[..., None, None], symmetrize(belief.cov - V.mT @ V), belief.cov)
        m = zs.shape[-1]
        log_likelihood = -0.5 * (sum_last(w.square()) + m * math.log(2 * math.pi)) - half_log_det(L)
        log_likelihood = torch.where(present, log_likelihood, 0.0)
        return StepOutput(GaussianBelief(mean, cov), belief, log_likelihood, innovation, innovation_cov,
                          {"singular": singular.expand(log_likelihood.shape), "failed": flag_failed(log_likelihood)})


@kernels.joins("linear_gaussian")
class KalmanFilter(ExtendedKalmanFilter):
    """Kalman filter for :class:`LinearMotion` / :class:`LinearMeasurement` models (and banks).

    Same interface and shapes as :class:`ExtendedKalmanFilter`; uses the model matrices directly.
    A list of Kalman filters with unbatched models can be fused into one vectorised bank with
    :meth:`stack`.
    """

    @entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel), joseph=Flag())
    def __init__(self, motion: LinearMotion, measurement: LinearMeasurement, *, joseph: bool = False):
        if not isinstance(motion, LinearMotion):
            raise ValueError(
                f"motion: KalmanFilter needs a LinearMotion, got {type(motion).__name__} "
                "(use ExtendedKalmanFilter or UnscentedKalmanFilter for nonlinear models)"
            )
        if not isinstance(measurement, LinearMeasurement):
            raise ValueError(
                f"measurement: KalmanFilter needs a LinearMeasurement, got {type(measurement).__name__}"
            )
        super().__init__(motion, measurement, joseph=joseph)

    def _with_module(self, slot, module, name):
        expected = LinearMotion if slot == "motion" else LinearMeasurement
        if isinstance(module, torch.nn.Module) and not isinstance(module, expected):
            raise ValueError(f"{name}: KalmanFilter needs a {expected.__name__}, got {type(module).__name__} "
                             "(use ExtendedKalmanFilter or UnscentedKalmanFilter for nonlinear models)")
        return super()._with_module(slot, module, name)

    @property
    def param_batch_shape(self) -> torch.Size:
        return broadcast_shape(self.motion.param_batch_shape, self.measurement.param_batch_shape)

    def _transition_matrix(self, mean: Tensor, u: Tensor | None) -> Tensor:
        return self.motion.F

    def _measurement_matrix(self, mean: Tensor) -> Tensor:
        return self.measurement.H

    def linear_gaussian(self):
        """This filter's matrices for the linear-Gaussian kernel (:mod:`torchmm.kernels.linear`), or the
        reason it has none (a model that overrides its own ``forward``, ``noise_cov`` or ``jacobian``,
        the Joseph form); a motion's input matrix is its ``G`` (the kernels that take controls use it)."""
        if not kernels.joined(self, "linear_gaussian"):
            return f"{type(self).__name__} overrides the Kalman filter's steps"
        if self.joseph:
            return "the Joseph form"
        motion, sensor = self.motion, self.measurement
        if not (isinstance(motion, LinearMotion) and plain_linear(motion)):
            return "the motion is not a LinearMotion (its own forward and noise)"
        if not (isinstance(sensor, LinearMeasurement) and plain_linear(sensor)):
            return "the measurement is not a LinearMeasurement (its own forward and noise)"
        return LinearGaussian(motion.F, motion.offset, motion.Q, sensor.H, sensor.R, G=motion.input_matrix)

    @classmethod
    def stack(cls, filters: Sequence[KalmanFilter]) -> KalmanFilter:
        """One Kalman filter whose models are banks, mode ``j`` being ``filters[j]``."""
        filters = list(filters)
        if len({f.joseph for f in filters}) > 1:
            raise ValueError("filters: cannot stack filters with different joseph settings")
        motion = LinearMotion.stack([f.motion for f in filters])
        measurements = [f.measurement for f in filters]
        if all(m is measurements[0] for m in measurements):
            measurement = measurements[0]
        else:
            measurement = LinearMeasurement.stack(measurements)
        return cls(motion, measurement, joseph=filters[0].joseph)

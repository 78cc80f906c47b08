r"""VBAKF-PR (Huang, Zhang, Wu, Li, Chambers 2018): variational adaptive Kalman filtering with
inaccurate process and measurement noise covariances (docs/baselines.md §6).

The belief carries the inverse-Wishart posterior of ``R`` (:class:`~torchmm.beliefs.AdaptiveGaussianBelief`);
the prediction covariance ``P_{k|k-1}`` is estimated per step from the nominal ``Q~`` (``tau``) and
``R`` is forgotten with ``rho`` between steps.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.beliefs import AdaptiveGaussianBelief, GaussianBelief
from torchmm.filters.base import Filter, StepOutput
from torchmm.filters.vb_common import check_iterations, check_linear_models, fill_missing, keep_prior_where_missing
from torchmm.linalg import check_joseph, condition, symmetrize, use_joseph
from torchmm.models.base import MeasurementModel, MotionModel
from torchmm.models.linear import LinearMeasurement, LinearMotion, matvec
from torchmm.validation import (
    as_float,
    as_tensor,
    check_covariance,
    check_filter_dtype,
    check_measurement,
    check_shape,
    gaussian_batch,
)
from torchmm.contract import BeliefArg, Cov, Flag, Int, Of, Real, entry_point

__all__ = ["VBAKFPR"]


class VBAKFPR(Filter):
    r"""VBAKF-PR (Huang et al., IEEE TAC 63(2), 2018): IW priors on ``P_{k|k-1}`` and ``R_k``.

    Exactly docs/baselines.md §6 (the authors' ``aprivbkf.m``):

    .. math::
        x^- = F\hat x,\ \tilde P = F P F^\top + \tilde Q,\ \hat t = n + \tau + 1,\ \hat T = \tau\tilde P,\
        \hat u^- = \rho(\hat u - m - 1) + m + 1,\ \hat U^- = \rho\hat U

        \text{repeat } N:\ A = P^{(i)} + (x^{(i)} - x^-)(\cdot)^\top,\
        \hat P = (\hat T + A)/(\hat t + 1 - n - 1),\
        B = (z - Hx^{(i)})(\cdot)^\top + HP^{(i)}H^\top,\ \hat R = (\hat U^- + B)/(\hat u^- + 1 - m - 1)

        K = \hat PH^\top(H\hat PH^\top + \hat R)^{-1},\ x^{(i+1)} = x^- + K(z - Hx^-),\ 
        P^{(i+1)} = \hat P - KH\hat P

    Output ``u = û^- + 1``, ``U = Û^- + B`` (from the last iteration's ``B``, as in the code).
    ``log_likelihood`` is the plug-in ``log N(z; Hx^-, H P^ H^T + R^)`` of the last iteration.

    Args:
        motion: linear motion with the nominal ``Q~``.
        measurement: linear measurement (its ``R`` is only a default for :meth:`initial_belief`).
        tau: ``tau_P`` (default 3); rho: forgetting factor (default ``1 - exp(-4)``);
        iterations: ``N`` (default 10); tau_r: ``tau_R`` for :meth:`initial_belief` (default 3).
        joseph: Joseph-form (PSD-preserving) inner updates; ``None`` (default): in float32 and
            below only (:func:`~torchmm.linalg.use_joseph`).

    Shapes:
        belief :class:`AdaptiveGaussianBelief` batch ``(*B,)``; ``z (*B, m)``; extras
        ``predicted_cov (*B, n, n)`` (``P^``), ``noise_cov (*B, m, m)`` (``R^``).

    Examples:
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> f = VBAKFPR(ConstantVelocity(2), PositionMeasurement(4, [0, 2], 100.0))
        >>> b0 = f.initial_belief(GaussianBelief(torch.zeros(6, 4), torch.eye(4)))
        >>> out = f.step(b0, torch.randn(6, 2))
        >>> out.belief.noise_cov().shape
        torch.Size([6, 2, 2])
    """

    @entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel), tau=Real(positive=True),
                 rho=Real(positive=True, maximum=1.0), iterations=Int(1), tau_r=Real(positive=True),
                 joseph=Flag(optional=True))
    def __init__(self, motion, measurement, tau: float = 3.0, rho: float = 1 - math.exp(-4),
                 iterations: int = 10, tau_r: float = 3.0, joseph: bool | None = None):
        super().__init__()
        check_linear_models(motion, measurement)
        self.motion, self.measurement = motion, measurement
        self.tau = as_float(tau, "tau", positive=True)
        self.tau_r = as_float(tau_r, "tau_r", positive=True)
        self.rho = as_float(rho, "rho", positive=True, maximum=1.0)
        self.iterations = check_iterations(iterations)
        self.joseph = check_joseph(joseph)

    def _with_module(self, slot, module, name):
        expected = LinearMotion if slot == "motion" else LinearMeasurement
        if isinstance(module, torch.nn.Module) and not isinstance(module, expected):
            raise ValueError(f"{name}: VBAKFPR needs a {expected.__name__}, got {type(module).__name__}")
        return super()._with_module(slot, module, name)

    @entry_point(belief=BeliefArg(), R0=Cov(optional=True, check=False))
    def initial_belief(self, belief: GaussianBelief, R0: Tensor | None = None) -> AdaptiveGaussianBelief:
        """``u_0 = m + 1 + tau_R``, ``U_0 = tau_R R~_0`` (so ``E[R_0] = R~_0``; default the model's R).

        Shapes:
            belief batch ``(*B,)``; R0 ``(m, m)`` or ``(*B, m, m)`` -> batch ``(*B,)``
        """
        belief.validate("belief")
        check_filter_dtype(self, belief, "belief")
        m = self.measurement.meas_dim
        if R0 is None:
            R0 = self.measurement.R
        else:
            R0 = as_tensor(R0, "R0", dtype=belief.dtype, device=belief.device)
            check_shape(R0, "R0", (m, m))
        check_covariance(R0, "R0", definite=True)
        batch = gaussian_batch(belief, self.motion.state_dim)
        dof = torch.full(batch, m + 1 + self.tau_r, dtype=belief.dtype, device=belief.device)
        return AdaptiveGaussianBelief(belief.mean, belief.cov, dof, (self.tau_r * R0).expand(*batch, m, m))

    def predict(self, belief: AdaptiveGaussianBelief, *, u: Tensor | None = None,
                motion=None) -> AdaptiveGaussianBelief:
        if motion is not None:
            return self.with_motion(motion).predict(belief, u=u)
        _check_adaptive(belief)
        gaussian_batch(belief, self.motion.state_dim)
        F = self.motion.F
        m = belief.r_scale.shape[-1]
        mean = self.motion(belief.mean, u=u)
        cov = F @ belief.cov @ F.mT + self.motion.Q
        dof = self.rho * (belief.r_dof - m - 1) + m + 1
        return AdaptiveGaussianBelief(mean, cov, dof, self.rho * belief.r_scale)

    def informative(self, z: Tensor) -> Tensor:
        """``(*B,)`` bool: where every component is finite (a partly missing datum is skipped, as in
        :meth:`torchmm.filters.vb_common.LinearVBFilter.informative`)."""
        return torch.isfinite(z).all(-1)

    def update(self, belief: AdaptiveGaussianBelief, z: Tensor, *, sensor=None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z)
        _check_adaptive(belief)
        z = check_measurement(z, self.measurement.meas_dim, gaussian_batch(belief, self.motion.state_dim),
                              belief.mean)
        H = self.measurement.H
        n, m = belief.mean.shape[-1], z.shape[-1]
        x_pred, P_nom = belief.mean, belief.cov
        z_pred = matvec(H, x_pred)
        present = torch.isfinite(z)  # (the record's innovation is NaN where a component is missing)
        missing, z = fill_missing(z, z_pred)
        observed = ~missing.unsqueeze(-1)  # from the data: a NaN prediction is a failure, not missing
        innovation = z - z_pred
        T_prior, t_q = self.tau * P_nom, n + self.tau + 1 + 1
        u_q = belief.r_dof + 1
        mean, cov = x_pred, P_nom
        singular = torch.zeros(z.shape[:-1], dtype=torch.bool, device=z.device)
        joseph = use_joseph(self.joseph, z.dtype)
        for _ in range(self.iterations):
            dx = mean - x_pred
            T = T_prior + cov + dx.unsqueeze(-1) * dx.unsqueeze(-2)
            rz = z - matvec(H, mean)
            Bm = rz.unsqueeze(-1) * rz.unsqueeze(-2) + H @ cov @ H.mT
            U = belief.r_scale + Bm
            P_hat = symmetrize(T / (t_q - n - 1))
            R_hat = symmetrize(U / (u_q - m - 1)[..., None, None])
            cross = P_hat @ H.mT
            S = H @ cross + R_hat
            mean, cov, loglik, flag = condition(x_pred, P_hat, innovation, S, cross,
                                                joseph=(H, R_hat) if joseph else None, with_flag=True,
                                                observed=observed)
            singular = singular | flag
        keep = missing
        mean, cov, loglik, failed = keep_prior_where_missing(keep, belief.estimate(), mean, cov, loglik)
        dof = torch.where(keep, belief.r_dof, u_q)
        U = torch.where(keep[..., None, None], belief.r_scale, U)
        return StepOutput(
            AdaptiveGaussianBelief(mean, cov, dof, U), belief, loglik, torch.where(present, innovation, math.nan), S,
            extras={"predicted_cov": P_hat, "noise_cov": R_hat, "singular": singular, "failed": failed},
        )


def _check_adaptive(belief) -> None:
    if not isinstance(belief, AdaptiveGaussianBelief):
        raise TypeError(f"belief: VBAKFPR needs an AdaptiveGaussianBelief (from VBAKFPR.initial_belief), got "
                        f"{type(belief).__name__}")

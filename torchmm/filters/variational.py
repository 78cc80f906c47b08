r"""Variational-Bayes filters for heavy-tailed / skewed noise and unknown covariances.

All filters share the :class:`~torchmm.filters.Filter` interface, are batched over any leading
dims (Monte Carlo runs, and modes when used as an IMM bank, see :mod:`torchmm.multimodel.variational`)
and loop only over their fixed-point iterations. The time update is the Kalman prediction with the
nominal process noise of the motion model.

* :class:`StudentTVBFilter` — Student-t measurement noise with one scalar mixing variable
  ``z ~ N(Hx, R/u)``, ``u ~ Ga(nu/2, nu/2)`` (Shen et al. 2015, the mode filter of IMM-VBT;
  docs/baselines.md §4). ``log_likelihood`` is the ELBO of the converged ``q(x) q(u)``.
* :class:`SkewTVBFilter` — STVBF (Nurminen, Ardeshiri, Piché, Gustafsson 2018; docs/baselines.md §5):
  independent skew-t components, coupled ``q(x, u) q(Lambda)``, the truncated Gaussian ``q(x, u)``
  approximated by sequential truncation of the ``u`` coordinates.
* :class:`SkewTIWVBFilter` — the per-model filter of GIMMAF (paper 004, eqs. (9)-(35)): skew-t noise
  (14)-(16) and an inverse-Wishart prior on ``P_{k|k-1}`` (12), mean-field
  ``q(x) q(P) q(u) q(Lambda)`` (18); ``log_likelihood`` is the ELBO (39), the mode likelihood (38).
* :class:`VBAKFPR` — Huang, Zhang, Wu, Li, Chambers (IEEE TAC 2018): inverse-Wishart priors on
  ``P_{k|k-1}`` and ``R_k`` (docs/baselines.md §6, pinned down against the authors' MATLAB). Its
  belief, :class:`AdaptiveGaussianBelief`, carries the ``R`` posterior ``IW(u, U)`` between steps.

Inverse-Wishart convention (shared by VBAKF-PR and GIMMAF). ``IW(t, T)`` is the density
``prop. |P|^{-t/2} exp(-tr(T P^{-1})/2)``, i.e. the standard inverse Wishart with
``t - n - 1`` degrees of freedom. Then ``E[P^{-1}] = (t - n - 1) T^{-1}`` exactly, so the
point estimate ``T / (t - n - 1)`` used in the gains (Huang's code) *is* the variational update,
the prior ``t = n + 1 + tau, T = tau P`` has ``E[P^{-1}]^{-1} = P`` and the fixed-point iterations
are a coordinate ascent of one ELBO (tested: it never decreases). When ``tau <= n - 1`` that
prior is improper; its normaliser ``log Gamma_n(tau/2)`` is then left out of the ELBO, and when
``tau + 1 <= n - 1`` also the posterior's ``psi_n``/``log Gamma_n`` terms (they depend on ``tau`` and
``n`` only: the same for every mode, run and iteration, so mode probabilities and the ELBO's
monotonicity are unaffected).

Missing data: a measurement with any NaN component is skipped for that run (posterior = prior,
``log_likelihood = 0``).
"""

from __future__ import annotations

import logging
import math

import torch
from torch import Tensor

from torchmm.contract import Choice, Finite, Flag, Int, Of, Real, entry_point
from torchmm.beliefs import GaussianBelief
from torchmm.beliefs.ops import symmetrize
from torchmm.distributions import truncated_normal_entropy, truncated_normal_moments
from torchmm.filters.base import Filter, StepOutput
from torchmm.filters.kalman import KalmanFilter
from torchmm.linalg import check_joseph, cholesky, cholesky_solve, condition, flag_failed, use_joseph
from torchmm.models.base import MeasurementModel, MotionModel
from torchmm.models.linear import LinearMeasurement, LinearMotion, matvec
from torchmm.validation import (
    as_float,
    as_int,
    as_tensor,
    broadcast_shape,
    check_covariance,
    check_measurement,
    gaussian_batch,
)

__all__ = [
    "VBAKFPR",
    "AdaptiveGaussianBelief",
    "SkewTIWVBFilter",
    "SkewTVBFilter",
    "StudentTVBFilter",
    "gamma_kl",
    "wishart_kl",
]

log = logging.getLogger("torchmm")
_LOG_2PI = math.log(2 * math.pi)


# -- shared helpers ----------------------------------------------------------------------------------
def gamma_kl(a: Tensor, b: Tensor, a0: Tensor, b0: Tensor) -> Tensor:
    r"""``KL(Ga(a, b) || Ga(a0, b0))`` (shape, rate).

    ``(a - a0) psi(a) - lnGamma(a) + lnGamma(a0) + a0 (ln b - ln b0) + a (b0 - b) / b``.

    Shapes:
        all broadcastable ``(*B,)`` -> ``(*B,)``
    """
    return (
        (a - a0) * torch.digamma(a) - torch.lgamma(a) + torch.lgamma(a0)
        + a0 * (torch.log(b) - torch.log(b0)) + a * (b0 - b) / b
    )


def _mvdigamma(x: Tensor, n: int) -> Tensor:
    offsets = torch.arange(n, dtype=x.dtype, device=x.device) * 0.5
    return torch.digamma(x.unsqueeze(-1) - offsets).sum(-1)


def wishart_kl(dof_q: float, scale_q: Tensor, dof_p: float, scale_p: Tensor) -> Tensor:
    r"""``KL(IW(dof_q, Psi_q) || IW(dof_p, Psi_p))`` of standard inverse Wisharts (= the KL of the
    Wisharts of ``P^{-1}`` with scales ``Psi^{-1}``).

    .. math::
        \tfrac{\nu_q - \nu_p}{2}\psi_n(\nu_q/2) + \ln\Gamma_n(\nu_p/2) - \ln\Gamma_n(\nu_q/2)
        + \tfrac{\nu_p}{2}(\ln|\Psi_q| - \ln|\Psi_p|) + \tfrac{\nu_q}{2}(\mathrm{tr}(\Psi_p\Psi_q^{-1}) - n)

    Terms that depend on the degrees of freedom only are omitted where they are infinite: ``ln
    Gamma_n(dof_p/2)`` when ``dof_p <= n - 1``, and ``psi_n(dof_q/2)``, ``ln Gamma_n(dof_q/2)`` when
    ``dof_q <= n - 1`` (improper inverse Wisharts; see the module doc).

    Shapes:
        scale_q, scale_p: ``(*B, n, n)`` -> ``(*B,)``
    """
    n = scale_q.shape[-1]
    Lq, Lp = cholesky(scale_q), cholesky(scale_p)
    logdet_q = 2 * Lq.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    logdet_p = 2 * Lp.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    trace = torch.cholesky_solve(scale_p, Lq).diagonal(dim1=-2, dim2=-1).sum(-1)
    kl = 0.5 * dof_p * (logdet_q - logdet_p) + 0.5 * dof_q * (trace - n)
    if dof_q > n - 1:
        dq = torch.full((), 0.5 * dof_q, dtype=scale_q.dtype, device=scale_q.device)  # (no host-to-device copy)
        kl = kl + 0.5 * (dof_q - dof_p) * _mvdigamma(dq, n) - _mvlgamma(0.5 * dof_q, n)
    if dof_p > n - 1:
        kl = kl + _mvlgamma(0.5 * dof_p, n)
    return kl


def _mvlgamma(x: float, n: int) -> float:
    """``ln Gamma_n(x)`` of a Python number (``torch.mvlgamma`` without a tensor)."""
    return 0.25 * n * (n - 1) * math.log(math.pi) + sum(math.lgamma(x - 0.5 * i) for i in range(n))


def _gaussian_entropy(cov: Tensor) -> Tensor:
    n = cov.shape[-1]
    L = cholesky(cov)
    return 0.5 * n * (_LOG_2PI + 1.0) + L.diagonal(dim1=-2, dim2=-1).log().sum(-1)


def _diag_param(value, name: str, m: int, like: Tensor) -> Tensor:
    """A per-component parameter: a number, ``(*P, m)`` or a diagonal ``(*P, m, m)``."""
    value = as_tensor(value, name, dtype=like.dtype, device=like.device)
    if value.dim() >= 2 and value.shape[-2:] == (m, m):
        off = value - torch.diag_embed(value.diagonal(dim1=-2, dim2=-1))
        if m > 1 and bool((off.detach().abs() > 0).any()):
            raise ValueError(f"{name}: must be diagonal (independent skew-t components)")
        value = value.diagonal(dim1=-2, dim2=-1)
    if value.dim() == 0:
        value = value.expand(m)
    if value.shape[-1] != m:
        raise ValueError(f"{name}: expected a number, (*P, {m}) or ({m}, {m}); got {tuple(value.shape)}")
    return value


def _check_positive(value: Tensor, name: str) -> None:
    if bool((value.detach() <= 0).any()):
        raise ValueError(f"{name}: must be positive")


def check_linear_models(motion, measurement) -> None:
    if not isinstance(motion, LinearMotion):
        raise ValueError(f"motion: expected a LinearMotion, got {type(motion).__name__}")
    if not isinstance(measurement, LinearMeasurement):
        raise ValueError(f"measurement: expected a LinearMeasurement, got {type(measurement).__name__}")


def _rederive_scale(filter) -> None:
    """A skew-t filter given another sensor (``with_sensor``): its per-component scale ``r`` from the
    new ``R``; skewness and degrees of freedom are per component, so ``m`` must not change."""
    R = filter.measurement.R
    m = R.shape[-1]
    if m != filter.r.shape[-1]:
        raise ValueError(f"sensor: {type(filter).__name__}'s skewness and df have {filter.r.shape[-1]} components, "
                         f"the sensor {m}")
    r = _diag_param(R, "sensor.R", m, R)
    _check_positive(r, "sensor.R")
    filter._buffers["r"] = r


def check_iterations(value) -> int:
    return as_int(value, "iterations", minimum=1)


def fill_missing(z: Tensor, z_pred: Tensor) -> tuple[Tensor, Tensor]:
    """Runs whose measurement has a non-finite component (NaN = missing, or +-inf) are skipped:
    ``(mask (*B,), z with the prediction filled in)``."""
    finite = torch.isfinite(z)
    missing = ~finite.all(-1)
    z = torch.where(finite, z, z_pred)
    return missing, z


def keep_prior_where_missing(missing: Tensor, prior: GaussianBelief, mean: Tensor, cov: Tensor, loglik: Tensor):
    """The prior and log-likelihood 0 where the datum is skipped; where it is present and the update
    is not finite (a NaN prediction: not missing data) the log-likelihood is NaN and the run is
    flagged: ``(mean, cov, loglik, failed)`` (:func:`~torchmm.linalg.flag_failed`)."""
    mean = torch.where(missing.unsqueeze(-1), prior.mean, mean)
    cov = torch.where(missing[..., None, None], prior.cov, cov)
    loglik = torch.where(missing, torch.zeros_like(loglik), loglik)
    return mean, cov, loglik, flag_failed(loglik)


class _LinearVBFilter(Filter):
    """Shared set-up: a linear motion (nominal ``Q``) and a linear measurement (scale ``R``)."""

    def __init__(self, motion: LinearMotion, measurement: LinearMeasurement, iterations: int,
                 joseph: bool | None = None):
        super().__init__()
        check_linear_models(motion, measurement)
        self.kalman = KalmanFilter(motion, measurement)
        self.motion, self.measurement = motion, measurement
        self.iterations = check_iterations(iterations)
        self.joseph = check_joseph(joseph)

    @property
    def param_batch_shape(self) -> torch.Size:
        return self.kalman.param_batch_shape

    def predict(self, belief: GaussianBelief, *, u: Tensor | None = None, motion=None) -> GaussianBelief:
        """Kalman time update with the nominal ``Q``: ``x- = F x``, ``P~ = F P F^T + Q``."""
        if motion is not None:
            return self.with_motion(motion).predict(belief, u=u)
        return self.kalman.predict(belief, u=u)

    def _with_module(self, slot, module, name):
        expected = LinearMotion if slot == "motion" else LinearMeasurement
        if isinstance(module, torch.nn.Module) and not isinstance(module, expected):
            raise ValueError(f"{name}: {type(self).__name__} needs a {expected.__name__}, got {type(module).__name__}")
        clone = super()._with_module(slot, module, name)
        if clone is not self:
            clone._modules["kalman"] = self.kalman._with_module(slot, module, name)
        return clone

    def _measurement(self, belief: GaussianBelief, z) -> Tensor:
        """``z`` checked against the sensor and the belief (shapes only)."""
        return check_measurement(z, self.measurement.meas_dim, gaussian_batch(belief, self.motion.state_dim),
                                 belief.mean)


# -- Student-t VB (IMM-VBT mode filter) ----------------------------------------------------------------
class StudentTVBFilter(_LinearVBFilter):
    r"""VB filter for Student-t measurement noise with one scalar mixing variable (docs/baselines.md §4).

    Model: ``z ~ N(H x, R / u)``, ``u ~ Ga(nu/2, nu/2)`` (``R`` the scale matrix of the
    measurement model). Iterations from ``E[u] = 1``:

    .. math::
        S = H P^- H^\top + R/E[u],\ x = x^- + K(z - H x^-),\ P = P^- - K S K^\top,\
        D = \|z - Hx\|^2_{R^{-1}} + \mathrm{tr}(R^{-1} H P H^\top),\
        a = \tfrac{\nu + m}{2},\ b = \tfrac{\nu + D}{2},\ E[u] = a/b

    ``log_likelihood`` is the ELBO
    ``-m/2 log 2pi + m/2 (psi(a) - log b) - 1/2 log|R| - (a/b) D/2 - KL_x - KL_u``.

    Args:
        motion, measurement: linear models (banks allowed).
        df: ``nu > 0``.
        iterations: fixed-point iterations per step.
        elbo_history: also return the ELBO after every iteration (always on at DEBUG log level).
        joseph: Joseph-form (PSD-preserving) inner updates; ``None`` (default): in float32 and
            below only (:func:`~torchmm.linalg.use_joseph`).

    Shapes:
        belief ``GaussianBelief`` batch ``(*B,)``; ``z (*B, m)``; ``extras["elbo"] (*B, iterations)``
        (with ``elbo_history``),
        ``extras["noise_cov"] (*B, m, m)`` (``R / E[u]``), ``extras["predicted_cov"] (*B, n, n)``.

    Examples:
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> f = StudentTVBFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0), df=5.0,
        ...                      elbo_history=True)
        >>> out = f.step(GaussianBelief(torch.zeros(3, 2), torch.eye(2)), torch.randn(3, 1))
        >>> out.belief.mean.shape, out.extras["elbo"].shape
        (torch.Size([3, 2]), torch.Size([3, 10]))
    """

    @entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel), df=Real(positive=True),
                 iterations=Int(1), elbo_history=Flag(), joseph=Flag(optional=True))
    def __init__(self, motion, measurement, df: float = 5.0, iterations: int = 10,
                 elbo_history: bool = False, joseph: bool | None = None):
        super().__init__(motion, measurement, iterations, joseph)
        check_covariance(measurement.R, "measurement.R", definite=True)  # R^{-1} enters D
        self.elbo_history = bool(elbo_history)
        df = as_tensor(df, "df", dtype=measurement.R.dtype, device=measurement.R.device)
        _check_positive(df, "df")
        self.register_buffer("df", df)

    def update(self, belief: GaussianBelief, z: Tensor, *, sensor=None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z)
        z = self._measurement(belief, z)
        H, R = self.measurement.H, self.measurement.R
        m, n = R.shape[-1], belief.mean.shape[-1]
        z_pred = matvec(H, belief.mean)
        missing, z = fill_missing(z, z_pred)
        observed = ~missing.unsqueeze(-1)  # from the data: a NaN prediction is a failure, not missing
        innovation = z - z_pred
        cross = belief.cov @ H.mT
        HPH = H @ cross
        L_R = cholesky(R)
        nu = self.df
        Eu = torch.ones(z.shape[:-1], dtype=z.dtype, device=z.device)
        a = 0.5 * (nu + m)
        half_logdet_R = L_R.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        L_prior = cholesky(belief.cov)
        elbos = []
        history = self.elbo_history or log.isEnabledFor(logging.DEBUG)
        singular = torch.zeros(z.shape[:-1], dtype=torch.bool, device=z.device)
        joseph = use_joseph(self.joseph, z.dtype)
        for it in range(self.iterations):
            R_eff = R / Eu[..., None, None]
            mean, cov, _, flag = condition(belief.mean, belief.cov, innovation, HPH + R_eff, cross,
                                           joseph=(H, R_eff) if joseph else None, with_flag=True,
                                           observed=observed)
            singular = singular | flag
            resid = z - matvec(H, mean)
            quad = cholesky_solve(L_R, resid.unsqueeze(-1)).squeeze(-1).mul(resid).sum(-1)
            D = quad + cholesky_solve(L_R, H @ cov @ H.mT).diagonal(dim1=-2, dim2=-1).sum(-1)
            b = 0.5 * (nu + D)
            Eu = a / b
            if history or it == self.iterations - 1:
                elbos.append(self._elbo(belief, mean, cov, a, b, D, half_logdet_R, L_prior, m, n))
        extras = {"noise_cov": R / Eu[..., None, None], "predicted_cov": belief.cov.expand_as(cov),
                  "singular": singular}
        if history:
            extras["elbo"] = torch.stack(elbos, -1)
            if log.isEnabledFor(logging.DEBUG):  # (a host read: only when asked for)
                log.debug("StudentTVBFilter ELBO per iteration (mean over batch): %s",
                          extras["elbo"].detach().flatten(0, -2).mean(0).tolist())
        mean, cov, loglik, failed = keep_prior_where_missing(missing, belief, mean, cov, elbos[-1])
        extras["failed"] = failed
        return StepOutput(GaussianBelief(mean, cov), belief, loglik, innovation, HPH + extras["noise_cov"],
                          extras=extras)

    def _elbo(self, prior, mean, cov, a, b, D, half_logdet_R, L_prior, m, n):
        nu = self.df
        Elog_u = torch.digamma(a) - torch.log(b)
        diff = (mean - prior.mean).unsqueeze(-1)
        # KL(N(mean, cov) || N(x-, P-))
        Lc = cholesky(cov)
        kl_x = 0.5 * (
            torch.cholesky_solve(cov, L_prior).diagonal(dim1=-2, dim2=-1).sum(-1)
            + torch.cholesky_solve(diff, L_prior).mul(diff).sum((-1, -2)) - n
        ) + L_prior.diagonal(dim1=-2, dim2=-1).log().sum(-1) - Lc.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        kl_u = gamma_kl(a, b, 0.5 * nu, 0.5 * nu)
        return -0.5 * m * _LOG_2PI + 0.5 * m * Elog_u - half_logdet_R - 0.5 * (a / b) * D - kl_x - kl_u


# -- skew-t + inverse Wishart (GIMMAF mode filter) -----------------------------------------------------
class SkewTIWVBFilter(_LinearVBFilter):
    r"""The per-model VB filter of GIMMAF (paper 004, eqs. (9)-(35), (39)).

    Model per step: ``x ~ N(x-, P)``, ``P ~ IW(t^ = n + 1 + tau, T^ = tau P~)`` (``P~`` the nominal
    prediction), ``z_i | x, u, lam ~ N(h_i x + delta_i u_i, r_i / lam_i)``,
    ``u_i | lam_i ~ N+(0, 1/lam_i)``, ``lam_i ~ Ga(nu_i/2, nu_i/2)`` (independent components, eq. (2)).
    Fixed-point iterations (``q_u`` initialised from ``x-`` with ``E[lam] = 1``):

    .. math::
        t = \hat t + 1,\ T = \hat T + P_x + (\hat x - x^-)(\hat x - x^-)^\top,\ \hat P = T/(t - n - 1)

        K = \hat P H^\top (H\hat P H^\top + \bar\Lambda^{-1}R)^{-1},\
        \hat x = x^- + K(z - Hx^- - \Delta\bar u),\ P_x = (I - KH)\hat P

        q(u_i) = N_+\big(\tfrac{\delta_i (z_i - h_i\hat x)}{\delta_i^2 + r_i},\
        \tfrac{r_i}{\bar\lambda_i(\delta_i^2 + r_i)}\big),\quad
        \varphi_i = \tfrac{(z_i - h_i \hat x - \delta_i\bar u_i)^2 + h_i P_x h_i^\top
        + \delta_i^2 \mathrm{Var}[u_i]}{r_i} + E[u_i^2]

        q(\lambda_i) = \mathrm{Ga}(\nu_i/2 + 1, (\nu_i + \varphi_i)/2)

    ``gamma_shape="printed"`` uses the paper's ``Ga(nu/2, .)`` (``lam = nu/(nu + phi)``) instead of
    the derived ``nu/2 + 1`` (see docs/reproduction-004.md). ``log_likelihood`` is the ELBO (39)
    after the last iteration; ``extras`` carry the ELBO per iteration, the point estimate
    ``P^`` of ``P_{k|k-1}`` and the plug-in noise covariance ``diag((r + delta^2 (1 - 2/pi)) / lam)``.

    Args:
        motion: linear motion (bank allowed) with the nominal process noise ``Q_0``.
        measurement: linear measurement whose (diagonal) ``R`` is the skew-t spread matrix.
        skewness: ``Delta`` (number, ``(m,)`` or diagonal ``(m, m)``).
        df: ``nu`` (number or ``(m,)``).
        tau: inverse-Wishart prior confidence ``tau_P > 0``.
        iterations: ``S`` fixed-point iterations.
        gamma_shape: ``"derived"`` (default) or ``"printed"``.
        elbo_history: also return the ELBO after every iteration (always on at DEBUG log level).
        joseph: Joseph-form (PSD-preserving) inner updates; ``None`` (default): in float32 and
            below only (:func:`~torchmm.linalg.use_joseph`).

    Shapes:
        belief ``GaussianBelief`` batch ``(*B,)``; ``z (*B, m)``; extras ``elbo (*B, S)`` (with
        ``elbo_history``),
        ``predicted_cov (*B, n, n)``, ``noise_cov (*B, m, m)``, ``precision (*B, m)`` (``E[lam]``),
        ``skew (*B, m)`` (``E[u]``) and the final factors: ``q(u_i) = N+(u_loc, u_scale^2)`` (before
        truncation), ``q(lam_i) = Ga(shape, gamma_rate)``, ``q(P) = IW(t, (tau + 1) predicted_cov)``.

    Examples:
        >>> from torchmm.models import CoordinatedTurn, PositionMeasurement
        >>> f = SkewTIWVBFilter(CoordinatedTurn(0.0), PositionMeasurement(4, [0, 2], 4.0),
        ...                     skewness=1.0, df=10.0, elbo_history=True)
        >>> out = f.step(GaussianBelief(torch.zeros(5, 4), torch.eye(4)), torch.randn(5, 2))
        >>> out.belief.mean.shape, out.extras["elbo"].shape
        (torch.Size([5, 4]), torch.Size([5, 10]))
    """

    @entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel), skewness=Finite(check=False),
                 df=Finite(check=False), tau=Real(positive=True), iterations=Int(1),
                 gamma_shape=Choice("derived", "printed"), elbo_history=Flag(), joseph=Flag(optional=True))
    def __init__(self, motion, measurement, skewness=0.0, df=5.0, tau: float = 3.0, iterations: int = 10,
                 gamma_shape: str = "derived", elbo_history: bool = False, joseph: bool | None = None):
        super().__init__(motion, measurement, iterations, joseph)
        self.elbo_history = bool(elbo_history)
        R = measurement.R
        m = R.shape[-1]
        r = _diag_param(R, "measurement.R", m, R)
        _check_positive(r, "measurement.R")
        delta = _diag_param(skewness, "skewness", m, R)
        nu = _diag_param(df, "df", m, R)
        _check_positive(nu, "df")
        tau = as_float(tau, "tau", positive=True)
        if gamma_shape not in ("derived", "printed"):
            raise ValueError(f"gamma_shape: expected 'derived' or 'printed', got {gamma_shape!r}")
        self.register_buffer("r", r)
        self.register_buffer("delta", delta)
        self.register_buffer("nu", nu)
        self.tau, self.gamma_shape = tau, gamma_shape

    def _sensor_changed(self) -> None:
        _rederive_scale(self)

    def update(self, belief: GaussianBelief, z: Tensor, *, sensor=None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z)
        z = self._measurement(belief, z)
        H = self.measurement.H
        r, delta, nu, tau = self.r, self.delta, self.nu, self.tau
        n = belief.mean.shape[-1]
        x_pred, P_nom = belief.mean, belief.cov
        z_pred = matvec(H, x_pred)
        missing, z = fill_missing(z, z_pred)
        observed = ~missing.unsqueeze(-1)  # from the data: a NaN prediction is a failure, not missing
        T_prior = tau * P_nom
        t_q = n + 1 + tau + 1  # (27): t = t^ + 1 (never accumulated)
        shape_a = 0.5 * nu + (1.0 if self.gamma_shape == "derived" else 0.0)
        gain_u = delta / (delta.square() + r)  # (34) K_u = Delta (Delta^2 + R)^{-1}
        lam = torch.ones_like(z)
        u_loc = gain_u * (z - z_pred)  # q_u initialised from the prediction
        u_scale = (r / (delta.square() + r) / lam).sqrt()
        Eu, Varu = truncated_normal_moments(u_loc, u_scale)
        mean, cov = x_pred, P_nom
        elbos = []
        history = self.elbo_history or log.isEnabledFor(logging.DEBUG)
        singular = torch.zeros(z.shape[:-1], dtype=torch.bool, device=z.device)
        joseph = use_joseph(self.joseph, z.dtype)
        for it in range(self.iterations):
            diff = mean - x_pred
            T = T_prior + cov + diff.unsqueeze(-1) * diff.unsqueeze(-2)  # (28)
            P_hat = symmetrize(T / (t_q - n - 1))
            cross = P_hat @ H.mT
            R_eff = torch.diag_embed(r / lam)
            mean, cov, _, flag = condition(x_pred, P_hat, z - z_pred - delta * Eu, H @ cross + R_eff, cross,
                                           joseph=(H, R_eff) if joseph else None, with_flag=True,
                                           observed=observed)  # (29)-(31)
            singular = singular | flag
            resid = z - matvec(H, mean)
            u_loc = gain_u * resid  # (32)
            u_scale = (r / (delta.square() + r) / lam).sqrt()  # (33)
            Eu, Varu = truncated_normal_moments(u_loc, u_scale)
            HPH = (H @ cov @ H.mT).diagonal(dim1=-2, dim2=-1)
            phi = ((resid - delta * Eu).square() + HPH + delta.square() * Varu) / r + Varu + Eu.square()
            rate_b = 0.5 * (nu + phi)
            lam = shape_a / rate_b
            if history or it == self.iterations - 1:
                elbos.append(self._elbo(x_pred, P_nom, T, t_q, mean, cov, z, u_loc, u_scale, Eu, Varu,
                                        shape_a, rate_b))
        noise_var = (r + delta.square() * (1 - 2 / math.pi)) / lam
        extras = {"predicted_cov": P_hat, "noise_cov": torch.diag_embed(noise_var), "precision": lam,
                  "skew": Eu, "u_loc": u_loc, "u_scale": u_scale, "gamma_rate": rate_b, "singular": singular}
        if history:
            extras["elbo"] = torch.stack(elbos, -1)
            if log.isEnabledFor(logging.DEBUG):  # (a host read: only when asked for)
                log.debug("SkewTIWVBFilter ELBO per iteration (mean over batch): %s",
                          extras["elbo"].detach().flatten(0, -2).mean(0).tolist())
        mean, cov, loglik, failed = keep_prior_where_missing(missing, belief, mean, cov, elbos[-1])
        extras["failed"] = failed
        return StepOutput(GaussianBelief(mean, cov), belief, loglik, z - z_pred,
                          H @ P_hat @ H.mT + extras["noise_cov"], extras=extras)

    def _elbo(self, x_pred, P_nom, T, t_q, mean, cov, z, u_loc, u_scale, Eu, Varu, a, b):
        """ELBO (39): expected log joint + entropies, with the IW terms as ``-KL(q_P || p_P)``."""
        H, r, delta, nu, tau = self.measurement.H, self.r, self.delta, self.nu, self.tau
        n = x_pred.shape[-1]
        dof_q, dof_p = t_q - n - 1, tau  # standard IW degrees of freedom (module doc)
        # E_q[ln N(x; x-, P)] with E[P^-1] = dof_q T^-1, E[ln|P|] = ln|T| - n ln 2 - psi_n(dof_q/2)
        L_T = cholesky(T)
        logdet_T = 2 * L_T.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        diff = (mean - x_pred).unsqueeze(-1)
        A = cov + diff @ diff.mT
        tr = torch.cholesky_solve(A, L_T).diagonal(dim1=-2, dim2=-1).sum(-1)
        e_logdet_P = logdet_T - n * math.log(2.0)
        if dof_q > n - 1:  # otherwise an infinite constant (same for every mode and iteration): left out
            e_logdet_P = e_logdet_P - _mvdigamma(torch.full((), 0.5 * dof_q, dtype=T.dtype, device=T.device), n)
        e_log_px = -0.5 * n * _LOG_2PI - 0.5 * e_logdet_P - 0.5 * dof_q * tr
        neg_kl_P = -wishart_kl(dof_q, T, dof_p, tau * P_nom)
        # measurement, half-normal and gamma terms (independent components)
        Elog_lam, Elam = torch.digamma(a) - torch.log(b), a / b
        resid = z - (H @ mean.unsqueeze(-1)).squeeze(-1) - delta * Eu
        HPH = (H @ cov @ H.mT).diagonal(dim1=-2, dim2=-1)
        e_sq = resid.square() + HPH + delta.square() * Varu
        e_log_z = -0.5 * _LOG_2PI - 0.5 * torch.log(r) + 0.5 * Elog_lam - 0.5 * Elam * e_sq / r
        e_log_u = math.log(2.0) - 0.5 * _LOG_2PI + 0.5 * Elog_lam - 0.5 * Elam * (Varu + Eu.square())
        neg_kl_lam = -gamma_kl(a, b, 0.5 * nu, 0.5 * nu)
        h_u = truncated_normal_entropy(u_loc, u_scale)
        h_x = _gaussian_entropy(cov)
        per_component = (e_log_z + e_log_u + neg_kl_lam + h_u).sum(-1)
        return e_log_px + neg_kl_P + h_x + per_component


# -- STVBF ---------------------------------------------------------------------------------------------
class SkewTVBFilter(_LinearVBFilter):
    r"""STVBF: skew-t VB filter with coupled ``q(x, u) q(Lambda)`` (Nurminen et al. 2018; IND variant).

    Per iteration (from ``E[lam] = 1``): the Kalman update of the augmented state ``xi = [x; u]`` with
    prior ``N([x-; 0], blkdiag(P-, diag(1/lam)))``, measurement matrix ``[H  Delta]`` and noise
    ``diag(r/lam)``; truncation of ``u >= 0`` by sequential moment matching over the ``m``
    coordinates (exact for one constraint); then
    ``q(lam_i) = Ga(nu_i/2 + 1, nu_i/2 + ([E_r]_ii / r_i + E[u_i^2])/2)`` with
    ``E_r = (z - A xi)(z - A xi)^T + A Sigma A^T``.

    ``log_likelihood`` is a plug-in value (the augmented Gaussian evidence with the final ``E[lam]``,
    truncation ignored); the filter is used on its own, not inside an IMM.

    Args:
        motion, measurement: linear models; ``measurement.R`` is the (diagonal) spread matrix.
        skewness, df: ``Delta`` and ``nu`` (numbers, ``(m,)`` or diagonal matrices).
        iterations: VB iterations per step.
        joseph: Joseph-form (PSD-preserving) inner updates; ``None`` (default): in float32 and
            below only (:func:`~torchmm.linalg.use_joseph`).

    Shapes:
        belief ``GaussianBelief`` batch ``(*B,)``; ``z (*B, m)``; extras ``noise_cov (*B, m, m)``,
        ``predicted_cov (*B, n, n)``, ``precision (*B, m)``, ``skew (*B, m)``.

    Examples:
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> f = SkewTVBFilter(ConstantVelocity(2), PositionMeasurement(4, [0, 2], 4.0), skewness=1.0, df=10.0)
        >>> f.step(GaussianBelief(torch.zeros(5, 4), torch.eye(4)), torch.randn(5, 2)).belief.mean.shape
        torch.Size([5, 4])
    """

    @entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel), skewness=Finite(check=False),
                 df=Finite(check=False), iterations=Int(1), joseph=Flag(optional=True))
    def __init__(self, motion, measurement, skewness=0.0, df=5.0, iterations: int = 10,
                 joseph: bool | None = None):
        super().__init__(motion, measurement, iterations, joseph)
        R = measurement.R
        m = R.shape[-1]
        r = _diag_param(R, "measurement.R", m, R)
        _check_positive(r, "measurement.R")
        nu = _diag_param(df, "df", m, R)
        _check_positive(nu, "df")
        self.register_buffer("r", r)
        self.register_buffer("delta", _diag_param(skewness, "skewness", m, R))
        self.register_buffer("nu", nu)

    def _sensor_changed(self) -> None:
        _rederive_scale(self)

    def update(self, belief: GaussianBelief, z: Tensor, *, sensor=None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z)
        z = self._measurement(belief, z)
        H, r, delta, nu = self.measurement.H, self.r, self.delta, self.nu
        n, m = belief.mean.shape[-1], r.shape[-1]
        x_pred, P_pred = belief.mean, belief.cov
        batch = broadcast_shape(x_pred.shape[:-1], z.shape[:-1])
        z_pred = matvec(H, x_pred)
        missing, z = fill_missing(z, z_pred)
        observed = ~missing.unsqueeze(-1)  # from the data: a NaN prediction is a failure, not missing
        Hb = H.expand(*batch, m, n)
        A = torch.cat([Hb, torch.diag_embed(delta).expand(*batch, m, m)], -1)  # [H Delta], (*B, m, n+m)
        u_prior = torch.zeros(*batch, m, dtype=z.dtype, device=z.device)
        xi_prior = torch.cat([x_pred.expand(*batch, n), u_prior], -1)
        lam = torch.ones(*batch, m, dtype=z.dtype, device=z.device)
        zeros = torch.zeros(n + m, n + m, dtype=z.dtype, device=z.device)
        eye = torch.eye(n + m, dtype=z.dtype, device=z.device)
        singular = torch.zeros(batch, dtype=torch.bool, device=z.device)
        joseph = use_joseph(self.joseph, z.dtype)
        for _ in range(self.iterations):
            Sigma_prior = zeros.expand(*batch, n + m, n + m).clone()
            Sigma_prior[..., :n, :n] = P_pred
            Sigma_prior[..., n:, n:] = torch.diag_embed(1.0 / lam)
            cross = Sigma_prior @ A.mT
            R_eff = torch.diag_embed(r / lam)
            xi, Sigma, loglik, flag = condition(xi_prior, Sigma_prior, z - z_pred, A @ cross + R_eff, cross,
                                                joseph=(A, R_eff) if joseph else None, with_flag=True,
                                                observed=observed)
            singular = singular | flag
            for i in range(m):  # sequential truncation u_i >= 0 (a loop over measurement coordinates)
                j = n + i
                var_j = Sigma[..., j, j].clamp_min(torch.finfo(z.dtype).tiny)
                t_mean, t_var = truncated_normal_moments(xi[..., j], var_j.sqrt())
                g = Sigma[..., :, j] / var_j.unsqueeze(-1)
                xi = xi + g * (t_mean - xi[..., j]).unsqueeze(-1)
                if joseph:
                    # Sigma - g g^T (var_j - t_var) as the product A Sigma A^T, A = I - a g e_j^T,
                    # a = 1 - sqrt(t_var / var_j): PSD by construction (no cancellation in float32)
                    a = 1 - (t_var / var_j).clamp(0.0, 1.0).sqrt()
                    Aj = eye - (a.unsqueeze(-1) * g).unsqueeze(-1) * eye[j]
                    Sigma = symmetrize(Aj @ Sigma @ Aj.mT)
                else:
                    shrink = (t_var - var_j)[..., None, None]
                    Sigma = symmetrize(Sigma + g.unsqueeze(-1) * g.unsqueeze(-2) * shrink)
            resid = z - (A @ xi.unsqueeze(-1)).squeeze(-1)
            Er = resid.square() + (A @ Sigma @ A.mT).diagonal(dim1=-2, dim2=-1)
            Eu2 = Sigma[..., n:, n:].diagonal(dim1=-2, dim2=-1) + xi[..., n:].square()
            lam = (0.5 * nu + 1.0) / (0.5 * nu + 0.5 * (Er / r + Eu2))
        mean, cov = xi[..., :n], symmetrize(Sigma[..., :n, :n])
        mean, cov, loglik, failed = keep_prior_where_missing(missing, belief, mean, cov, loglik)
        noise_var = (r + delta.square() * (1 - 2 / math.pi)) / lam
        return StepOutput(
            GaussianBelief(mean, cov), belief, loglik, z - z_pred,
            H @ P_pred @ H.mT + torch.diag_embed(noise_var),
            extras={"noise_cov": torch.diag_embed(noise_var), "predicted_cov": P_pred.expand(*batch, n, n),
                    "precision": lam, "skew": xi[..., n:], "singular": singular, "failed": failed},
        )


# VBAKF-PR lives in torchmm.filters.vbakf and its belief in torchmm.beliefs (re-exported here)
from torchmm.beliefs.adaptive import AdaptiveGaussianBelief  # noqa: E402
from torchmm.filters.vbakf import VBAKFPR  # noqa: E402


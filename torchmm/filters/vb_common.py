"""What the variational-Bayes filters share (:mod:`torchmm.filters.variational`, :mod:`torchmm.filters.skew_t`,
:mod:`torchmm.filters.vbakf`): the Gamma and inverse-Wishart divergences of their ELBOs, the Gaussian
entropy, the per-component parameters of skew-t noise, missing data skipped per run, and the linear
set-up (a Kalman prediction with the nominal ``Q``) of :class:`LinearVBFilter`. The inverse-Wishart
convention is the one :mod:`torchmm.filters.variational`'s docstring states."""

from __future__ import annotations

import logging
import math

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief
from torchmm.filters.base import Filter
from torchmm.filters.kalman import KalmanFilter
from torchmm.linalg import check_joseph, cholesky, flag_failed
from torchmm.models.linear import LinearMeasurement, LinearMotion
from torchmm.validation import as_int, as_tensor, check_measurement, gaussian_batch

__all__ = [
    "LOG_2PI",
    "LinearVBFilter",
    "check_iterations",
    "check_linear_models",
    "check_positive",
    "diag_param",
    "fill_missing",
    "gamma_kl",
    "gaussian_entropy",
    "keep_prior_where_missing",
    "mvdigamma",
    "record_elbo",
    "rederive_scale",
    "wishart_kl",
]

LOG_2PI = math.log(2 * math.pi)
log = logging.getLogger("torchmm")


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


def mvdigamma(x: Tensor, n: int) -> Tensor:
    """``psi_n(x)``, the multivariate digamma function (the derivative of ``ln Gamma_n``)."""
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
        kl = kl + 0.5 * (dof_q - dof_p) * mvdigamma(dq, n) - _mvlgamma(0.5 * dof_q, n)
    if dof_p > n - 1:
        kl = kl + _mvlgamma(0.5 * dof_p, n)
    return kl


def _mvlgamma(x: float, n: int) -> float:
    """``ln Gamma_n(x)`` of a Python number (``torch.mvlgamma`` without a tensor)."""
    return 0.25 * n * (n - 1) * math.log(math.pi) + sum(math.lgamma(x - 0.5 * i) for i in range(n))


def gaussian_entropy(cov: Tensor) -> Tensor:
    n = cov.shape[-1]
    L = cholesky(cov)
    return 0.5 * n * (LOG_2PI + 1.0) + L.diagonal(dim1=-2, dim2=-1).log().sum(-1)


def diag_param(value, name: str, m: int, like: Tensor) -> Tensor:
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


def check_positive(value: Tensor, name: str) -> None:
    if bool((value.detach() <= 0).any()):
        raise ValueError(f"{name}: must be positive")


def check_linear_models(motion, measurement) -> None:
    if not isinstance(motion, LinearMotion):
        raise ValueError(f"motion: expected a LinearMotion, got {type(motion).__name__}")
    if not isinstance(measurement, LinearMeasurement):
        raise ValueError(f"measurement: expected a LinearMeasurement, got {type(measurement).__name__}")


def rederive_scale(filter) -> None:
    """A skew-t filter given another sensor (``with_sensor``): its per-component scale ``r`` from the
    new ``R``; skewness and degrees of freedom are per component, so ``m`` must not change."""
    R = filter.measurement.R
    m = R.shape[-1]
    if m != filter.r.shape[-1]:
        raise ValueError(f"sensor: {type(filter).__name__}'s skewness and df have {filter.r.shape[-1]} components, "
                         f"the sensor {m}")
    r = diag_param(R, "sensor.R", m, R)
    check_positive(r, "sensor.R")
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


class LinearVBFilter(Filter):
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

    def informative(self, z: Tensor) -> Tensor:
        """``(*B,)`` bool: the datum is used only where every component is finite (:func:`fill_missing`
        skips the rest), so a multiple-model filter over these scores a partly missing datum exactly 0,
        as each mode does (tests/filters/test_vb_partial_datum.py)."""
        return torch.isfinite(z).all(-1)

    def _measurement(self, belief: GaussianBelief, z) -> Tensor:
        """``z`` checked against the sensor and the belief (shapes only)."""
        return check_measurement(z, self.measurement.meas_dim, gaussian_batch(belief, self.motion.state_dim),
                                 belief.mean)


def record_elbo(extras: dict, elbos: list, history: bool, filter_name: str) -> None:
    """With ``history`` (``elbo_history``, or DEBUG logging): the ELBO after every iteration in ``extras["elbo"]``
    ``(*B, iterations)``, and at DEBUG level its mean over the batch logged (a host read: only when asked for)."""
    if history:
        extras["elbo"] = torch.stack(elbos, -1)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s ELBO per iteration (mean over batch): %s", filter_name,
                      extras["elbo"].detach().flatten(0, -2).mean(0).tolist())

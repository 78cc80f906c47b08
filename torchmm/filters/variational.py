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

import math

import logging

import torch
from torch import Tensor

from torchmm.contract import Flag, Int, Of, Real, entry_point
from torchmm.beliefs import GaussianBelief
from torchmm.filters.base import StepOutput
from torchmm.linalg import cholesky, cholesky_solve, condition, use_joseph
from torchmm.models.base import MeasurementModel, MotionModel
from torchmm.models.linear import matvec
from torchmm.filters.vb_common import (
    LOG_2PI,
    LinearVBFilter,
    check_positive,
    fill_missing,
    gamma_kl,
    keep_prior_where_missing,
    record_elbo,
    wishart_kl,
)
from torchmm.validation import as_tensor, check_covariance

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


# -- Student-t VB (IMM-VBT mode filter) ----------------------------------------------------------------
class StudentTVBFilter(LinearVBFilter):
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
        check_positive(df, "df")
        self.register_buffer("df", df)

    def update(self, belief: GaussianBelief, z: Tensor, *, sensor=None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z)
        z = self._measurement(belief, z)
        H, R = self.measurement.H, self.measurement.R
        m, n = R.shape[-1], belief.mean.shape[-1]
        z_pred = matvec(H, belief.mean)
        present = torch.isfinite(z)  # (the record's innovation is NaN where a component is missing)
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
        record_elbo(extras, elbos, history, "StudentTVBFilter")
        mean, cov, loglik, failed = keep_prior_where_missing(missing, belief, mean, cov, elbos[-1])
        extras["failed"] = failed
        return StepOutput(GaussianBelief(mean, cov), belief, loglik, torch.where(present, innovation, math.nan), HPH + extras["noise_cov"],
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
        return -0.5 * m * LOG_2PI + 0.5 * m * Elog_u - half_logdet_R - 0.5 * (a / b) * D - kl_x - kl_u


# the skew-t filters live in torchmm.filters.skew_t; VBAKF-PR in torchmm.filters.vbakf and its belief in
# torchmm.beliefs (all re-exported here: configs name them as torchmm.filters.variational.<class>)
from torchmm.beliefs.adaptive import AdaptiveGaussianBelief  # noqa: E402
from torchmm.filters.skew_t import SkewTIWVBFilter, SkewTVBFilter  # noqa: E402
from torchmm.filters.vbakf import VBAKFPR  # noqa: E402

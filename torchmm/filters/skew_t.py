r"""The skew-t variational-Bayes filters (re-exported by :mod:`torchmm.filters.variational`, whose docstring
states their models and the inverse-Wishart convention):

* :class:`SkewTIWVBFilter` - the per-model filter of GIMMAF (paper 004, eqs. (9)-(35)): skew-t noise and an
  inverse-Wishart prior on ``P_{k|k-1}``; ``log_likelihood`` is the ELBO (39), the mode likelihood (38).
* :class:`SkewTVBFilter` - STVBF (Nurminen, Ardeshiri, Piche, Gustafsson 2018; docs/baselines.md section 5).
"""

from __future__ import annotations

import logging
import math

import torch
from torch import Tensor

from torchmm.contract import Choice, Finite, Flag, Int, Of, Real, entry_point
from torchmm.beliefs import GaussianBelief
from torchmm.beliefs.ops import symmetrize
from torchmm.distributions import skew_t_mean_factor, truncated_normal_entropy, truncated_normal_moments
from torchmm.filters.base import StepOutput
from torchmm.linalg import cholesky, condition, not_psd, use_joseph
from torchmm.models.base import MeasurementModel, MotionModel
from torchmm.models.linear import matvec
from torchmm.validation import as_float, broadcast_shape
from torchmm.filters.vb_common import (
    LOG_2PI,
    LinearVBFilter,
    check_positive,
    diag_param,
    fill_missing,
    gamma_kl,
    gaussian_entropy,
    keep_prior_where_missing,
    mvdigamma,
    record_elbo,
    rederive_scale,
    wishart_kl,
)

__all__ = ["SkewTIWVBFilter", "SkewTVBFilter"]

log = logging.getLogger("torchmm")


def _noise_mean(delta: Tensor, nu: Tensor) -> Tensor:
    """The skew-t noise's mean ``delta c(nu)``, ``c(nu) = E[u]``
    (:func:`~torchmm.distributions.skew_t_mean_factor`): NaN where it does not exist (``nu <= 1``
    with ``delta != 0``), 0 where ``delta = 0``.

    Shapes:
        delta, nu: ``(m,)`` -> ``(m,)``
    """
    c = torch.where(nu > 1, skew_t_mean_factor(nu.clamp_min(1.0 + 1e-12)), math.nan)
    return torch.where(delta == 0, torch.zeros_like(delta), delta * c)


def _skew_innovation(z: Tensor, z_pred: Tensor, present: Tensor, delta: Tensor, nu: Tensor) -> Tensor:
    """``z - E[z | past] = z - H x- - delta c(nu)``, NaN where a component is missing (``present``
    False) or its noise has no mean. Shapes: ``(*B, m)`` -> ``(*B, m)``."""
    return torch.where(present, z - z_pred - _noise_mean(delta, nu), math.nan)


# -- skew-t + inverse Wishart (GIMMAF mode filter) -----------------------------------------------------
class SkewTIWVBFilter(LinearVBFilter):
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
    ``innovation`` is ``z - E[z | past] = z - H x- - delta c(nu)`` (``delta c(nu)`` the skew noise's
    mean, :func:`~torchmm.distributions.skew_t_mean_factor`; NaN where a component is missing or
    its noise has no mean, ``nu <= 1`` and ``delta != 0``); ``innovation_cov`` is the plug-in
    ``H P^ H^T + noise_cov`` (an approximation of its covariance, docs/variational.md). A step whose
    posterior covariance is not numerically PSD or whose ELBO is not finite fails (NaN
    log-likelihood and posterior, ``extras["failed"]``; docs/robustness.md).

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
        r = diag_param(R, "measurement.R", m, R)
        check_positive(r, "measurement.R")
        delta = diag_param(skewness, "skewness", m, R)
        nu = diag_param(df, "df", m, R)
        check_positive(nu, "df")
        tau = as_float(tau, "tau", positive=True)
        if gamma_shape not in ("derived", "printed"):
            raise ValueError(f"gamma_shape: expected 'derived' or 'printed', got {gamma_shape!r}")
        self.register_buffer("r", r)
        self.register_buffer("delta", delta)
        self.register_buffer("nu", nu)
        self.tau, self.gamma_shape = tau, gamma_shape

    def _sensor_changed(self) -> None:
        rederive_scale(self)

    def update(self, belief: GaussianBelief, z: Tensor, *, sensor=None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z)
        z = self._measurement(belief, z)
        H = self.measurement.H
        r, delta, nu, tau = self.r, self.delta, self.nu, self.tau
        n = belief.mean.shape[-1]
        x_pred, P_nom = belief.mean, belief.cov
        z_pred = matvec(H, x_pred)
        present = torch.isfinite(z)
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
        record_elbo(extras, elbos, history, "SkewTIWVBFilter")
        # a posterior covariance that is not PSD (e.g. after an outlier of ~1e12 x the noise scale) or a
        # non-finite ELBO: the update failed (NaN log-likelihood and posterior, extras["failed"])
        broken = not_psd(cov) | ~torch.isfinite(elbos[-1])
        nan = torch.full((), math.nan, dtype=cov.dtype, device=cov.device)
        loglik = torch.where(broken, nan, elbos[-1])
        mean = torch.where(broken.unsqueeze(-1), nan, mean)
        cov = torch.where(broken[..., None, None], nan, cov)
        mean, cov, loglik, failed = keep_prior_where_missing(missing, belief, mean, cov, loglik)
        extras["failed"] = failed
        innovation = _skew_innovation(z, z_pred, present, delta, nu)
        return StepOutput(GaussianBelief(mean, cov), belief, loglik, innovation,
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
            e_logdet_P = e_logdet_P - mvdigamma(torch.full((), 0.5 * dof_q, dtype=T.dtype, device=T.device), n)
        e_log_px = -0.5 * n * LOG_2PI - 0.5 * e_logdet_P - 0.5 * dof_q * tr
        neg_kl_P = -wishart_kl(dof_q, T, dof_p, tau * P_nom)
        # measurement, half-normal and gamma terms (independent components)
        Elog_lam, Elam = torch.digamma(a) - torch.log(b), a / b
        resid = z - (H @ mean.unsqueeze(-1)).squeeze(-1) - delta * Eu
        HPH = (H @ cov @ H.mT).diagonal(dim1=-2, dim2=-1)
        e_sq = resid.square() + HPH + delta.square() * Varu
        e_log_z = -0.5 * LOG_2PI - 0.5 * torch.log(r) + 0.5 * Elog_lam - 0.5 * Elam * e_sq / r
        e_log_u = math.log(2.0) - 0.5 * LOG_2PI + 0.5 * Elog_lam - 0.5 * Elam * (Varu + Eu.square())
        neg_kl_lam = -gamma_kl(a, b, 0.5 * nu, 0.5 * nu)
        h_u = truncated_normal_entropy(u_loc, u_scale)
        h_x = gaussian_entropy(cov)
        per_component = (e_log_z + e_log_u + neg_kl_lam + h_u).sum(-1)
        return e_log_px + neg_kl_P + h_x + per_component


# -- STVBF ---------------------------------------------------------------------------------------------
class SkewTVBFilter(LinearVBFilter):
    r"""STVBF: skew-t VB filter with coupled ``q(x, u) q(Lambda)`` (Nurminen et al. 2018; IND variant).

    Per iteration (from ``E[lam] = 1``): the Kalman update of the augmented state ``xi = [x; u]`` with
    prior ``N([x-; 0], blkdiag(P-, diag(1/lam)))``, measurement matrix ``[H  Delta]`` and noise
    ``diag(r/lam)``; truncation of ``u >= 0`` by sequential moment matching over the ``m``
    coordinates (exact for one constraint); then
    ``q(lam_i) = Ga(nu_i/2 + 1, nu_i/2 + ([E_r]_ii / r_i + E[u_i^2])/2)`` with
    ``E_r = (z - A xi)(z - A xi)^T + A Sigma A^T``.

    ``log_likelihood`` is a plug-in value: the Gaussian evidence of the last iteration's augmented
    update, ``N(z; H x-, H P- H^T + Delta diag(1/lam) Delta + diag(r/lam))`` with the ``E[lam]`` that
    iteration started from (before the final ``q(Lambda)`` update, whose ``E[lam]`` is
    ``extras["precision"]``), ``u``'s prior mean 0 and the truncation ignored; the filter is used on
    its own, not inside an IMM. ``innovation`` is
    ``z - H x- - delta c(nu)`` (as :class:`SkewTIWVBFilter`'s), ``innovation_cov`` the plug-in
    ``H P- H^T + diag((r + delta^2 (1 - 2/pi)) / lam)``.

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
        r = diag_param(R, "measurement.R", m, R)
        check_positive(r, "measurement.R")
        nu = diag_param(df, "df", m, R)
        check_positive(nu, "df")
        self.register_buffer("r", r)
        self.register_buffer("delta", diag_param(skewness, "skewness", m, R))
        self.register_buffer("nu", nu)

    def _sensor_changed(self) -> None:
        rederive_scale(self)

    def update(self, belief: GaussianBelief, z: Tensor, *, sensor=None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z)
        z = self._measurement(belief, z)
        H, r, delta, nu = self.measurement.H, self.r, self.delta, self.nu
        n, m = belief.mean.shape[-1], r.shape[-1]
        x_pred, P_pred = belief.mean, belief.cov
        batch = broadcast_shape(x_pred.shape[:-1], z.shape[:-1])
        z_pred = matvec(H, x_pred)
        present = torch.isfinite(z)
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
            GaussianBelief(mean, cov), belief, loglik, _skew_innovation(z, z_pred, present, delta, nu),
            H @ P_pred @ H.mT + torch.diag_embed(noise_var),
            extras={"noise_cov": torch.diag_embed(noise_var), "predicted_cov": P_pred.expand(*batch, n, n),
                    "precision": lam, "skew": xi[..., n:], "singular": singular, "failed": failed},
        )

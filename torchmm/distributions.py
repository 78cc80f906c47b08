r"""Heavy-tailed and skewed noise distributions, and stable truncated-normal moments.

* :class:`MultivariateStudentT` — ``t_m(loc, scale, df)``: ``e = loc + L n / sqrt(lam)``,
  ``lam ~ Ga(df/2, df/2)`` (shape, rate), ``L L^T = scale``.
* :class:`SkewT` — the skew-t of paper 004, eqs. (2)-(5) (Nurminen et al.'s parametrisation): a
  product over components of univariate skew-t laws ``ST(e_i; mu_i, sigma_i^2, delta_i, nu_i)``
  with the hierarchy (14)-(16)

  .. math::
      e_i = \mu_i + \delta_i u_i + \sigma_i n_i / \sqrt{\lambda_i},\quad
      u_i = |n_{u,i}| / \sqrt{\lambda_i},\quad \lambda_i \sim \mathrm{Ga}(\nu_i/2, \nu_i/2)

  and density ``ST(e) = 2 t(e; mu, delta^2 + sigma^2, nu) T(e~; nu + 1)`` with
  ``e~ = (e - mu) delta / sigma * sqrt((nu + 1) / (nu (delta^2 + sigma^2) + (e - mu)^2))``.
  ``delta -> 0`` gives the Student-t, and ``delta -> 0, nu -> inf`` the Gaussian.
* :func:`truncated_normal_moments` / :func:`truncated_normal_entropy` — ``N(mu, s^2)`` truncated
  to ``[0, inf)``, computed in float64 through ``erfcx`` (the naive ``phi / (1 - Phi)`` fails
  from ``alpha = -mu/s ~ 8`` on) with an asymptotic series for ``alpha > 30`` (docs/baselines.md §5),
  and through ``log_ndtr`` for ``alpha <= 0`` (where ``erfcx`` overflows from ``alpha ~ -37.7`` on).

All classes follow ``torch.distributions`` conventions (``batch_shape``, ``event_shape``,
``sample(sample_shape)``, ``log_prob``, ``mean``), and ``sample`` takes an explicit
``generator``.
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
from torch import Tensor
from torch.distributions import Distribution

from torchmm.contract import Cov, Finite, Flag, Real, entry_point
from torchmm.validation import SYMMETRY_RTOL, as_tensor, broadcast_shape

__all__ = [
    "MultivariateStudentT",
    "SkewT",
    "sample_gamma",
    "skew_t_mean_factor",
    "student_t_cdf",
    "student_t_log_cdf",
    "truncated_normal_entropy",
    "truncated_normal_moments",
]

_SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)
_LOG_2PI = math.log(2.0 * math.pi)
#: coefficients of the asymptotic series of 1 - lambda (lambda - alpha) in y = 1/alpha^2
_SERIES = (1.0, -6.0, 50.0, -518.0, 6354.0, -89782.0, 1435330.0)


# -- truncated normal ------------------------------------------------------------------------------
def _alpha_terms(loc: Tensor, scale: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``alpha = -mu/s``, inverse Mills ratio ``lambda(alpha)``, the variance factor and
    ``d = lambda - alpha`` (without cancellation for ``alpha > 30``), float64.

    Each side of ``alpha = 0`` is evaluated on its own clamped argument, so neither side overflows
    and the unused side of a ``torch.where`` has finite values and derivatives: ``alpha > 0``
    through ``erfcx`` (``<= 1`` there), ``alpha <= 0`` as ``exp(log phi(alpha) - log_ndtr(-alpha))``
    (``erfcx`` of a large negative argument overflows from ``alpha ~ -37.7`` on).
    """
    mu, s = loc.to(torch.float64), scale.to(torch.float64)
    alpha = -mu / s
    a_pos, a_neg = alpha.clamp_min(0.0), alpha.clamp_max(0.0)
    lam_pos = _SQRT_2_OVER_PI / torch.special.erfcx(a_pos / math.sqrt(2.0))
    lam_neg = torch.exp(-0.5 * (a_neg.square() + _LOG_2PI) - torch.special.log_ndtr(-a_neg))
    lam = torch.where(alpha > 0.0, lam_pos, lam_neg)
    direct = 1.0 - lam * (lam - alpha)
    tail = alpha > 30.0
    a_tail = alpha.clamp_min(30.0)
    y = 1.0 / a_tail.square()
    series = torch.zeros_like(y)
    for c in reversed(_SERIES):
        series = series * y + c
    factor = torch.where(tail, y * series, direct).clamp_min(0.0)
    # far in the tail lambda - alpha cancels; there d = lambda - alpha solves d^2 + alpha d = 1 - V/s^2
    one_minus = 1.0 - y * series
    d_tail = 2.0 * one_minus / (a_tail + torch.sqrt(a_tail.square() + 4.0 * one_minus))
    d = torch.where(tail, d_tail, lam - alpha)
    return alpha, lam, factor, d


def truncated_normal_moments(loc: Tensor, scale: Tensor) -> tuple[Tensor, Tensor]:
    r"""Mean and variance of ``N(loc, scale^2)`` truncated to ``[0, inf)``.

    .. math::
        \alpha = -\mu/s,\quad \lambda = \phi(\alpha)/(1 - \Phi(\alpha))
        = \sqrt{2/\pi}/\mathrm{erfcx}(\alpha/\sqrt2),\quad
        E = \mu + s\lambda,\quad V = s^2 (1 - \lambda(\lambda - \alpha))

    Computed in float64 (the float32 variance is already 0.1 % off at ``alpha = 10``) and cast
    back to the input dtype; for ``alpha > 30`` the variance factor uses the asymptotic series and
    the mean ``s (lambda - alpha)`` is recovered from it without cancellation; for ``alpha <= 0``
    ``lambda = exp(log phi(alpha) - log_ndtr(-alpha))`` (finite values and gradients at any
    ``loc / scale``).

    Shapes:
        loc, scale: broadcastable ``(*B,)`` -> mean ``(*B,)``, variance ``(*B,)``

    Examples:
        >>> mean, var = truncated_normal_moments(torch.tensor([0.0, -100.0]), torch.tensor([1.0, 1.0]))
        >>> [round(v, 4) for v in mean.tolist()], bool((var > 0).all())
        ([0.7979, 0.01], True)
    """
    dtype = torch.promote_types(loc.dtype, scale.dtype)
    s = scale.to(torch.float64)
    alpha, lam, factor, d = _alpha_terms(loc, scale)
    mean = torch.where(alpha > 30.0, s * d, loc.to(torch.float64) + s * lam)
    var = s.square() * factor
    return mean.to(dtype), var.to(dtype)


def truncated_normal_entropy(loc: Tensor, scale: Tensor) -> Tensor:
    r"""Differential entropy of ``N(loc, scale^2)`` truncated to ``[0, inf)``.

    ``H = 1/2 log(2 pi e) + log s + log Z + alpha lambda / 2`` with ``log Z = log(1 - Phi(alpha))``.
    For ``alpha <= 0`` (``loc >= 0``) ``log Z = log_ndtr(-alpha)``; for ``alpha > 0``
    ``log Z = log(erfcx(alpha/sqrt2)/2) - alpha^2/2`` and the two ``alpha^2/2`` terms are cancelled
    by hand: ``log Z + alpha lambda / 2 = log(erfcx(alpha/sqrt2)/2) + alpha (lambda - alpha) / 2``.
    Finite (and with finite gradients) for any finite ``loc / scale``.

    Shapes:
        loc, scale: ``(*B,)`` -> ``(*B,)``
    """
    dtype = torch.promote_types(loc.dtype, scale.dtype)
    alpha, lam, _, d = _alpha_terms(loc, scale)
    a_pos, a_neg = alpha.clamp_min(0.0), alpha.clamp_max(0.0)
    upper = torch.log(0.5 * torch.special.erfcx(a_pos / math.sqrt(2.0))) + 0.5 * a_pos * d
    lower = torch.special.log_ndtr(-a_neg) + 0.5 * a_neg * lam
    h = 0.5 * (_LOG_2PI + 1.0) + scale.to(torch.float64).log() + torch.where(alpha > 0.0, upper, lower)
    return h.to(dtype)


# -- Student-t CDF ---------------------------------------------------------------------------------
def _betainc_cf(a: Tensor, b: Tensor, x: Tensor, iterations: int = 300) -> Tensor:
    """Continued fraction of the regularised incomplete beta (modified Lentz), valid for
    ``x < (a + 1) / (a + b + 2)``; fixed iteration count (batched)."""
    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c = torch.ones_like(x)
    d = 1.0 - qab * x / qap
    d = torch.where(d.abs() < tiny, torch.full_like(d, tiny), d)
    d = 1.0 / d
    h = d
    for i in range(1, iterations + 1):
        m2 = 2 * i
        aa = i * (b - i) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = torch.where(d.abs() < tiny, torch.full_like(d, tiny), d)
        c = 1.0 + aa / c
        c = torch.where(c.abs() < tiny, torch.full_like(c, tiny), c)
        d = 1.0 / d
        h = h * d * c
        aa = -(a + i) * (qab + i) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = torch.where(d.abs() < tiny, torch.full_like(d, tiny), d)
        c = 1.0 + aa / c
        c = torch.where(c.abs() < tiny, torch.full_like(c, tiny), c)
        d = 1.0 / d
        h = h * d * c
    return h


def _log_betainc(a: Tensor, b: Tensor, x: Tensor) -> Tensor:
    """``log I_x(a, b)`` for ``x`` in ``[0, (a + 1)/(a + b + 2)]`` (the directly convergent side)."""
    log_front = (
        torch.special.xlogy(a, x) + torch.log1p(-x) * b
        - (torch.lgamma(a) + torch.lgamma(b) - torch.lgamma(a + b)) - a.log()
    )
    return log_front + _betainc_cf(a, b, x).log()


def student_t_log_cdf(x: Tensor, df: Tensor) -> Tensor:
    r"""``log T_nu(x)``, the log-CDF of the standard Student-t (float64 inside).

    ``T_nu(x) = 1 - I_{nu/(nu + x^2)}(nu/2, 1/2) / 2`` for ``x >= 0`` and the mirror image below;
    the incomplete beta is evaluated on whichever side its continued fraction converges.

    Shapes:
        x, df: broadcastable ``(*B,)`` -> ``(*B,)``
    """
    dtype = torch.promote_types(x.dtype, df.dtype)
    x64, nu = torch.broadcast_tensors(x.to(torch.float64), df.to(torch.float64))
    a, b = 0.5 * nu, torch.full_like(nu, 0.5)
    w = nu / (nu + x64.square())  # tail probability 2 P(T > |x|) = I_w(nu/2, 1/2)
    thresh_direct = (a + 1.0) / (a + b + 2.0)
    thresh_mirror = (b + 1.0) / (a + b + 2.0)
    direct = w < thresh_direct
    w_d = torch.minimum(w, thresh_direct)  # clamped so the unused branch stays finite
    w_m = torch.minimum(1.0 - w, thresh_mirror)
    log_tail_direct = _log_betainc(a, b, w_d)  # log I_w(a, b)
    head_mirror = _log_betainc(b, a, w_m).exp()  # I_{1-w}(b, a) = 1 - I_w(a, b)
    log_tail = torch.where(direct, log_tail_direct, torch.log1p(-head_mirror.clamp(max=1.0)))
    log_half_tail = log_tail - math.log(2.0)  # log P(T > |x|)
    out = torch.where(x64 < 0, log_half_tail, torch.log1p(-log_half_tail.exp()))
    return out.to(dtype)


def student_t_cdf(x: Tensor, df: Tensor) -> Tensor:
    """CDF of the standard Student-t, ``exp(student_t_log_cdf(x, df))``. Shapes: as that."""
    return student_t_log_cdf(x, df).exp()


# -- Gamma sampling --------------------------------------------------------------------------------
def sample_gamma(shape_param: Tensor, rate: Tensor, sample_shape=(),
                 generator: torch.Generator | None = None) -> Tensor:
    """``Ga(shape, rate)`` samples (mean ``shape / rate``) with an explicit generator.

    Shapes:
        shape_param, rate: broadcastable ``(*B,)`` -> ``(*sample_shape, *B)``
    """
    a, b = torch.broadcast_tensors(shape_param, rate)
    a = a.expand(*sample_shape, *a.shape).contiguous()
    return torch._standard_gamma(a, generator=generator) / b


def skew_t_mean_factor(df: Tensor) -> Tensor:
    r"""``c(nu) = E[u] = sqrt(nu/pi) Gamma((nu-1)/2) / Gamma(nu/2)`` (finite for ``nu > 1``).

    Shapes:
        df: ``(*B,)`` -> ``(*B,)``
    """
    return torch.exp(0.5 * torch.log(df / math.pi) + torch.lgamma(0.5 * (df - 1.0)) - torch.lgamma(0.5 * df))


def _check_df(df: Tensor) -> None:
    if bool((df.detach() <= 0).any()):
        raise ValueError("df: degrees of freedom must be positive")


# -- multivariate Student-t ------------------------------------------------------------------------
class MultivariateStudentT(Distribution):
    r"""Multivariate Student-t ``t_m(loc, scale, df)`` (scale matrix, not covariance).

    ``e = loc + L n / sqrt(lam)``, ``n ~ N(0, I)``, ``lam ~ Ga(df/2, df/2)``; covariance
    ``df/(df - 2) scale`` for ``df > 2``.

    Args:
        loc: ``(*B, m)``.
        scale: scale matrix ``(*B, m, m)`` (symmetric positive definite).
        df: degrees of freedom ``(*B,)`` or a number (``> 0``, finite).
        validate_args: accepted for ``torch.distributions`` compatibility; the arguments are
            always checked at construction (and ``log_prob``/``sample`` never validate).

    Shapes:
        sample: ``(*sample_shape, *B, m)``; log_prob: ``value (*S, *B, m)`` -> ``(*S, *B)``

    Examples:
        >>> d = MultivariateStudentT(torch.zeros(2), torch.eye(2), 5.0)
        >>> d.sample((3,), generator=torch.Generator().manual_seed(0)).shape
        torch.Size([3, 2])
    """

    arg_constraints: ClassVar[dict] = {}
    has_rsample = False

    @entry_point(loc=Finite(check=False), scale=Cov(definite=True, check=False),
                 df=Real(positive=True, tensor=True), validate_args=Flag(optional=True))
    def __init__(self, loc, scale, df, validate_args=None):
        loc = as_tensor(loc, "loc")
        scale = as_tensor(scale, "scale", dtype=loc.dtype, device=loc.device)
        df = as_tensor(df, "df", dtype=loc.dtype, device=loc.device)
        if loc.dim() < 1 or scale.shape[-2:] != (loc.shape[-1], loc.shape[-1]):
            m = loc.shape[-1]
            raise ValueError(f"scale: expected (*B, {m}, {m}), got {tuple(scale.shape)}")
        _check_df(df)
        value = scale.detach()
        size = value.abs().amax(dim=(-1, -2), keepdim=True)
        if bool(((value - value.mT).abs() > SYMMETRY_RTOL * size).any()):
            raise ValueError("scale: must be symmetric positive definite (it is not symmetric)")
        chol, info = torch.linalg.cholesky_ex(scale)
        if bool((info != 0).any()):
            raise ValueError("scale: must be symmetric positive definite")
        batch = broadcast_shape(loc.shape[:-1], scale.shape[:-2], df.shape)
        m = loc.shape[-1]
        self.loc = loc.expand(*batch, m)
        self.scale_matrix = scale.expand(*batch, m, m)
        self.scale_tril = chol.expand(*batch, m, m)
        self.df = df.expand(batch)
        super().__init__(batch, torch.Size([m]), validate_args=False)

    @property
    def mean(self) -> Tensor:
        return torch.where((self.df > 1).unsqueeze(-1), self.loc, torch.nan)

    @property
    def covariance_matrix(self) -> Tensor:
        factor = torch.where(self.df > 2, self.df / (self.df - 2), torch.inf)
        return factor[..., None, None] * self.scale_matrix

    def sample(self, sample_shape=(), generator: torch.Generator | None = None) -> Tensor:
        shape = torch.Size(sample_shape) + self.batch_shape + self.event_shape
        n = torch.randn(shape, dtype=self.loc.dtype, device=self.loc.device, generator=generator)
        lam = sample_gamma(0.5 * self.df, 0.5 * self.df, sample_shape, generator)
        return self.loc + (self.scale_tril @ n.unsqueeze(-1)).squeeze(-1) / lam.sqrt().unsqueeze(-1)

    def log_prob(self, value: Tensor) -> Tensor:
        m = self.event_shape[0]
        diff = (value - self.loc).unsqueeze(-1)
        L = self.scale_tril.expand(*diff.shape[:-2], m, m)
        white = torch.linalg.solve_triangular(L, diff, upper=False).squeeze(-1)
        q = white.square().sum(-1)
        nu = self.df
        half_logdet = self.scale_tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        return (
            torch.lgamma(0.5 * (nu + m)) - torch.lgamma(0.5 * nu) - 0.5 * m * torch.log(nu * math.pi)
            - half_logdet - 0.5 * (nu + m) * torch.log1p(q / nu)
        )


# -- skew-t ----------------------------------------------------------------------------------------
def _as_diagonal(value, name: str, like: Tensor) -> Tensor:
    """A per-component parameter given as ``(*B, m)`` or a diagonal ``(*B, m, m)`` matrix."""
    value = as_tensor(value, name, dtype=like.dtype, device=like.device)
    m = like.shape[-1]
    if value.dim() >= 2 and value.shape[-2:] == (m, m):
        off = value - torch.diag_embed(value.diagonal(dim1=-2, dim2=-1))
        if bool((off.detach().abs() > 0).any()) and m > 1:
            raise ValueError(f"{name}: the independent skew-t needs a diagonal matrix")
        value = value.diagonal(dim1=-2, dim2=-1)
    return value


class SkewT(Distribution):
    r"""Skew-t with independent components (paper 004, eqs. (2)-(5); Nurminen et al. 2015/2018).

    Args:
        loc: location ``mu``, ``(*B, m)``.
        scale: spread ``sigma^2`` (variances) as ``(*B, m)`` or a diagonal ``R (*B, m, m)``.
        skewness: ``delta`` as ``(*B, m)`` or a diagonal ``Delta (*B, m, m)``.
        df: ``nu`` as a number, ``(*B,)`` or ``(*B, m)`` (``> 0``, finite).
        validate_args: accepted for ``torch.distributions`` compatibility; the arguments are
            always checked at construction.

    Moments (``nu > 2``): ``E[e_i] = mu_i + c(nu_i) delta_i`` with
    :func:`skew_t_mean_factor`, ``Var[e_i] = nu_i/(nu_i - 2) (sigma_i^2 + delta_i^2) -
    (c(nu_i) delta_i)^2``, no cross-covariance.

    Shapes:
        sample: ``(*sample_shape, *B, m)``; log_prob: ``value (*S, *B, m)`` -> ``(*S, *B)``

    Examples:
        >>> d = SkewT(torch.zeros(2), torch.full((2,), 4.0), torch.full((2,), 1.0), 10.0)
        >>> e = d.sample((1000,), generator=torch.Generator().manual_seed(0))
        >>> e.shape, d.log_prob(e).shape
        (torch.Size([1000, 2]), torch.Size([1000]))
    """

    arg_constraints: ClassVar[dict] = {}
    has_rsample = False

    @entry_point(loc=Finite(check=False), scale=Finite(check=False), skewness=Finite(check=False),
                 df=Real(positive=True, tensor=True), validate_args=Flag(optional=True))
    def __init__(self, loc, scale, skewness, df, validate_args=None):
        loc = as_tensor(loc, "loc")
        if loc.dim() < 1:
            raise ValueError(f"loc: expected shape (*B, m), got {tuple(loc.shape)}")
        scale = _as_diagonal(scale, "scale", loc)
        skewness = _as_diagonal(skewness, "skewness", loc)
        df = as_tensor(df, "df", dtype=loc.dtype, device=loc.device)
        m = loc.shape[-1]
        if df.dim() == 0 or df.shape[-1] != m:
            df = df.unsqueeze(-1)
        if bool((scale.detach() <= 0).any()):
            raise ValueError("scale: spread parameters must be positive")
        _check_df(df)
        shape = broadcast_shape(loc.shape, scale.shape, skewness.shape, df.shape)
        if shape[-1] != m:
            raise ValueError(f"scale/skewness/df: do not broadcast with loc of size {m}")
        self.loc, self.scale, self.skewness, self.df = (t.expand(shape) for t in (loc, scale, skewness, df))
        super().__init__(shape[:-1], shape[-1:], validate_args=False)

    @property
    def mean(self) -> Tensor:
        c = torch.where(self.df > 1, skew_t_mean_factor(self.df.clamp_min(1.0 + 1e-12)), torch.nan)
        return self.loc + c * self.skewness

    @property
    def variance(self) -> Tensor:
        nu = self.df
        c = skew_t_mean_factor(nu.clamp_min(1.0 + 1e-12))
        var = nu / (nu - 2) * (self.scale + self.skewness.square()) - (c * self.skewness).square()
        return torch.where(nu > 2, var, torch.inf)

    @property
    def covariance_matrix(self) -> Tensor:
        return torch.diag_embed(self.variance)

    def sample(self, sample_shape=(), generator: torch.Generator | None = None) -> Tensor:
        shape = torch.Size(sample_shape) + self.batch_shape + self.event_shape
        kw = {"dtype": self.loc.dtype, "device": self.loc.device, "generator": generator}
        lam = sample_gamma(0.5 * self.df, 0.5 * self.df, sample_shape, generator)
        u = torch.randn(shape, **kw).abs() / lam.sqrt()
        n = torch.randn(shape, **kw)
        return self.loc + self.skewness * u + self.scale.sqrt() * n / lam.sqrt()

    def log_prob(self, value: Tensor) -> Tensor:
        e = value - self.loc
        nu, r, d = self.df, self.scale, self.skewness
        omega = r + d.square()  # delta^2 + sigma^2
        log_t = (
            torch.lgamma(0.5 * (nu + 1)) - torch.lgamma(0.5 * nu) - 0.5 * torch.log(nu * math.pi * omega)
            - 0.5 * (nu + 1) * torch.log1p(e.square() / (nu * omega))
        )
        arg = e * d / r.sqrt() * torch.sqrt((nu + 1) / (nu * omega + e.square()))
        return (math.log(2.0) + log_t + student_t_log_cdf(arg, nu + 1)).sum(-1)

"""Noise distributions: Student-t / skew-t sampling and densities, truncated-normal moments.

References are independent: scipy (t, multivariate_t, norm, truncnorm), mpmath at 50 digits, and
1-D quadrature of the skew-t hierarchy (14)-(16) over the mixing variable.
"""

from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest
import torch
from scipy import integrate, stats

from torchmm.distributions import (
    MultivariateStudentT,
    SkewT,
    sample_gamma,
    skew_t_mean_factor,
    student_t_log_cdf,
    truncated_normal_entropy,
    truncated_normal_moments,
)

mpmath.mp.dps = 50


def _mp_truncnorm(mu: float, s: float) -> tuple[float, float]:
    """Mean and variance of N(mu, s^2) on [0, inf) with 50-digit arithmetic."""
    mu, s = mpmath.mpf(mu), mpmath.mpf(s)
    a = -mu / s
    z = mpmath.erfc(a / mpmath.sqrt(2)) / 2
    lam = mpmath.npdf(a) / z
    return float(mu + s * lam), float(s**2 * (1 - lam * (lam - a)))


# -- truncated normal ----------------------------------------------------------------------------
@pytest.mark.parametrize("alpha", [-30.0, -5.0, -1.0, 0.0, 0.5, 3.0, 8.0, 20.0, 29.9, 30.1, 45.0, 300.0, 1e4])
def test_truncated_normal_moments_match_mpmath(alpha):
    s = 2.5
    mu = -alpha * s
    mean, var = truncated_normal_moments(torch.tensor(mu), torch.tensor(s))
    ref_mean, ref_var = _mp_truncnorm(mu, s)
    assert mean.item() == pytest.approx(ref_mean, rel=1e-9, abs=1e-12)
    assert var.item() == pytest.approx(ref_var, rel=1e-8)


def test_truncated_normal_naive_formula_breaks_but_ours_does_not():
    mu = torch.tensor([-40.0, -200.0])
    naive = torch.distributions.Normal(0.0, 1.0)
    alpha = -mu
    lam_naive = naive.log_prob(alpha).exp() / (1 - naive.cdf(alpha))
    assert not torch.isfinite(lam_naive).all()  # 0/0: why the stable form exists
    mean, var = truncated_normal_moments(mu, torch.ones(2))
    assert torch.isfinite(mean).all() and torch.isfinite(var).all() and (var > 0).all()


def test_truncated_normal_float32_is_computed_in_float64():
    mu, s = torch.tensor([-10.0, -15.0, 2.0]), torch.tensor([1.0, 1.0, 1.0])
    m32, v32 = truncated_normal_moments(mu.float(), s.float())
    m64, v64 = truncated_normal_moments(mu, s)
    assert m32.dtype == torch.float32
    torch.testing.assert_close(v32.double(), v64, rtol=1e-6, atol=0)
    torch.testing.assert_close(m32.double(), m64, rtol=1e-6, atol=0)


@pytest.mark.parametrize("mu", [-6.0, -1.0, 0.0, 2.0, 30.0])
def test_truncated_normal_entropy_matches_quadrature(mu):
    s = 1.7
    dist = stats.truncnorm(-mu / s, np.inf, loc=mu, scale=s)
    lo, hi = 0.0, max(mu, 0.0) + 40 * s
    ref, _ = integrate.quad(lambda x: -dist.pdf(x) * dist.logpdf(x) if dist.pdf(x) > 0 else 0.0, lo, hi,
                            points=[max(mu, 0.0)], limit=400)
    got = truncated_normal_entropy(torch.tensor(mu), torch.tensor(s)).item()
    assert got == pytest.approx(ref, abs=1e-6)


def _mp_truncnorm_entropy(mu: float, s: float):
    """Entropy of N(mu, s^2) on [0, inf) with 50-digit arithmetic (an mpmath number)."""
    mu, s = mpmath.mpf(mu), mpmath.mpf(s)  # (no-ops on mpf arguments)
    a = -mu / s
    z = mpmath.erfc(a / mpmath.sqrt(2)) / 2
    lam = mpmath.npdf(a) / z
    return mpmath.log(mpmath.sqrt(2 * mpmath.pi * mpmath.e) * s * z) + a * lam / 2


@pytest.mark.parametrize("ratio", [-1e4, -100.0, -40.0, -38.0, -20.0, -3.0, 0.0, 4.0, 37.0, 38.0, 40.0, 100.0,
                                   1e4])
def test_truncated_normal_entropy_is_finite_and_matches_references_in_both_tails(ratio):
    """loc / scale from -1e4 to 1e4 (erfcx overflowed to +inf from loc/scale ~ 37.7 on): scipy's
    truncnorm entropy where it is finite, else quadrature of scipy's (log-space) truncnorm logpdf,
    and mpmath at 50 digits everywhere."""
    s = 1.7
    mu = ratio * s
    got = truncated_normal_entropy(torch.tensor(mu), torch.tensor(s)).item()
    assert math.isfinite(got)
    assert got == pytest.approx(float(_mp_truncnorm_entropy(mu, s)), rel=1e-10, abs=1e-12)
    dist = stats.truncnorm(-ratio, np.inf, loc=mu, scale=s)
    with np.errstate(all="ignore"):
        ref = float(dist.entropy())
    if not math.isfinite(ref) and abs(ratio) <= 100:  # scipy's closed form fails in the tails
        width = s / max(-ratio, 1.0)  # the support's scale: s, or s / alpha far in the lower tail
        lo, hi = 0.0, max(mu, 0.0) + 40 * width
        ref, _ = integrate.quad(lambda x: -math.exp(dist.logpdf(x)) * dist.logpdf(x), lo, hi,
                                points=[max(mu, 0.0) + width], limit=400)
    if math.isfinite(ref):
        assert got == pytest.approx(ref, abs=1e-7)


@pytest.mark.parametrize("ratio", [-1e4, -100.0, -40.0, -2.0, 0.5, 40.0, 100.0, 1e4])
def test_truncated_normal_gradients_are_finite_and_match_mpmath(ratio):
    """d/d(loc) and d/d(scale) of the mean, variance and entropy against mpmath's numerical
    derivatives (the erfcx form gave NaN gradients from loc/scale ~ 37 on)."""
    s0 = 1.3
    mu0 = ratio * s0
    loc = torch.tensor(mu0, requires_grad=True)
    scale = torch.tensor(s0, requires_grad=True)
    mean, var = truncated_normal_moments(loc, scale)
    outs = {"mean": mean, "var": var, "entropy": truncated_normal_entropy(loc, scale)}
    def mp_moments(m, s):  # 50 digits, unrounded (mpmath.diff differentiates it numerically)
        a = -m / s
        lam = mpmath.npdf(a) / (mpmath.erfc(a / mpmath.sqrt(2)) / 2)
        return m + s * lam, s**2 * (1 - lam * (lam - a))

    refs = {"mean": lambda m, s: mp_moments(m, s)[0], "var": lambda m, s: mp_moments(m, s)[1],
            "entropy": _mp_truncnorm_entropy}
    for name, out in outs.items():
        g_loc, g_scale = torch.autograd.grad(out, (loc, scale), retain_graph=True)
        f = refs[name]
        for got, ref in ((g_loc, mpmath.diff(lambda m: f(m, mpmath.mpf(s0)), mpmath.mpf(mu0))),
                         (g_scale, mpmath.diff(lambda s: f(mpmath.mpf(mu0), s), mpmath.mpf(s0)))):
            assert math.isfinite(got.item()), name
            assert got.item() == pytest.approx(float(ref), rel=1e-6, abs=1e-12), name


# -- Student-t CDF ---------------------------------------------------------------------------------
def _mp_t_log_cdf(x: float, df: float) -> float:
    df = mpmath.mpf(df)
    tail = mpmath.betainc(df / 2, mpmath.mpf(1) / 2, 0, df / (df + mpmath.mpf(x) ** 2), regularized=True) / 2
    return float(mpmath.log(tail if x < 0 else 1 - tail))


@pytest.mark.parametrize("df", [0.7, 1.0, 3.0, 11.0, 21.0, 300.0])
def test_student_t_log_cdf_matches_mpmath_and_scipy(df):
    x = np.array([-1e3, -60.0, -8.0, -2.0, -0.3, 0.0, 0.4, 1.5, 6.0, 50.0])
    got = student_t_log_cdf(torch.tensor(x), torch.tensor(df)).numpy()
    ref = np.array([_mp_t_log_cdf(v, df) for v in x])
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)
    ok = np.isfinite(stats.t.logcdf(x, df))  # scipy underflows to -inf far in the tail
    np.testing.assert_allclose(got[ok], stats.t.logcdf(x, df)[ok], rtol=1e-9, atol=1e-12)


# -- multivariate Student-t --------------------------------------------------------------------------
def test_multivariate_student_t_log_prob_matches_scipy():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3))
    scale = A @ A.T + 0.5 * np.eye(3)
    loc = rng.normal(size=3)
    x = rng.normal(size=(7, 3)) * 3
    d = MultivariateStudentT(torch.tensor(loc), torch.tensor(scale), 4.5)
    ref = stats.multivariate_t(loc, scale, df=4.5).logpdf(x)
    np.testing.assert_allclose(d.log_prob(torch.tensor(x)).numpy(), ref, rtol=1e-10)


def test_multivariate_student_t_sample_moments(generator):
    scale = torch.tensor([[2.0, 0.6], [0.6, 1.0]])
    d = MultivariateStudentT(torch.tensor([1.0, -2.0]), scale, 7.0)
    e = d.sample((400_000,), generator=generator)
    assert e.shape == (400_000, 2)
    se = (d.covariance_matrix.diagonal() / e.shape[0]).sqrt()
    assert ((e.mean(0) - d.mean).abs() < 5 * se).all()
    torch.testing.assert_close(torch.cov(e.T), d.covariance_matrix, rtol=0.03, atol=0.0)


# -- skew-t --------------------------------------------------------------------------------------------
def test_skew_t_mean_factor_matches_half_t_mean():
    nu = 9.0
    # E[u] with u = |n| / sqrt(lam): sqrt(2/pi) E[lam^-1/2]
    ref, _ = integrate.quad(lambda lam: lam**-0.5 * stats.gamma(nu / 2, scale=2 / nu).pdf(lam), 0, np.inf)
    expected = math.sqrt(2 / math.pi) * ref
    assert skew_t_mean_factor(torch.tensor(nu)).item() == pytest.approx(expected, rel=1e-8)


@pytest.mark.parametrize("params", [(2500.0, 9.0, 20.0), (4.0, -3.0, 6.0), (1.0, 0.0, 12.0)])
def test_skew_t_sampler_mean_and_covariance_match_closed_forms(params, generator):
    r, delta, nu = params
    d = SkewT(torch.tensor([5.0, -1.0]), torch.full((2,), r), torch.full((2,), delta), nu)
    e = d.sample((400_000,), generator=generator)
    n = e.shape[0]
    se = (d.variance / n).sqrt()
    assert ((e.mean(0) - d.mean).abs() < 5 * se).all(), (e.mean(0), d.mean)
    cov = torch.cov(e.T)
    torch.testing.assert_close(cov.diagonal(), d.variance, rtol=0.04, atol=0.0)
    assert cov[0, 1].abs() < 5 * d.variance.prod().sqrt() / math.sqrt(n) * 2  # independent axes


def test_skew_t_delta_zero_is_student_t_and_nu_inf_is_gaussian():
    x = torch.linspace(-30, 30, 41).reshape(-1, 1).expand(-1, 2) * torch.tensor([1.0, 0.5])
    r = torch.tensor([4.0, 9.0])
    d = SkewT(torch.zeros(2), r, torch.zeros(2), 5.0)
    ref = stats.t.logpdf(x.numpy(), 5.0, scale=r.sqrt().numpy()).sum(-1)
    np.testing.assert_allclose(d.log_prob(x).numpy(), ref, rtol=1e-10)
    small = SkewT(torch.zeros(2), r, torch.full((2,), 1e-7), 5.0)
    np.testing.assert_allclose(small.log_prob(x).numpy(), ref, rtol=1e-6)
    gauss = SkewT(torch.zeros(2), r, torch.zeros(2), 1e9)
    ref_n = stats.norm.logpdf(x.numpy(), scale=r.sqrt().numpy()).sum(-1)
    np.testing.assert_allclose(gauss.log_prob(x).numpy(), ref_n, rtol=1e-6)


def _skew_t_pdf_by_quadrature(e: float, r: float, delta: float, nu: float) -> float:
    """Integrate the skew-normal given lambda (the hierarchy (14)-(16)) over lam ~ Ga(nu/2, nu/2)."""
    omega = r + delta**2
    alpha = delta / math.sqrt(r)

    def integrand(lam):
        w = omega / lam
        return 2 * stats.norm.pdf(e, scale=math.sqrt(w)) * stats.norm.cdf(alpha * e / math.sqrt(w)) * \
            stats.gamma(nu / 2, scale=2 / nu).pdf(lam)

    val, _ = integrate.quad(integrand, 0, np.inf, limit=400)
    return val


@pytest.mark.parametrize("e", [-40.0, -5.0, 0.0, 3.0, 25.0, 120.0])
def test_skew_t_log_prob_matches_hierarchy_quadrature(e):
    r, delta, nu = 25.0, 9.0, 4.0
    d = SkewT(torch.zeros(1), torch.tensor([r]), torch.tensor([delta]), nu)
    got = d.log_prob(torch.tensor([[e]])).item()
    assert got == pytest.approx(math.log(_skew_t_pdf_by_quadrature(e, r, delta, nu)), abs=1e-7)


def test_skew_t_density_integrates_to_one():
    d = SkewT(torch.zeros(1), torch.tensor([2.0]), torch.tensor([-3.0]), 3.5)
    theta = np.linspace(-np.pi / 2, np.pi / 2, 40_001)[1:-1]  # e = 3 tan(theta): the tails in one grid
    e = 3 * np.tan(theta)
    dens = d.log_prob(torch.tensor(e).unsqueeze(-1)).exp().numpy() * 3 / np.cos(theta) ** 2
    assert integrate.simpson(dens, x=theta) == pytest.approx(1.0, abs=1e-6)


def test_skew_t_accepts_diagonal_matrices_and_rejects_bad_input():
    d = SkewT(torch.zeros(2), 4.0 * torch.eye(2), torch.diag(torch.tensor([1.0, 2.0])), 5.0)
    assert d.batch_shape == () and d.event_shape == (2,)
    with pytest.raises(ValueError, match="skewness"):
        SkewT(torch.zeros(2), torch.ones(2), torch.ones(2, 2), 5.0)
    with pytest.raises(ValueError, match="df"):
        SkewT(torch.zeros(2), torch.ones(2), torch.ones(2), 0.0)
    with pytest.raises(ValueError, match="scale"):
        SkewT(torch.zeros(2), torch.tensor([1.0, -1.0]), torch.ones(2), 3.0)
    with pytest.raises(ValueError, match="df"):
        MultivariateStudentT(torch.zeros(2), torch.eye(2), -1.0)


def test_skew_t_batch_shapes_and_float32(generator):
    d = SkewT(torch.zeros(3, 2, dtype=torch.float32), torch.ones(2, dtype=torch.float32),
              torch.ones(2, dtype=torch.float32), torch.tensor(6.0, dtype=torch.float32))
    e = d.sample((5,), generator=generator)
    assert e.shape == (5, 3, 2) and e.dtype == torch.float32
    lp = d.log_prob(e)
    assert lp.shape == (5, 3) and torch.isfinite(lp).all()


def test_sample_gamma_uses_the_rate(generator):
    x = sample_gamma(torch.tensor(3.0), torch.tensor(6.0), (200_000,), generator)
    assert x.mean().item() == pytest.approx(0.5, rel=0.01)

r"""Monte Carlo uncertainty of the studies' figures.

**Average RMSE** (the papers' figure): ``A = (1/T) sum_t sqrt(m_t)`` with ``m_t = (1/N) sum_r e_{t,r}``
the mean squared error of step ``t`` over the ``N`` runs. Runs are independent, so by the delta
method (the root of a mean: linearise ``sqrt`` at ``m_t``)

.. math::
    \operatorname{se}(A) = \frac{\operatorname{sd}_r(h_r)}{\sqrt N},\qquad
    h_r = \sum_t \frac{e_{t,r}}{2 T \sqrt{m_t}},

which accounts for the correlation of a run's errors over time. For iid errors of variance
``sigma^2`` it is ``sigma / sqrt(2 N T)`` (tests/experiments/test_uncertainty.py checks both that
and the spread over repeated experiments). A 95 % interval is ``A +- 1.96 se``.

**RMSE of one step** (the curves' bands): ``sqrt(m_t)`` has, by the same linearisation,

.. math::
    \operatorname{se}(\sqrt{m_t}) = \frac{\operatorname{sd}_r(e_{t,r})}{2 \sqrt{m_t} \sqrt N},

:func:`rmse_se_per_step`; for iid errors of variance ``sigma^2`` (scalar, ``e = x^2``) it is
``sigma / sqrt(2 N)``. A step whose errors are all zero (a deterministic start) gets 0.

**NEES**: with ``N`` runs and an ``n``-dimensional state, ``N`` times the average NEES of a step is
``chi^2(N n)`` for a consistent filter; :func:`chi2_interval` gives the two-sided bounds of the
average (the exact chi-square quantiles, ``scipy.stats.chi2.ppf``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["armse_influence", "armse_se", "chi2_interval", "inside", "mean_se_per_step", "nees_consistency", "rmse_se_per_step"]

#: two-sided 95 % normal quantile
Z95 = 1.959963984540054


def armse_se(sq_err: Tensor) -> float:
    """Delta-method standard error of the average RMSE from squared errors ``(T, N)`` (step, run)."""
    T, N = sq_err.shape
    if N < 2:
        return float("nan")
    m = sq_err.mean(1)  # (T,)
    weight = 1.0 / (2 * T * m.clamp_min(torch.finfo(m.dtype).tiny).sqrt())
    h = (sq_err * weight.unsqueeze(1)).sum(0)  # (N,)
    return float(h.std(unbiased=True) / math.sqrt(N))


def armse_influence(sq: Tensor) -> tuple[float, Tensor, Tensor]:
    """ARMSE of squared errors ``(T, N)`` with NaN where a step of a run is not scored (padding,
    missing truth), its per-run influence values ``(N,)`` (the delta method: ARMSE ~ const + mean_r h_r
    over the ``N'`` runs with a scored step, so ``sd(h) / sqrt(N')`` is :func:`armse_se`'s standard error,
    and paired differences of estimators are differences of their ``h``; NaN for a run without any scored
    step: it is no run of the ARMSE), and the per-step RMSE ``(T,)``."""
    ok = torch.isfinite(sq)
    n_t = ok.sum(1).clamp_min(1)
    m = torch.where(ok, sq, 0.0).sum(1) / n_t
    steps = (ok.sum(1) > 0)
    T = int(steps.sum())
    w = torch.where(steps, 1.0 / (2 * T * m.clamp_min(torch.finfo(m.dtype).tiny).sqrt()), 0.0)
    scored = ok.any(0)  # (N,) the runs with a scored step
    N = int(scored.sum())
    h = (torch.where(ok, sq - m.unsqueeze(1), 0.0) * (w * N / n_t).unsqueeze(1)).sum(0)  # (N,)
    h = torch.where(scored, h, torch.nan)
    return float(m[steps].sqrt().mean()), h, m.sqrt()


def rmse_se_per_step(sq_err: Tensor) -> Tensor:
    """Delta-method standard error of each step's RMSE from squared errors ``(T, N)`` (step, run): ``(T,)``.

    ``sd_r(e_t) / (2 sqrt(m_t) sqrt(N))`` with ``m_t`` the step's mean squared error (module docstring);
    NaN for one run, 0 where every run's error is 0. A 95 % band is ``rmse_t +- 1.96 se_t``. A NaN entry
    (a padded step, missing truth) is no run of its step: ``N``, ``m_t`` and ``sd`` are over the step's
    ``N_t`` finite entries (NaN where ``N_t < 2``).
    """
    T, N = sq_err.shape
    ok = torch.isfinite(sq_err)
    if not bool(ok.all()):
        n_t = ok.sum(1)
        m = torch.where(ok, sq_err, 0.0).sum(1) / n_t.clamp_min(1)
        var = torch.where(ok, sq_err - m.unsqueeze(1), 0.0).square().sum(1) / (n_t - 1).clamp_min(1)
        se = var.sqrt() / (2 * m.clamp_min(torch.finfo(m.dtype).tiny).sqrt() * n_t.clamp_min(1).sqrt())
        return torch.where(n_t > 1, se, torch.nan)
    if N < 2:
        return torch.full((T,), float("nan"), dtype=sq_err.dtype, device=sq_err.device)
    m = sq_err.mean(1)
    sd = sq_err.std(1, unbiased=True)
    return sd / (2 * m.clamp_min(torch.finfo(m.dtype).tiny).sqrt() * math.sqrt(N))


def mean_se_per_step(sums, sq_sums, runs: int) -> Tensor:
    """Standard error ``sd_r(x_t) / sqrt(N)`` of each step's mean over ``N`` runs, from the per-step
    sums over the runs of the values and of their squares (``sd`` with the ``N - 1`` divisor), float64,
    the shape of ``sums``; NaN for one run. A 95 % band is ``mean_t +- 1.96 se_t``."""
    sums = torch.as_tensor(sums).to(torch.float64)
    sq_sums = torch.as_tensor(sq_sums).to(torch.float64)
    if runs < 2:
        return torch.full_like(sums, float("nan"))
    var = (sq_sums - sums.square() / runs).clamp_min(0) / (runs - 1)
    return (var / runs).sqrt()


def chi2_interval(dof: int, level: float = 0.95) -> tuple[float, float]:
    """Bounds ``(lo, hi)`` with ``P(lo <= chi^2(dof) / dof <= hi) = level``, equal tails: the exact
    quantiles ``chi2.ppf((1 -+ level) / 2, dof) / dof`` (scipy; the Wilson-Hilferty approximation used before
    was off by half at ``dof = 2``)."""
    from scipy.stats import chi2

    if dof <= 0:
        raise ValueError(f"dof: {dof!r} is not positive")
    tail = (1.0 - level) / 2.0
    return float(chi2.ppf(tail, dof)) / dof, float(chi2.ppf(1.0 - tail, dof)) / dof


def nees_consistency(nees: Tensor, runs: int, state_dim: int, level: float = 0.95) -> tuple[float, float, float]:
    """``(low, high, steps_inside)``: the ``level`` chi-square interval of a step's run-averaged NEES
    (``chi^2(N n) / N``) and the fraction of the steps of ``nees (T,)`` inside it (``level`` for a
    consistent filter)."""
    lo, hi = chi2_interval(runs * state_dim, level)
    lo, hi = lo * state_dim, hi * state_dim
    nees = torch.as_tensor(nees, dtype=torch.float64)
    return lo, hi, ((nees >= lo) & (nees <= hi)).double().mean().item()


def inside(value: float, estimate: float, se: float, z: float = Z95) -> bool | None:
    """Whether ``value`` (e.g. a published figure) lies inside ``estimate +- z se`` (None if unknown)."""
    if value is None or estimate is None or se is None or not math.isfinite(se):
        return None
    return abs(value - estimate) <= z * se

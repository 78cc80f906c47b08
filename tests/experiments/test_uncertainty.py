"""Monte Carlo uncertainty: the delta-method SE of the average RMSE and the NEES chi-square interval."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from experiments.uncertainty import armse_se, chi2_interval, inside, rmse_se_per_step


def test_armse_se_matches_theory_for_iid_errors_and_the_spread_over_experiments():
    """iid N(0, sigma^2) scalar errors: se(A) = sigma / sqrt(2 N T); and the delta-method SE of one
    experiment matches the standard deviation of A over many independent experiments."""
    g = torch.Generator().manual_seed(0)
    sigma, T, N, experiments = 3.0, 50, 200, 400
    e = sigma * torch.randn(experiments, T, N, generator=g, dtype=torch.float64)
    sq = e.square()
    averages = sq.mean(2).sqrt().mean(1)  # A per experiment
    ses = torch.tensor([armse_se(sq[i]) for i in range(experiments)])
    theory = sigma / math.sqrt(2 * N * T)
    assert ses.mean().item() == pytest.approx(theory, rel=0.03)
    assert averages.std().item() == pytest.approx(theory, rel=0.1)  # 400 experiments: ~3.5 % sampling error
    # coverage of A +- 1.96 se around the true value (sigma, to O(1/N)) is near 95 %
    truth = sigma * (1 - 1 / (4 * N))  # E[sqrt(m)] for chi-square m: sigma (1 - 1/(4N) + ...)
    covered = sum(bool(inside(truth, a.item(), s.item())) for a, s in zip(averages, ses)) / experiments
    assert 0.91 <= covered <= 0.99


def test_armse_se_accounts_for_errors_correlated_over_time():
    """A run's error constant over time: the SE is that of one draw per run, sigma / sqrt(2 N)."""
    g = torch.Generator().manual_seed(1)
    sigma, T, N = 2.0, 40, 4000
    per_run = sigma * torch.randn(1, N, generator=g, dtype=torch.float64)
    sq = per_run.expand(T, N).square()
    assert armse_se(sq) == pytest.approx(sigma / math.sqrt(2 * N), rel=0.05)
    assert math.isnan(armse_se(sq[:, :1]))  # one run: no spread to estimate


def test_rmse_se_per_step_matches_theory_and_the_spread_over_experiments():
    """iid N(0, sigma^2) scalar errors: se(rmse_t) = sigma / sqrt(2 N) at every step; and, with a noise
    level varying over the steps (2-D errors, as a position), each step's SE matches the standard
    deviation of that step's RMSE over many independent experiments."""
    g = torch.Generator().manual_seed(2)
    sigma, T, N, experiments = 3.0, 50, 200, 400
    sq = (sigma * torch.randn(experiments, T, N, generator=g, dtype=torch.float64)).square()
    ses = torch.stack([rmse_se_per_step(sq[i]) for i in range(experiments)])  # (experiments, T)
    assert ses.shape == (experiments, T)
    theory = sigma / math.sqrt(2 * N)
    assert ses.mean().item() == pytest.approx(theory, rel=0.03)  # O(1/N) bias of the ratio: ~ -1 %
    spread = sq.mean(2).sqrt().std(0)  # (T,): the spread of each step's RMSE over the experiments
    assert spread.mean().item() == pytest.approx(theory, rel=0.03)

    levels = torch.linspace(0.5, 20.0, T, dtype=torch.float64)  # per-step noise std
    e = levels[:, None, None] * torch.randn(experiments, T, N, 2, generator=g, dtype=torch.float64)
    sq = e.square().sum(-1)  # (experiments, T, N)
    ses = torch.stack([rmse_se_per_step(sq[i]) for i in range(experiments)])
    spread = sq.mean(2).sqrt().std(0)
    ratio = spread / ses.mean(0)  # 400 experiments: ~3.5 % sampling error per step
    assert ratio.mean().item() == pytest.approx(1.0, abs=0.03)
    assert ((ratio - 1).abs() < 0.2).all(), ratio
    # 2-D Gaussian errors: e = sigma^2 chi^2(2), sd(e) = 2 sigma^2, m = 2 sigma^2 -> se = sigma / sqrt(2 N)
    assert (ses.mean(0) / (levels / math.sqrt(2 * N))).sub(1).abs().max().item() < 0.05


def test_rmse_se_per_step_edge_cases():
    sq = torch.zeros(5, 10, dtype=torch.float64)
    sq[3] = torch.arange(10, dtype=torch.float64)
    se = rmse_se_per_step(sq)
    assert se[[0, 1, 2, 4]].eq(0).all() and se[3] > 0  # deterministic steps: no spread
    assert rmse_se_per_step(sq[:, :1]).isnan().all()  # one run: no spread to estimate


def test_rmse_se_per_step_skips_nan_entries():
    """A NaN entry (a padded step) is no run of its step: each step's SE is that of its finite entries
    alone (a float64 NumPy reference), NaN with one left (before: NaN taken as a zero error by the caller)."""
    sq = torch.rand(6, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 3
    sq[2:, 4] = torch.nan
    sq[4:, 1:] = torch.nan
    se = rmse_se_per_step(sq).numpy()
    for t in range(6):
        x = sq[t].numpy()
        x = x[np.isfinite(x)]
        want = x.std(ddof=1) / (2 * np.sqrt(x.mean()) * np.sqrt(len(x))) if len(x) > 1 else np.nan
        np.testing.assert_allclose(se[t], want, rtol=1e-12)
    assert np.isnan(se[4:]).all() and np.isfinite(se[:4]).all()


@pytest.mark.parametrize("dof", [1, 2, 3, 10, 40, 400, 4000])
def test_chi2_interval_against_scipy(dof):
    """The exact quantiles, small dof included (before: Wilson-Hilferty, dof 2: [0.02614, 7.336] for
    [0.05064, 7.378]; dof 1: a lower bound of 0)."""
    lo, hi = chi2_interval(dof)
    want_lo, want_hi = stats.chi2.ppf([0.025, 0.975], dof) / dof
    assert lo == pytest.approx(want_lo, rel=1e-12) and hi == pytest.approx(want_hi, rel=1e-12)


def test_chi2_interval_covers_its_level_by_simulation():
    """An independent check: the fraction of 200000 draws of chi^2(2) / 2 inside the bounds is 95 %."""
    lo, hi = chi2_interval(2)
    x = np.random.default_rng(0).chisquare(2, 200000) / 2
    assert np.mean((x >= lo) & (x <= hi)) == pytest.approx(0.95, abs=0.003)  # (sd 0.0005)
    assert np.mean(x < lo) == pytest.approx(0.025, abs=0.002)


def test_mean_se_per_step_is_sd_over_sqrt_n():
    """The per-step SE of a mean over the runs from sums and sums of squares: sd_r (N - 1) / sqrt(N)."""
    from experiments.uncertainty import mean_se_per_step

    x = torch.randn(7, 11, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)  # (T, N, M)
    se = mean_se_per_step(x.sum(1), x.square().sum(1), 11)
    assert torch.allclose(se, x.std(1) / 11 ** 0.5, rtol=1e-10)
    assert torch.isnan(mean_se_per_step(x[:, :1].sum(1), x[:, :1].square().sum(1), 1)).all()
    assert (mean_se_per_step(torch.full((4,), 6.0), torch.full((4,), 12.0), 3) == 0).all()  # a constant: 0


def test_armse_influence_gives_armse_se_without_gaps_and_skips_nan():
    """armse_influence: sd(h)/sqrt(N) is armse_se's standard error when every entry is scored; a NaN entry
    (a padded step) leaves the ARMSE that of the scored entries."""
    import math

    import torch

    from experiments.uncertainty import armse_influence, armse_se

    sq = torch.rand(20, 30, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 4
    value, h, per_step = armse_influence(sq)
    assert value == pytest.approx(float(sq.mean(1).sqrt().mean()), rel=1e-14)
    assert float(h.std() / math.sqrt(30)) == pytest.approx(armse_se(sq), rel=1e-12)
    gappy = sq.clone()
    gappy[19, 3] = torch.nan
    value, _, per_step = armse_influence(gappy)
    kept = torch.cat([sq[19, :3], sq[19, 4:]])
    assert float(per_step[19]) == pytest.approx(float(kept.mean().sqrt()), rel=1e-14)

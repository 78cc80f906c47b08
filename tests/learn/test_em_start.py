"""EM's start belief over several series (torchmm.learn.em): with shared parameters a start broadcast over
the series (``belief0.expand(S)``) is one start for all of them, as torchmm.learn.estimate holds it, so
EM's fixed point is that model's maximum-likelihood estimate, whatever the order of the series and their
padding; ``per_series=True`` keeps one start per series."""

from __future__ import annotations

import pytest
import torch

from torchmm import GaussianBelief, KalmanFilter
from torchmm.learn import em, estimate
from torchmm.models import LinearMeasurement, LinearMotion

F64 = torch.float64
LENGTHS = [60, 45, 30, 50]
NAMES = ["Q", "R", "initial_mean", "initial_cov"]


def _series(seed=5):
    """Four local-level series of different lengths (NaN padding after each one's end), their start
    levels spread (so the start's variance is identified and away from 0)."""
    g = torch.Generator().manual_seed(seed)
    S, T = len(LENGTHS), max(LENGTHS)
    level0 = 10 + 5 * torch.randn(S, dtype=F64, generator=g)
    x = level0 + (0.7 * torch.randn(T, S, dtype=F64, generator=g)).cumsum(0)
    y = (x + 1.5 * torch.randn(T, S, dtype=F64, generator=g)).unsqueeze(-1)
    present = torch.arange(T).unsqueeze(-1) < torch.tensor(LENGTHS)
    return torch.where(present.unsqueeze(-1), y, torch.nan), present


def _local_level():
    one = torch.ones(1, 1, dtype=F64)
    return KalmanFilter(LinearMotion(one.clone(), one.clone()), LinearMeasurement(one.clone(), one.clone()))


def _start(S):
    return GaussianBelief(torch.zeros(1, dtype=F64), 10 * torch.ones(1, 1, dtype=F64)).expand(S)


def _em(y, present, **kwargs):
    kf = _local_level()
    out = em(kf, _start(y.shape[1]), y, NAMES, iterations=3000, tol=1e-13, present=present, progress=False,
             **kwargs)
    return kf, out


def test_a_shared_start_is_the_maximum_likelihood_start_whatever_the_order():
    y, present = _series()
    kf, out = _em(y, present)
    assert out.converged and out.monotone
    assert out.belief0.mean.shape == (4, 1) and bool((out.belief0.mean == out.belief0.mean[0]).all())
    assert bool((out.belief0.cov == out.belief0.cov[0]).all())
    # the maximum likelihood of the same model (one start for every series: estimate's expanded start)
    mle = estimate(_local_level(), _start(4), y, {"motion.Q": "variance", "measurement.R": "variance",
                                                  "belief0.mean": "free", "belief0.cov": "variance"},
                   update_first=True, progress=False, se=False)
    assert mle.converged
    got = [kf.motion.Q.item(), kf.measurement.R.item(), out.belief0.mean[0, 0].item(),
           out.belief0.cov[0, 0, 0].item()]
    assert got == pytest.approx(mle.estimates, rel=2e-5)
    assert out.loglik[-1] == pytest.approx(mle.loglik, abs=1e-6)
    # the series in another order (their padding with them), and other values in the padding: the same numbers
    order = [2, 0, 3, 1]
    kf2, out2 = _em(y[:, order], present[:, order])
    assert out2.loglik[-1] == pytest.approx(out.loglik[-1], rel=1e-12)
    assert out2.belief0.mean[0].item() == pytest.approx(out.belief0.mean[0].item(), rel=1e-10)
    assert out2.belief0.cov[0].item() == pytest.approx(out.belief0.cov[0].item(), rel=1e-10)
    assert kf2.motion.Q.item() == pytest.approx(kf.motion.Q.item(), rel=1e-10)
    kf3, out3 = _em(torch.where(present.unsqueeze(-1), y, 1e3), present)
    assert out3.loglik[-1] == pytest.approx(out.loglik[-1], rel=1e-12)
    assert out3.belief0.mean[0].item() == pytest.approx(out.belief0.mean[0].item(), rel=1e-10)
    assert out3.belief0.cov[0].item() == pytest.approx(out.belief0.cov[0].item(), rel=1e-10)


def test_one_em_step_of_the_shared_start_is_the_pooled_smoothed_first_state():
    """One iteration from given parameters: the new start is the mean over the series of the smoothed
    first state, its covariance the average of ``P_0 + (x_0 - mu)(x_0 - mu)^T`` - each series' smoothed
    first state being what the per-series run (per_series=True, from the same parameters) returns as its
    start."""
    y, present = _series(seed=8)
    shared = _local_level()
    one = em(shared, _start(4), y, NAMES, iterations=1, present=present, progress=False)
    apart = _local_level()
    each = em(apart, _start(4), y, NAMES, iterations=1, present=present, per_series=True, progress=False)
    x0, P0 = each.belief0.mean[:, 0], each.belief0.cov[:, 0, 0]  # per series: mu_s = x_0s, V_s = P_0s
    assert float(x0.std()) > 1.0  # (the per-series starts differ: a start per series)
    mu = x0.mean()
    torch.testing.assert_close(one.belief0.mean[:, 0], mu.expand(4), rtol=1e-12, atol=0)
    pooled = (P0 + (x0 - mu) ** 2).mean()
    torch.testing.assert_close(one.belief0.cov[:, 0, 0], pooled.expand(4), rtol=1e-12, atol=0)


def test_a_shared_mean_with_a_covariance_per_series_is_refused():
    y, present = _series()
    covs = torch.arange(1.0, 5.0, dtype=F64).reshape(4, 1, 1)
    start = GaussianBelief(torch.zeros(1, dtype=F64).expand(4, 1), covs)
    with pytest.raises(ValueError, match="^belief0: its mean is one value for the series"):
        em(_local_level(), start, y, ["Q", "initial_mean"], present=present, progress=False)

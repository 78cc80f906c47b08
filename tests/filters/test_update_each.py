"""``Filter.update_each``: one prior, D alternative measurements (data association's hypotheses). The
Kalman and extended Kalman filters share the gain, an IMM / GPB1 over them shares each mode's; every
other filter repeats the prior. All equal ``update`` of each measurement, absent rows keep the prior,
a NaN prediction fails, no host read."""

from __future__ import annotations

import math

import pytest
import torch

from torchmm import GPB1, GPB2, IMM, GaussianBelief, KalmanFilter
from torchmm.filters import ExtendedKalmanFilter, UnscentedKalmanFilter
from torchmm.models import ConstantVelocity, PositionMeasurement, RangeBearing
from torchmm.multimodel import VariableStructureIMM
from torchmm.multimodel.mevsmm import ExactMinimumEntropy

DT = torch.float64
PI = torch.tensor([[0.8, 0.1, 0.1], [0.2, 0.7, 0.1], [0.15, 0.15, 0.7]], dtype=DT)


def _filters():
    cv = ConstantVelocity(2, dt=1.0, q=0.5, dtype=DT)
    bank = ConstantVelocity(2, dt=1.0, q=0.5, acceleration=[[0.0, 0.0], [1.0, 0.0], [0.0, -1.0]], dtype=DT)
    pos = PositionMeasurement(4, [0, 2], torch.tensor([[2.0, 0.3], [0.3, 1.5]], dtype=DT))
    rb = RangeBearing(4, torch.diag(torch.tensor([1.0, 1e-3], dtype=DT)), origin=(-30.0, -40.0))
    kf = KalmanFilter(bank, pos)
    return {
        "kalman": (KalmanFilter(cv, pos), None),
        "extended": (ExtendedKalmanFilter(cv, rb), None),
        "unscented": (UnscentedKalmanFilter(cv, rb), None),
        "joseph": (KalmanFilter(cv, pos, joseph=True), None),
        "imm": (IMM(kf, PI), "modes"),
        "gpb1": (GPB1(kf, PI), "modes"),
        "gpb2": (GPB2(kf, PI), "pairs"),
        "vsimm": (VariableStructureIMM(kf, PI, ExactMinimumEntropy()), "modes"),
    }


def _prior(filt, kind, runs=4):
    gen = torch.Generator().manual_seed(0)
    g = GaussianBelief(torch.randn(runs, 4, generator=gen, dtype=DT) * 2, torch.eye(4, dtype=DT) * 3)
    if kind is None:
        return g
    b = filt.initial_belief(g)
    return filt.predict(b) if kind == "pairs" else b  # GPB2 updates its M^2 pair prediction


@pytest.mark.parametrize("name", list(_filters()))
def test_equals_update_of_each_measurement(name):
    filt, kind = _filters()[name]
    prior = _prior(filt, kind)
    m = 2
    zs = torch.randn(5, 4, m, generator=torch.Generator().manual_seed(1), dtype=DT) * 2
    if name in ("extended", "unscented"):
        zs = torch.tensor([50.0, 0.9], dtype=DT) + zs * torch.tensor([1.0, 0.02], dtype=DT)
    zs[3, 1] = math.nan  # an absent row
    zs[4, 2, 0] = math.nan  # a partial row: absent as a whole
    each = filt.update_each(prior, zs)
    for d in range(5):
        z = zs[d].clone()
        z[~torch.isfinite(z).all(-1)] = math.nan
        one = filt.update(prior, z)
        a, b = each.belief.estimate(), one.belief.estimate()
        torch.testing.assert_close(a.mean[d], b.mean, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(a.cov[d], b.cov, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(each.log_likelihood[d], one.log_likelihood, rtol=1e-12, atol=1e-12)
    assert float(each.log_likelihood[3, 1]) == 0.0 and float(each.log_likelihood[4, 2]) == 0.0
    assert type(each.belief) is type(filt.update(prior, zs[0]).belief)  # a VSIMM keeps its model-set belief


def test_kalman_shares_the_innovation_covariance_and_fails_a_nan_prediction():
    filt, _ = _filters()["kalman"]
    prior = _prior(filt, None)
    prior = GaussianBelief(prior.mean.clone(), prior.cov)
    prior.mean[2, 0] = math.nan
    zs = torch.randn(3, 4, 2, generator=torch.Generator().manual_seed(2), dtype=DT)
    zs[1, 2] = math.nan
    out = filt.update_each(prior, zs)
    assert out.innovation_cov.dim() <= 3  # one S a prior (no D axis), broadcasting against (D, *B, m)
    assert out.extras["failed"][:, 2].tolist() == [True, False, True]  # absent: no datum, no failure
    assert not out.extras["failed"][:, [0, 1, 3]].any()


def test_no_host_read():
    from torchmm.runtime import no_host_sync

    zs = torch.randn(3, 4, 2, generator=torch.Generator().manual_seed(3), dtype=DT)
    for name in ("kalman", "imm"):
        filt, kind = _filters()[name]
        prior = _prior(filt, kind)
        with no_host_sync("update_each"):
            filt.update_each(prior, zs)

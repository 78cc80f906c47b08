"""em's series with nothing to estimate a parameter from, and its default ``present`` (docs/estimation.md,
"EM"): a series without a measurement has no R (nor H, nor start), one of a single step no Q (nor F,
offset): NaN and flagged in ``EMResult.unestimated``, not the 0 of an empty sum, the other series' fits
unchanged; trailing NaN padding is not latent steps (``present`` defaults to each series up to its last
datum), so a padded series' fit is its fit alone."""

from __future__ import annotations

import math

import numpy as np
import torch

from torchmm import GaussianBelief, KalmanFilter, LinearMeasurement, LinearMotion
from torchmm.learn import em

T = 50
PARAMETERS = ["Q", "R", "initial_mean", "initial_cov"]


def _local_level(q: float, r: float) -> KalmanFilter:
    one = torch.ones(1, 1, dtype=torch.float64)
    return KalmanFilter(LinearMotion(one.clone(), q * one.clone()),
                        LinearMeasurement(one.clone(), r * one.clone()))


def _series(steps: int, seed: int) -> np.ndarray:
    g = np.random.default_rng(seed)
    return np.cumsum(g.standard_normal(steps)) + 2 * g.standard_normal(steps)


def _fit(columns: list[np.ndarray], present=None, iterations: int = 20):
    z = torch.tensor(np.stack(columns, 1)).reshape(T, len(columns), 1)
    kf = _local_level(2.0, 2.0)
    start = GaussianBelief(torch.zeros(len(columns), 1, dtype=torch.float64),
                           10 * torch.ones(len(columns), 1, 1, dtype=torch.float64))
    out = em(kf, start, z, PARAMETERS, iterations=iterations, per_series=True, present=present,
             progress=False)
    return kf, out


def test_a_series_without_data_or_transitions_is_nan_and_flagged():
    """Per series, beside three good ones: an all-NaN series (before: R = 0, Q = 0) and a series of one
    step (before: Q = 0). Their unestimable values are NaN and flagged; the good series' fits are bit for
    bit those without them."""
    good = [_series(T, s) for s in range(3)]
    kf_good, _ = _fit(good)
    one_step = np.r_[1.0, np.full(T - 1, np.nan)]
    present = torch.ones(T, 5, dtype=torch.bool)
    present[1:, 4] = False
    kf, out = _fit(good + [np.full(T, np.nan), one_step], present=present)
    Q, R = kf.motion.Q.reshape(-1), kf.measurement.R.reshape(-1)
    assert torch.equal(Q[:3], kf_good.motion.Q.reshape(-1))
    assert torch.equal(R[:3], kf_good.measurement.R.reshape(-1))
    assert math.isnan(Q[3]) and math.isnan(R[3]) and math.isnan(Q[4])
    assert float(R[4]) >= 0 and not math.isnan(R[4])  # (one datum: R has something to go on)
    assert out.unestimated["Q"].tolist() == [False, False, False, True, True]
    assert out.unestimated["R"].tolist() == [False, False, False, True, False]
    assert out.unestimated["initial_mean"].tolist() == [False, False, False, True, False]
    assert math.isnan(out.belief0.mean[3, 0]) and math.isnan(out.belief0.cov[3, 0, 0])
    assert torch.isfinite(out.belief0.mean[[0, 1, 2, 4]]).all()
    assert out.loglik[-1][3] == 0 and all(torch.isfinite(v).all() for v in out.loglik)
    _, clean = _fit(good)
    assert clean.unestimated == {}


def test_trailing_nan_padding_does_not_change_the_fit():
    """A 40-step series padded with NaN to 70 beside a 70-step one, without present: its fit is its fit
    alone and that with present (before: Q 0.6424 padded vs 0.4970 alone after 30 iterations)."""
    y1, y2 = _series(40, 1), _series(70, 2)
    z = torch.full((70, 2, 1), math.nan, dtype=torch.float64)
    z[:40, 0, 0], z[:, 1, 0] = torch.tensor(y1), torch.tensor(y2)
    present = torch.zeros(70, 2, dtype=torch.bool)
    present[:40, 0], present[:, 1] = True, True
    start = GaussianBelief(torch.zeros(2, 1, dtype=torch.float64),
                           10 * torch.ones(2, 1, 1, dtype=torch.float64))
    fits = {}
    for label, given in (("padded", None), ("present", present)):
        kf = _local_level(2.0, 2.0)
        out = em(kf, start, z, PARAMETERS, iterations=30, per_series=True, present=given, progress=False)
        fits[label] = (kf.motion.Q[0].item(), kf.measurement.R[0].item(), out.belief0.mean[0].item(),
                       out.loglik[-1][0].item())
    kf = _local_level(2.0, 2.0)
    one = GaussianBelief(torch.zeros(1, dtype=torch.float64), 10 * torch.ones(1, 1, dtype=torch.float64))
    alone = em(kf, one, torch.tensor(y1).reshape(-1, 1), PARAMETERS, iterations=30, progress=False)
    reference = (kf.motion.Q.item(), kf.measurement.R.item(), alone.belief0.mean.item(), alone.loglik[-1])
    np.testing.assert_allclose(fits["padded"], reference, rtol=1e-9)
    np.testing.assert_allclose(fits["present"], reference, rtol=1e-9)

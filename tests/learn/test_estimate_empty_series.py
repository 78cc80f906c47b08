"""estimate with a series that has no finite measurement (torchmm/learn/search.py's ``untouched``): the
entries no datum touches (that series' start mean) are held out of the information and of ``k``, reported
NaN and named in the note; every other number is the fit's without that series."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchmm import GaussianBelief, KalmanFilter, LinearMeasurement, LinearMotion
from torchmm.learn import estimate


def _fit(z: torch.Tensor, se: bool = True):
    one = torch.ones(1, 1, dtype=torch.float64)
    kf = KalmanFilter(LinearMotion(one.clone(), one.clone()), LinearMeasurement(one.clone(), one.clone()))
    S = z.shape[1]
    b0 = GaussianBelief(torch.zeros(S, 1, dtype=torch.float64), (10 * one).repeat(S, 1, 1))
    return estimate(kf, b0, z, {"motion.Q": "variance", "measurement.R": "variance", "belief0.mean": "free"},
                    update_first=True, se=se, progress=False)


@pytest.fixture(scope="module")
def series():
    g = np.random.default_rng(3)
    T = 80
    y = np.stack([np.cumsum(np.sqrt(0.3) * g.standard_normal(T)) + g.standard_normal(T) for _ in range(2)], 1)
    z = torch.tensor(y).unsqueeze(-1)  # (T, 2, 1)
    return z, torch.cat([z, torch.full((T, 1, 1), math.nan, dtype=torch.float64)], 1)  # third series empty


def test_an_empty_series_start_is_not_estimated_and_the_rest_is_unchanged(series):
    """Before, the empty series' start mean (gradient and information row 0) made the information singular:
    every standard error NaN ("not positive definite"), k = 5 (AIC off by 2, BIC by log nobs), and the entry
    reported as an estimate at its start value 0.0."""
    z, z_empty = series
    ref, est = _fit(z), _fit(z_empty)
    assert ref.converged and est.converged
    assert est.names[:4] == ref.names and est.names[4] == "belief0.mean[2,0]"
    np.testing.assert_allclose(est.estimates[:4], ref.estimates, rtol=1e-6)
    np.testing.assert_allclose(est.se[:4], ref.se, rtol=1e-4)
    assert all(math.isfinite(s) and s > 0 for s in est.se[:4])
    assert math.isnan(est.estimates[4]) and math.isnan(est.se[4])
    assert est.k == ref.k == 4 and est.nobs == ref.nobs
    assert est.aic == pytest.approx(ref.aic, rel=1e-9) and est.bic == pytest.approx(ref.bic, rel=1e-9)
    assert "not estimated: belief0.mean[2,0]" in est.note
    assert bool(torch.isnan(est.theta_cov[4]).all()) and bool(torch.isfinite(est.theta_cov[:4, :4]).all())


def test_without_standard_errors_the_empty_series_start_is_still_left_out_of_k(series):
    _, z_empty = series
    est = _fit(z_empty, se=False)
    assert est.k == 4 and math.isnan(est.estimates[4]) and all(math.isfinite(v) for v in est.estimates[:4])
    assert "belief0.mean[2,0]" in est.note

"""estimate's answers where the search leaves the model's domain or stops short (torchmm/learn/search.py,
docs/estimation.md "When the search fails"): a non-finite objective is a failed step, not a number passed
to scipy; a fit is never converged at a point worse than its start; a fit that did not converge has no
standard errors unless a Newton step from it is negligible against them; a ``"variance"`` whose start has
off-diagonal entries is refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.optimize
import torch

from torchmm import GaussianBelief, KalmanFilter, LinearMeasurement, LinearMotion
from torchmm.learn import Param, estimate
from torchmm.learn.search import Guarded


def _local_level(q: float, r: float) -> KalmanFilter:
    one = torch.ones(1, 1, dtype=torch.float64)
    return KalmanFilter(LinearMotion(one.clone(), q * one.clone()),
                        LinearMeasurement(one.clone(), r * one.clone()))


def _np_loglik(y: np.ndarray, q: float, r: float, m0: float, p0: float) -> float:
    """A float64 NumPy local-level Kalman log-likelihood, ``(m0, p0)`` the prior of the first datum."""
    x, p, ll = m0, p0, 0.0
    for t, v in enumerate(y):
        if t:
            p = p + q
        s = p + r
        e = v - x
        ll += -0.5 * (math.log(2 * math.pi * s) + e * e / s)
        k = p / s
        x, p = x + k * e, p - k * p
    return ll


@pytest.fixture(scope="module")
def level_data():
    """A level with measurement noise and (almost) no drift: the MLE of Q is close to 0."""
    return 10 + 2 * np.random.default_rng(5).standard_normal(200)


def test_a_non_finite_objective_is_a_failed_step(level_data):
    """Q with lower=-0.5: the search steps to a Q where the likelihood is inf (a negative variance), its
    gradient NaN. Before, scipy's L-BFGS-B took that value, went back to its iterate and reported
    CONVERGENCE there (log-likelihood -432.13, the gradient not 0); now the step is failed and the search
    backtracks, to the maximum a NumPy reference finds with Q held >= 0 (-416.03)."""
    y = level_data
    z = torch.tensor(y).reshape(-1, 1)
    b0 = GaussianBelief(torch.tensor([10.0], dtype=torch.float64), torch.eye(1, dtype=torch.float64))
    est = estimate(_local_level(1.0, 1.0), b0, z, {"motion.Q": Param(lower=-0.5), "measurement.R": "variance"},
                   update_first=True, progress=False)
    ref = scipy.optimize.minimize(lambda v: -_np_loglik(y, v[0], v[1], 10.0, 1.0), [1.0, 1.0],
                                  method="L-BFGS-B", bounds=[(0.0, None), (1e-6, None)],
                                  options={"ftol": 1e-15, "gtol": 1e-10})
    assert est.converged and "not finite" in est.message  # (it did meet such a point)
    assert est.loglik == pytest.approx(_np_loglik(y, *est.estimates, 10.0, 1.0), abs=1e-8)
    assert est.loglik >= -ref.fun - 1e-6
    np.testing.assert_allclose(est.estimates[1], ref.x[1], rtol=1e-3)


def test_guarded_backtracks_where_the_raw_infinity_stops():
    """The wrapper alone on a function defined for x > 0.5 only, whose first L-BFGS-B step (length 1)
    leaves that domain: the minimum 0.9 + sqrt(0.18) / 2 - 0.2 (the root of 2 (x - 0.9) = 0.01 / (x - 0.5))
    is reached; a start outside the domain is a ValueError."""

    def fun(x):
        if x[0] <= 0.5:
            return math.inf, np.full(1, math.nan)
        value = (x[0] - 0.9) ** 2 - 0.01 * math.log(x[0] - 0.5)
        return value, np.array([2 * (x[0] - 0.9) - 0.01 / (x[0] - 0.5)])

    guarded = Guarded(fun)
    res = scipy.optimize.minimize(guarded, np.array([1.5]), jac=True, method="L-BFGS-B",
                                  callback=guarded.callback, options={"ftol": 1e-15, "gtol": 1e-10})
    assert guarded.failed >= 1 and res.success
    assert res.x[0] == pytest.approx((1.4 + math.sqrt(0.18)) / 2, abs=1e-7)
    with pytest.raises(ValueError, match="start values"):
        scipy.optimize.minimize(Guarded(fun), np.array([0.2]), jac=True, method="L-BFGS-B")


def test_a_fit_ending_below_its_start_is_not_converged(level_data, monkeypatch):
    """An optimiser that reports success at a point worse than its start (the audit's -1679 from -533):
    estimate reports the best point it evaluated (here the start), not converged, no standard errors."""
    y = level_data
    z = torch.tensor(y).reshape(-1, 1)
    b0 = GaussianBelief(torch.tensor([10.0], dtype=torch.float64), torch.eye(1, dtype=torch.float64))

    def bad_minimize(fun, x0, **options):  # one evaluation at the start, then "success" far away
        fun(x0)
        return scipy.optimize.OptimizeResult(x=x0 + 8.0, success=True, message="CONVERGENCE (fake)", nit=1)

    monkeypatch.setattr(scipy.optimize, "minimize", bad_minimize)
    kf = _local_level(1.0, 4.0)
    est = estimate(kf, b0, z, {"motion.Q": "variance", "measurement.R": "variance"}, update_first=True,
                   progress=False)
    assert not est.converged and "best point evaluated" in est.message
    assert est.loglik == pytest.approx(_np_loglik(y, 1.0, 4.0, 10.0, 1.0), abs=1e-8)
    np.testing.assert_allclose(est.estimates, [1.0, 4.0], rtol=1e-12)
    assert all(math.isnan(s) for s in est.se) and "not converged" in est.note


def test_a_fit_stopped_short_has_no_standard_errors(level_data):
    """maxiter reached far from the maximum: NaN errors with a note, and no entry called 'at a bound'
    (before: errors and z-scores from the information at that point). From the maximum itself with
    maxiter=1 (a Newton step there is negligible), the errors are the converged fit's."""
    y = level_data
    z = torch.tensor(y).reshape(-1, 1)
    b0 = GaussianBelief(torch.tensor([10.0], dtype=torch.float64), torch.eye(1, dtype=torch.float64))
    params = {"motion.Q": "variance", "measurement.R": "variance"}
    short = estimate(_local_level(1.0, 1.0), b0, z, params, update_first=True, maxiter=2, progress=False)
    assert not short.converged
    assert all(math.isnan(s) for s in short.se) and all(math.isnan(v) for v in short.z)
    assert "not converged: no standard errors" in short.note and "bound" not in short.note
    kf = _local_level(1.0, 1.0)
    full = estimate(kf, b0, z, {"measurement.R": "variance"}, update_first=True, progress=False)
    assert full.converged and math.isfinite(full.se[0])
    r = full.estimates[0]
    kf.measurement.R.fill_(r * (1 + 1e-4))  # (a hair from the maximum: one iteration does not reach it)
    near = estimate(kf, b0, z, {"measurement.R": "variance"}, update_first=True, maxiter=1, progress=False)
    assert not near.converged and "not converged, but a Newton step" in near.note
    assert near.se[0] == pytest.approx(full.se[0], rel=1e-4)
    kf.measurement.R.fill_(r * 1.1)  # (a Newton step of about 5 % of the error: not a maximum)
    far = estimate(kf, b0, z, {"measurement.R": "variance"}, update_first=True, maxiter=1, progress=False)
    assert not far.converged and math.isnan(far.se[0])


def test_a_variance_with_off_diagonal_entries_is_refused():
    """kind 'variance' keeps the off-diagonal entries of its start: a non-zero one (EM's full Q) is refused,
    naming the entry and the kind that estimates it (before: held, the diagonal's search ran into an
    indefinite Q and 'converged' at -1679 from EM's -533)."""
    Q = torch.tensor([[1.0, 0.6], [0.6, 1.0]], dtype=torch.float64)
    eye = torch.eye(2, dtype=torch.float64)
    kf = KalmanFilter(LinearMotion(0.9 * eye, Q), LinearMeasurement(eye.clone(), eye.clone()))
    b0 = GaussianBelief(torch.zeros(2, dtype=torch.float64), eye.clone())
    z = torch.randn(20, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"parameters\['motion.Q'\].*off-diagonal.*'covariance'"):
        estimate(kf, b0, z, {"motion.Q": "variance"}, progress=False)
    est = estimate(kf, b0, z, {"motion.Q": "covariance"}, progress=False)  # (the full matrix: fine)
    assert math.isfinite(est.loglik)

"""Real data shipped in experiments/data, cross-checked against statsmodels at the library level.

* Fed funds: statsmodels' Markov-switching mean and variance (Hamilton's filter, Kim's smoother)
  against an IMM over a constant state (``experiments.realdata.fedfunds_imm``): filtered and
  smoothed regime probabilities and the log-likelihood at statsmodels' MLE.
* Nile: statsmodels' local level (exact diffuse initialisation) against a one-state Kalman filter
  (``experiments.realdata.local_level``) whose variances are learned with L-BFGS on
  :func:`torchmm.learn.negative_log_likelihood`; and the ``update_first`` convention against
  statsmodels with a known initialisation.

The measured figures are in docs/reproduction-learn.md ("Real data: Fed funds and Nile").
"""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import torch

sm = pytest.importorskip("statsmodels.api")

import torchmm
from experiments import data
from experiments.realdata import (
    fedfunds_imm,
    load_fedfunds,
    load_nile,
    local_level,
    local_level_start,
)
from torchmm.learn import negative_log_likelihood


def test_shipped_files():
    with data.path("fedfunds.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 226 and (rows[0]["date"], rows[-1]["date"]) == ("1954-07-01", "2010-10-01")
    with data.path("nile.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 100 and (rows[0]["year"], rows[-1]["year"]) == ("1871", "1970")
    # the same numbers as statsmodels' own copy of the Nile series
    nile = sm.datasets.nile.load_pandas().data
    np.testing.assert_array_equal(load_nile()[:, 0].numpy(), nile["volume"].to_numpy())
    assert data.path("README.md").exists()
    with pytest.raises(ValueError, match="^name"):
        data.path("gdp.csv")
    with pytest.raises(TypeError, match="^name"):
        data.path(3)


# --- Fed funds: Markov-switching mean and variance as an IMM ------------------------------------


@pytest.fixture(scope="module")
def fedfunds():
    y = load_fedfunds()
    model = sm.tsa.MarkovRegression(y[:, 0].numpy(), k_regimes=2, trend="c", switching_variance=True)
    result = model.fit()
    assert result.mle_retvals["converged"]
    return y, model, result.params  # p[0->0], p[1->0], const[0], const[1], sigma2[0], sigma2[1]


def _imm_against_statsmodels(y, model, params, mode_probs):
    result = model.smooth(params)
    # statsmodels: P[i, j] = P(s_t = i | s_{t-1} = j) (columns sum to 1); torchmm: rows = from
    transition = model.regime_transition_matrix(params)[:, :, 0].T
    imm, belief0 = fedfunds_imm(params[2:4], params[4:6], transition, mode_probs=mode_probs(transition))
    traj = torchmm.run_filter(imm, belief0, y)
    filtered = traj.belief.mode_log_probs.exp().numpy()
    smoothed = torchmm.smooth(traj, method="kim").belief.mode_log_probs.exp().numpy()
    return (np.abs(filtered - result.filtered_marginal_probabilities).max(),
            np.abs(smoothed - result.smoothed_marginal_probabilities).max(),
            abs(traj.log_likelihood.sum().item() - result.llf))


def test_fedfunds_imm_matches_statsmodels_markov_regression(fedfunds):
    """Default initial probabilities: the ergodic ones (invariant under the chain)."""
    y, model, params = fedfunds
    ergodic = model.initial_probabilities(params)
    filtered, smoothed, llf = _imm_against_statsmodels(y, model, params, lambda transition: ergodic)
    assert filtered < 1e-8 and smoothed < 1e-8 and llf < 1e-8
    # the check can fail: another regime variance moves every figure
    wrong = params.copy()
    wrong[5] *= 1.01
    transition = model.regime_transition_matrix(params)[:, :, 0].T
    imm, belief0 = fedfunds_imm(wrong[2:4], wrong[4:6], transition, mode_probs=ergodic)
    assert abs(torchmm.run_filter(imm, belief0, y).log_likelihood.sum().item() - model.smooth(params).llf) > 1e-3


def test_fedfunds_imm_first_step_convention(fedfunds):
    """Known, non-ergodic initial probabilities pi_0: statsmodels propagates them twice before the
    first observation (its filter starts the joint (s_t, s_{t-1}) from pi_0), so the IMM starts from
    pi_0 @ transition and predicts at the first step."""
    y, model, params = fedfunds
    pi0 = np.array([0.9, 0.1])
    model = sm.tsa.MarkovRegression(y[:, 0].numpy(), k_regimes=2, trend="c", switching_variance=True)
    model.initialize_known(pi0)
    filtered, smoothed, llf = _imm_against_statsmodels(y, model, params, lambda transition: pi0 @ transition)
    assert filtered < 1e-8 and smoothed < 1e-8 and llf < 1e-8
    filtered, _, llf = _imm_against_statsmodels(y, model, params, lambda transition: pi0)
    assert llf > 1e-3 and filtered > 1e-4  # one propagation short: visibly different


# --- Nile: local level, variances by maximum likelihood --------------------------------------------

#: statsmodels' exact diffuse log-likelihood (Durbin and Koopman's definition) keeps the constant
#: -log(2 pi)/2 of the diffuse first observation; the prediction-error decomposition over t = 2..T
#: (what torchmm computes from the conditioned start) has no term for it.
DIFFUSE_CONSTANT = -0.5 * math.log(2 * math.pi)


@pytest.fixture(scope="module")
def nile():
    y = load_nile()
    model = sm.tsa.UnobservedComponents(y[:, 0].numpy(), "llevel", use_exact_diffuse=True)
    # a tight BFGS: the default L-BFGS stops early on this flat likelihood
    result = model.fit(method="bfgs", gtol=1e-8, maxiter=1000, disp=False)
    assert result.mle_retvals["converged"]
    return y, model, result.params  # sigma2.irregular (r), sigma2.level (q)


def test_nile_loglikelihood_at_statsmodels_mle(nile):
    y, model, params = nile
    r, q = params
    kf, belief0 = local_level(q, r, first=y[0])
    loglik = -negative_log_likelihood(kf, belief0, y[1:], reduction="sum").item()
    assert abs(loglik + DIFFUSE_CONSTANT - model.loglike(params)) < 1e-6
    # Durbin and Koopman's figures (sigma2_eps = 15099, sigma2_eta = 1469.1)
    assert abs(r / 15099 - 1) < 1e-3 and abs(q / 1469.1 - 1) < 1e-3


def test_nile_variances_learned_by_lbfgs(nile):
    y, _, params = nile
    r_ref, q_ref = params
    kf, _ = local_level(1000.0, 10000.0, first=y[0], learnable=True)  # start far off (x0.7, x0.66)
    optimizer = torch.optim.LBFGS(kf.parameters(), line_search_fn="strong_wolfe", max_iter=100,
                                  tolerance_grad=1e-9, tolerance_change=1e-12)

    def closure():
        optimizer.zero_grad()
        # the conditioned start N(y_1, r) depends on the learned r: rebuilt at every evaluation
        loss = negative_log_likelihood(kf, local_level_start(kf, y[0]), y[1:], reduction="sum")
        loss.backward()
        return loss

    optimizer.step(closure)
    q, r = kf.motion.Q.item(), kf.measurement.R.item()
    assert abs(q / q_ref - 1) < 2e-3 and abs(r / r_ref - 1) < 2e-3


def test_nile_update_first_matches_a_known_initialisation(nile):
    y, _, params = nile
    r, q = params
    a1, p1 = 1000.0, 5000.0
    model = sm.tsa.UnobservedComponents(y[:, 0].numpy(), "llevel")
    model.ssm.initialize_known(np.array([a1]), np.array([[p1]]))
    model.loglikelihood_burn = 0
    expected = model.loglike(params)
    kf, belief0 = local_level(q, r, known=(a1, p1))
    loglik = -negative_log_likelihood(kf, belief0, y, reduction="sum", update_first=True).item()
    assert abs(loglik - expected) < 1e-9
    # without update_first the prior is predicted once more (P_1 + q): a different likelihood
    other = -negative_log_likelihood(kf, belief0, y, reduction="sum").item()
    assert abs(other - expected) > 1e-4

"""The real-data studies from config alone (``experiment=fedfunds``, ``experiment=nile``) against statsmodels:
the Hamilton filter and Kim smoother of the Fed funds rate, and the Nile local level learned by maximum
likelihood (docs/reproduction-learn.md, "Real data: Fed funds and Nile")."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from experiments.config import validate
from experiments.run import CONFIG_DIR, run_study
from experiments.realdata import load_fedfunds, load_nile

sm = pytest.importorskip("statsmodels.api")

DIFFUSE_CONSTANT = -0.5 * math.log(2 * math.pi)  # statsmodels' exact-diffuse llf keeps it (D&K's does not)


def _run(name: str, tmp_path, *overrides: str) -> tuple[dict, dict]:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("config", overrides=[f"experiment={name}", "logger=none", "progress=false", "figures=false",
                                           *overrides])
    validate(cfg)
    run_study(cfg, tmp_path)
    curves = dict(np.load(tmp_path / "curves.npz"))
    return json.loads((tmp_path / "results.json").read_text()), curves | {"cfg": cfg}


def test_fedfunds_study_equals_statsmodels_markov_regression(tmp_path):
    """Filtered and Kim-smoothed regime probabilities and the log-likelihood at the study's parameters: 1e-8."""
    res, curves = _run("fedfunds", tmp_path)
    scen = OmegaConf.to_container(curves["cfg"].scenario)
    (p00, _), (p10, _) = scen["transition"]
    mu = [s["H"][0][0] for s in scen["sensors"]]
    sigma2 = [s["R"][0][0] for s in scen["sensors"]]
    y = load_fedfunds()[:, 0].numpy()
    model = sm.tsa.MarkovRegression(y, k_regimes=2, trend="c", switching_variance=True)
    result = model.smooth(np.array([p00, p10, *mu, *sigma2]))
    assert res["metrics"]["Hamilton-IMM"]["loglik"] == pytest.approx(result.llf, abs=1e-8)
    for j, label in enumerate(["low", "high"]):
        filtered = curves[f"mode_probability/Hamilton-IMM/{label}"]
        smoothed = curves[f"mode_probability/Hamilton-IMM smoothed/{label}"]
        np.testing.assert_allclose(filtered, result.filtered_marginal_probabilities[:, j], atol=1e-8, rtol=0)
        np.testing.assert_allclose(smoothed, result.smoothed_marginal_probabilities[:, j], atol=1e-8, rtol=0)
    assert np.abs(filtered - smoothed).max() > 1e-2  # the smoother changed something


@pytest.fixture(scope="module")
def nile_mle():
    y = load_nile()[:, 0].numpy()
    model = sm.tsa.UnobservedComponents(y, "llevel", use_exact_diffuse=True)
    result = model.fit(method="bfgs", gtol=1e-8, maxiter=1000, disp=False)
    assert result.mle_retvals["converged"]
    return model, result.params  # sigma2.irregular (R), sigma2.level (Q)


def test_nile_study_learns_the_mle(tmp_path, nile_mle):
    """Q and R estimated by the study (method mle) within 0.2 % of the exact-diffuse MLE (measured: 1e-5),
    their standard errors within 1 % of statsmodels' (cov_type approx; the study's start is the nearly
    diffuse N(0, 1e12), statsmodels' the exact diffuse one)."""
    model, (r, q) = nile_mle
    res, _ = _run("nile", tmp_path)
    learned = {row[1]: (row[2], row[3]) for row in res["tables"]["learned"]["rows"] if row[0] == "KF"}
    assert learned["modes[0].Q[0,0]"][0] == pytest.approx(q, rel=2e-3)
    assert learned["sensors[0].R[0,0]"][0] == pytest.approx(r, rel=2e-3)
    bse = model.fit(start_params=[r, q], method="bfgs", gtol=1e-8, disp=False, cov_type="approx").bse
    assert learned["sensors[0].R[0,0]"][1] == pytest.approx(bse[0], rel=1e-2)
    assert learned["modes[0].Q[0,0]"][1] == pytest.approx(bse[1], rel=1e-2)
    fit = {row[0]: dict(zip(res["tables"]["fit"]["columns"], row)) for row in res["tables"]["fit"]["rows"]}["KF"]
    assert fit["k"] == 2 and fit["nobs"] == 99 and fit["converged"]


def test_nile_study_loglikelihood_at_the_mle(tmp_path, nile_mle):
    """At statsmodels' MLE (no learning) the study's log-likelihood is statsmodels' to 1e-6 (its llf keeps
    the diffuse observation's -log(2 pi)/2); its NIS and whiteness are those of statsmodels' standardised
    forecast errors after the diffuse first one (``burn: 1``): their mean square, 1 at the MLE of a common
    scale, and their lag-1 sample autocorrelation, in [-1, 1] (the burned innovation once made it 0.99 and
    0.1215)."""
    model, (r, q) = nile_mle
    res, _ = _run("nile", tmp_path, "learn=null", f"scenario.modes.0.Q=[[{float(q)!r}]]",
               f"scenario.sensors.0.R=[[{float(r)!r}]]")
    assert res["metrics"]["KF"]["loglik"] + DIFFUSE_CONSTANT == pytest.approx(model.loglike(np.array([r, q])), abs=1e-6)
    e = model.smooth(np.array([r, q])).standardized_forecasts_error[0, 1:]  # (the diffuse first one: NaN)
    assert res["metrics"]["KF"]["nis"] == pytest.approx(np.mean(e * e), rel=1e-6)
    assert res["metrics"]["KF"]["nis"] == pytest.approx(1.0, abs=1e-4)  # the scale's score at the MLE
    assert res["metrics"]["KF"]["whiteness_lag1"] == pytest.approx(np.sum(e[:-1] * e[1:]) / np.sum(e * e), abs=1e-6)


def test_nile_by_em_and_by_em_then_mle(tmp_path, nile_mle):
    """learn.method em (EM from config: every iteration raises the likelihood) and em_then_mle (EM, then
    maximum likelihood from there, as statsmodels' fit: the MLE with its standard errors)."""
    _, (r, q) = nile_mle
    res, _ = _run("nile", tmp_path / "em", "learn.method=em", "learn.iterations=40", "burn=0")
    rows = {row[1]: row[2] for row in res["tables"]["learned"]["rows"]}
    assert set(rows) == {"modes[0].Q[0,0]", "sensors[0].R[0,0]"}
    fit = dict(zip(res["tables"]["fit"]["columns"], res["tables"]["fit"]["rows"][0]))
    assert fit["converged"] is False or fit["iterations"] <= 40
    both, _ = _run("nile", tmp_path / "em_mle", "learn.method=em_then_lbfgs", "learn.iterations=10")
    learned = {row[1]: (row[2], row[3]) for row in both["tables"]["learned"]["rows"]}
    assert learned["modes[0].Q[0,0]"][0] == pytest.approx(q, rel=2e-3)
    assert learned["sensors[0].R[0,0]"][0] == pytest.approx(r, rel=2e-3)
    assert learned["modes[0].Q[0,0]"][1] > 0


def test_whiteness_of_a_short_series_is_an_autocorrelation_or_named_as_dropped(tmp_path, monkeypatch):
    """Three years of Nile (two innovations after the burn-in): the lag-1 sample autocorrelation of the two,
    x1 x2 / (x1^2 + x2^2), inside [-1, 1] (it was -5.06: the burned diffuse innovation, ~0, in the
    denominator); two years (one innovation after it): no pair, so named as dropped, never a number."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "three.csv").write_text("year,flow\n1871,1120\n1872,1160\n1873,963\n")
    (tmp_path / "two.csv").write_text("year,flow\n1871,1120\n1872,1160\n")
    res, _ = _run("nile", tmp_path / "three", "learn=null", "scenario.data.path=three.csv")
    x = res["metrics"]["KF"]
    assert -1.0 <= x["whiteness_lag1"] <= 1.0 and x["nis"] > 0
    res, _ = _run("nile", tmp_path / "two", "learn=null", "scenario.data.path=two.csv")
    assert "whiteness_lag1" not in res["metrics"]["KF"]
    assert "consecutive innovations" in res["dropped"]["whiteness_lag1 (KF)"]

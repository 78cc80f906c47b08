"""``learn.parameters`` of ``experiment=markov_switching`` read the same way by every method
(docs/studies.md, "Learning"):

* a ``fixed`` transition entry is held by ``mle`` and ``em_then_mle`` as by ``em`` (before: only EM held
  it, the others estimated it and counted it in k), at the maximum statsmodels' own likelihood confirms;
* EM's ``learned`` table has one row per estimated entry, named as under ``mle`` (``const[i]``,
  ``x[i]``, ``sigma2[i]``), and its k counts the free values only (before: regime 1's constant was
  missing, a fixed zero constant listed, k 5 for 6 and 6 for 5), its note says EM gave no errors;
* a ``scenario.start`` of the wrong length is one line naming ``scenario.start``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

sm = pytest.importorskip("statsmodels.api")

from experiments.config import precheck, validate
from experiments.realdata import load_fedfunds
from experiments.run import CONFIG_DIR, run_study

HOLD = "learn.parameters=[{name: transition, fixed: [[true, false], [false, false]]}, " \
       "{model: sensors, name: H}, {model: sensors, name: R}]"


def _run(out: Path, *overrides) -> tuple[dict, dict]:
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("config", overrides=["experiment=markov_switching", "logger=none", "progress=false",
                                           "figures=false", *overrides])
    validate(cfg)
    run_study(cfg, out)
    res = json.loads((out / "results.json").read_text())
    fit = dict(zip(res["tables"]["fit"]["columns"], res["tables"]["fit"]["rows"][0]))
    return {row[1]: row[2] for row in res["tables"]["learned"]["rows"]}, fit


def test_a_fixed_transition_entry_is_held_by_every_method(tmp_path):
    y = load_fedfunds()[:, 0].numpy()
    model = sm.tsa.MarkovRegression(y, k_regimes=2, trend="c", switching_variance=True)
    fits = {}
    for method in ("mle", "em_then_mle", "em"):
        est, fit = _run(tmp_path / method, HOLD, f"learn.method={method}")
        assert "transition[0,0]" not in est and "transition[0,1]" not in est  # held: not estimates
        assert est["duration of transition[0]"] == pytest.approx(2.0, abs=1e-12)  # 1 / (1 - 0.5)
        assert fit["k"] == 5  # p[1->0], two constants, two variances
        assert fit["aic"] == pytest.approx(-2 * fit["loglik"] + 2 * 5, abs=1e-9)
        fits[method] = est, fit
    est, fit = fits["mle"]
    params = np.array([0.5, est["transition[1,0]"], est["sensors[0].H[0,0]"], est["sensors[1].H[0,0]"],
                       est["sensors[0].R[0,0]"], est["sensors[1].R[0,0]"]])
    assert model.loglike(params) == pytest.approx(fit["loglik"], abs=1e-6)  # statsmodels' likelihood there
    # a constrained maximum: statsmodels' likelihood, p[0->0] held, has no ascent direction there
    step = 1e-5 * np.maximum(np.abs(params), 1e-2)
    for i in range(1, 6):
        e = np.zeros(6)
        e[i] = step[i]
        assert abs(model.loglike(params + e) - model.loglike(params - e)) / (2 * step[i]) < 1e-2
    assert fits["em_then_mle"][1]["loglik"] == pytest.approx(fit["loglik"], abs=1e-6)
    assert fits["em"][1]["loglik"] <= fit["loglik"] + 1e-6


def test_em_table_rows_and_k_are_the_models(tmp_path):
    est, fit = _run(tmp_path / "ff", "learn.method=em", "+learn.iterations=300", "+learn.tolerance=1e-12")
    assert sorted(k for k in est if not k.startswith(("transition", "duration"))) == \
        ["const[0]", "const[1]", "sigma2[0]", "sigma2[1]"]
    assert fit["k"] == 6 and fit["aic"] == pytest.approx(-2 * fit["loglik"] + 12, abs=1e-9)
    y = load_fedfunds()[:, 0].numpy()
    model = sm.tsa.MarkovRegression(y, k_regimes=2, trend="c", switching_variance=True)
    params = [est[k] for k in ("transition[0,0]", "transition[1,0]", "const[0]", "const[1]", "sigma2[0]",
                               "sigma2[1]")]
    # the reported entries are the model EM fitted: statsmodels' likelihood at them is EM's (converged)
    assert model.loglike(params) == pytest.approx(fit["loglik"], abs=1e-6)


def test_em_table_without_a_constant_lists_each_regimes_slope(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.standard_normal(150)
    regime = (np.arange(150) // 25) % 2
    y = np.where(regime == 0, 1.0, -0.8) * x + 0.4 * rng.standard_normal(150)
    path = tmp_path / "reg.csv"
    path.write_text("y,x\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(y, x)))
    est, fit = _run(tmp_path / "run", f"scenario.data={{path:{path},measurements:[y],inputs:[x]}}",
                    "scenario.trend=n", "learn.method=em")
    assert sorted(k for k in est if not k.startswith(("transition", "duration"))) == \
        ["sigma2[0]", "sigma2[1]", "x[0]", "x[1]"]
    assert fit["k"] == 6
    model = sm.tsa.MarkovRegression(y, k_regimes=2, trend="n", exog=x, switching_variance=True)
    params = [est["transition[0,0]"], est["transition[1,0]"], est["x[0]"], est["x[1]"], est["sigma2[0]"],
              est["sigma2[1]"]]
    assert model.loglike(params) == pytest.approx(fit["loglik"], abs=1e-4)


def test_a_start_of_the_wrong_length_names_scenario_start(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        precheck(["experiment=markov_switching", "logger=none",
                  "scenario.start={const: [1.0], variance: [1.0, 2.0]}", f"hydra.run.dir={tmp_path / 'run'}"],
                 CONFIG_DIR)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("torchmm-run: error: scenario.start=") and \
        "expected const (2)" in err, err
    assert not (tmp_path / "run").exists()

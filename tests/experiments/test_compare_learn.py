"""``learn:`` in the generic study (issue 44): each learning estimator fits its own copy of the models
and runs with its own fit; the others keep the configured values (before: one estimator's fit - a CV
Kalman filter's R of 3.4e5 on turning data - was given silently to every estimator, and learning
through an IMM crashed)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from omegaconf import open_dict

from experiments.config import validate
from experiments.run import run_study
from tests.experiments.test_compare_study import _compose


def _run(tmp_path, tag, learn, *overrides):
    cfg = _compose("debug=compare", "figures=false", "mc_runs=6", "scenario.steps=30", *overrides)
    with open_dict(cfg):
        cfg.learn = learn
        cfg.estimators.IMM.smooth = False
    validate(cfg)
    run_study(cfg, tmp_path / tag)
    res = json.loads((tmp_path / tag / "results.json").read_text())
    return res, (tmp_path / tag / "results.md").read_text()


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("base"), "base", None)[0]


def test_each_learning_estimator_fits_its_own_models(tmp_path, base):
    learn = {"parameters": [{"model": "sensors[0]", "name": "R", "kind": "log_diagonal"}],
             "estimators": ["IMM", "KF-CV"], "iterations": 8}
    res, md = _run(tmp_path, "learn", learn)
    rows = {(row[0], row[1]): row for row in res["tables"]["learned"]["rows"]}
    assert {est for est, _ in rows} == {"IMM", "KF-CV"}
    assert res["tables"]["learned"]["columns"] == ["estimator", "parameter", "estimate", "se", "z"]
    assert {p for _, p in rows} == {"sensors[0].R[0,0]", "sensors[0].R[1,1]"}
    r_imm, r_kf = (torch.tensor([rows[(n, f"sensors[0].R[{i},{i}]")][2] for i in (0, 1)]) for n in ("IMM", "KF-CV"))
    assert all(row[3] > 0 and row[4] == pytest.approx(row[2] / row[3]) for row in rows.values())
    # the CV filter explains the turns with measurement noise: its own R is far larger than the IMM's
    assert bool((r_kf > 2 * r_imm).all())
    # each fit raised its own likelihood; the estimators that do not learn are unchanged, bit for bit
    for name in ("IMM", "KF-CV"):
        assert res["metrics"][name]["loglik"] > base["metrics"][name]["loglik"]
    for name in ("GPB2", "KF-CV-q"):
        assert res["metrics"][name] == base["metrics"][name]
    assert "Learned by IMM: 2 estimates" in md and "Learned by KF-CV: 2 estimates" in md
    assert "Not learning (configured values): GPB2, KF-CV-q" in md


def test_learn_estimator_names_the_one_that_learns(tmp_path, base):
    res, _ = _run(tmp_path, "one", {"parameters": [{"model": "sensors[0]", "name": "R"}], "estimator": "KF-CV",
                                    "iterations": 5})
    assert {row[0] for row in res["tables"]["learned"]["rows"]} == {"KF-CV"}
    assert res["metrics"]["IMM"] == base["metrics"]["IMM"]  # the KF's fit does not reach the IMM


def test_both_learn_estimator_and_estimators_is_a_config_error():
    cfg = _compose("debug=compare")
    with open_dict(cfg):
        cfg.learn = {"parameters": [{"model": "sensors[0]", "name": "R"}], "estimator": "IMM", "estimators": ["IMM"]}
    with pytest.raises(ValueError, match="learn.estimators=.*not both"):
        validate(cfg)


def test_the_start_is_estimated_and_the_estimator_runs_from_it(tmp_path, base):
    """initial_mean, initial_cov and initial_mode_probs (issue 45: the initial state): one start for every
    series, reported in the learned table, and the estimator runs from it - its log-likelihood in the
    study is the fit's (the sum over the runs), above the configured start's."""
    learn = {"parameters": [{"name": "initial_mean"}, {"name": "initial_mode_probs"},
                            {"model": "sensors[0]", "name": "R"}], "estimator": "IMM"}
    res, md = _run(tmp_path, "start", learn, "scenario.initial_mode_probs=[0.6,0.2,0.2]")
    rows = {row[1]: row for row in res["tables"]["learned"]["rows"]}
    n = sum(1 for name in rows if name.startswith("initial_mean["))
    assert n == 4 and {f"initial_mode_probs[{j}]" for j in range(3)} <= set(rows)
    assert sum(rows[f"initial_mode_probs[{j}]"][2] for j in range(3)) == pytest.approx(1.0, abs=1e-12)
    fit = dict(zip(res["tables"]["fit"]["columns"], res["tables"]["fit"]["rows"][0]))
    assert fit["k"] == 4 + 2 + 2 and fit["converged"]
    assert res["metrics"]["IMM"]["loglik"] * 6 == pytest.approx(fit["loglik"], rel=1e-9)
    configured, _ = _run(tmp_path, "configured", None, "scenario.initial_mode_probs=[0.6,0.2,0.2]")
    assert res["metrics"]["IMM"]["loglik"] > configured["metrics"]["IMM"]["loglik"]
    assert res["metrics"]["GPB2"] == configured["metrics"]["GPB2"]
    kf = {"parameters": [{"name": "initial_mean"}, {"name": "initial_cov", "kind": "variance"}], "estimator": "KF-CV"}
    res, _ = _run(tmp_path, "kf", kf)
    assert res["metrics"]["KF-CV"]["loglik"] > base["metrics"]["KF-CV"]["loglik"]
    names = [row[1] for row in res["tables"]["learned"]["rows"]]
    assert names[:4] == [f"initial_mean[{i}]" for i in range(4)] and names[4:] == [f"initial_cov[{i},{i}]"
                                                                                   for i in range(4)]
    fit = dict(zip(res["tables"]["fit"]["columns"], res["tables"]["fit"]["rows"][0]))
    assert res["metrics"]["KF-CV"]["loglik"] * 6 == pytest.approx(fit["loglik"], rel=1e-9)



def test_method_gradient_runs_the_study_with_its_fit(tmp_path, base):
    """learn.method: gradient (experiments/learning_gradient.py): R made learnable through
    torchmm.learnable_noise and fitted by Adam through the learning estimator; its NLL over the iterations
    is recorded, it ends below where it started, the estimator runs with the fit (a higher log-likelihood
    than the configured R's), and the other estimators keep the configured models bit for bit."""
    learn = {"parameters": [{"model": "sensors[0]", "name": "R", "kind": "log_diagonal"}], "estimator": "KF-CV",
             "method": "gradient", "optimizer": "adam", "lr": 0.3, "iterations": 12}
    res, md = _run(tmp_path, "gradient", learn)
    rows = {row[1]: row for row in res["tables"]["learned"]["rows"]}
    assert {row[0] for row in rows.values()} == {"KF-CV"}
    assert set(rows) == {f"sensors[0].R[{i},{j}]" for i in (0, 1) for j in (0, 1)}  # (the whole matrix)
    assert rows["sensors[0].R[0,0]"][2] > 0 and rows["sensors[0].R[1,1]"][2] > 0
    assert rows["sensors[0].R[0,1]"][2] == 0 and rows["sensors[0].R[1,0]"][2] == 0  # (log_diagonal: diagonal)
    curve = np.load(tmp_path / "gradient" / "curves.npz")["learn/nll/KF-CV"]
    assert curve.shape[-1] == 12 and curve[..., -1].max() < curve[..., 0].min()  # the fit lowered its NLL
    assert res["metrics"]["KF-CV"]["loglik"] > base["metrics"]["KF-CV"]["loglik"]
    for name in ("IMM", "GPB2", "KF-CV-q"):
        assert res["metrics"][name] == base["metrics"][name]
    assert "fitted with adam (method gradient: no standard errors)" in md
    assert all(row[3] is None for row in rows.values())


def test_em_with_fixed_entries_from_config(tmp_path, base):
    """learn.method: em with fixed entries (issue 45): the position sensor's H with only its two gains
    free, R diagonal; the table lists the free entries only, the likelihood never falls and the fixed
    entries keep their values (the filter runs with them: its log-likelihood is the fit's)."""
    H_fixed = [[False, True, True, True], [True, True, False, True]]
    learn = {"method": "em", "iterations": 15, "estimator": "KF-CV",
             "parameters": [{"model": "sensors[0]", "name": "H", "fixed": H_fixed},
                            {"model": "sensors[0]", "name": "R", "fixed": [[False, True], [True, False]]}]}
    res, _ = _run(tmp_path, "em_fixed", learn)
    names = [row[1] for row in res["tables"]["learned"]["rows"]]
    assert names == ["sensors[0].H[0,0]", "sensors[0].H[1,2]", "sensors[0].R[0,0]", "sensors[0].R[1,1]"]
    fit = dict(zip(res["tables"]["fit"]["columns"], res["tables"]["fit"]["rows"][0]))
    assert fit["k"] == 4
    import numpy as np

    curve = np.load(tmp_path / "em_fixed" / "curves.npz")["learn/em_loglik/KF-CV"]
    assert len(curve) == 16 and bool((np.diff(curve) >= -1e-9 * np.abs(curve[1:])).all())
    assert res["metrics"]["KF-CV"]["loglik"] * 6 == pytest.approx(fit["loglik"], rel=1e-9)
    assert res["metrics"]["KF-CV"]["loglik"] > base["metrics"]["KF-CV"]["loglik"]

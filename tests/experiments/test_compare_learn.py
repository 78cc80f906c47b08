"""``learn:`` in the generic study (issue 44): each learning estimator fits its own copy of the models
and runs with its own fit; the others keep the configured values (before: one estimator's fit - a CV
Kalman filter's R of 3.4e5 on turning data - was given silently to every estimator, and learning
through an IMM crashed)."""

from __future__ import annotations

import json

import pytest
import torch
from omegaconf import open_dict

from experiments.config import validate
from experiments.run import run_study
from tests.experiments.test_compare_study import _compose


def _run(tmp_path, tag, learn):
    cfg = _compose("debug=compare", "figures=false", "mc_runs=6", "scenario.steps=30")
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

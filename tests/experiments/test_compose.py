"""Studies compose library parts from config groups: mode filters, combinators, policies, debug sizes."""

from __future__ import annotations

import json

import pytest

from experiments.config import ConfigError, validate
from experiments.run import run_study
from tests.experiments.test_studies import _compose_numbers as _compose


def _tables(name, tmp_path, *overrides):
    run_study(_compose(name, f"debug={name}", "logger=none", *overrides), tmp_path)
    return json.loads((tmp_path / "results.json").read_text())["tables"]


def _numbers(rows):
    return [[v for v in row if isinstance(v, float)] for row in rows]


def test_imm_tf_with_unscented_modes_equals_kalman_modes(tmp_path):
    """`mode_filter=unscented` runs all six paper-000 estimators over UKF modes; on the linear model
    they compute the Kalman versions' numbers."""
    a = _tables("imm_tf", tmp_path / "kf", "scenario.steps=40")
    b = _tables("imm_tf", tmp_path / "ukf", "scenario.steps=40", "mode_filter=unscented")
    for table in ("table1", "rs_sweep"):
        for ra, rb in zip(_numbers(a[table]["rows"]), _numbers(b[table]["rows"])):
            assert ra == pytest.approx(rb, rel=1e-8, abs=1e-10)


def test_imm_baseline_composes_combinators_policies_and_particle_modes(tmp_path):
    t = _tables("imm_baseline", tmp_path / "a", "+estimator@estimators.VS=vsmm", "policy=all",
                "+estimator@estimators.Static=static")
    rows = {row[0]: row for row in t["rmse"]["rows"]}
    assert rows["VS"][1:4] == pytest.approx(rows["IMM"][1:4], rel=1e-10)  # every model active: the IMM
    assert rows["Static"][1] != rows["IMM"][1]
    p = _tables("imm_baseline", tmp_path / "b", "mode_filter=particle", "mode_filter.num_particles=200")
    prow = {row[0]: row for row in p["rmse"]["rows"]}
    for name in ("IMM", "GPB1", "GPB2", "KF"):  # particle modes: Monte Carlo error of 200 particles
        assert prow[name][1] == pytest.approx(rows[name][1], rel=0.1)


def test_mevsmm_selection_over_a_kalman_bank(tmp_path):
    t = _tables("mevsmm", tmp_path, "+mevsmm_estimator@mevsmm.estimators.KF-VSMM=vsmm", "policy=all")
    rows = {row[0]: row for row in t["table1"]["rows"]}
    assert rows["KF-VSMM"][1] == 21.0  # policy=all keeps the 21 models
    rmse = {row[0]: row for row in t["rmse"]["rows"]}
    assert rmse["KF-VSMM"][1] > 0


@pytest.mark.parametrize("override, key", [
    (["+mode_filter.num_particles=5"], "mode_filter.num_particles"),
    (["mode_filter=particle", "mode_filter.num_particles=0"], "mode_filter.num_particles"),
    (["policy.entropy=exact"], "policy.entropy"),
    (["estimators.IMM.combinator._target_=torch.nn.Linear"], "estimators.IMM.combinator"),
])
def test_bad_composition_keys_name_the_key(override, key):
    with pytest.raises(ConfigError, match=rf"^{key}"):
        validate(_compose("imm_baseline", *override))


def test_imm_tf_estimators_are_config_nodes(tmp_path):
    """A new multi-rate estimator is a config entry: a TransferIMM with the other smoothing reference
    equals the IMM-TF of a run where that is the study-wide option."""
    added = _tables("imm_tf", tmp_path / "a",
                    "+tf_estimators.TF-mixed={_target_:torchmm.TransferIMM,_partial_:true,smoothing_reference:mixed}",
                    "estimator_names=[IMM-TF,TF-mixed]")
    global_mixed = _tables("imm_tf", tmp_path / "b", "transfer.smoothing_reference=mixed", "estimator_names=[IMM-TF]")
    rows = {(r[0], r[1]): r for r in added["table1"]["rows"]}
    ref = {(r[0], r[1]): r for r in global_mixed["table1"]["rows"]}
    for (ratio, name), row in ref.items():
        assert rows[(ratio, "TF-mixed")][2:] == pytest.approx(row[2:], rel=1e-12)
        assert rows[(ratio, "IMM-TF")][2] != row[2]  # the default (combined) reference differs
    with pytest.raises(ConfigError, match=r"^tf_estimators"):
        validate(_compose("imm_tf", "tf_estimators.IMM._target_=torch.nn.Linear"))

"""Study learn_dynamics: tables and artefacts at a tiny size; the acceptance figures at full size (slow)."""

from __future__ import annotations

import json

import pytest
from hydra import compose, initialize_config_dir

from experiments.run import CONFIG_DIR, run_study

#: the overrides tests/experiments/test_studies.py needs for this study (mc_runs=4 in seconds)
FAST = ["learn.scenario.steps=30", "learn.part_a.iterations=2", "learn.part_b.iterations=2"]


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose("config", overrides=["experiment=learn_dynamics", *overrides])


def test_study_tables_figures_and_resume(tmp_path):
    cfg = _compose("mc_runs=4", "progress=false", "logger=tensorboard", *FAST)
    results = run_study(cfg, tmp_path)
    data = json.loads((tmp_path / "results.json").read_text())
    learn, rmse = data["tables"]["learn"], data["tables"]["rmse"]
    assert learn["columns"][:4] == ["quantity", "true", "learned", "initial"]
    quantities = [row[0] for row in learn["rows"]]
    assert quantities[:10] == [f"tpm[{i},{j}]" for i in range(3) for j in range(3)] + ["q"]
    assert "mlp_turn_rate" in quantities
    assert rmse["columns"][:3] == ["estimator", "pos_rmse", "vel_rmse"]
    assert {row[0] for row in rmse["rows"]} == {"true-model IMM", "learned IMM", "initial IMM"}
    for row in learn["rows"][:9]:  # the learned matrix is a transition matrix; truth as configured
        assert 0 <= row[2] <= 1 and row[1] == pytest.approx(0.9 if row[0][4] == row[0][6] else 0.05)
    for name in ("loss_curve", "parameter_trajectories", "rmse_before_after", "rmse_over_time"):
        assert (tmp_path / "figures" / f"{name}.png").exists(), name
    assert list((tmp_path / "tb").glob("events.out.tfevents.*"))
    assert (tmp_path / "checkpoints" / "mlp_mode.pt").exists()
    # resume: the training units are not recomputed and give the same tables
    again = run_study(_compose("mc_runs=4", "progress=false", "logger=none", *FAST), tmp_path)
    assert again.tables["learn"].rows == results.tables["learn"].rows


@pytest.mark.slow
def test_full_study_meets_the_acceptance_figures(tmp_path):
    """400 training runs: TPM within 0.05, learned IMM within 5 % of the true model, MLP helps."""
    results = run_study(_compose("progress=false", "logger=none"), tmp_path)
    learn = {row[0]: row for row in results.tables["learn"].rows}
    for i in range(3):
        for j in range(3):
            row = learn[f"tpm[{i},{j}]"]
            assert abs(row[2] - row[1]) < 0.05, row
    rmse = {(row[0], row[3]): row for row in results.tables["rmse"].rows}
    true_pos = rmse[("true-model IMM", "a, b")][1]
    assert abs(rmse[("learned IMM", "a")][1] / true_pos - 1) <= 0.05
    assert rmse[("learned IMM", "b")][1] < rmse[("initial IMM", "b")][1]

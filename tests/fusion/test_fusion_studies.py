"""The paper-002 studies run, write the issue's tables and respect the theory's orderings."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir

from experiments.run import CONFIG_DIR, run_study


def _run(name, tmp_path, *overrides):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("config", overrides=[f"experiment={name}", "progress=false", "logger=none", *overrides])
    return run_study(cfg, tmp_path)


def test_fusion_radar_tables(tmp_path):
    res = _run("fusion_radar", tmp_path, "mc_runs=40", "radar.steps=30")
    table = res.tables["ex1_rmse"]
    assert table.columns[:2] == ["estimator", "pos_rmse"]
    rows = {r[0]: r for r in table.rows}
    assert {"LF1", "LF2", "LF3", "AUG1", "AUG2", "AUG3", "MF"} <= set(rows)
    for i in (1, 2, 3):  # augmented and non-augmented local filters give the same estimates
        assert rows[f"AUG{i}"][1] == pytest.approx(rows[f"LF{i}"][1], rel=1e-9)
    # computed: CF <= MF <= every local filter (time-averaged computed RMSE)
    assert rows["CF"][2] <= rows["MF"][2] + 1e-9
    assert all(rows["MF"][2] <= rows[f"LF{i}"][2] + 1e-9 for i in (1, 2, 3))
    assert res.metrics["AUG"]["max_abs_diff_vs_LF"] < 1e-6
    assert (tmp_path / "figures" / "fig1_tracking.png").exists()
    assert (tmp_path / "figures" / "fig2_rmse.png").exists()


def test_fusion_ups_tables_and_orderings(tmp_path):
    res = _run("fusion_ups", tmp_path, "mc_runs=60", "ups.steps=50", "ups.burn_in=20")
    var = {r[0]: r[1:] for r in res.tables["ex2_variance"].rows}
    assert list(var) == ["LF1", "LF2", "LF3", "SF", "DF", "MF", "CF"]
    assert res.tables["ex2_variance"].columns == ["estimator", "comp1", "comp2", "comp3"]
    for c in range(3):
        assert var["CF"][c] <= var["MF"][c] <= var["DF"][c] <= var["SF"][c]
        assert all(var["SF"][c] <= var[f"LF{i}"][c] for i in (1, 2, 3))
    mc = res.tables["ex2_mc"]
    assert mc.columns[:4] == ["estimator", "comp1", "comp2", "comp3"]
    assert [r[0] for r in mc.rows] == list(var)
    hz = res.tables["ex2_horizon"]
    assert hz.columns[:4] == ["N", "comp1", "comp2", "comp3"]
    assert [r[0] for r in hz.rows] == [-2, -1, 0, 1, 2]
    for a, b in zip(hz.rows, hz.rows[1:]):  # predictor >= filter >= smoother, per component
        assert all(b[c] <= a[c] + 1e-12 for c in (1, 2, 3))
    assert {"fig3_variances.png", "fig4_horizon.png"} <= {p.name for p in (tmp_path / "figures").iterdir()}


def test_fusion_benchmark_runs_and_agrees():
    import re
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run(
        [sys.executable, str(root / "benchmarks" / "fusion_throughput.py"),
         "--runs", "8", "--steps", "12", "--numpy-runs", "3", "--repeats", "1"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert re.fullmatch(r"speedup_vs_numpy_loop=[0-9.]+ augmented_over_nonaugmented=[0-9.]+", lines[-1])
    diff = float(re.search(r"numpy reference: ([0-9.e+-]+)", proc.stdout).group(1))
    assert diff < 1e-9

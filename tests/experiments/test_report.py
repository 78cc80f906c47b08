"""torchmm-report: runs and sweeps combined into one table with Student-t intervals over seeds."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from experiments import report as rep

ROOT = Path(__file__).resolve().parents[2]


def _write_run(path: Path, config: dict, tables: dict, overrides=()) -> None:
    path.mkdir(parents=True)
    (path / "results.json").write_text(json.dumps({"experiment": "toy", "config": config, "tables": tables}))
    if overrides:
        (path / ".hydra").mkdir()
        (path / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))


def _synthetic_sweep(root: Path, rng: np.random.Generator) -> dict:
    """A 2 x 2 override sweep (a, b) x 3 seeds; returns the values written, by (a, b, estimator, column)."""
    written: dict = {}
    job = 0
    for a in (1, 2):
        for b in ("x", "y"):
            for seed in (0, 1, 2):
                rows = []
                for est in ("IMM", "KF"):
                    rmse, nees = rng.normal(5 + a, 1), rng.normal(2, 0.5)
                    written.setdefault((a, b, est, "rmse"), []).append(rmse)
                    written.setdefault((a, b, est, "nees"), []).append(nees)
                    rows.append([est, 0.25, rmse, nees])  # 0.25: the same in every run -> a label
                config = {"experiment_name": "toy", "seed": seed, "a": a, "model": {"b": b}, "mc_runs": 10,
                          "progress": job % 2 == 0, "logger": {"kind": "none"}}  # progress/logger: not factors
                _write_run(root / f"{job}_a={a},b={b},seed={seed}", config,
                           {"rmse": {"columns": ["estimator", "alpha", "rmse", "nees"], "rows": rows}},
                           overrides=[f"a={a}", f"model.b={b}", f"seed={seed}"])
                job += 1
    return written


def test_report_of_a_2x2_sweep_over_3_seeds_gives_the_means_and_t_intervals(tmp_path):
    written = _synthetic_sweep(tmp_path / "sweep", np.random.default_rng(7))
    runs = rep.collect_runs([tmp_path / "sweep"])
    assert len(runs) == 12
    out = rep.combine(runs)["toy"]
    assert out["factors"] == ["a", "model.b"]  # seed is the replicate; progress and logger are ignored
    assert len(out["groups"]) == 4 and all(sorted(g["replicates"]) == [0, 1, 2] for g in out["groups"])
    table = out["tables"]["rmse"]
    assert table["labels"] == ["estimator", "alpha"] and table["measurements"] == ["rmse", "nees"]
    assert len(table["rows"]) == 8
    for row in table["rows"]:
        factors = out["groups"][row["group"]]["factors"]
        for column in ("rmse", "nees"):
            values = np.array(written[(factors["a"], factors["model.b"], row["labels"]["estimator"], column)])
            got = row["values"][column]
            low, high = stats.t.interval(0.95, df=2, loc=values.mean(), scale=stats.sem(values))
            assert got["n"] == 3
            assert got["mean"] == pytest.approx(values.mean(), rel=1e-12)
            assert got["sd"] == pytest.approx(values.std(ddof=1), rel=1e-12)
            assert (got["ci_low"], got["ci_high"]) == pytest.approx((low, high), rel=1e-10)


def test_report_files_and_cli(tmp_path):
    _synthetic_sweep(tmp_path / "sweep", np.random.default_rng(1))
    assert rep.main([str(tmp_path / "sweep"), "--level", "0.9"]) == 0
    out = tmp_path / "sweep" / "report"
    for name in ("report.md", "report.csv", "report.json", "report.tex", "report.png", "report.pdf"):
        assert (out / name).stat().st_size > 0, name
    md = (out / "report.md").read_text()
    assert "| a | model.b | estimator | alpha | n | rmse | nees |" in md and "±" in md
    lines = (out / "report.csv").read_text().splitlines()
    assert lines[0].split(",")[:7] == ["experiment", "table", "group", "factors", "labels", "measurement", "n"]
    assert len(lines) == 1 + 8 * 2 + 4 * 2  # 8 rows x 2 measurements; paired: 4 (KF - IMM) x 2
    assert json.loads((out / "report.json").read_text())["toy"]["level"] == 0.9


def test_report_errors_are_one_line(tmp_path, capsys):
    assert rep.main([str(tmp_path / "missing")]) == 2
    assert "PATH" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert rep.main([str(tmp_path / "empty")]) == 2
    assert rep.main([str(tmp_path / "empty"), "--level", "95"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "--level" in err[-1]


def test_rows_are_matched_by_their_estimator_not_their_position(tmp_path, capsys):
    """Two seeds of one config whose second lists the estimators in another order (the flattened config is
    the same): each report row averages one estimator's values, and the paired differences subtract the
    reference's (before: row "IMM" averaged IMM at seed 0 with KF at seed 1). A run of the config with
    another estimator (KF-q for KF): the table is combined on the union of the rows, each over the runs
    holding it, and the runs lacking a row are named (before: the whole table was left out)."""
    values = {0: {"IMM": 4.0, "KF": 6.0, "GPB2": 5.0}, 1: {"IMM": 4.5, "KF": 6.3, "GPB2": 5.6}}
    orders = {0: ["IMM", "KF", "GPB2"], 1: ["GPB2", "KF", "IMM"]}
    for seed in (0, 1):
        rows = [[est, values[seed][est], 2.0 * values[seed][est]] for est in orders[seed]]
        _write_run(tmp_path / "runs" / f"s{seed}", {"seed": seed, "mc_runs": 10},
                   {"summary": {"columns": ["estimator", "rmse", "nees"], "rows": rows}})
    report = rep.combine(rep.collect_runs([tmp_path / "runs"]), reference="IMM")["toy"]
    got = {row["labels"]["estimator"]: row["values"] for row in report["tables"]["summary"]["rows"]}
    for est in ("IMM", "KF", "GPB2"):
        want = [values[s][est] for s in (0, 1)]
        assert got[est]["rmse"]["mean"] == pytest.approx(np.mean(want), rel=1e-14)
        assert got[est]["nees"]["sd"] == pytest.approx(2 * np.std(want, ddof=1), rel=1e-12)
    paired = {row["labels"]["estimator"]: row["values"] for row in report["paired"]["summary"]["rows"]}
    for est in ("KF", "GPB2"):
        d = [values[s][est] - values[s]["IMM"] for s in (0, 1)]
        assert paired[est]["rmse"]["mean"] == pytest.approx(np.mean(d), rel=1e-12)
        assert paired[est]["rmse"]["sd"] == pytest.approx(np.std(d, ddof=1), rel=1e-10)
    capsys.readouterr()
    _write_run(tmp_path / "runs" / "s2", {"seed": 2, "mc_runs": 10},
               {"summary": {"columns": ["estimator", "rmse", "nees"], "rows": [["IMM", 4.1, 8.2], ["KF-q", 6.1, 1.0],
                                                                            ["GPB2", 5.2, 10.4]]}})
    values[2] = {"IMM": 4.1, "KF-q": 6.1, "GPB2": 5.2}
    report = rep.combine(rep.collect_runs([tmp_path / "runs"]), reference="IMM")["toy"]
    table = report["tables"]["summary"]
    got = {row["labels"]["estimator"]: row["values"] for row in table["rows"]}
    assert sorted(got) == ["GPB2", "IMM", "KF", "KF-q"]
    assert [e for e in got if e != "KF-q"] == orders[0]  # the first run's order
    for est in got:
        want = [values[s][est] for s in (0, 1, 2) if est in values[s]]
        assert got[est]["rmse"]["n"] == len(want)
        assert got[est]["rmse"]["mean"] == pytest.approx(np.mean(want), rel=1e-14)
    assert got["KF-q"]["rmse"]["ci_low"] is None  # one run: no interval
    paired = {row["labels"]["estimator"]: row["values"]["rmse"]
              for row in report["paired"]["summary"]["rows"]}
    d = [values[s]["KF"] - values[s]["IMM"] for s in (0, 1)]
    assert paired["KF"]["n"] == 2 and paired["KF"]["mean"] == pytest.approx(np.mean(d), rel=1e-12)
    assert paired["KF-q"]["n"] == 1 and paired["KF-q"]["mean"] == pytest.approx(6.1 - 4.1, rel=1e-12)
    absent = {item["labels"]["estimator"]: item["runs"] for item in table["absent"]["rows"]}
    runs = {p.name: str(p) for p in (tmp_path / "runs").iterdir()}
    assert absent == {"KF": [runs["s2"]], "KF-q": [runs["s0"], runs["s1"]]}
    err = capsys.readouterr().err
    assert "toy/summary: " in err and "row KF not in 1 run(s)" in err and "row KF-q not in 2 run(s)" in err


def test_single_runs_and_constant_columns():
    assert rep.mean_interval([3.0])["ci_low"] is None
    constant = rep.mean_interval([2.5, 2.5, 2.5])
    assert constant["sd"] == 0.0 and constant["ci_low"] == constant["ci_high"] == 2.5
    nan = rep.mean_interval([1.0, float("nan"), 3.0])
    assert nan["n"] == 2 and nan["mean"] == 2.0
    assert not math.isnan(nan["ci_high"])


def test_report_of_a_real_sweep(tmp_path):
    """torchmm-run -m over 2 mc_runs x 2 seeds, then torchmm-report: the report's means are the
    means of the runs' own results.json (folders named by their overrides)."""
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "experiments.run", "-m", "experiment=imm_baseline", "debug=imm_baseline",
           "mc_runs=2,3", "seed=0,1", "scenario.steps=30", "progress=false", "logger=none",
           "hydra/launcher=basic", f"hydra.sweep.dir={sweep}"]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    folders = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    assert len(folders) == 4 and "0_debug=imm_baseline,mc_runs=2,scenario.steps=30,seed=0" in folders
    proc = subprocess.run([sys.executable, "-m", "experiments.report", str(sweep)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    body = json.loads((sweep / "report" / "report.json").read_text())["imm_baseline"]
    assert body["factors"] == ["mc_runs"] and len(body["groups"]) == 2
    own = {}
    for path in sweep.glob("*/results.json"):
        res = json.loads(path.read_text())
        cfg = res["config"]
        for row in res["tables"]["rmse"]["rows"]:
            own.setdefault((cfg["mc_runs"], row[0]), []).append(row[1])
    rows = body["tables"]["rmse"]["rows"]
    assert len(rows) == 2 * 4
    for row in rows:
        f = body["groups"][row["group"]]["factors"]
        values = own[(f["mc_runs"], row["labels"]["estimator"])]
        assert row["values"]["pos_rmse"]["n"] == 2
        assert row["values"]["pos_rmse"]["mean"] == pytest.approx(float(np.mean(values)), rel=1e-12)


def test_a_true_false_column_is_a_measurement_the_fraction_of_runs_where_it_is_true(tmp_path):
    """Two seeds whose ``rmse_inside_95`` differ for IMM (True, False): the table is reported (before: the
    bool was taken for a row label, the runs' rows did not match and the whole table was left out), with
    the fraction of runs where it is True and its n; a column True in every run is a measurement too (never
    a label), an empty cell is left out of n, and the flag is not differenced in the paired table."""
    flags = {0: {"IMM": True, "KF": False}, 1: {"IMM": False, "KF": False}}
    rmse = {0: {"IMM": 4.0, "KF": 6.0}, 1: {"IMM": 4.4, "KF": 6.5}}
    for seed in (0, 1):
        rows = [[est, rmse[seed][est], flags[seed][est], True, None if (est, seed) == ("KF", 1) else True]
                for est in ("IMM", "KF")]
        _write_run(tmp_path / "runs" / f"s{seed}", {"seed": seed, "mc_runs": 10},
                   {"t": {"columns": ["estimator", "rmse", "rmse_inside_95", "always", "sometimes"],
                          "rows": rows}})
    assert rep.main([str(tmp_path / "runs")]) == 0
    body = json.loads((tmp_path / "runs" / "report" / "report.json").read_text())["toy"]
    table = body["tables"]["t"]
    assert table["labels"] == ["estimator"]
    assert table["measurements"] == ["rmse", "rmse_inside_95", "always", "sometimes"]
    assert table["fractions"] == ["rmse_inside_95", "always", "sometimes"]
    got = {row["labels"]["estimator"]: row["values"] for row in table["rows"]}
    for est in ("IMM", "KF"):
        cells = [flags[s][est] for s in (0, 1)]
        assert got[est]["rmse_inside_95"]["n"] == 2 and got[est]["rmse_inside_95"]["true"] == sum(cells)
        assert got[est]["rmse_inside_95"]["mean"] == pytest.approx(np.mean(cells), rel=1e-15)
        assert got[est]["rmse_inside_95"]["ci_low"] is None
        assert got[est]["always"]["mean"] == 1.0 and got[est]["always"]["n"] == 2
        assert got[est]["rmse"]["mean"] == pytest.approx(np.mean([rmse[s][est] for s in (0, 1)]), rel=1e-14)
    assert (got["KF"]["sometimes"]["n"], got["KF"]["sometimes"]["true"]) == (1, 1)
    assert body["paired"]["t"]["measurements"] == ["rmse"]
    md = (tmp_path / "runs" / "report" / "report.md").read_text()
    assert "| IMM | 2 | 4.2000 ± " in md and "| 0.5000 (1/2) | 1.0000 (2/2) |" in md
    assert "rmse_inside_95, always, sometimes: true or false in each run" in md


def _job(sweep: Path, num: int, seed: int) -> Path:
    """A sweep job's folder with Hydra's record of its number (as -m writes it)."""
    folder = sweep / f"{num}_seed={seed}"
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "hydra.yaml").write_text(f"hydra:\n  job:\n    num: {num}\n")
    (folder / ".hydra" / "config.yaml").write_text(f"experiment_name: toy\nseed: {seed}\n")
    return folder


def test_interrupted_runs_and_jobs_that_never_started_are_named_and_counted(tmp_path, capsys):
    """A sweep of seed=0,1,2,3 (multirun.yaml) where job 0 finished, job 1 was interrupted after 2 units
    (checkpoint.json, no results.json), job 2 stopped inside a study that rewrites results.json after each
    unit (a results.json whose provenance has no end) and job 3 never started: the report holds job 0 only,
    and names the 3 others with why (before: only results.json was looked for, so job 1 and 3 were skipped
    without a word and job 2's partial tables were averaged as if it had finished)."""
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "multirun.yaml").write_text("hydra:\n  overrides:\n    task:\n    - experiment=toy\n"
                                         "    - seed=0,1,2,3\n    - mc_runs=10\n")
    table = {"t": {"columns": ["estimator", "rmse"], "rows": [["IMM", 4.0]]}}
    done = _job(sweep, 0, 0)
    finished = {"experiment": "toy", "config": {"seed": 0}, "tables": table,
                "provenance": {"start": "s", "end": "e"}}
    (done / "results.json").write_text(json.dumps(finished))
    stopped = _job(sweep, 1, 1)
    (stopped / "checkpoint.json").write_text(json.dumps({"config_hash": "x",
                                                         "config": {"experiment_name": "toy"},
                                                         "units": {"a": 1, "b": 2}}))
    partial = _job(sweep, 2, 2)
    partial_table = {"t": {"columns": ["estimator", "rmse"], "rows": [["IMM", 99.0]]}}
    (partial / "results.json").write_text(json.dumps({"experiment": "toy", "config": {"seed": 2},
                                                      "tables": partial_table, "provenance": {}}))
    assert rep.main([str(sweep)]) == 0
    err = capsys.readouterr().err
    assert (f"{stopped.resolve()}: left out: interrupted or failed: no results.json (checkpoint.json holds 2 "
            in err)
    assert f"{partial.resolve()}: left out: interrupted or failed: its results.json was written before" in err
    assert (f"{sweep.resolve()}: left out: 1 of the 4 jobs of its multirun.yaml never started "
            "(no folder: job 3)" in err)
    body = json.loads((sweep / "report" / "report.json").read_text())["toy"]
    assert [g["runs"] for g in body["groups"]] == [[str(done)]]
    (row,) = body["tables"]["t"]["rows"]
    assert row["labels"]["rmse"] == 4.0  # one run: its value (a label: the same in every run), not 99
    named = sorted(map(str, (stopped.resolve(), partial.resolve(), sweep.resolve())))
    assert sorted(item["path"] for item in body["left_out"]) == named
    assert sum(item["runs"] for item in body["left_out"]) == 4 - 1
    assert "**Left out: 3 run(s)**" in (sweep / "report" / "report.md").read_text()
    (done / "results.json").unlink()  # nothing finished: an error that says why
    assert rep.main([str(sweep)]) == 2
    assert "no finished run (results.json) under" in capsys.readouterr().err

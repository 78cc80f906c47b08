"""torchmm-report over runs whose tables differ: a metric that some runs could not compute (a column they
lack), a study's paired row some runs lack, a standard error only some replicates have. Before: the whole
table was left out (exit 0, one warning), a standard error of one replicate was shown as that of the mean of
five, and report.md showed one n per row whatever a cell's."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import stats

from experiments import report as rep
from tests.experiments.test_report import _write_run


def _interval(values):
    """Mean and Student-t half-width (95 %) of ``values``, by scipy."""
    values = np.asarray(values, dtype=float)
    low, high = stats.t.interval(0.95, df=len(values) - 1, loc=values.mean(), scale=stats.sem(values))
    return values.mean(), (high - low) / 2


def _summary_sweep(root):
    """2 groups (missing = 0.0, 0.7) x 3 seeds of a summary table; group 0.0's runs have ``white`` and
    ``white_bound`` (21 vs 19 columns in compare), group 0.7's seed 2 alone has ``extra``; seed 1 of group 0.7
    records that it could not compute ``white``. Returns the values written, by (missing, estimator,
    column)."""
    rng = np.random.default_rng(11)
    written: dict = {}
    for missing in (0.0, 0.7):
        for seed in (0, 1, 2):
            columns = ["estimator", "rmse", "rmse_se", "nees"]
            if missing == 0.0:
                columns += ["white", "white_bound"]
            if missing == 0.7 and seed == 2:
                columns.insert(2, "extra")
            rows = []
            for est in ("IMM", "KF"):
                cells = {"estimator": est, "rmse": rng.normal(4, 1), "rmse_se": abs(rng.normal(0.3, 0.05)),
                         "nees": rng.normal(2, 0.3), "white": rng.normal(0, 0.1), "white_bound": 0.5,
                         "extra": rng.normal(9, 1)}
                for c in columns[1:]:
                    written.setdefault((missing, est, c), []).append(cells[c])
                rows.append([cells[c] for c in columns])
            dropped = {"white (IMM)": "no two consecutive innovations"} if (missing, seed) == (0.7, 1) else {}
            path = root / f"m{missing}_s{seed}"
            _write_run(path, {"seed": seed, "scenario": {"missing": missing}},
                       {"summary": {"columns": columns, "rows": rows}})
            data = json.loads((path / "results.json").read_text())
            (path / "results.json").write_text(json.dumps({**data, "dropped": dropped}))
    return written


def test_runs_with_other_columns_are_combined_on_the_union(tmp_path, capsys):
    written = _summary_sweep(tmp_path / "runs")
    assert rep.main([str(tmp_path / "runs")]) == 0
    err = capsys.readouterr().err
    assert "left out" not in err
    assert "toy/summary: extra not in 5 run(s); white not in 3 run(s); white_bound not in 3 run(s)" in err
    body = json.loads((tmp_path / "runs" / "report" / "report.json").read_text())["toy"]
    table = body["tables"]["summary"]
    assert table["measurements"] == ["rmse", "extra", "nees", "white"]
    assert table["standard_errors"] == ["rmse_se"]
    assert "white_bound" in table["labels"]  # the same in every run of its group (None in the other)
    for row in table["rows"]:
        missing = body["groups"][row["group"]]["factors"]["scenario.missing"]
        for column in ("rmse", "nees", "white", "extra"):
            values = written.get((missing, row["labels"]["estimator"], column), [])
            got = row["values"][column]
            assert got["n"] == len(values)
            if len(values) >= 2:
                mean, half = _interval(values)
                assert got["mean"] == pytest.approx(mean, rel=1e-12)
                assert (got["ci_high"] - got["ci_low"]) / 2 == pytest.approx(half, rel=1e-9)
            elif values:
                assert got["mean"] == values[0] and got["ci_low"] is None
            else:
                assert got["mean"] is None
    runs = {p.name: str(p) for p in (tmp_path / "runs").iterdir() if p.is_dir() and p.name != "report"}
    absent = table["absent"]["columns"]
    assert absent["white"] == absent["white_bound"] == [runs[f"m0.7_s{s}"] for s in (0, 1, 2)]
    assert absent["extra"] == [runs[f"m0.0_s{s}"] for s in (0, 1, 2)] + [runs[f"m0.7_s{s}"] for s in (0, 1)]
    paired = body["paired"]["summary"]
    assert paired["measurements"] == ["rmse", "extra", "nees", "white"]
    for row in paired["rows"]:
        missing = body["groups"][row["group"]]["factors"]["scenario.missing"]
        d = np.subtract(written[(missing, "KF", "rmse")], written[(missing, "IMM", "rmse")])
        assert row["values"]["rmse"]["mean"] == pytest.approx(d.mean(), rel=1e-12)
    md = (tmp_path / "runs" / "report" / "report.md").read_text()
    assert "- column white: not in 3 of 6 runs: scenario.missing=0.7000 (seed 0, 1, 2)" in md
    assert ("- column extra: not in 5 of 6 runs: scenario.missing=0.0000 (seed 0, 1, 2); "
            "scenario.missing=0.7000 (seed 0, 1)") in md
    # the runs' own dropped entries, with the runs (the report read none before)
    assert "- white (IMM): no two consecutive innovations (1 of 6 runs: scenario.missing=0.7000 (seed 1))" \
        in md
    assert body["dropped"] == [{"metric": "white (IMM)", "reason": "no two consecutive innovations",
                                "runs": [runs["m0.7_s1"]]}]
    # a cell with fewer replicates than its row says so: extra (n=1) in a row of n = 3, in report.md and .tex
    (kf,) = [r for r in table["rows"] if r["labels"]["estimator"] == "KF" and r["group"] == 1]
    extra = format(kf["values"]["extra"]["mean"], ".4f")
    assert f"| {extra} (n=1) |" in md
    tex = (tmp_path / "runs" / "report" / "report.tex").read_text()
    assert f"& {extra} (n=1) &" in tex
    assert "% toy: dropped in the runs: white (IMM): no two consecutive innovations" in tex


def test_a_standard_error_is_pooled_only_over_every_replicate_in_the_mean():
    """nis in 5 seeds, nis_se in one (compare with mc_runs=2: fewer than two Monte Carlo runs with a value in
    the others): no pooled value, named as dropped (before: 2.6485, the one seed's own, in a row of n 5).
    Every replicate with an se: sqrt(sum se^2) / n. The se of replicates whose estimate is missing does not
    count, and an se without its estimate is dropped."""
    se4 = 2.6485139772947326
    nis = [4.9189, 0.2954, 1.2910, 0.0595, 3.2363]
    got = rep.pooled_se([None, None, None, None, se4], nis)
    assert got["mean"] is None and got["n"] == 1 and "4 of the 5 replicates" in got["dropped"]
    ses = [0.5, 0.25, 1.5, 0.75, se4]
    got = rep.pooled_se(ses, nis)
    assert got["n"] == 5 and got["mean"] == pytest.approx(np.sqrt(np.sum(np.square(ses))) / 5, rel=1e-15)
    assert "dropped" not in got
    got = rep.pooled_se([0.5, float("nan"), 0.25], [1.0, None, 2.0])  # replicate 1 is not in the mean
    assert got["n"] == 2 and got["mean"] == pytest.approx(math.hypot(0.5, 0.25) / 2, rel=1e-15)
    assert rep.pooled_se([None, None], [1.0, 2.0]) == {"n": 0, "mean": None, "sd": None, "ci_low": None,
                                                       "ci_high": None}  # no se anywhere: an empty cell
    assert "dropped" in rep.pooled_se([0.5], [None])  # an se without its estimate


def test_a_study_paired_table_with_rows_only_some_runs_hold(tmp_path, capsys):
    """The study's own paired table (metric, estimator, reference, difference, se): the row of a metric the
    study could compute in seed 4 only is combined over that seed (n 1), the others over 5, and the report
    names the 4 runs lacking it (before: the table was left out: 14 vs 19 rows)."""
    rng = np.random.default_rng(5)
    columns = ["metric", "estimator", "reference", "difference", "se", "ci_low", "ci_high"]
    written: dict = {}
    for seed in range(5):
        rows = []
        for metric in ("rmse", "nis", "nees"):
            if metric == "nis" and seed != 4:
                continue
            d, se = rng.normal(0.1, 0.05), abs(rng.normal(0.02, 0.005))
            written.setdefault(metric, []).append((d, se))
            rows.append([metric, "KF", "IMM", d, se, d - 2 * se, d + 2 * se])
        _write_run(tmp_path / "runs" / f"s{seed}", {"seed": seed},
                   {"paired": {"columns": columns, "rows": rows}})
    assert rep.main([str(tmp_path / "runs")]) == 0
    assert "toy/paired: row nis, KF, IMM not in 4 run(s)" in capsys.readouterr().err
    body = json.loads((tmp_path / "runs" / "report" / "report.json").read_text())["toy"]
    table = body["tables"]["paired"]
    got = {row["labels"]["metric"]: row for row in table["rows"]}
    assert list(got) == ["rmse", "nis", "nees"] and not body["paired"]  # not paired again
    for metric, pairs in written.items():
        d, se = np.array(pairs).T
        values = got[metric]["values"]
        assert values["difference"]["n"] == len(d) and got[metric]["held_by"] == len(d)
        assert values["difference"]["mean"] == pytest.approx(d.mean(), rel=1e-12)
        assert values["se"]["mean"] == pytest.approx(np.sqrt(np.sum(se ** 2)) / len(se), rel=1e-12)
    (item,) = table["absent"]["rows"]
    assert item["labels"] == {"metric": "nis", "estimator": "KF", "reference": "IMM"}
    assert len(item["runs"]) == 4
    md = (tmp_path / "runs" / "report" / "report.md").read_text()
    assert "- row nis, KF, IMM: not in 4 of 5 runs: seed 0, 1, 2, 3" in md
    assert f"| nis | KF | IMM | 1 | {written['nis'][0][0]:.4f} |" in md  # its own row's n


def test_a_dropped_standard_error_reads_dropped_in_the_report(tmp_path):
    """The reproduction of the audit (compare, 5 seeds, nis_se in seed 4 only), in the files: report.md's
    cell reads ``dropped`` and the note says why; report.csv's mean is empty."""
    for seed in range(5):
        se = 2.6485 if seed == 4 else None
        _write_run(tmp_path / "runs" / f"s{seed}", {"seed": seed},
                   {"summary": {"columns": ["estimator", "nis", "nis_se"],
                                "rows": [["IMM", 1.0 + seed, se]]}})
    assert rep.main([str(tmp_path / "runs")]) == 0
    out = tmp_path / "runs" / "report"
    md = (out / "report.md").read_text()
    mean, half = _interval([1.0, 2.0, 3.0, 4.0, 5.0])
    assert f"| IMM | 5 | {mean:.4f} ± {half:.4f} | dropped |" in md
    assert "- nis_se of IMM: dropped: 4 of the 5 replicates in the mean have no standard error" in md
    line = next(x for x in (out / "report.csv").read_text().splitlines() if ",nis_se," in x)
    assert line.split(",")[-5:-1] == ["", "", "", ""]  # mean, sd, ci_low, ci_high: no value


@pytest.mark.slow  # four compare runs (~10 s); the synthetic tests above check the same rules
def test_the_audited_compare_sweep_keeps_every_table(tmp_path, capsys):
    """compare, mc_runs=2, 4 steps, missing 0.0 and 0.7, seeds 0 and 1 (the audit's sweep): before, report.md
    held 0 tables (whiteness_lag1/whiteness_bound in 2 of the 4 runs' summaries; the study's paired table
    with 19 and 14 rows). Every cell is recomputed from the runs' own results.json."""
    from experiments.config import validate
    from experiments.run import run_study
    from tests.experiments.test_compare_study import _compose

    for missing in ("0.0", "0.7"):
        for seed in (0, 1):
            cfg = _compose("mc_runs=2", "scenario.steps=4", f"scenario.missing={missing}", f"seed={seed}",
                           "figures=false")
            validate(cfg)
            run_study(cfg, tmp_path / f"m{missing}_s{seed}")
    assert rep.main([str(tmp_path)]) == 0
    capsys.readouterr()
    body = json.loads((tmp_path / "report" / "report.json").read_text())["compare"]
    assert set(body["tables"]) == {"summary", "paired"} and set(body["paired"]) == {"summary"}
    assert (tmp_path / "report" / "report.md").read_text().count("\n### ") == 3
    own = {}
    for path in sorted(tmp_path.glob("m*/results.json")):
        res = json.loads(path.read_text())
        own[(res["config"]["scenario"]["missing"], res["config"]["seed"])] = res["tables"]["summary"]
    table = body["tables"]["summary"]
    for row in table["rows"]:
        missing = body["groups"][row["group"]]["factors"]["scenario.missing"]
        for column in table["measurements"]:
            cells = []
            for (m, _), t in own.items():
                if m == missing and column in t["columns"]:
                    (r,) = [r for r in t["rows"] if r[0] == row["labels"]["estimator"]]
                    cells.append(r[t["columns"].index(column)])
            finite = [v for v in cells if isinstance(v, (int, float)) and math.isfinite(v)]
            got = row["values"][column]
            assert got["n"] == len(finite), (column, row["labels"])
            if finite:
                assert got["mean"] == pytest.approx(float(np.mean(finite)), rel=1e-12, abs=1e-15)

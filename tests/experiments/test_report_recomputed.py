"""torchmm-report over a seed sweep of ``compare``, every cell recomputed from the runs' own results.json
(issue 44): measurements are means with Student-t intervals, a run's standard errors are pooled (never
averaged or differenced), its bounds are not combined, the study's paired table is not paired again, and
no pair is dropped for an empty label cell (before: negative standard errors, ci_low > ci_high, and
`GPB2 - IMM`, `IMM smoothed - IMM` missing)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from omegaconf import open_dict
from scipy import stats

from experiments import report as rep
from experiments.config import validate
from experiments.run import run_study
from tests.experiments.test_compare_study import _compose


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    for seed in (0, 1, 2):
        cfg = _compose("debug=compare", "figures=false", f"seed={seed}")
        with open_dict(cfg):
            cfg.metrics = ["rmse", "nees", "nis", "loglik", "mode_accuracy"]
        validate(cfg)
        run_study(cfg, root / f"seed{seed}")
    runs = [json.loads((root / f"seed{s}" / "results.json").read_text()) for s in (0, 1, 2)]
    return root, runs


def _interval(values):
    values = np.asarray(values, dtype=float)
    half = stats.t.ppf(0.975, len(values) - 1) * values.std(ddof=1) / math.sqrt(len(values))
    return values.mean(), half


def test_every_cell_is_recomputed_from_the_runs(sweep):
    root, runs = sweep
    body = rep.combine(rep.collect_runs([root]))["compare"]
    summary = body["tables"]["summary"]
    columns = runs[0]["tables"]["summary"]["columns"]
    assert "rmse_position_se" in summary["standard_errors"] and "nees_low" not in summary["measurements"]
    for r, row in enumerate(summary["rows"]):
        label = row["labels"]["estimator"]
        assert all(run["tables"]["summary"]["rows"][r][0] == label for run in runs)
        for column in summary["measurements"]:
            values = [run["tables"]["summary"]["rows"][r][columns.index(column)] for run in runs]
            stats_ = row["values"][column]
            if any(v is None for v in values):
                assert stats_["n"] == sum(v is not None for v in values)
                continue
            mean, half = _interval(values)
            assert stats_["mean"] == pytest.approx(mean, rel=1e-12, abs=1e-14)
            if half > 0:
                assert (stats_["ci_high"] - stats_["ci_low"]) / 2 == pytest.approx(half, rel=1e-9)
            assert stats_["ci_low"] <= stats_["ci_high"]
        for column in summary["standard_errors"]:  # sqrt(sum se^2) / n: the se of the mean of the runs,
            # over the runs in the mean of its metric, each with an se (else no value: dropped where some
            # have one)
            cells = [run["tables"]["summary"]["rows"][r] for run in runs]
            values = [c[columns.index(column)] for c in cells if c[columns.index(column[:-3])] is not None]
            got = row["values"][column]
            if values and all(v is not None for v in values):
                assert got["mean"] == pytest.approx(math.sqrt(sum(v * v for v in values)) / len(values))
                assert got["mean"] >= 0 and got["n"] == len(values)
            else:
                assert got["mean"] is None
                assert ("dropped" in got) == any(v is not None for v in values)


def test_every_pair_is_there_and_the_paired_table_is_not_paired_again(sweep):
    root, runs = sweep
    body = rep.combine(rep.collect_runs([root]))["compare"]
    assert set(body["paired"]) == {"summary"}  # not the study's own `paired` table
    paired = body["paired"]["summary"]
    names = [row[0] for row in runs[0]["tables"]["summary"]["rows"]]
    assert {row["labels"]["estimator"] for row in paired["rows"]} == set(names) - {"IMM"}
    columns = runs[0]["tables"]["summary"]["columns"]
    for row in paired["rows"]:
        est = row["labels"]["estimator"]
        for column, s in row["values"].items():
            assert not rep.is_standard_error(column) and not rep.is_bound(column, columns)
            diffs = []
            for run in runs:
                table = {r[0]: r for r in run["tables"]["summary"]["rows"]}
                a, b = table[est][columns.index(column)], table["IMM"][columns.index(column)]
                if a is not None and b is not None:
                    diffs.append(a - b)
            if len(diffs) < 2:
                continue
            mean, half = _interval(diffs)
            assert s["mean"] == pytest.approx(mean, rel=1e-9, abs=1e-12)
            assert s["ci_low"] <= s["ci_high"]
    # the study's own paired table: differences averaged with intervals, its se pooled (never negative),
    # its own bounds not combined
    own = body["tables"]["paired"]
    assert "difference" in own["measurements"] and own["standard_errors"] == ["se"]
    assert set(own["not_combined"]) == {"ci_low", "ci_high", "separate_half_width"}
    assert all(row["values"]["se"]["mean"] >= 0 for row in own["rows"])


def test_the_report_files_hold_no_empty_label(sweep, tmp_path):
    root, _ = sweep
    assert rep.main([str(root), "--out", str(tmp_path / "report")]) == 0
    md = (tmp_path / "report" / "report.md").read_text()
    assert "GPB2 − IMM" in md and "IMM smoothed − IMM" in md
    assert "sqrt(sum se^2) / n" in md
    report = rep.combine(rep.collect_runs([root]))
    fig = rep.figure(report)
    labels = [t.get_text() for ax in fig.axes for t in ax.get_yticklabels()]
    assert labels and all(", ," not in text and not text.endswith(", ") for text in labels)


def test_report_arguments_are_one_line(sweep, tmp_path, capsys):
    """--replicate naming no config key (before: seed silently a factor, 3 groups of n = 1) and --level
    that is not a number (before: argparse's usage, 4 lines) are one line, exit 2."""
    root, _ = sweep
    assert rep.main([str(root), "--replicate", "NOPE", "--out", str(tmp_path / "r1")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchmm-report: error: --replicate: no run's config has a key 'NOPE'") and "\n" not in err
    assert rep.main([str(root), "--level", "abc", "--out", str(tmp_path / "r2")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "torchmm-report: error: --level: expected a number in (0, 1), got abc"
    assert not (tmp_path / "r1").exists() and not (tmp_path / "r2").exists()


def test_replicates_that_change_nothing_are_warned_about(tmp_path, capsys):
    """Seeds over recorded data give identical runs: the report says their zero-width intervals measure
    nothing (before: "n = 3 replicates" without a word)."""
    from tests.experiments.test_report import _write_run

    for seed in (0, 1, 2):
        _write_run(tmp_path / f"run{seed}", {"seed": seed, "experiment_name": "toy"},
                   {"t": {"columns": ["estimator", "loglik"], "rows": [["KF", -10.0], ["IMM", -9.0]]}})
    rep.combine(rep.collect_runs([tmp_path]))
    err = capsys.readouterr().err
    assert "the 3 runs with different seed give identical tables" in err

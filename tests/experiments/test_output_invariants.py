"""The output invariants of one's own experiment (issue 44): what a study reports from a data file
does not change when the file is padded (a longer series beside it), reordered or has a series
duplicated, and truth given for some state components only scores those; every metric asked for is
either computed from data or named as dropped, never reported as 0."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import open_dict

from experiments.config import ConfigError, validate
from experiments.run import run_study
from tests.experiments.test_compare_study import PRIOR_COV, PRIOR_MEAN, TRANSITION, _data_config, _library_models
from torchmm import IMM, GaussianBelief, KalmanFilter, run_filter
from torchmm.simulate import simulate_jump_system, simulate_measurements

LENGTHS = {"s0": 40, "s1": 14, "s2": 40}
SMOOTHED = ("IMM smoothed", "IMM-kim smoothed", "KF smoothed")


@pytest.fixture(scope="module")
def series():
    """Three simulated series ``{name: (z (T, 1), x (T, 2))}`` of the lengths in LENGTHS."""
    modes, sensor = _library_models()
    g = torch.Generator().manual_seed(11)
    prior = GaussianBelief.create(PRIOR_MEAN, PRIOR_COV, dtype=torch.float64)
    T = max(LENGTHS.values())
    sim = simulate_jump_system(modes, torch.tensor(TRANSITION, dtype=torch.float64), prior, T, (3,), generator=g)
    z = simulate_measurements(sensor, sim.states, generator=g)
    z[5, 0] = torch.nan  # a missing datum inside a series (not padding)
    return {name: (z[:n, j].numpy(), sim.states[:n, j].numpy()) for j, (name, n) in enumerate(LENGTHS.items())}


def _write(path: Path, series: dict, names: list[str], *, velocity: str = "given", rename: dict | None = None,
           empty: tuple = (), no_truth: tuple = ()) -> Path:
    """A CSV ``series, t, y, pos, vel`` of the named series in this order (``velocity="empty"``: the
    velocity column's cells empty; ``empty``: series whose measurement cells are all empty; ``no_truth``:
    series whose truth cells are all empty)."""
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["series", "t", "y", "pos", "vel"])
        for name in names:
            z, x = series[name]
            for k in range(len(z)):
                y = "" if name in empty or math.isnan(z[k, 0]) else repr(float(z[k, 0]))
                vel = "" if velocity == "empty" or name in no_truth else repr(float(x[k, 1]))
                pos = "" if name in no_truth else repr(float(x[k, 0]))
                w.writerow([(rename or {}).get(name, name), k + 1, y, pos, vel])
    return path


def _run(tmp_path: Path, file: Path, tag: str, *, truth=("pos", "vel"), metrics=None):
    cfg = _data_config(file, "figures=false")  # test_compare_study's two-mode scenario over the file
    with open_dict(cfg):
        cfg.scenario.data.truth = None if truth is None else list(truth)
        imm = {"_target_": "experiments.estimators.multiple_model", "_partial_": True,
               "combinator": {"_target_": "torchmm.IMM", "_partial_": True}, "mode_filter": None}
        cfg.estimators = {"IMM": {**imm, "smooth": "two_filter"}, "IMM-kim": {**imm, "smooth": "kim"},
                          "KF": {"_target_": "experiments.estimators.kalman", "_partial_": True, "mode": 0,
                                 "smooth": True}}
        if metrics is not None:
            cfg.metrics = list(metrics)
    validate(cfg)
    out = tmp_path / tag
    run_study(cfg, out)
    return json.loads((out / "results.json").read_text()), (out / "results.md").read_text()


def _series_rows(res: dict) -> dict:
    table = res["tables"]["series"]
    cols = table["columns"]
    return {(row[0], row[1]): dict(zip(cols, row)) for row in table["rows"]}


def _same(a, b, smoothed: bool):
    if a is None or b is None:
        assert a is None and b is None
        return
    # the two-filter smoother's flat start costs ~1e-8 of rounding between batch sizes; the rest agree
    assert a == pytest.approx(b, rel=1e-6 if smoothed else 1e-11, abs=1e-12)


def test_padding_reordering_and_a_series_alone_give_the_same_numbers(series, tmp_path):
    """s1 (14 steps) beside two 40-step series, after them, and alone: its row of every estimator and
    smoother is the same (before: the smoothers ran back through its 26 padded steps)."""
    beside, _ = _run(tmp_path, _write(tmp_path / "a.csv", series, ["s1", "s0", "s2"]), "beside")
    after, _ = _run(tmp_path, _write(tmp_path / "b.csv", series, ["s0", "s2", "s1"]), "after")
    alone, _ = _run(tmp_path, _write(tmp_path / "c.csv", series, ["s1"]), "alone")
    rows = [_series_rows(r) for r in (beside, after, alone)]
    labels = {label for label, name in rows[2] if name == "s1"}
    assert set(SMOOTHED) <= labels
    for label in labels:
        want = rows[2][(label, "s1")]
        assert want["steps"] == 14
        for other in rows[:2]:
            got = other[(label, "s1")]
            for key, value in want.items():
                if key not in ("estimator", "series"):
                    _same(got[key], value, label in SMOOTHED)
    # the summary of the file of s1 alone is its row
    for label in labels:
        for key in ("rmse_position", "nees", "loglik"):
            _same(alone["metrics"][label].get(key), rows[2][(label, "s1")].get(key), label in SMOOTHED)


def test_a_duplicated_series_changes_no_mean(series, tmp_path):
    """s0 and an exact copy of it: every mean of the summary is s0's alone (the standard errors, the
    chi-square bounds of N runs and the fraction of steps inside them depend on N)."""
    once, _ = _run(tmp_path, _write(tmp_path / "once.csv", series, ["s0"]), "once")
    twice, _ = _run(tmp_path, _write(tmp_path / "twice.csv", {**series, "copy": series["s0"]}, ["s0", "copy"]),
                    "twice")
    for label, values in once["metrics"].items():
        for key, value in values.items():
            if key.endswith(("_se", "_low", "_high", "_bound", "_inside")) or value is None:
                continue
            _same(twice["metrics"][label][key], value, label in SMOOTHED)


def test_truth_for_some_components_scores_those_and_names_the_rest(series, tmp_path):
    """Position-only truth (the velocity column empty, or `null` in the config): rmse_position is the full
    truth's, rmse_velocity is dropped and named, NEES is over the position alone (checked by hand); no
    metric is 0 (before: NEES = 0.0000, paired NEES 0 +- 0)."""
    names = ["s0", "s1"]
    full, _ = _run(tmp_path, _write(tmp_path / "full.csv", series, names), "full")
    empty, md = _run(tmp_path, _write(tmp_path / "pos.csv", series, names, velocity="empty"), "empty")
    null, _ = _run(tmp_path, _write(tmp_path / "full2.csv", series, names), "null", truth=("pos", None))
    for res in (empty, null):
        assert "rmse_velocity" in res["dropped"] and "mode_accuracy" in res["dropped"]
        for label, values in res["metrics"].items():
            assert "rmse_velocity" not in values
            _same(values["rmse_position"], full["metrics"][label]["rmse_position"], False)
            assert values["nees"] > 0.05
        assert all(row[0] != "rmse_velocity" for row in res["tables"]["paired"]["rows"])
    assert "## not computed" in md and "`rmse_velocity`: no truth for state component(s) [1]" in md
    # the IMM's NEES over the position: e^2 / P_00 at each present step, each series' mean, then the mean
    modes, sensor = _library_models()
    imm = IMM([KalmanFilter(m, sensor) for m in modes], torch.tensor(TRANSITION, dtype=torch.float64))
    per_series = []
    for name in names:
        z, x = series[name]
        prior = GaussianBelief.create(PRIOR_MEAN, PRIOR_COV, dtype=torch.float64).expand(1)
        est = run_filter(imm, imm.initial_belief(prior), torch.as_tensor(z)[:, None]).estimate()
        e = est.mean[:, 0, 0].numpy() - x[:, 0]
        per_series.append(np.mean(e ** 2 / est.cov[:, 0, 0, 0].numpy()))
    assert null["metrics"]["IMM"]["nees"] == pytest.approx(np.mean(per_series), rel=1e-10)
    assert null["metrics"]["IMM"]["nees_low"] == pytest.approx(empty["metrics"]["IMM"]["nees_low"])


def test_without_truth_every_truth_metric_is_named_and_none_is_zero(series, tmp_path):
    res, md = _run(tmp_path, _write(tmp_path / "nt.csv", series, ["s0", "s1"]), "notruth", truth=None)
    asked = ("rmse", "nees", "nis", "mode_accuracy", "loglik", "whiteness", "time")
    assert {"rmse", "nees", "mode_accuracy"} <= set(res["dropped"])
    assert not {row[0] for row in res["tables"]["paired"]["rows"]} & {"nees", "rmse_position", "rmse_velocity"}
    for label, values in res["metrics"].items():
        assert all(v != 0 for k, v in values.items() if not k.endswith(("_se", "_inside")))
    _every_metric_computed_or_named(res, asked)


def test_a_series_without_any_measurement_is_not_scored_as_measured(series, tmp_path):
    """A series whose measurement cells are all empty: measured 0, no NIS and no log-likelihood (before: NIS
    0.0 as if measured, and a log-likelihood of 0 averaged into the summary's), said in the notes; the
    summary is the other series' alone."""
    with_empty, md = _run(tmp_path, _write(tmp_path / "e.csv", series, ["s0", "s1"], empty=("s1",)), "withempty")
    rows = _series_rows(with_empty)
    assert rows[("IMM", "s1")]["measured"] == 0 and rows[("IMM", "s1")]["nis"] is None
    assert rows[("IMM", "s1")]["loglik"] is None and rows[("IMM", "s0")]["measured"] == 39
    assert "loglik (IMM): 1 of 2 series left out of the mean" in md
    alone, _ = _run(tmp_path, _write(tmp_path / "s0.csv", series, ["s0"]), "s0alone")
    for key in ("nis", "loglik"):
        assert with_empty["metrics"]["IMM"][key] == pytest.approx(alone["metrics"]["IMM"][key], rel=1e-12)


@pytest.mark.parametrize("kind, keys", [
    ("no_truth", ("rmse_position", "rmse_velocity", "nees")),
    ("empty", ("nis", "loglik")),
])
def test_a_series_with_nothing_to_score_is_no_run_of_its_metrics(series, tmp_path, kind, keys):
    """A third series without truth (or without measurements) beside s0 and s1: every number of the metrics it
    cannot have (the mean, its standard error, the chi-square bounds, the paired rows with their t intervals)
    is the file of s0 and s1's (before: it counted as a run with 0 spread, N = 3: KF's rmse_position_se
    shrank, a paired t quantile of 2 dof for 1, nees_low/high of 3 runs)."""
    two, _ = _run(tmp_path, _write(tmp_path / f"two_{kind}.csv", series, ["s0", "s1"]), f"two_{kind}")
    three, _ = _run(tmp_path, _write(tmp_path / f"three_{kind}.csv", series, ["s0", "s1", "s2"], **{kind: ("s2",)}),
                    f"three_{kind}")
    for label, values in two["metrics"].items():
        for key, value in values.items():
            if key.split("_se")[0].split("_low")[0].split("_high")[0].split("_dof")[0] in keys:
                _same(three["metrics"][label].get(key), value, label in SMOOTHED)
    rows = {(r[0], r[1]): r for r in two["tables"]["paired"]["rows"] if r[0] in keys}
    got = {(r[0], r[1]): r for r in three["tables"]["paired"]["rows"] if r[0] in keys}
    assert rows and set(rows) == set(got)
    for k, row in rows.items():
        for a, b in zip(row[3:], got[k][3:]):
            _same(b, a, False)


def test_padding_changes_no_per_step_band(series, tmp_path):
    """curves.npz: at the steps after s1's end (14 steps) the file s0, s1, s2 has the per-step RMSE standard
    errors and NEES bands of the file s0, s2 (before: padded steps counted as zero error in the SE, and the
    NEES band was the one of all 3 runs at every step); s1 alone: each step's SE is NaN (one run)."""
    _run(tmp_path, _write(tmp_path / "p3.csv", series, ["s0", "s1", "s2"]), "p3")
    _run(tmp_path, _write(tmp_path / "p2.csv", series, ["s0", "s2"]), "p2")
    _run(tmp_path, _write(tmp_path / "p1.csv", series, ["s1"]), "p1")
    three, two, one = (np.load(tmp_path / tag / "curves.npz") for tag in ("p3", "p2", "p1"))
    n = LENGTHS["s1"]
    for key in ("rmse_position_se/KF", "rmse_velocity_se/IMM", "nees_low/KF", "nees_high/IMM", "nees/KF"):
        np.testing.assert_allclose(three[key][n:], two[key][n:], rtol=1e-12)
        assert not np.allclose(three[key][:n], two[key][:n], rtol=1e-6)  # (3 runs there: another band)
    assert np.isnan(one["rmse_position_se/KF"]).all()
    # every step's band is chi2(N_t n) / N_t of its own N_t runs (scipy): 3 then 2, n = 2
    from scipy import stats
    count = np.where(np.arange(len(three["nees_low/KF"])) < n, 3, 2)
    np.testing.assert_allclose(three["nees_low/KF"], stats.chi2.ppf(0.025, 2 * count) / count, rtol=1e-10)
    np.testing.assert_allclose(three["nees_high/KF"], stats.chi2.ppf(0.975, 2 * count) / count, rtol=1e-10)


def test_one_series_names_its_standard_errors_and_paired_differences_as_dropped(series, tmp_path):
    """One series: every standard error is null and the paired table empty, and `dropped` says so (before:
    nothing said); two series: no such entry."""
    one, _ = _run(tmp_path, _write(tmp_path / "one.csv", series, ["s0"]), "one")
    assert not one["tables"]["paired"]["rows"] and one["metrics"]["KF"]["nees_se"] is None
    assert "need two" in one["dropped"]["standard errors (_se) and paired"]
    two, _ = _run(tmp_path, _write(tmp_path / "two.csv", series, ["s0", "s1"]), "two")
    assert "standard errors (_se) and paired" not in two["dropped"] and two["tables"]["paired"]["rows"]


def test_a_file_without_any_measurement_is_a_config_error(series, tmp_path):
    file = _write(tmp_path / "none.csv", series, ["s0", "s1"], empty=("s0", "s1"))
    with pytest.raises(ConfigError, match=r"scenario.data.measurements=\['y'\]: .*every measurement cell is missing"):
        _run(tmp_path, file, "none")
    assert not (tmp_path / "none").exists()


def _every_metric_computed_or_named(res: dict, asked) -> None:
    dropped = set(res["dropped"])
    for label, values in res["metrics"].items():
        for metric in asked:
            if metric == "time":
                continue
            key = {"whiteness": "whiteness_lag1"}.get(metric, metric)
            present = any(k == key or k.startswith(f"{key}_") for k in values)
            named = metric in dropped or any(d.startswith(f"{key}") for d in dropped)
            assert present or named or label.endswith("smoothed") and metric in ("nis", "loglik", "whiteness"), \
                (label, metric)

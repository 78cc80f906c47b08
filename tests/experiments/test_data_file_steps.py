"""Reading one's own data file step by step (an audit of experiments/datafile.py and the compare study): a row
of empty cells is a missing step (it was dropped, shifting every later step), step 0 predicts over the first
step's length whether or not another series makes the grid irregular, a regular grid of decimal stamps is
regular, a series' NEES is over its own truth components, EM's precheck refuses partly missing vectors, and
an NPZ's NaN padding and a shared ``(T,)`` time array read as a CSV's. The references: a float64 NumPy Kalman
filter written here, and the same series alone or as a CSV."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from omegaconf import open_dict

from experiments.config import precheck, validate
from experiments.datafile import DataFileError, read_series
from experiments.datafile_io import step_lengths
from experiments.run import CONFIG_DIR, run_study
from tests.experiments.test_compare_study import PRIOR_COV, PRIOR_MEAN, _data_config

Q_CV, R_Y = 0.05, 4.0  # test_compare_study's mode 0 (a 1-D constant velocity, discrete noise) and its sensor


def _kf(z: np.ndarray, dts: list[float]) -> tuple[float, np.ndarray]:
    """A float64 NumPy Kalman filter of mode 0 over ``z (T,)`` (NaN: missing), step ``k`` predicting over
    ``dts[k]``: ``(log-likelihood, filtered means (T, 2))``."""
    x, P, ll = np.array(PRIOR_MEAN, float), np.array(PRIOR_COV, float), 0.0
    H = np.array([[1.0, 0.0]])
    means = np.zeros((len(z), 2))
    for k, y in enumerate(z):
        dt = dts[k]
        F, G = np.array([[1.0, dt], [0.0, 1.0]]), np.array([[dt * dt / 2], [dt]])
        x, P = F @ x, F @ P @ F.T + Q_CV * G @ G.T
        if not math.isnan(y):
            S = float((H @ P @ H.T)[0, 0]) + R_Y
            nu = y - float((H @ x)[0])
            ll += -0.5 * (nu * nu / S + math.log(2 * math.pi * S))
            K = P @ H.T / S
            x, P = x + (K * nu).ravel(), P - K @ H @ P
        means[k] = x
    return ll, means


def _kf_loglik(z: np.ndarray, dts: list[float]) -> float:
    return _kf(z, dts)[0]


def _track(T: int, seed: int, dt: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``(z (T,), x (T, 2))``: a 1-D constant-velocity track and its noisy positions."""
    rng = np.random.default_rng(seed)
    x = np.zeros((T, 2))
    s = np.array([0.0, 1.0])
    for k in range(T):
        s = np.array([s[0] + dt * s[1], s[1] + rng.normal(0, 0.2)])
        x[k] = s
    return x[:, 0] + rng.normal(0, 2.0, T), x


def _study(tmp_path: Path, path: Path, tag: str, *, time="t", series="series", truth=("pos", "vel"),
           metrics="[loglik,rmse,nees]", learn=None, one_mode=False) -> dict:
    cfg = _data_config(path, "figures=false", f"metrics={metrics}")
    with open_dict(cfg):
        if one_mode:  # mode 0 alone: its model has no mode axis
            cfg.scenario.modes, cfg.scenario.labels = [cfg.scenario.modes[0]], ["a=0"]
            cfg.scenario.transition = [[1.0]]
        cfg.scenario.data = {"path": str(path), "measurements": ["y"], "time": time, "series": series,
                             "truth": None if truth is None else list(truth)}
        cfg.estimators = {"KF": {"_target_": "experiments.estimators.kalman", "_partial_": True, "mode": 0}}
        if learn is not None:
            cfg.learn = learn
    validate(cfg)
    run_study(cfg, tmp_path / tag)
    return json.loads((tmp_path / tag / "results.json").read_text())


def _series(res: dict) -> dict:
    table = res["tables"]["series"]
    return {(row[0], row[1]): dict(zip(table["columns"], row)) for row in table["rows"]}


def _write(path: Path, rows: list[list], header=("series", "t", "y", "pos", "vel")) -> Path:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


def _cell(v: float) -> str:
    return "" if math.isnan(v) else repr(float(v))


# -- 1. a row of empty cells is a missing step ---------------------------------------------------------------
def test_a_row_of_empty_cells_is_a_missing_step(tmp_path):
    """``csv.writer`` writes a step with every value missing as ``,,``: it is a step (it was dropped: 28 steps
    read for 30 and every later step shifted; an audit's KF log-likelihood -193.44 for the NumPy filter's
    -170.31); the study's log-likelihood equals the NumPy Kalman filter's with those steps missing, and the
    NPZ of the same data."""
    z, x = _track(30, 1)
    z[5:7] = np.nan
    truth = x.copy()
    truth[5:7] = np.nan
    rows = [[_cell(z[k]), _cell(truth[k, 0]), _cell(truth[k, 1])] for k in range(30)]
    path = _write(tmp_path / "blank.csv", rows, header=("y", "pos", "vel"))
    assert path.read_text().splitlines()[6:8] == [",,", ",,"]
    data = read_series(path, measurements=["y"], truth=["pos", "vel"])
    assert data.steps == 30 and data.present.all()
    np.testing.assert_array_equal(data.measurements[:, 0, 0], z)
    np.testing.assert_array_equal(data.truth[:, 0], truth)
    np.savez(tmp_path / "blank.npz", y=z, pos=truth[:, 0], vel=truth[:, 1])
    res = _study(tmp_path, path, "csv", time=None, series=None, metrics="[loglik]")
    npz = _study(tmp_path, tmp_path / "blank.npz", "npz", time=None, series=None, metrics="[loglik]")
    assert res["metrics"]["KF"]["loglik"] == pytest.approx(_kf_loglik(z, [1.0] * 30), rel=1e-10)
    assert res["metrics"]["KF"]["loglik"] == pytest.approx(npz["metrics"]["KF"]["loglik"], rel=1e-12)


def test_blank_lines_of_a_one_column_file_are_missing_values(tmp_path):
    """One column: a blank line or ``""`` between rows is a missing value; blank lines at the end are
    nothing."""
    path = tmp_path / "one.csv"
    path.write_text('y\n1.5\n\n3.0\n""\n5.0\n\n\n')
    data = read_series(path, measurements=["y"])
    np.testing.assert_array_equal(data.measurements[:, 0, 0], [1.5, np.nan, 3.0, np.nan, 5.0])
    np.testing.assert_array_equal(data.rows[:, 0], [2, 3, 4, 5, 6])


def test_a_blank_line_between_rows_of_several_columns_is_an_error(tmp_path):
    """Several columns: a blank line between rows names its line (it would drop a step, or be read as one);
    blank lines at the end of the file are ignored."""
    path = tmp_path / "gap.csv"
    path.write_text("y,pos\n1,2\n\n3,4\n")
    with pytest.raises(DataFileError, match=r"gap.csv: row 3: a blank line between rows .*','; blank "
                                            "lines are ignored only at the end of the file"):
        read_series(path, measurements=["y"], truth=["pos"])
    path.write_text("y,pos\n1,2\n,\n3,4\n\n\n")
    data = read_series(path, measurements=["y"], truth=["pos"])
    np.testing.assert_array_equal(data.measurements[:, 0, 0], [1.0, np.nan, 3.0])


# -- 2. and 3. step 0 and the step length of time stamps -----------------------------------------------------
def _stamped(path: Path, series: dict) -> Path:
    """``series``: ``{name: (stamps, z, x)}`` as rows ``series, t, y, pos, vel``."""
    return _write(path, [[name, repr(float(t)), _cell(z[k]), repr(float(x[k, 0])), repr(float(x[k, 1]))]
                         for name, (ts, z, x) in series.items() for k, t in enumerate(ts)])


def test_step_zero_does_not_depend_on_another_series(tmp_path):
    """Series A on a grid of 2 alone, and beside B with one extra stamp 1 later (the shared grid irregular):
    step 0 predicts over the first step's length (2) in both, so A's numbers are the same (before: over the
    config's dt 1 beside B, an audit's -124.90 for -125.01 alone) and equal the NumPy filter's at dt 2."""
    za, xa = _track(15, 3, dt=2.0)
    zb, xb = _track(16, 4, dt=2.0)
    ta = [2.0 * k for k in range(15)]
    alone = _study(tmp_path, _stamped(tmp_path / "a.csv", {"A": (ta, za, xa)}), "alone")
    both = _study(tmp_path, _stamped(tmp_path / "ab.csv", {"A": (ta, za, xa), "B": (ta + [29.0], zb, xb)}),
                  "both")
    a, b = _series(alone)[("KF", "A")], _series(both)[("KF", "A")]
    for key in ("steps", "loglik", "rmse_position", "rmse_velocity", "nees"):
        assert b[key] == pytest.approx(a[key], rel=1e-10), key
    assert a["loglik"] == pytest.approx(_kf_loglik(za, [2.0] * 15), rel=1e-10)
    b = _series(both)[("KF", "B")]["loglik"]
    assert b == pytest.approx(_kf_loglik(zb, [2.0] * 15 + [1.0]), rel=1e-10)


def test_a_regular_grid_of_decimal_stamps_is_regular(tmp_path):
    """Stamps 0.0, 0.1, ..., 2.9 (their float differences take six values): one step length 0.1 at every step,
    step 0 included (before: per-step models, step 0 over the config's dt 1, an audit's -165.888 for
    -164.878), and ``learn.method=em`` is allowed (it was refused: "irregular time stamps")."""
    z, x = _track(30, 5, dt=0.1)
    stamps = [float(f"{k / 10:.1f}") for k in range(30)]
    assert len(set(np.diff(stamps).tolist())) > 1
    path = _stamped(tmp_path / "hz10.csv", {"A": (stamps, z, x)})
    res = _study(tmp_path, path, "run", truth=None, metrics="[loglik]")
    assert res["metrics"]["KF"]["loglik"] == pytest.approx(_kf_loglik(z, [0.1] * 30), rel=1e-10)
    em = {"method": "em", "estimators": ["KF"], "parameters": [{"model": "sensors", "name": "R"}]}
    cfg = _data_config(path, "figures=false")
    with open_dict(cfg):
        cfg.scenario.data.truth = None
        cfg.estimators = {"KF": {"_target_": "experiments.estimators.kalman", "_partial_": True, "mode": 0}}
        cfg.learn = em
    validate(cfg)  # (the precheck's dry build: no refusal)


def test_step_lengths_merge_float_rounding_only():
    """A regular grid gives one length; an irregular one keeps its distinct lengths, those equal but for float
    rounding merged into one (the tracking grid's tolerance, GRID_TOLERANCE)."""
    dt, lengths = step_lengths(np.array([k / 10 for k in range(30)]))
    assert dt == pytest.approx(0.1, rel=1e-12) and np.all(lengths == dt)
    t = np.cumsum([0.0, 0.1, 0.2, 0.1, 0.1, 0.2, 0.1])  # float sums: 0.1s and 0.2s differ in last bits
    dt, lengths = step_lengths(t)
    assert dt is None and len(set(lengths.tolist())) == 2
    np.testing.assert_allclose(lengths, [0.1, 0.2, 0.1, 0.1, 0.2, 0.1], rtol=1e-12)
    assert step_lengths(np.array([3.0]))[0] is None


# -- 4. a series' NEES over its own truth components ---------------------------------------------------------
def test_a_series_nees_is_over_its_own_truth_components(tmp_path):
    """A with position truth only beside B with full truth: A's NEES in the table series is its NEES alone
    (before: None, "no truth where scored"); the summary's NEES pools only the series with truth for every
    component (B's alone), and a note names A."""
    za, xa = _track(20, 6)
    zb, xb = _track(14, 7)
    xa[:, 1] = np.nan
    ta, tb = [float(k) for k in range(20)], [float(k) for k in range(14)]
    alone = _study(tmp_path, _stamped(tmp_path / "a.csv", {"A": (ta, za, xa)}), "a")
    b_alone = _study(tmp_path, _stamped(tmp_path / "b.csv", {"B": (tb, zb, xb)}), "b")
    both = _study(tmp_path, _stamped(tmp_path / "ab.csv", {"A": (ta, za, xa), "B": (tb, zb, xb)}), "ab")
    a = _series(alone)[("KF", "A")]["nees"]
    assert a is not None and _series(both)[("KF", "A")]["nees"] == pytest.approx(a, rel=1e-12)
    assert alone["metrics"]["KF"]["nees"] == pytest.approx(a, rel=1e-12)
    assert both["metrics"]["KF"]["nees"] == pytest.approx(b_alone["metrics"]["KF"]["nees"], rel=1e-12)
    notes = (tmp_path / "ab" / "results.md").read_text()
    assert "nees: series A left out of the summary's NEES" in notes


# -- 5. EM refuses partly missing vectors before anything runs -----------------------------------------------
@pytest.mark.parametrize("method", ["em", "em_then_mle"])
def test_em_with_partly_missing_vectors_is_refused_in_the_precheck(tmp_path, capsys, method):
    """EM's steps take whole vectors (docs/estimation.md): a file with y missing where x is given is one line
    naming learn.method and the file's first such row, exit 2, no folder (before: a traceback after the folder
    was made)."""
    rng = np.random.default_rng(8)
    rows = []
    for k in range(12):
        y = "" if k in (4, 7) else f"{rng.normal():.6f}"
        rows.append(["a", k + 1, f"{k + rng.normal():.6f}", y])
    path = _write(tmp_path / "half.csv", rows, header=("series", "t", "x", "y"))
    argv = ["experiment=compare", "logger=none", "~estimators.IMM", "~estimators.GPB2", "~estimators.KF-CV-q",
            f"scenario.data={{path:{path},measurements:[x,y],series:series,time:t}}",
            f"learn={{method:{method},estimators:[KF-CV],parameters:[{{model:sensors,name:R}}]}}",
            f"hydra.run.dir={tmp_path / 'run'}"]
    with pytest.raises(SystemExit) as stop:
        precheck(argv, CONFIG_DIR)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"torchmm-run: error: learn.method={method}: "), err
    assert "row 6 (series 'a', step 4)" in err
    assert not (tmp_path / "run").exists()


# -- 6. and 7. an NPZ's NaN padding and a shared (T,) time array ---------------------------------------------
def _npz_and_csv(tmp_path: Path) -> tuple[Path, Path, dict]:
    lengths = {"A": 12, "B": 7, "C": 9}
    T = max(lengths.values())
    arrays = {c: np.full((T, 3), np.nan) for c in ("y", "pos", "vel", "u")}
    rows = []
    for j, (name, n) in enumerate(lengths.items()):
        z, x = _track(n, 10 + j)
        z[2] = np.nan  # a missing datum inside a series (not padding)
        arrays["y"][:n, j], arrays["pos"][:n, j], arrays["vel"][:n, j] = z, x[:, 0], x[:, 1]
        arrays["u"][:n, j] = 0.5 * j
        rows += [[name, k, _cell(z[k]), repr(float(x[k, 0])), repr(float(x[k, 1])), repr(0.5 * j)]
                 for k in range(n)]
    np.savez(tmp_path / "abc.npz", t=np.arange(T, dtype=float), **arrays)
    csv_path = _write(tmp_path / "abc.csv", rows, header=("series", "t", "y", "pos", "vel", "u"))
    return tmp_path / "abc.npz", csv_path, lengths


def test_nan_padding_of_an_npz_is_no_step_and_a_time_array_is_shared(tmp_path):
    """(T, runs) columns padded with NaN: each series' trailing steps with no measurement and no truth are its
    padding (before: every series had the padded length, 12/12/12 for 12/7/9), and the arrays equal the CSV's
    (NaN inputs in the padding are accepted, 0 as in the CSV); a (T,) time array beside (T, runs) columns is
    shared by the runs (before: "arrays of different shapes")."""
    npz, path, lengths = _npz_and_csv(tmp_path)
    kw = {"measurements": ["y"], "truth": ["pos", "vel"], "inputs": ["u"], "time": "t"}
    a, b = read_series(npz, **kw), read_series(path, series="series", **kw)
    assert a.present.sum(0).tolist() == list(lengths.values())
    np.testing.assert_array_equal(a.present, b.present)
    for field in ("measurements", "truth", "inputs", "times"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.where(3, 1) == "entry (3, 1)" and b.where(3, 1) == "row 17"


def test_arrays_of_other_shapes_say_what_is_allowed(tmp_path):
    np.savez(tmp_path / "bad.npz", y=np.zeros((5, 2)), pos=np.zeros((5, 3)), t=np.arange(5.0))
    shapes = r"arrays of different shapes .*\(T,\) array for one series or one \(T, runs\) array "
    with pytest.raises(DataFileError, match=shapes + r".*'t' array may be one \(T,\) array shared"):
        read_series(tmp_path / "bad.npz", measurements=["y"], truth=["pos"], time="t")
    with pytest.raises(DataFileError, match=r"'u', entry \(1, 0\): an input is missing"):
        np.savez(tmp_path / "u.npz", y=np.array([1.0, np.nan, 3.0]), u=np.array([1.0, np.nan, 1.0]))
        read_series(tmp_path / "u.npz", measurements=["y"], inputs=["u"])


# -- 8. one mode with irregular time stamps ------------------------------------------------------------------
def test_one_mode_with_irregular_stamps_runs_its_kalman_filter_over_each_step(tmp_path):
    """A one-mode scenario's per-step models have no mode axis (the model is mode 0's): ``kalman`` ran
    ``select_mode`` on them (before: a ValueError traceback after the run folder existed). Each series'
    log-likelihood and RMSEs equal the NumPy filter's with the per-step dt (one run: a step's RMSE is its
    absolute error)."""
    stamps = [float(k) for k in range(8)] + [7.5] + [float(k) for k in range(8, 15)]  # one half step
    dts = [1.0] + list(np.diff(stamps))
    za, xa = _track(16, 12)
    zb, xb = _track(11, 13)
    za[3] = np.nan
    path = _stamped(tmp_path / "irr.csv", {"A": (stamps, za, xa), "B": (stamps[:11], zb, xb)})
    one = _study(tmp_path, path, "one", one_mode=True)
    for name, z, x in (("A", za, xa), ("B", zb, xb)):
        row = _series(one)[("KF", name)]
        ll, means = _kf(z, dts[:len(z)])
        assert row["steps"] == len(z) and row["loglik"] == pytest.approx(ll, rel=1e-10)
        assert row["rmse_position"] == pytest.approx(np.abs(means[:, 0] - x[:, 0]).mean(), rel=1e-10)
        assert row["rmse_velocity"] == pytest.approx(np.abs(means[:, 1] - x[:, 1]).mean(), rel=1e-10)


def test_a_mode_a_one_mode_scenario_lacks_is_refused_in_the_precheck(tmp_path, capsys):
    """``kalman``'s ``mode: 1`` on a one-mode scenario with irregular stamps: one line naming the key, exit 2,
    no folder."""
    za, xa = _track(6, 14)
    path = _stamped(tmp_path / "irr.csv", {"A": ([0.0, 1.0, 1.5, 2.0, 3.0, 4.0], za, xa)})
    argv = ["experiment=compare", "logger=none", "~estimators.IMM", "~estimators.GPB2", "~estimators.KF-CV-q",
            "scenario.modes=[{_target_:torchmm.ConstantVelocity,ndim:1,dt:1.0,q:0.05}]",
            "scenario.labels=[CV]",
            "scenario.sensors=[{_target_:torchmm.PositionMeasurement,state_dim:2,indices:[0],R:4.0}]",
            "scenario.transition=[[1.0]]", "scenario.initial_mode_probs=[1.0]",
            "scenario.initial_mean=[0.0,1.0]",
            "scenario.initial_cov=[[4.0,0.0],[0.0,1.0]]", "scenario.groups={position:[0],velocity:[1]}",
            f"scenario.data={{path:{path},measurements:[y],truth:[pos,vel],series:series,time:t}}",
            "estimators.KF-CV.mode=1", f"hydra.run.dir={tmp_path / 'run'}"]
    with pytest.raises(SystemExit) as stop:
        precheck(argv, CONFIG_DIR)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("torchmm-run: error: estimators.KF-CV.mode=1: "), err
    assert not (tmp_path / "run").exists()


# -- 9. a value that cannot be computed is an empty cell, never "nan" ----------------------------------------
def _cells(text: str, latex: bool) -> list[str]:
    """Every table cell of results.md (rows ``| ... |``) or of results.tex (rows ``a & b \\\\``)."""
    if latex:
        rows = [line.removesuffix("\\\\") for line in text.splitlines()
                if line.endswith("\\\\") and "&" in line]
        return [cell.strip() for row in rows for cell in row.split("&")]
    rows = [line.strip().strip("|") for line in text.splitlines() if line.startswith("|")]
    return [cell.strip() for row in rows for cell in row.split("|")]


def test_one_series_standard_errors_are_empty_cells_not_nan(tmp_path):
    """With one series no standard error exists: results.json has null and names it in "dropped", and
    results.md / results.tex leave the cell empty (before: ``nan`` in every ``_se`` column)."""
    za, xa = _track(12, 15)
    res = _study(tmp_path, _stamped(tmp_path / "a.csv", {"A": ([float(k) for k in range(12)], za, xa)}), "a")
    summary = res["tables"]["summary"]
    row = dict(zip(summary["columns"], summary["rows"][0]))
    assert row["rmse_position_se"] is None and row["loglik_se"] is None
    assert "standard errors (_se) and paired" in res["dropped"]
    md = (tmp_path / "a" / "results.md").read_text()
    tex = (tmp_path / "a" / "results.tex").read_text()
    for cells in (_cells(md, latex=False), _cells(tex, latex=True)):
        assert cells and not [c for c in cells if c.lower() in ("nan", "-nan", "$-$nan")]
    lines = md.splitlines()
    at = lines.index("| " + " | ".join(summary["columns"]) + " |")  # the summary: header, rule, its one row
    cells = dict(zip(summary["columns"], (c.strip() for c in lines[at + 2].strip("|").split("|"))))
    assert cells["rmse_position_se"] == cells["loglik_se"] == ""
    assert float(cells["rmse_position"]) == pytest.approx(row["rmse_position"], abs=1e-4)

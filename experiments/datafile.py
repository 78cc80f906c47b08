"""Recorded data for a study: measurements (and optional truth and time stamps) from CSV or NPZ.

A study's ``scenario.data`` node names a file and its columns (docs/studies.md, "Your own data").
The file becomes time-major tensors, the layout every torchmm filter takes:

* **CSV** (UTF-8): one row per time step (and series), a header naming the columns. Empty cells,
  ``nan`` (any case or sign), ``NA``, ``N/A``, ``null`` and ``none`` are missing (NaN: the filters skip
  them exactly); ``inf`` is not missing but an error, as is any other cell that is not a finite number.
  With a ``series`` column, the rows of each series value are one run (in order of first appearance;
  every row names its series); series of different lengths are padded at the end with missing steps,
  which score nothing (``DataSeries.present``).
* **NPZ**: one array per column name, ``(T,)`` for one series or ``(T, runs)`` for several (NaN:
  missing; infinite entries are an error); the time column may be one ``(T,)`` array shared by the runs.
  A series' trailing steps where every measurement and truth value is NaN are its padding (not its
  steps: ``DataSeries.present``), as a shorter series' in a CSV.
* **Blank lines** (CSV): a row of empty cells (``,,``, as ``csv.writer`` writes a step with every
  value missing) is a step with every value missing. A blank line is ignored at the end of the file;
  before another row it is a missing value in a file of one column and an error in a file of several
  (it would drop a step, or be read as one).

Detections in clutter (:func:`read_detections`, docs/tracking.md) are read one row per detection
instead, grouped into scans by their time stamp: the padded sets every association filter takes.

A malformed file is one :class:`DataFileError` (a ``ValueError``) naming the file, the column and
the row (the CSV line number, header = line 1): a column missing from the header or named twice in
it, a cell that is not a finite number, an empty series cell, bytes that are not UTF-8. An argument
of the wrong type (``measurements="pos"`` for ``["pos"]``) is a ``TypeError`` naming it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from experiments.datafile_io import (
    DataFileError,
    check_increasing,
    column_name,
    column_names,
    locate,
    read_csv,
    read_npz,
)

__all__ = ["DataFileError", "DataSeries", "DetectionScans", "TargetRows", "read_detections", "read_series",
           "npz_label", "read_targets"]


@dataclass
class DataSeries:
    """Time-major arrays of one data file (float64 numpy).

    Shapes:
        measurements: ``(T, runs, m)`` (NaN: missing)
        truth: ``(T, runs, n)`` or None
        times: ``(T,)`` the time stamps shared by every series, or None
        present: ``(T, runs)`` bool: the step exists in that series (False: padding)
        inputs: ``(T, runs, k)`` exogenous inputs (regressors, the models' controls ``u_k``), or None;
            0 at padding steps
        rows: ``(T, runs)`` int: each step's CSV line (header = 1; -1 at padding), or None (NPZ: the
            step ``k`` of series ``j`` is entry ``(k, j)``)
    """

    measurements: np.ndarray
    truth: np.ndarray | None
    times: np.ndarray | None
    present: np.ndarray
    series: list[str]
    inputs: np.ndarray | None = None
    rows: np.ndarray | None = None

    def where(self, k: int, j: int) -> str:
        """Step ``k`` of series ``j`` as the file names it: ``row 12`` (CSV) or ``entry (k, j)`` (NPZ)."""
        return f"row {int(self.rows[k, j])}" if self.rows is not None else f"entry ({k}, {j})"

    @property
    def steps(self) -> int:
        return self.measurements.shape[0]

    @property
    def runs(self) -> int:
        return self.measurements.shape[1]


def read_series(path: str | Path, *, measurements: list[str], truth: list[str] | None = None,
                time: str | None = None, series: str | None = None, base: Path | None = None,
                inputs: list[str] | None = None) -> DataSeries:
    """Read a CSV or NPZ file into a :class:`DataSeries`.

    Args:
        path: the file (``.csv`` or ``.npz``); relative paths are looked up in ``base`` (the working
            directory by default), then in the repository's ``experiments/data``.
        measurements: the measurement columns, in the order of the sensor's components.
        truth: optional state columns, in the order of the state's components (for RMSE and NEES).
        time: optional time-stamp column; increasing, the same grid in every series (NPZ: one ``(T,)``
            array may serve ``(T, runs)`` columns). A study rebuilds its modes with the grid's step, or
            per-step motion models for irregular steps (``experiments.scenarios_system.per_step_motions``).
        series: optional CSV column whose values name the series; each series is one run.
        inputs: optional columns of exogenous inputs (regressors): the controls ``u_k`` of the motion
            models (``DataSeries.inputs``). Every step of a series needs them (a missing input is an error,
            where a missing measurement is skipped).

    Raises:
        DataFileError: naming the file, the column and the row: a column not in the header or named
            twice in it, a cell that is not a finite number (``inf`` is not missing), an empty series
            cell, a file that is not UTF-8.
        TypeError: naming the argument: a string for a list of columns (``measurements="pos"``), a
            column name that is not a string.
    """
    measurements = column_names(measurements, "measurements")
    truth = column_names(truth, "truth", optional=True) or []
    inputs = column_names(inputs, "inputs", optional=True) or []
    time, series = column_name(time, "time"), column_name(series, "series")
    file = locate(path, base, measurements)
    wanted = measurements + truth + inputs + ([time] if time else [])
    suffix = file.suffix.lower()
    if suffix == ".npz":
        if series:
            raise DataFileError(f"{file}: column {series!r}: NPZ arrays hold several series as (T, runs) columns; "
                                "no series column")
        arrays = read_npz(file, wanted, shared=[time] if time else [])
        z = np.stack([arrays[c] for c in measurements], -1)
        x = np.stack([arrays[c] for c in truth], -1) if truth else None
        u = np.stack([arrays[c] for c in inputs], -1) if inputs else None
        # a series' padding: its trailing steps where every measurement and truth value is NaN (NaN-padded
        # (T, runs) columns); they score nothing either way, but are not its steps (the series table's length)
        known = np.isfinite(z).any(-1) | (np.isfinite(x).any(-1) if x is not None else False)
        last = np.where(known.any(0), known.shape[0] - np.argmax(known[::-1], axis=0), 0)  # (runs,) kept
        present = np.arange(z.shape[0])[:, None] < last[None, :]
        if u is not None:
            bad = ~np.isfinite(u) & present[..., None]
            if bad.any():
                where = tuple(int(i) for i in np.argwhere(bad)[0])
                raise DataFileError(f"{file}: column {inputs[where[2]]!r}, entry {where[:2]}: an input is "
                                    "missing (every step needs its inputs; NaN only in a series' padding)")
            u = np.where(present[..., None], u, 0.0)
        stamps = None
        if time:
            t = arrays[time]
            if not np.all(t == t[:, :1]):
                raise DataFileError(f"{file}: column {time!r}: the series have different time stamps "
                                    "(one shared time grid is supported)")
            stamps = t[:, 0]
            check_increasing(stamps, file, time, list(range(len(stamps))), "index")
        return DataSeries(z, x, stamps, present, [str(i) for i in range(z.shape[1])], u)
    if suffix != ".csv":
        raise DataFileError(f"{file}: expected a .csv or .npz file")
    values, lines = read_csv(file, wanted, series)
    labels = values.pop(series) if series else ["0"] * len(lines)
    order = list(dict.fromkeys(labels))
    rows = {s: [i for i, label in enumerate(labels) if label == s] for s in order}
    T = max(len(r) for r in rows.values())
    R = len(order)
    z = np.full((T, R, len(measurements)), np.nan)
    x = np.full((T, R, len(truth)), np.nan) if truth else None
    u = np.zeros((T, R, len(inputs))) if inputs else None
    present = np.zeros((T, R), dtype=bool)
    line_of = np.full((T, R), -1, dtype=np.int64)
    stamps = None
    for j, s in enumerate(order):
        idx = rows[s]
        present[:len(idx), j] = True
        line_of[:len(idx), j] = [lines[i] for i in idx]
        z[:len(idx), j] = np.array([[values[c][i] for c in measurements] for i in idx])
        if truth:
            x[:len(idx), j] = np.array([[values[c][i] for c in truth] for i in idx])
        if inputs:
            cells = np.array([[values[c][i] for c in inputs] for i in idx])
            bad = np.argwhere(~np.isfinite(cells))
            if len(bad):
                raise DataFileError(f"{file}: column {inputs[bad[0][1]]!r}, row {lines[idx[bad[0][0]]]}: an input is "
                                    "missing (every step needs its inputs; a missing measurement is skipped)")
            u[:len(idx), j] = cells
        if time:
            t = np.array([values[time][i] for i in idx])
            bad = [lines[i] for i, v in zip(idx, t) if not math.isfinite(v)]
            if bad:
                raise DataFileError(f"{file}: column {time!r}, row {bad[0]}: a time stamp is missing")
            check_increasing(t, file, time, [lines[i] for i in idx], "row")
            if stamps is None:
                stamps = t
            elif len(t) > len(stamps) and np.array_equal(t[:len(stamps)], stamps):
                stamps = t
            elif not np.array_equal(t, stamps[:len(t)]):
                raise DataFileError(f"{file}: column {time!r}, row {lines[idx[0]]}: series {s!r} has other time "
                                    "stamps than the first series (one shared time grid is supported)")
    return DataSeries(z, x, stamps, present, order, u, line_of)


def npz_label(value: float) -> str:
    """An NPZ entry of a label column (series, sensor, target) as its exact label: an integral value as
    its integer (``1000001.0`` -> ``'1000001'``, as a CSV cell ``1000001`` reads), any other as its
    shortest exact decimal (``repr``: ``0.5`` -> ``'0.5'``); two distinct values are never one label."""
    value = float(value)
    return str(int(value)) if value.is_integer() else repr(value)


@dataclass
class DetectionScans:
    """Scans of detections read from a file, padded (float64 numpy): what ``PDA``, ``JPDA`` and
    ``GNN`` take (``torch.as_tensor(scans.z)``), as :func:`torchmm.simulate.simulate_detections` makes.

    Shapes:
        z: ``(T, runs, D, m)``, NaN where ``present`` is False; with a sensor column ``(T, runs, S, D, m)``
        present: ``(T, runs, D)`` bool (the detections of a scan first, in file order; ``(T, runs, S, D)``
            with a sensor column)
        times: ``(T,)`` the scans' time stamps (the union over the series, increasing)
        reported: ``(T, runs)`` bool (``(T, runs, S)``): the file has a row there (a detection or an empty
            scan's row)
        sensors: the sensor column's values in order of appearance (None without one)
    """

    z: np.ndarray
    present: np.ndarray
    times: np.ndarray
    series: list[str]
    reported: np.ndarray | None = None
    sensors: list[str] | None = None


def read_detections(path: str | Path, *, measurements: list[str], time: str, series: str | None = None,
                    sensor: str | None = None, base: Path | None = None) -> DetectionScans:
    """Read detections, one per row (CSV) or per entry (NPZ), into padded scans.

    The rows with the same time stamp (and series) are one scan; the scans are every time stamp that
    appears, in increasing order, so a series without a row at a stamp has an empty scan there. A row
    whose measurement cells are all missing (empty, ``nan``, ``NA``) records an empty scan (nothing
    detected) without a detection; a row with only some missing is an error (a detection has every
    component), and so is an infinite cell (``inf`` is not missing: it would drop a detection).

    Args:
        path: a ``.csv`` (a header naming the columns) or ``.npz`` (one ``(K,)`` array per column, one
            entry per detection); relative paths as for :func:`read_series`.
        measurements: the measurement columns, in the order of the sensor's components.
        time: the time-stamp column (finite).
        series: optional column whose values name the series (runs), e.g. recordings of several
            sensors or days; NPZ: a numeric array, each value's label exact (:func:`npz_label`: ``1000001``,
            as the CSV cell ``1000001`` reads; integers beyond 2^53 are refused).
        sensor: optional column naming each row's sensor (several sensors in one recording): the scans
            get a sensor axis, ``z (T, runs, S, D, m)``, a sensor's scan at a time stamp holding its rows.

    Raises:
        DataFileError: naming the file, the column and the row (CSV line, header = 1; NPZ entry index),
            as for :func:`read_series` (a missing or duplicated column, an infinite or non-numeric cell,
            an empty series cell, a file that is not UTF-8), and a detection missing a component.
        TypeError: naming the argument (``measurements="pos"`` for ``["pos"]``, ``time=None``).

    Examples:
        A CSV ``time,x,y`` with rows ``0,1.5,2.0``, ``0,40,-3``, ``1,,`` and ``2,2.1,2.2`` gives
        ``z`` of shape ``(3, 1, 2, 2)``: two detections at t = 0, none at 1, one at 2.
    """
    measurements = column_names(measurements, "measurements")
    if time is None:
        raise TypeError("time: expected the time-stamp column's name, got None")
    time, series, sensor = column_name(time, "time"), column_name(series, "series"), column_name(sensor, "sensor")
    file = locate(path, base, measurements)
    wanted = measurements + [time]
    suffix = file.suffix.lower()
    sensor_labels = None
    if suffix == ".npz":
        arrays = read_npz(file, wanted + ([series] if series else []) + ([sensor] if sensor else []))
        if any(a.shape[1] != 1 for a in arrays.values()):
            raise DataFileError(f"{file}: expected one (K,) array per column, one entry per detection")
        values = {c: list(arrays[c][:, 0]) for c in wanted}
        if series:
            missing = np.flatnonzero(np.isnan(arrays[series][:, 0]))
            if len(missing):
                raise DataFileError(f"{file}: column {series!r}, entry {int(missing[0])}: the series value is "
                                    "missing (every entry names its series)")
        labels = [npz_label(v) for v in arrays[series][:, 0]] if series else ["0"] * len(values[time])
        where, what = list(range(len(labels))), "entry"
        if sensor:
            missing = np.flatnonzero(np.isnan(arrays[sensor][:, 0]))
            if len(missing):
                raise DataFileError(f"{file}: column {sensor!r}, entry {int(missing[0])}: the sensor is missing "
                                    "(every entry names its sensor)")
            sensor_labels = [npz_label(v) for v in arrays[sensor][:, 0]]
    elif suffix == ".csv":
        values, where = read_csv(file, wanted, series, names=[sensor] if sensor else ())
        labels = values.pop(series) if series else ["0"] * len(where)
        sensor_labels = values.pop(sensor) if sensor else None
        what = "row"
    else:
        raise DataFileError(f"{file}: expected a .csv or .npz file")
    stamps = np.array(values[time], dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(stamps))
    if len(bad):
        raise DataFileError(f"{file}: column {time!r}, {what} {where[bad[0]]}: a time stamp is missing")
    z_rows = np.array([[values[c][i] for c in measurements] for i in range(len(stamps))], dtype=np.float64)
    finite = np.isfinite(z_rows)
    partial = np.flatnonzero(finite.any(-1) & ~finite.all(-1))
    if len(partial):
        i = int(partial[0])
        column = measurements[int(np.argmin(finite[i]))]
        raise DataFileError(f"{file}: column {column!r}, {what} {where[i]}: a detection misses a component "
                            "(leave every measurement cell of a row empty to record an empty scan)")
    grid = np.unique(stamps)
    order = list(dict.fromkeys(labels))
    sensors = list(dict.fromkeys(sensor_labels)) if sensor_labels is not None else ["0"]
    run_of = {s: j for j, s in enumerate(order)}
    sensor_of = {s: j for j, s in enumerate(sensors)}
    scan_of = np.searchsorted(grid, stamps)
    cell = [(scan_of[i], run_of[labels[i]], sensor_of[sensor_labels[i]] if sensor_labels is not None else 0)
            for i in range(len(stamps))]
    detected = finite.all(-1)
    counts = np.zeros((len(grid), len(order), len(sensors)), dtype=int)
    reported = np.zeros(counts.shape, dtype=bool)
    for i, at in enumerate(cell):
        reported[at] = True
        counts[at] += int(detected[i])
    D = int(counts.max()) if counts.size else 0
    z = np.full((*counts.shape, D, len(measurements)), np.nan)
    present = np.zeros((*counts.shape, D), dtype=bool)
    fill = np.zeros_like(counts)
    for i in np.flatnonzero(detected):
        at = cell[i]
        z[at + (fill[at],)] = z_rows[i]
        present[at + (fill[at],)] = True
        fill[at] += 1
    if sensor_labels is None:  # no sensor axis
        return DetectionScans(z[:, :, 0], present[:, :, 0], grid, order, reported[:, :, 0])
    return DetectionScans(z, present, grid, order, reported, sensors)


@dataclass
class TargetRows:
    """Rows of a per-target file (:func:`read_targets`), in file order (float64 numpy).

    Shapes:
        values: ``(K, c)`` the ``columns`` of each row
        target: ``K`` labels (the target column's cells as text)
        series: ``K`` labels (``"0"`` without a series column)
        times: ``(K,)`` time stamps, or None without a time column
        rows: ``K`` row numbers (CSV line, header = 1; NPZ entry index), for errors
    """

    file: Path
    values: np.ndarray
    target: list[str]
    series: list[str]
    times: np.ndarray | None
    rows: list[int]
    what: str


def read_targets(path: str | Path, *, columns: list[str], target: str, time: str | None = None,
                 series: str | None = None, base: Path | None = None) -> TargetRows:
    """Read a per-target file, one row per target (and time stamp, and series): the truth of a
    tracking study (``time``, ``target``, the positions) or the tracks' start (``target``, the state,
    its variances) (docs/tracking.md, "Your own detections").

    Args:
        path: a ``.csv`` (a header naming the columns) or ``.npz`` (one ``(K,)`` array per column, one
            entry per row); relative paths as for :func:`read_series`.
        columns: the value columns (every cell finite: a row is a target that exists).
        target: the column naming the target (any text in a CSV; numbers in an NPZ, labelled exactly as
            :func:`npz_label`).
        time: optional time-stamp column (finite).
        series: optional column naming the series (run) of the row, as in :func:`read_detections`.

    Raises:
        DataFileError: naming the file, the column and the row, as :func:`read_series`; a missing value
            cell, and a (series, target[, time]) given twice.
        TypeError: naming the argument.
    """
    columns = column_names(columns, "columns")
    target, time, series = column_name(target, "target"), column_name(time, "time"), column_name(series, "series")
    if target is None:
        raise TypeError("target: expected the target column's name, got None")
    file = locate(path, base, columns)
    wanted = columns + ([time] if time else [])
    suffix = file.suffix.lower()
    if suffix == ".npz":
        labelled = [target] + ([series] if series else [])
        arrays = read_npz(file, wanted + labelled)
        if any(a.shape[1] != 1 for a in arrays.values()):
            raise DataFileError(f"{file}: expected one (K,) array per column, one entry per row")
        for name in labelled:
            missing = np.flatnonzero(np.isnan(arrays[name][:, 0]))
            if len(missing):
                raise DataFileError(f"{file}: column {name!r}, entry {int(missing[0])}: the label is missing")
        values = {c: list(arrays[c][:, 0]) for c in wanted}
        names = {c: [npz_label(v) for v in arrays[c][:, 0]] for c in labelled}
        rows, what = list(range(len(values[columns[0]]))), "entry"
    elif suffix == ".csv":
        values, rows = read_csv(file, wanted, series, names=[target])
        names = {target: values.pop(target)} | ({series: values.pop(series)} if series else {})
        what = "row"
    else:
        raise DataFileError(f"{file}: expected a .csv or .npz file")
    cells = np.array([[values[c][i] for c in columns] for i in range(len(rows))], dtype=np.float64)
    bad = np.argwhere(~np.isfinite(cells))
    if len(bad):
        i, j = (int(v) for v in bad[0])
        raise DataFileError(f"{file}: column {columns[j]!r}, {what} {rows[i]}: a value is missing (a row is a "
                            "target that exists: leave the row out where it does not)")
    stamps = None
    if time:
        stamps = np.array(values[time], dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(stamps))
        if len(bad):
            raise DataFileError(f"{file}: column {time!r}, {what} {rows[bad[0]]}: a time stamp is missing")
    labels = names[series] if series else ["0"] * len(rows)
    seen: dict = {}
    for i, key in enumerate(zip(labels, names[target], stamps if time else [None] * len(rows))):
        if key in seen:
            raise DataFileError(f"{file}: column {target!r}, {what} {rows[i]}: target {key[1]!r} is given again"
                                + (f" at time {key[2]:g}" if time else "") + (f" in series {key[0]!r}" if series else "")
                                + f" (first at {what} {rows[seen[key]]})")
        seen[key] = i
    return TargetRows(file, cells, list(names[target]), list(labels), stamps, list(rows), what)

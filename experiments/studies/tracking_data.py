"""The tracking study's own detections (issue 46; docs/tracking.md, "Your own detections"): a detections
file, an optional truth file and an optional file of the tracks' start, read into the study's arrays,
and the simulated scenario written as those three files (``tracking.export``).

Files (CSV or NPZ, :mod:`experiments.datafile`):

* **detections**: one row per detection, ``time`` and the two position columns (``measurements``), an
  optional ``series`` column (each series is one run) and, with ``tracking.sensors``, a ``sensor`` column
  naming each row's sensor. A row with empty measurement cells records an empty scan; so does a time on
  the scan grid (a sensor's: its schedule) with no row at all. The scans lie on the grid
  ``t0 + k * tracking.dt`` (``t0`` the earliest time stamp of the files), every stamp on it (within
  ``1e-6 dt``: ``experiments.datafile_io.GRID_TOLERANCE``, shared with the step lengths of
  :func:`experiments.datafile.read_series`' time column); the rows whose stamps fall on the same grid
  point (``0.3`` and ``0.1 + 0.2``) are one scan.
* **truth** (optional; GOSPA and the track-quality table need it): one row per target and time stamp
  where it exists (births and deaths: the rows it has), ``time``, ``target``, the two ``position``
  columns, optional ``series`` (without one, every series has this truth). A target given twice in one
  scan (two stamps on the same grid point included) is an error.
* **start** (the estimators that keep one track per target need it: every one but the managed
  trackers): one row per target (and series): ``target``, the four ``state`` columns ``[x, vx, y, vy]``
  and optional ``variances`` (the four diagonal entries of that track's covariance; ``tracking.P0``
  where not given). The start is the belief one period before the first scan, as ``run_filter``'s
  initial belief (each scan is predicted to, then updated).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from experiments.config import ConfigError
from experiments.datafile import DataFileError, read_detections, read_targets
from experiments.datafile_io import GRID_TOLERANCE, grid_offsets

#: the files a study exports and the columns it writes (conf: tracking.export)
FILES = {"detections": "detections.csv", "truth": "truth.csv", "start": "start.csv"}


class Recorded(NamedTuple):
    """The study's arrays from files (float64).

    Shapes: ``z (T, R, D, 2)`` (``(T, R, S, D, 2)``: each sensor's); ``truth (T, R, N, 2)`` positions (NaN
    where a target does not exist) or None; ``present (T, R, N)`` bool or None; ``x0 (R, K, 4)`` and
    ``P0 (R, K, 4, 4)`` the tracks' start (``K = 0`` without a start file); ``times (T,)``; ``series``: R
    labels."""

    z: Tensor
    truth: Tensor | None
    present: Tensor | None
    x0: Tensor
    P0: Tensor
    times: np.ndarray
    series: list[str]


#: splitmix64's constants (Steele, Lea & Flood, OOPSLA 2014), as signed 64-bit integers
_GOLDEN, _MIX1, _MIX2 = (c - (1 << 64) if c >= 1 << 63 else c
                         for c in (0x9E3779B97F4A7C15, 0xBF58476D1CE4E5B9, 0x94D049BB133111EB))


def _shift(x: Tensor, bits: int) -> Tensor:
    """``x >> bits`` as unsigned 64-bit integers (torch shifts int64 arithmetically)."""
    return (x >> bits) & ((1 << (64 - bits)) - 1)


def _mix(x: Tensor) -> Tensor:
    """splitmix64's finaliser on int64 (products wrap modulo 2^64, the same on every CPU)."""
    x = (x ^ _shift(x, 30)) * _MIX1
    x = (x ^ _shift(x, 27)) * _MIX2
    return x ^ _shift(x, 31)


def canonical_order(z: Tensor) -> Tensor:
    """The scans ``z (T, *B, D, m)`` with each scan's detections in one canonical order: the order of a
    hash of each detection's values (their bits, ``-0.0`` as ``0.0``, mixed by splitmix64), absent
    detections (a NaN component) last, all NaN. Any order of a scan's rows, and padding
    anywhere, give the same scans (up to the width ``D``); identical detections tie harmlessly. A hash,
    not a sort by value: no place in the plane comes first, so where the managed trackers' capacity binds
    (they fill free slots in detection order) the detections left over are not those of one region.

    The tracking study puts every scan its trackers see in this order (simulated or read from
    ``tracking.detections``; with ``tracking.sensors`` each sensor's, ``(T, R, S, D, 2)``), docs/tracking.md
    ("Detection order"); tests/experiments/test_tracking_detections.py."""
    bits = {torch.float64: torch.int64, torch.float32: torch.int32}.get(z.dtype)
    if bits is None:
        raise TypeError(f"z: expected float32 or float64 detections, got {z.dtype}")
    absent = torch.isnan(z).any(-1)  # (T, *B, D)
    words = torch.where(z == 0, torch.zeros_like(z), z).view(bits).long()  # (T, *B, D, m): -0.0 as 0.0
    key = torch.full(absent.shape, _GOLDEN, dtype=torch.int64)
    for j in range(z.shape[-1]):  # (m components: a handful); the key's order of components matters
        key = _mix(key ^ _mix(words[..., j])) + _GOLDEN
    order = torch.argsort(key, dim=-1, stable=True)
    order = order.gather(-1, torch.argsort(absent.gather(-1, order).to(torch.uint8), dim=-1, stable=True))
    z = torch.where(absent.unsqueeze(-1), math.nan, z)  # (an absent detection: every component NaN)
    return z.gather(-2, order.unsqueeze(-1).expand(z.shape))


def _fail(key: str, node, err: Exception, columns: tuple[str, ...] = ()):
    """A reader's error as one ConfigError naming the config key the user gave, with its value: the file's
    (``key.path``) for a :class:`DataFileError`, else the argument's. ``columns``: the config lists the
    reader's ``columns`` argument joins, in order (truth: ``position``; start: ``state``, ``variances``)."""
    if isinstance(err, DataFileError):
        return ConfigError(key, node["path"], str(err))
    name, _, why = str(err).partition(": ")
    if not why:
        return ConfigError(key, node["path"], name)

    def field(match: re.Match) -> str:  # columns[i] as the config list and index it came from
        index = int(match.group(1))
        for part in columns:
            size = len(node.get(part) or [])
            if index < size:
                return f"{part}[{index}]"
            index -= size
        return match.group(0)
    if columns:
        name, why = (re.sub(r"\bcolumns\[(\d+)\]", field, text) for text in (name, why))
        name = columns[0] if name == "columns" else name
    arg = name.split("[", 1)[0]
    value = node.get(arg)
    listed = isinstance(value, Sequence) and not isinstance(value, str)
    return ConfigError(f"{key}.{arg}", list(value) if listed else value, why)


def _grid(stamps: dict[str, np.ndarray | None], dt: float) -> tuple[float, int]:
    """``(t0, T)``: the scan grid ``t0 + k dt`` holding every stamp of ``stamps`` (the file's ``path`` key:
    its stamps)."""
    given = {key: s for key, s in stamps.items() if s is not None and len(s)}
    t0 = float(min(s.min() for s in given.values()))
    T = 0
    for key, every in given.items():
        off = grid_offsets(every, t0, dt)
        if off.max() > GRID_TOLERANCE:
            bad = float(every[int(np.argmax(off))])
            raise ConfigError("tracking.dt", dt, f"the time stamp {bad!r} of {key} is not on the scan grid "
                              f"{t0!r} + k * dt (give the sensor's period as tracking.dt)")
        T = max(T, int(_index(every, t0, dt).max()) + 1)
    return t0, T


def _index(stamps: np.ndarray, t0: float, dt: float) -> np.ndarray:
    return np.round((stamps - t0) / dt).astype(int)


def _on_grid(z: np.ndarray, steps: np.ndarray, T: int) -> np.ndarray:
    """The file's scans ``z (T', *B, D, m)`` (one for each distinct time stamp, NaN padding) as the grid's
    ``(T, *B, D', m)``: the scans whose stamps round to the same grid index ``steps (T',)`` (stamps that
    differ by float rounding, ``0.3`` and ``0.1 + 0.2``) are one scan holding all their detections;
    each scan's detections first (in the order of their stamps, then of the file's rows), its padding
    after them."""
    B, m = z.shape[1:-2], z.shape[-1]
    merged = []
    for k in range(T):
        part = np.moveaxis(z[steps == k], 0, -3)  # (*B, n_k, D, m): the file's scans on grid index k
        part = part.reshape(*B, -1, m)
        order = np.argsort(~np.isfinite(part).all(-1), axis=-1, kind="stable")
        merged.append(np.take_along_axis(part, order[..., None], -2))
    D = max([int(np.isfinite(p).all(-1).sum(-1).max(initial=0)) for p in merged], default=0)
    out = np.full((T, *B, D, m), np.nan)
    for k, part in enumerate(merged):
        n = min(D, part.shape[-2])
        out[k, ..., :n, :] = part[..., :n, :]
    return out


def _series_of(rows, series: list[str], key: str, node) -> list[list[int]]:
    """For each detection series, the rows that belong to it (every row where the file has no series
    column); a series the detections do not have is an error."""
    if node.get("series") is None:
        return [list(range(len(rows.target)))] * len(series)
    unknown = sorted(set(rows.series) - set(series))
    if unknown:
        raise ConfigError(f"{key}.series", node.get("series"), f"series {unknown[0]!r} of {rows.file.name} has no "
                          f"detections (the detections' series: {', '.join(series)})")
    return [[i for i, s in enumerate(rows.series) if s == label] for label in series]


def read(node, *, dt: float, P0: list[float], sensors: list[str] | None = None, schedule=None) -> Recorded:
    """``tracking.detections``'s files as the study's arrays; every error one ConfigError naming the key.
    With ``sensors`` (``tracking.sensors``' names) the scans are each sensor's, ``z (T, R, S, D, 2)``
    (the file's ``sensor`` column; one sensor may go without), and ``schedule(T) -> (T, S)`` bool says
    when each reports: a row off it is an error, a scheduled time without a row an empty scan."""
    key = "tracking.detections"
    try:
        scans = read_detections(node["path"], measurements=list(node["measurements"]), time=node["time"],
                                series=node.get("series"), sensor=node.get("sensor"))
    except (DataFileError, TypeError, ValueError) as err:
        raise _fail(key, node, err) from None
    if scans.z.shape[-1] != 2:
        raise ConfigError(f"{key}.measurements", list(node["measurements"]), "expected the two position columns "
                          "[x, y] (the study's sensor measures position)")
    truth_node, start_node = node.get("truth"), node.get("start")
    truth_rows = start_rows = None
    if truth_node is not None:
        try:
            truth_rows = read_targets(truth_node["path"], columns=list(truth_node["position"]),
                                      target=truth_node["target"], time=truth_node["time"],
                                      series=truth_node.get("series"))
        except (DataFileError, TypeError, ValueError) as err:
            raise _fail(f"{key}.truth", truth_node, err, ("position",)) from None
        if truth_rows.values.shape[-1] != 2:
            raise ConfigError(f"{key}.truth.position", list(truth_node["position"]), "expected two columns [x, y]")
    if start_node is not None:
        columns = list(start_node["state"]) + list(start_node.get("variances") or [])
        for name in ("state", "variances"):
            given = start_node.get(name)
            if given is not None and len(given) != 4:
                raise ConfigError(f"{key}.start.{name}", list(given), "expected four columns, for [x, vx, y, vy]")
        try:
            start_rows = read_targets(start_node["path"], columns=columns, target=start_node["target"],
                                      series=start_node.get("series"))
        except (DataFileError, TypeError, ValueError) as err:
            raise _fail(f"{key}.start", start_node, err, ("state", "variances")) from None
    t0, T = _grid({f"{key}.path={node['path']}": scans.times,
                   f"{key}.truth.path={truth_node['path']}" if truth_node is not None else "": (
                       truth_rows.times if truth_rows is not None else None)}, dt)
    R = scans.z.shape[1]
    if sensors is None:
        z = _on_grid(scans.z, _index(scans.times, t0, dt), T)
    else:
        z = _by_sensor(node, scans, sensors, schedule, t0, dt, T)
    truth = present = None
    if truth_rows is not None:
        targets = list(dict.fromkeys(truth_rows.target))
        which = {name: i for i, name in enumerate(targets)}
        truth = np.full((T, R, len(targets), 2), np.nan)
        steps = _index(truth_rows.times, t0, dt)
        for r, rows in enumerate(_series_of(truth_rows, scans.series, f"{key}.truth", truth_node)):
            given: dict = {}
            for i in rows:
                at = (steps[i], which[truth_rows.target[i]])
                if at in given:  # (stamps that differ by float rounding: read_targets saw two times)
                    what, stamps = truth_rows.what, truth_rows.times
                    both = " and ".join(f"{what} {truth_rows.rows[j]} (time {float(stamps[j])!r})"
                                        for j in (given[at], i))
                    raise ConfigError(f"{key}.truth", truth_node["path"], (
                        f"{truth_rows.file.name}: target {truth_rows.target[i]!r} is given twice in scan "
                        f"{at[0]} (time {t0 + at[0] * dt:g}): {both} round to the same scan of the grid "
                        "t0 + k * tracking.dt"))
                given[at] = i
                truth[steps[i], r, at[1]] = truth_rows.values[i]
        present = np.isfinite(truth).all(-1)
    if start_rows is not None:
        per_series = _series_of(start_rows, scans.series, f"{key}.start", start_node)
        counts = {len(rows) for rows in per_series}
        if len(counts) != 1:
            raise ConfigError(f"{key}.start", start_node["path"], "every series needs the same number of tracks "
                              f"(one row per target); the series have {sorted(counts)}")
        values = np.stack([start_rows.values[rows] for rows in per_series])  # (R, K, 4 or 8)
        x0 = values[..., :4]
        variances = values[..., 4:] if values.shape[-1] == 8 else np.broadcast_to(np.asarray(P0, float), x0.shape)
        if (variances < 0).any():
            raise ConfigError(f"{key}.start.variances", list(start_node["variances"]), "a variance is negative")
        cov = np.zeros(x0.shape + (4,))
        cov[..., range(4), range(4)] = variances
    else:
        x0, cov = np.zeros((R, 0, 4)), np.zeros((R, 0, 4, 4))
    as_t = torch.as_tensor
    return Recorded(as_t(z), None if truth is None else as_t(truth), None if present is None else as_t(present),
                    as_t(x0), as_t(cov), t0 + dt * np.arange(T), list(scans.series))


def _by_sensor(node, scans, sensors: list[str], schedule, t0: float, dt: float, T: int) -> np.ndarray:
    """The scans ``(T, R, S, D, 2)`` in ``sensors``' order; a row of a sensor that is not configured, or off
    its schedule, is a ConfigError."""
    z_file, reported = scans.z, scans.reported
    labels = scans.sensors
    if labels is None:  # one sensor, no column
        z_file, reported, labels = z_file[:, :, None], reported[:, :, None], [sensors[0]]
    unknown = [label for label in labels if label not in sensors]
    if unknown:
        raise ConfigError("tracking.detections.sensor", node.get("sensor"), f"sensor {unknown[0]!r} of "
                          f"{Path(node['path']).name} is not in tracking.sensors ({', '.join(sensors)})")
    steps = _index(scans.times, t0, dt)
    where = [sensors.index(label) for label in labels]  # the file's sensor j is tracking.sensors[where[j]]
    z = np.full(z_file.shape[:2] + (len(sensors),) + z_file.shape[3:], np.nan)
    z[:, :, where] = z_file
    z = _on_grid(z, steps, T)
    rows = np.zeros((T, z_file.shape[1], len(sensors)), dtype=bool)
    for j, s in enumerate(where):  # (scans merged on the grid: a row in any of them)
        for step, at in zip(steps, reported[:, :, j]):
            rows[step, :, s] |= at
    off = rows & ~np.asarray(schedule(T))[:, None, :]
    if off.any():
        k, _, s = (int(v[0]) for v in np.nonzero(off))
        raise ConfigError(f"tracking.sensors[{s}]", sensors[s], f"{Path(node['path']).name} has a row of this "
                          f"sensor at time {t0 + k * dt:g}, off its schedule (offset + n * period from {t0:g})")
    return z


def _cells(values) -> list[str]:
    return [repr(float(v)) if math.isfinite(v) else "" for v in values]


def export(folder: Path, *, z: Tensor, truth: Tensor, present: Tensor, x0: Tensor, dt: float,
           sensors: list[str] | None = None, reports: Tensor | None = None) -> dict[str, Path]:
    """Write a simulated scenario as the files :func:`read` takes (full precision: read back, every
    number is the same): ``detections.csv`` (``time, series, x, y``; an empty row for an empty scan; with
    ``sensors`` a ``sensor`` column, a sensor's rows where ``reports`` says it reported),
    ``truth.csv`` (``time, series, target, x, y``, the rows where a target exists) and ``start.csv``
    (``series, target, x, vx, y, vy``).

    Shapes: ``z (T, R, D, 2)`` (with sensors ``(T, R, S, D, 2)`` and ``reports (T, S)``), ``truth (T, R, N,
    2)``, ``present (T, R, N)``, ``x0 (R, N, 4)``."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = {name: folder / file for name, file in FILES.items()}
    z, truth, present, x0 = (v.detach().cpu().double().numpy() if v.is_floating_point() else v.cpu().numpy()
                             for v in (z, truth, present, x0))
    T, R = z.shape[:2]
    if sensors is None:
        z, on, names, lines = z[:, :, None], np.ones((T, 1), dtype=bool), [None], ["time,series,x,y"]
    else:
        on, names, lines = reports.cpu().numpy(), sensors, ["time,series,sensor,x,y"]
    for k in range(T):
        for r in range(R):
            for s, name in enumerate(names):
                if not on[k, s]:
                    continue
                head = [repr(k * dt), str(r)] + ([] if name is None else [name])
                seen = np.isfinite(z[k, r, s]).all(-1)
                lines += [",".join([*head, *_cells(z[k, r, s, d])]) for d in np.flatnonzero(seen)]
                if not seen.any():
                    lines.append(",".join(head) + ",,")
    paths["detections"].write_text("\n".join(lines) + "\n")
    lines = ["time,series,target,x,y"]
    for k in range(T):
        for r in range(R):
            lines += [",".join([repr(k * dt), str(r), str(i), *_cells(truth[k, r, i])])
                      for i in np.flatnonzero(present[k, r])]
    paths["truth"].write_text("\n".join(lines) + "\n")
    lines = ["series,target,x,vx,y,vy"]
    for r in range(R):
        lines += [",".join([str(r), str(i), *_cells(x0[r, i])]) for i in range(x0.shape[1])]
    paths["start"].write_text("\n".join(lines) + "\n")
    return paths


#: the config node that reads the exported files back (tracking.detections)
def node_for(paths: dict[str, Path], *, sensors: bool = False) -> dict:
    return {"path": str(paths["detections"]), "measurements": ["x", "y"], "time": "time", "series": "series",
            "sensor": "sensor" if sensors else None,
            "truth": {"path": str(paths["truth"]), "time": "time", "target": "target", "position": ["x", "y"],
                      "series": "series"},
            "start": {"path": str(paths["start"]), "target": "target", "state": ["x", "vx", "y", "vy"],
                      "variances": None, "series": "series"}}

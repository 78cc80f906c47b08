"""Reading the cells of a recorded-data file (split from :mod:`experiments.datafile` by concern, issue 47): CSV
and NPZ columns as float64 arrays, missing cells as NaN, and every malformed file, column or cell one
:class:`DataFileError` naming the file, the column and the row (the rules: :mod:`experiments.datafile`'s
docstring)."""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["GRID_TOLERANCE", "MISSING", "DataFileError", "check_increasing", "column_name", "column_names",
           "file_text", "grid_offsets", "locate", "number_cell", "path_arg", "read_csv", "read_npz",
           "step_lengths"]

#: cells read as missing (case-insensitive)
MISSING = ("", "nan", "na", "n/a", "null", "none")
#: time stamps within this fraction of a step of a grid point are on it (float rounding: ``0.1 + 0.2`` is not
#: ``0.3``, and the differences of the stamps 0.0, 0.1, ..., 2.9 take six values): the tracking study's scan
#: grid and a data file's step lengths (:func:`grid_offsets`, :func:`step_lengths`)
GRID_TOLERANCE = 1e-6


class DataFileError(ValueError):
    """A data file that cannot be read as the config describes: one line naming file, column, row."""


def number_cell(text: str, file: Path, column: str, line: int) -> float:
    cell = text.strip()
    if cell.lower() in MISSING:
        return math.nan
    try:
        if "_" in cell:  # float() reads 1_000 as 1000: not a number a data file means
            raise ValueError
        value = float(cell)
    except ValueError:
        raise DataFileError(f"{file}: column {column!r}, row {line}: {cell!r} is not a number") from None
    if math.isinf(value):  # inf is not missing: only the MISSING cells (and NaN) are
        raise DataFileError(f"{file}: column {column!r}, row {line}: {cell!r} is not finite (leave the cell "
                            "empty or write nan for a missing value)")
    return value  # NaN in any spelling float() reads (nan, -nan, +NaN) is missing


def column_names(value, name: str, *, optional: bool = False) -> list[str] | None:
    """``value`` as a list of column names: a sequence (list, tuple, a config's list) of non-empty
    strings; a string, a mapping or an array is a ``TypeError`` naming ``name`` (a string would be
    read letter by letter)."""
    if value is None and optional:
        return None
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        hint = f" (one column: [{value!r}])" if isinstance(value, str) else ""
        raise TypeError(f"{name}: expected a list of column names, got {value!r}{hint}")
    out = list(value)
    for i, column in enumerate(out):
        if not isinstance(column, str) or not column.strip():
            raise TypeError(f"{name}[{i}]: expected a column name (a non-empty string), got {column!r}")
        if column in out[:i]:
            raise ValueError(f"{name}[{i}]: column {column!r} is named twice (as {name}[{out.index(column)}]): one "
                             "column would feed two components")
    return out


def column_name(value, name: str) -> str | None:
    """``value`` as one optional column name (a non-empty string or None), else a ``TypeError``."""
    if value is not None and (not isinstance(value, str) or not value.strip()):
        raise TypeError(f"{name}: expected a column name (a non-empty string) or None, got {value!r}")
    return value


def path_arg(value, name: str, *, optional: bool = False) -> Path | None:
    if value is None and optional:
        return None
    if not isinstance(value, (str, os.PathLike)) or not os.fspath(value):
        raise TypeError(f"{name}: expected a file path (str or pathlib.Path), got {value!r}")
    return Path(value)


def file_text(file: Path) -> str:
    """The file's text (UTF-8, an optional byte-order mark dropped), or one :class:`DataFileError`
    naming the file and the line of the first byte that is not UTF-8."""
    try:
        data = file.read_bytes()
    except OSError as err:
        raise DataFileError(f"{file}: cannot be read ({err.strerror or err})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        line = data[:err.start].count(b"\n") + 1
        raise DataFileError(f"{file}: line {line}: not UTF-8 text (byte 0x{data[err.start]:02x}); save the file "
                            "as UTF-8") from None


def read_csv(file: Path, wanted: list[str], series: str | None,
              names: Sequence[str] = ()) -> tuple[dict[str, list], list[int]]:
    """The columns ``wanted`` as numbers, ``series`` and ``names`` as labels (stripped, never empty), and
    each row's line number.

    Every row is read, a row of empty cells (``,,``: what ``csv.writer`` writes for a step with every value
    missing) as missing values. A blank line (nothing on it; spaces only, in a file of several columns) is
    ignored at the end of the file; before another row it is, in a file of one column, that column's cell,
    empty (a missing value), and in a file of several columns an error naming its line (it would otherwise
    drop a step, or be read as one)."""
    reader = csv.reader(io.StringIO(file_text(file), newline=""))
    header = next(reader, None)
    if not header:
        raise DataFileError(f"{file}: empty file (expected a header line naming the columns)")
    header = [h.strip() for h in header]
    index = {}
    labelled = ([series] if series else []) + list(names)
    for name in wanted + labelled:
        if name not in header:
            raise DataFileError(f"{file}: column {name!r}, row 1: not in the header "
                                f"(columns: {', '.join(header)})")
        if header.count(name) > 1:
            raise DataFileError(f"{file}: column {name!r}, row 1: named {header.count(name)} times in the header "
                                "(which one is meant?)")
        index[name] = header.index(name)
    values: dict[str, list] = {name: [] for name in index}
    lines = []
    blank: list[int] = []  # blank lines not yet followed by a row (at the end of the file they are ignored)
    for row in reader:
        line = reader.line_num  # the row's last line (a quoted cell may span lines)
        if not row or (len(header) > 1 and len(row) == 1 and not row[0].strip()):
            blank.append(line)  # a blank line (spaces only, in a file of several columns)
            continue
        if blank:
            if len(header) > 1:  # (a step with every value missing is a row of empty cells, `,,`)
                commas = "," * (len(header) - 1)
                raise DataFileError(f"{file}: row {blank[0]}: a blank line between rows (a step with every "
                                    f"value missing is a row of {len(header)} empty cells, e.g. {commas!r}; "
                                    "blank lines are ignored only at the end of the file)")
            for missing in blank:  # one column: a blank line is its one cell, empty (missing)
                _read_row([""], missing, index, labelled, series, values, file)
                lines.append(missing)
            blank = []
        if len(row) != len(header):
            raise DataFileError(f"{file}: row {line}: {len(row)} cells, the header has {len(header)}")
        _read_row(row, line, index, labelled, series, values, file)
        lines.append(line)
    if not lines:
        raise DataFileError(f"{file}: no data rows after the header")
    return values, lines


def _read_row(row: list[str], line: int, index: dict[str, int], labelled: list[str], series: str | None,
              values: dict[str, list], file: Path) -> None:
    for name, i in index.items():
        cell = row[i]
        if name in labelled:
            if not cell.strip():
                what = "series" if name == series else "label"
                raise DataFileError(f"{file}: column {name!r}, row {line}: the {what} cell is empty "
                                    f"(every row names its {what})")
            values[name].append(cell.strip())
        else:
            values[name].append(number_cell(cell, file, name, line))


def read_npz(file: Path, wanted: list[str], shared: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """The arrays ``wanted`` as ``(T, runs)`` float64 (a ``(T,)`` array as ``(T, 1)``), all of one shape; an
    array named in ``shared`` (a time column) may be one ``(T,)`` array beside ``(T, runs)`` ones, shared by
    the runs (broadcast)."""
    try:
        archive = np.load(file, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise DataFileError(f"{file}: cannot be read as NPZ ({err})") from None
    with archive:
        out = {}
        for name in wanted:
            if name not in archive.files:
                raise DataFileError(f"{file}: column {name!r}: no such array (arrays: {', '.join(archive.files)})")
            try:
                raw = archive[name]
            except ValueError:  # an object array (it would need pickle)
                raise DataFileError(f"{file}: column {name!r}: an object array (pickled Python objects); save numbers "
                                    "(a float or integer array)") from None
            # numbers only: booleans (True/False read as 1/0) and strings are not measurements
            array = np.asarray(raw, dtype=np.float64) if raw.dtype.kind in "fiu" else None
            if raw.dtype.kind in "iu" and raw.size and np.abs(raw).max() > 2 ** 53:  # (labels too: ids)
                where = np.unravel_index(int(np.argmax(np.abs(raw))), raw.shape)
                entry = where[0] if raw.ndim == 1 else where
                raise DataFileError(f"{file}: column {name!r}, entry {entry}: the integer {raw[where]} is "
                                    "beyond 2^53, not exact in float64 (distinct values would merge)")
            if array is None or array.ndim not in (1, 2):
                raise DataFileError(f"{file}: column {name!r}: expected a numeric (T,) or (T, runs) array")
            infinite = np.argwhere(np.isinf(array))
            if len(infinite):  # inf is not missing (NaN is)
                where = tuple(int(i) for i in infinite[0])
                raise DataFileError(f"{file}: column {name!r}, entry {where[0] if len(where) == 1 else where}: "
                                    f"{array[where]:g} is not finite (NaN marks a missing value)")
            out[name] = array if array.ndim == 2 else array[:, None]
    shapes = {name: a.shape for name, a in out.items()}
    widest = max(shapes.values(), key=lambda shape: shape[1])
    for name in shared:  # a (T,) array shared by the runs of (T, runs) columns
        if name in out and shapes[name][0] == widest[0] and shapes[name][1] == 1:
            out[name] = np.broadcast_to(out[name], widest)
            shapes[name] = widest
    if len(set(shapes.values())) > 1:
        also = f"; the {', '.join(map(repr, shared))} array may be one (T,) array shared by the runs" \
            if shared else ""
        raise DataFileError(f"{file}: arrays of different shapes {shapes} (every column is one (T,) array "
                            f"for one series or one (T, runs) array for several, the same in each{also})")
    return out


def find(file: Path, base: Path | None = None) -> Path:
    """Where the readers look for a data file: a relative path in ``base`` (the working directory), then in
    the shipped ``experiments/data`` (the first that exists; the first if neither does)."""
    if file.is_absolute():
        return file
    here = (base or Path.cwd()) / file
    shipped = Path(__file__).resolve().parent / "data" / file
    return here if here.exists() or not shipped.exists() else shipped


def locate(path: str | Path, base: Path | None, measurements: list[str]) -> Path:
    """The data file: a relative ``path`` in ``base`` (the working directory), then in the shipped
    ``experiments/data``; it must exist, and some measurement columns must be named."""
    file = find(path_arg(path, "path"), path_arg(base, "base", optional=True))
    if not measurements:
        raise ValueError("measurements: no columns given (name the measurement columns, e.g. ['x', 'y'])")
    if not file.exists():
        raise DataFileError(f"{file}: no such file")
    return file


def check_increasing(t: np.ndarray, file: Path, column: str, where: list[int], what: str) -> None:
    steps = np.diff(t)
    if np.any(steps <= 0):
        i = int(np.argmax(steps <= 0)) + 1
        raise DataFileError(f"{file}: column {column!r}, {what} {where[i]}: time stamps must increase "
                            f"({t[i - 1]:g} then {t[i]:g})")


def grid_offsets(stamps: np.ndarray, t0: float, dt: float) -> np.ndarray:
    """How far each of ``stamps (K,)`` lies from the grid ``t0 + k dt``, in steps ``dt`` (``(K,)``, in
    [0, 0.5]): a stamp is on the grid when its offset is at most :data:`GRID_TOLERANCE`."""
    k = (np.asarray(stamps, dtype=np.float64) - t0) / dt
    return np.abs(k - np.round(k))


def step_lengths(times: np.ndarray) -> tuple[float | None, np.ndarray]:
    """``(dt, lengths (T-1,))``: the step lengths ``t_k - t_{k-1}`` of increasing stamps ``times (T,)``.

    ``dt`` is the grid's one step length when every stamp lies on ``t_0 + k dt`` (:func:`grid_offsets`,
    within :data:`GRID_TOLERANCE`; ``dt = (t_{T-1} - t_0) / (T - 1)``, or the steps' one value where
    they are equal bit for bit), and ``lengths`` that ``dt`` at every step; otherwise ``dt`` is None and
    steps of equal length but for float rounding (relative difference at most :data:`GRID_TOLERANCE`)
    have one length, their mean. None and ``(0,)`` for a single stamp."""
    t = np.asarray(times, dtype=np.float64)
    if len(t) < 2:
        return None, np.zeros(0)
    steps = np.diff(t)
    dt = float(steps[0]) if np.all(steps == steps[0]) else float((t[-1] - t[0]) / (len(t) - 1))
    if grid_offsets(t, float(t[0]), dt).max() <= GRID_TOLERANCE:
        return dt, np.full(len(t) - 1, dt)
    order = np.argsort(steps, kind="stable")
    lengths = steps.copy()
    start = 0
    for i in range(1, len(order) + 1):  # runs of sorted steps within the tolerance of the run's shortest
        if i == len(order) or steps[order[i]] - steps[order[start]] > GRID_TOLERANCE * steps[order[start]]:
            lengths[order[start:i]] = steps[order[start:i]].mean()
            start = i
    return None, lengths

"""Malformed data specs for the recorded-data readers (experiments.datafile, issue 44), enumerated.

Every case is one malformed file or argument of ``read_series`` / ``read_detections`` and must give
one error naming the right thing: a ``TypeError`` whose message starts with the argument's name for
an argument of the wrong type (a string for a list of columns, a number for a column name), or one
one-line :class:`~experiments.datafile.DataFileError` naming the file, the column and the row (CSV
line, header = 1; NPZ entry) for a malformed file: a duplicated column, a missing column, bytes that
are not UTF-8, infinite cells (``inf`` is not missing: only the empty, ``nan`` and ``NA`` cells are),
an empty series cell (with and without a time column). Before issue 44 a row of ``inf`` cells was an
empty scan, a duplicated column used its first copy, an empty series cell made a series named ``''``,
a cp1252 header was a raw ``UnicodeDecodeError`` and ``measurements='pos'`` read the columns
``p``, ``o`` and ``s``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np
import pytest

from experiments.datafile import DataFileError, read_detections, read_series


@dataclass
class Spec:
    """A malformed spec: the file (CSV text, bytes, or NPZ arrays), the reader's keyword arguments,
    the error and the pattern its message must match (``{file}``: the file's path)."""

    content: str | bytes | dict
    kwargs: dict
    error: type
    pattern: str
    suffix: str = ".csv"
    path: object = field(default=None)  # a path argument in place of the file's


DETECTIONS = "t,x,y\n0,1,2\n1,3,4\n"
SERIES = "t,x,y,s\n0,1,2,a\n1,3,4,a\n"

READ_DETECTIONS = {
    # arguments of the wrong type: a TypeError naming the argument
    "measurements-string": Spec(DETECTIONS, dict(measurements="xy", time="t"), TypeError, r"^measurements\b"),
    "measurements-number-entry": Spec(DETECTIONS, dict(measurements=["x", 5], time="t"), TypeError,
                                      r"^measurements\[1\]"),
    "measurements-tensor-like": Spec(DETECTIONS, dict(measurements=np.array([1.0, 2.0]), time="t"), TypeError,
                                     r"^measurements\b"),
    "time-list": Spec(DETECTIONS, dict(measurements=["x", "y"], time=["t"]), TypeError, r"^time\b"),
    "series-number": Spec(SERIES, dict(measurements=["x", "y"], time="t", series=3), TypeError, r"^series\b"),
    "path-number": Spec(DETECTIONS, dict(measurements=["x", "y"], time="t"), TypeError, r"^path\b", path=5),
    "measurements-empty": Spec(DETECTIONS, dict(measurements=[], time="t"), ValueError,
                               r"^measurements: no columns given"),
    # malformed files: one DataFileError naming file, column and row
    "duplicated-column": Spec("t,x,x,y\n0,1,9,2\n", dict(measurements=["x", "y"], time="t"), DataFileError,
                              r"^{file}: column 'x', row 1: .*2 times in the header"),
    "missing-column": Spec("t,x\n0,1\n", dict(measurements=["x", "y"], time="t"), DataFileError,
                           r"^{file}: column 'y', row 1: not in the header"),
    "not-utf8": Spec(b"t,x\xe9,y\n0,1,2\n", dict(measurements=["y"], time="t"), DataFileError,
                     r"^{file}: line 1: not UTF-8"),
    "not-utf8-later-row": Spec(b"t,x,y\n0,1,2\n1,3,4 \x96\n", dict(measurements=["x", "y"], time="t"),
                               DataFileError, r"^{file}: line 3: not UTF-8"),
    "inf-row": Spec("t,x,y\n0,1,2\n1,inf,inf\n2,3,4\n", dict(measurements=["x", "y"], time="t"), DataFileError,
                    r"^{file}: column 'x', row 3: 'inf' is not finite"),
    "minus-inf-cell": Spec("t,x,y\n0,1,-Infinity\n", dict(measurements=["x", "y"], time="t"), DataFileError,
                           r"^{file}: column 'y', row 2: '-Infinity' is not finite"),
    "overflow-cell": Spec("t,x,y\n0,1e999,2\n", dict(measurements=["x", "y"], time="t"), DataFileError,
                          r"^{file}: column 'x', row 2: '1e999' is not finite"),
    "inf-time": Spec("t,x,y\ninf,1,2\n", dict(measurements=["x", "y"], time="t"), DataFileError,
                     r"^{file}: column 't', row 2: 'inf' is not finite"),
    "empty-series-cell": Spec("t,x,y,s\n0,1,2,a\n1,3,4,\n", dict(measurements=["x", "y"], time="t", series="s"),
                              DataFileError, r"^{file}: column 's', row 3: .*series"),
    "npz-inf-entry": Spec(dict(t=np.array([0.0, 1.0]), x=np.array([1.0, np.inf]), y=np.array([2.0, 3.0])),
                          dict(measurements=["x", "y"], time="t"), DataFileError,
                          r"^{file}: column 'x', entry 1: inf is not finite", suffix=".npz"),
    "npz-nan-series": Spec(dict(t=np.array([0.0, 1.0]), x=np.array([1.0, 2.0]), y=np.array([2.0, 3.0]),
                                s=np.array([0.0, np.nan])),
                           dict(measurements=["x", "y"], time="t", series="s"), DataFileError,
                           r"^{file}: column 's', entry 1: .*series", suffix=".npz"),
}

READ_SERIES = {
    "measurements-string": Spec(SERIES, dict(measurements="xy"), TypeError, r"^measurements\b"),
    "truth-string": Spec(SERIES, dict(measurements=["x"], truth="y"), TypeError, r"^truth\b"),
    "truth-number-entry": Spec(SERIES, dict(measurements=["x"], truth=[1]), TypeError, r"^truth\[0\]"),
    "time-number": Spec(SERIES, dict(measurements=["x"], time=0), TypeError, r"^time\b"),
    "series-list": Spec(SERIES, dict(measurements=["x"], series=["s"]), TypeError, r"^series\b"),
    "path-number": Spec(SERIES, dict(measurements=["x"]), TypeError, r"^path\b", path=5),
    "base-number": Spec(SERIES, dict(measurements=["x"], base=5), TypeError, r"^base\b"),
    "duplicated-column": Spec("t,x,x,y\n0,1,9,2\n", dict(measurements=["x", "y"]), DataFileError,
                              r"^{file}: column 'x', row 1: .*2 times in the header"),
    "duplicated-series-column": Spec("t,x,s,s\n0,1,a,b\n", dict(measurements=["x"], series="s"), DataFileError,
                                     r"^{file}: column 's', row 1: .*2 times in the header"),
    "missing-column": Spec("t,x\n0,1\n", dict(measurements=["x"], truth=["p"]), DataFileError,
                           r"^{file}: column 'p', row 1: not in the header"),
    "not-utf8": Spec("t,x,pos°\n0,1,2\n".encode("cp1252"), dict(measurements=["x"]), DataFileError,
                     r"^{file}: line 1: not UTF-8"),
    "inf-measurement": Spec("t,x,y\n0,1,2\n1,inf,4\n", dict(measurements=["x", "y"]), DataFileError,
                            r"^{file}: column 'x', row 3: 'inf' is not finite"),
    "inf-truth": Spec("t,x,p\n0,1,2\n1,3,-inf\n", dict(measurements=["x"], truth=["p"]), DataFileError,
                      r"^{file}: column 'p', row 3: '-inf' is not finite"),
    "empty-series-cell-with-time": Spec("t,x,s\n0,1,a\n1,2,a\n0,3,\n", dict(measurements=["x"], time="t",
                                                                         series="s"),
                                        DataFileError, r"^{file}: column 's', row 4: .*series"),
    "empty-series-cell-without-time": Spec("x,s\n1,a\n2, \n", dict(measurements=["x"], series="s"),
                                           DataFileError, r"^{file}: column 's', row 3: .*series"),
    "npz-inf-entry": Spec(dict(x=np.array([[1.0, 2.0], [3.0, -np.inf]])), dict(measurements=["x"]), DataFileError,
                          r"^{file}: column 'x', entry \(1, 1\): -inf is not finite", suffix=".npz"),
    # the second fuzz (issue 44): a column twice, no column, underscores, booleans and objects in an NPZ
    "measurements-twice": Spec(SERIES, dict(measurements=["x", "x"]), ValueError,
                               r"^measurements\[1\]: column 'x' is named twice"),
    "measurements-empty": Spec(SERIES, dict(measurements=[]), ValueError, r"^measurements: no columns given"),
    "underscore-number": Spec("t,x\n0,1_000\n", dict(measurements=["x"]), DataFileError,
                              r"^{file}: column 'x', row 2: '1_000' is not a number"),
    "npz-bool": Spec(dict(x=np.array([True, False])), dict(measurements=["x"]), DataFileError,
                     r"^{file}: column 'x': expected a numeric", suffix=".npz"),
    "npz-object": Spec(dict(x=np.array([1.0, "a"], dtype=object)), dict(measurements=["x"]), DataFileError,
                       r"^{file}: column 'x': an object array", suffix=".npz"),
}


def _write(tmp_path, spec: Spec):
    file = tmp_path / f"data{spec.suffix}"
    if isinstance(spec.content, dict):
        np.savez(file, **spec.content)
    elif isinstance(spec.content, bytes):
        file.write_bytes(spec.content)
    else:
        file.write_text(spec.content)
    return file


def _check(reader, tmp_path, spec: Spec):
    file = _write(tmp_path, spec)
    with pytest.raises(Exception) as info:
        reader(file if spec.path is None else spec.path, **spec.kwargs)
    err = info.value
    assert type(err) is spec.error, f"{type(err).__name__}: {err}"
    message = str(err)
    assert "\n" not in message, message
    assert re.search(spec.pattern.replace("{file}", re.escape(str(file))), message), message


@pytest.mark.parametrize("case", sorted(READ_DETECTIONS))
def test_read_detections_refuses_each_malformed_spec_naming_it(tmp_path, case):
    _check(read_detections, tmp_path, READ_DETECTIONS[case])


@pytest.mark.parametrize("case", sorted(READ_SERIES))
def test_read_series_refuses_each_malformed_spec_naming_it(tmp_path, case):
    _check(read_series, tmp_path, READ_SERIES[case])


def test_missing_cells_stay_missing(tmp_path):
    """Only the missing markers are missing: empty cells, ``nan`` (any sign or case), ``NA``; a
    detection's row of them is an empty scan, a series' step is NaN."""
    file = tmp_path / "ok.csv"
    file.write_text("t,x,y,s\n0,1,2,a\n1,,,a\n2,NA,-nan,a\n3,5,6,b\n")
    scans = read_detections(file, measurements=["x", "y"], time="t")
    assert scans.present.sum(-1)[:, 0].tolist() == [1, 0, 0, 1]
    data = read_series(file, measurements=["x", "y"], time=None, series="s")
    assert data.series == ["a", "b"]
    assert np.isnan(data.measurements[1:3, 0]).all() and np.isfinite(data.measurements[0, 0]).all()
    # the columns as any sequence of strings (a tuple, a config's list)
    assert read_series(file, measurements=("x",), truth=("y",)).measurements.shape == (4, 1, 1)

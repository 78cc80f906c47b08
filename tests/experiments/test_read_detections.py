"""Detections from a file (experiments.datafile.read_detections): padded scans grouped by time stamp,
series as runs, empty scans, the same scans from CSV and NPZ, errors naming file, column and row; the
scans feed the association filters."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from experiments.datafile import DataFileError, read_detections

CSV = """time,x,y,sensor
0,1.5,2.0,a
0,40,-3,a
0,7,7,b
1,,,a
2,2.1,2.2,a
2,50,1,b
2,51,2,b
2,52,3,b
"""


def test_csv_scans_series_and_empty_scans(tmp_path):
    path = tmp_path / "det.csv"
    path.write_text(CSV)
    scans = read_detections(path, measurements=["x", "y"], time="time", series="sensor")
    assert scans.series == ["a", "b"] and scans.times.tolist() == [0.0, 1.0, 2.0]
    assert scans.z.shape == (3, 2, 3, 2) and scans.present.shape == (3, 2, 3)
    assert scans.present.sum(-1).tolist() == [[2, 1], [0, 0], [1, 3]]  # scan 1: a recorded empty, b no row
    np.testing.assert_array_equal(scans.z[0, 0, :2], [[1.5, 2.0], [40.0, -3.0]])  # file order
    np.testing.assert_array_equal(scans.z[2, 1], [[50.0, 1.0], [51.0, 2.0], [52.0, 3.0]])
    assert np.isnan(scans.z[~scans.present]).all() and np.isfinite(scans.z[scans.present]).all()
    one = read_detections(path, measurements=["y", "x"], time="time")  # one series: every row, columns swapped
    assert one.z.shape == (3, 1, 4, 2) and one.present.sum() == 7
    np.testing.assert_array_equal(one.z[0, 0, 0], [2.0, 1.5])


def test_npz_gives_the_same_scans(tmp_path):
    rows = [line.split(",") for line in CSV.strip().splitlines()[1:]]
    cell = [[float(c) if c else math.nan for c in r[:3]] for r in rows]
    np.savez(tmp_path / "det.npz", time=np.array([c[0] for c in cell]), x=np.array([c[1] for c in cell]),
             y=np.array([c[2] for c in cell]), sensor=np.array([0.0 if r[3] == "a" else 1.0 for r in rows]))
    (tmp_path / "det.csv").write_text(CSV)
    a = read_detections(tmp_path / "det.npz", measurements=["x", "y"], time="time", series="sensor")
    b = read_detections(tmp_path / "det.csv", measurements=["x", "y"], time="time", series="sensor")
    np.testing.assert_array_equal(a.z, b.z)
    np.testing.assert_array_equal(a.present, b.present)
    assert a.series == ["0", "1"]


@pytest.mark.parametrize("text, message", [
    ("time,x,y\n0,1,\n", "column 'y', row 2: a detection misses a component"),
    ("time,x,y\n,1,2\n", "column 'time', row 2: a time stamp is missing"),
    ("time,x,y\n0,1,abc\n", "column 'y', row 2: 'abc' is not a number"),
    ("time,x\n0,1\n", "column 'y', row 1: not in the header"),
])
def test_errors_name_file_column_and_row(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(DataFileError, match=message):
        read_detections(path, measurements=["x", "y"], time="time")
    with pytest.raises(DataFileError, match="no such file"):
        read_detections(tmp_path / "none.csv", measurements=["x", "y"], time="time")


def test_the_scans_feed_jpda(tmp_path):
    from torchmm import GaussianBelief, KalmanFilter, run_filter
    from torchmm.association import JPDA
    from torchmm.models import ConstantVelocity, PositionMeasurement

    path = tmp_path / "det.csv"
    path.write_text(CSV)
    scans = read_detections(path, measurements=["x", "y"], time="time", series="sensor")
    jpda = JPDA(KalmanFilter(ConstantVelocity(2, dtype=torch.float64), PositionMeasurement(4, [0, 2], 4.0)),
                detection_probability=0.9, clutter_density=1e-4)
    tracks = GaussianBelief(torch.tensor([[1.0, 0.0, 2.0, 0.0], [40.0, 0.0, -3.0, 0.0]], dtype=torch.float64)
                            .expand(2, 2, 4), 10 * torch.eye(4, dtype=torch.float64))
    out = run_filter(jpda, tracks, torch.as_tensor(scans.z))
    assert out.belief.mean.shape == (3, 2, 2, 4) and torch.isfinite(out.belief.mean).all()


def test_npz_labels_are_exact_and_match_the_csv_s(tmp_path):
    """NPZ series, sensor and target values that agree in their first 6 digits are distinct labels, each
    the label the CSV reader gives the same cell (an integral value as its integer, others as repr)."""
    from experiments.datafile import read_targets

    ids = [1000000, 1000001, 1000000, 1000001]
    np.savez(tmp_path / "d.npz", time=np.array([0.0, 0.0, 1.0, 1.0]), x=np.array([1.0, 2.0, 3.0, 4.0]),
             y=np.zeros(4), series=np.array(ids), sensor=np.array([0.5, 0.25, 0.5, 0.25]))
    cells = zip([0, 0, 1, 1], ids, [0.5, 0.25, 0.5, 0.25], [1, 2, 3, 4])
    text = "".join(f"{t},{s},{c},{x},0\n" for t, s, c, x in cells)
    (tmp_path / "d.csv").write_text("time,series,sensor,x,y\n" + text)
    columns = {"measurements": ["x", "y"], "time": "time", "series": "series", "sensor": "sensor"}
    a = read_detections(tmp_path / "d.npz", **columns)
    b = read_detections(tmp_path / "d.csv", **columns)
    assert a.series == b.series == ["1000000", "1000001"] and a.sensors == b.sensors == ["0.5", "0.25"]
    np.testing.assert_array_equal(a.z, b.z)
    assert a.z[0, 0, 0, 0].tolist() == [1.0, 0.0] and a.z[0, 1, 1, 0].tolist() == [2.0, 0.0]  # not mixed
    np.savez(tmp_path / "t.npz", time=np.zeros(2), target=np.array([1234567, 1234568]), x=np.ones(2),
             y=np.ones(2))
    assert read_targets(tmp_path / "t.npz", columns=["x", "y"], target="target", time="time").target == [
        "1234567", "1234568"]
    np.savez(tmp_path / "big.npz", time=np.zeros(2), x=np.ones(2), y=np.ones(2),
             series=np.array([2 ** 53 + 1, 2 ** 53 + 2], dtype=np.int64))
    with pytest.raises(DataFileError, match=r"column 'series', entry 1: the integer 9007199254740994 is "
                                            r"beyond 2\^53"):
        read_detections(tmp_path / "big.npz", measurements=["x", "y"], time="time", series="series")

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

"""The tracking study's canonical order of a scan's detections (docs/tracking.md, "Detection order"): a
file's row order and NaN padding change no number, for every estimator; the order is a hash of the
detection's values (checked against a plain-Python splitmix64), absent detections last."""

from __future__ import annotations

import csv
import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from experiments.run import run_study
from experiments.studies.tracking_data import canonical_order
from tests.experiments.test_studies import _compose

DATA = Path(__file__).resolve().parents[2] / "experiments" / "data"
ALL = ("tracking.estimators=[IMM-JPDAF,IMM-JPDAF-LBP,IMM-JPDAF-kbest,IMM-MHT,JPDAF,IMM-PDAF,GNN-IMM,JIPDA-TM,"
       "IMM-JIPDA-TM]")
MASK = (1 << 64) - 1


def _splitmix(x: int) -> int:
    x &= MASK
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & MASK
    return x ^ (x >> 31)


def _key(row) -> int:
    """The canonical key of one float64 detection, in Python integers (unsigned; compared as signed)."""
    key = 0x9E3779B97F4A7C15
    for value in row:
        bits = struct.unpack("<Q", struct.pack("<d", 0.0 if value == 0 else float(value)))[0]
        key = (_splitmix(key ^ _splitmix(bits)) + 0x9E3779B97F4A7C15) & MASK
    return key - (1 << 64) if key >= 1 << 63 else key


def test_the_order_is_the_hash_order_with_absent_detections_last():
    """A plain-Python reference: each scan sorted by the signed key, the absent rows after, all NaN;
    -0.0 keys as 0.0; any permutation of a scan's rows, padding anywhere, gives the same scans."""
    g = torch.Generator().manual_seed(3)
    z = torch.randn(4, 3, 6, 2, generator=g, dtype=torch.float64) * 100
    z[0, 0, 1] = math.nan
    z[2, 1, 4, 0] = math.nan  # one NaN component: absent
    z[1, 2, 0] = torch.tensor([0.0, 5.0], dtype=torch.float64)
    z[1, 2, 3] = torch.tensor([-0.0, 5.0], dtype=torch.float64)
    got = canonical_order(z)
    for t in range(4):
        for r in range(3):
            rows = z[t, r].tolist()
            present = [row for row in rows if not any(math.isnan(v) for v in row)]
            absent = [[math.nan, math.nan] for row in rows if any(math.isnan(v) for v in row)]
            want = sorted(present, key=_key) + absent
            assert np.array_equal(np.array(want), got[t, r].numpy(), equal_nan=True), (t, r)
    assert _key([0.0, 5.0]) == _key([-0.0, 5.0])
    for seed in range(3):  # rows permuted within each scan, and NaN rows between them
        p = torch.Generator().manual_seed(seed)
        padded = torch.cat([z, torch.full((4, 3, 3, 2), math.nan, dtype=torch.float64)], -2)
        order = torch.argsort(torch.rand(padded.shape[:-1], generator=p), -1)
        shuffled = canonical_order(padded.gather(-2, order.unsqueeze(-1).expand(padded.shape)))
        assert torch.equal(shuffled[..., :6, :].nan_to_num(7.0), got.nan_to_num(7.0))
        assert shuffled[..., 6:, :].isnan().all()
    # no spatial bias: the first detection of a scan is not the one of the least (or largest) x
    firsts = canonical_order(torch.randn(200, 8, 2, generator=g, dtype=torch.float64))
    rank = (firsts[:, :, 0] < firsts[:, :1, 0]).sum(-1)  # the first one's rank in x, 0..7
    assert 0 < float(rank.double().mean()) < 7 and len(set(rank.tolist())) == 8


def _shuffled_copy(folder: Path, scans: int) -> tuple[Path, Path]:
    """The shipped detections' first ``scans`` scans as given, and with each scan's rows in another order
    and an empty row (NaN padding) among them, with the truth cut to the same scans."""
    with open(DATA / "tracking_detections.csv") as f:
        rows = [r for r in csv.DictReader(f) if float(r["time"]) < scans]
    rng = np.random.default_rng(0)
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["time"], r["series"]), []).append(r)
    shuffled = []
    for (time, series), group in groups.items():
        group = [group[i] for i in rng.permutation(len(group))]
        group.insert(int(rng.integers(len(group) + 1)), {"time": time, "series": series, "x": "", "y": ""})
        shuffled += group
    paths = []
    for name, lines in (("given.csv", rows), ("shuffled.csv", shuffled)):
        text = "".join(f"{r['time']},{r['series']},{r['x']},{r['y']}\n" for r in lines)
        (folder / name).write_text("time,series,x,y\n" + text)
        paths.append(folder / name)
    truth = (DATA / "tracking_truth.csv").read_text().splitlines()
    (folder / "truth.csv").write_text("\n".join([truth[0]] + [line for line in truth[1:]
                                                               if float(line.split(",")[0]) < scans]) + "\n")
    return paths[0], paths[1]


@pytest.mark.parametrize("start", ["file", "detections"])
def test_a_file_s_row_order_and_padding_change_no_number(tmp_path, start):
    """The shipped detections (first 12 scans) with every scan's rows in another order and an empty row
    among them give the same tables, bit for bit, for every estimator: with the start file, and with
    tracking.start: detections (the managed trackers, capacity 3 so that it binds; ManagedMHT's ties)."""
    given, shuffled = _shuffled_copy(tmp_path, 12)
    extra = ([] if start == "file" else ["tracking.start=detections", "tracking.detections.start=null",
                                          "tracking.estimators=[IMM-JPDAF,GNN-IMM,IMM-MHT,JIPDA-TM]"])
    tables = []
    for path in (given, shuffled):
        out = tmp_path / path.stem
        run_study(_compose("tracking_detections", "logger=none", "progress=false", "figures=false", ALL,
                           f"tracking.detections.path={path}", "tracking.management.capacity=3",
                           f"tracking.detections.truth.path={tmp_path / 'truth.csv'}", *extra), out)
        results = json.loads((out / "results.json").read_text())
        tables.append((results["tables"], results["metrics"]))
    (a, metrics_a), (b, metrics_b) = tables
    assert set(a) == set(b)
    for name in a:
        keep = [i for i, c in enumerate(a[name]["columns"]) if "seconds" not in c]
        cells = [[[row[i] for i in keep] for row in table[name]["rows"]] for table in (a, b)]
        assert cells[0] == cells[1], name
    strip = {name: {k: v for k, v in m.items() if "second" not in k} for name, m in metrics_a.items()}
    assert strip == {name: {k: v for k, v in m.items() if "second" not in k} for name, m in metrics_b.items()}
    assert any(m.get("unstarted_tracks", 0) > 0 for m in metrics_a.values())  # the capacity binds

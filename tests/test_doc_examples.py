"""The Python examples of docs/smoothing.md and docs/tracking.md run as a reader runs them.

docs/smoothing.md: every block, after README.md's example block (the set-up its first lines point to);
before, its first examples used ``bank``, ``prior`` and others nothing defined, and it held an empty block.
docs/tracking.md: "Detections from a file" and then the ``ManagedMHT`` example on its ``scans``; before, the
latter passed the ``DetectionScans`` itself to ``run_filter`` (a TypeError; the array is ``scans.z``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def _blocks(name: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", (ROOT / name).read_text(), re.S)


@pytest.fixture(autouse=True)
def _default_dtype():
    before = torch.get_default_dtype()
    yield
    torch.set_default_dtype(before)


def test_the_smoothing_examples_run_after_the_readme_set_up():
    ns: dict = {}
    exec(compile(_blocks("README.md")[0], "README.md", "exec"), ns)
    ns["belief0"] = ns["runs"]  # (docs/smoothing.md's parallel example: "belief0 = runs there")
    blocks = _blocks("docs/smoothing.md")
    assert all(block.strip() for block in blocks), "an empty python block"
    for i, block in enumerate(blocks):
        exec(compile(block, f"docs/smoothing.md, python block {i}", "exec"), ns)
        if i == 0:  # the IMM's smoother, as the comments give the shapes
            smoothed = ns["smoothed"]
            assert smoothed.estimate().mean.shape == (100, 400, 2)
            total = smoothed.belief.mode_probs.sum(-1)
            assert torch.allclose(total, torch.ones_like(total))
    # the last block: the parallel smoother of the README's single CV filter, as its comment says
    reference = ns["smooth"](ns["kf"], ns["run_filter"](ns["kf"], ns["runs"], ns["z"]))
    assert torch.allclose(ns["smoothed"].belief.mean, reference.belief.mean, atol=1e-9, rtol=0)


@pytest.fixture
def radar(tmp_path, monkeypatch) -> Path:
    """docs/tracking.md's ``radar.csv``: two series (column ``sensor``), two targets, clutter, an empty
    scan."""
    rng = np.random.default_rng(0)
    rows = ["time,x,y,sensor"]
    for series in ("north", "south"):
        for k in range(8):
            for start in (0.0, 300.0):
                if rng.random() < 0.9:
                    x, y = start + 10 * k + rng.normal(0, 5), start + rng.normal(0, 5)
                    rows.append(f"{k},{x:.4f},{y:.4f},{series}")
            if rng.random() < 0.5:
                rows.append(f"{k},{rng.uniform(0, 1000):.4f},{rng.uniform(0, 1000):.4f},{series}")
    rows.append("8,,,north")  # an empty scan
    (tmp_path / "radar.csv").write_text("\n".join(rows) + "\n")
    monkeypatch.chdir(tmp_path)
    return tmp_path / "radar.csv"


def test_the_detections_file_and_mht_examples_run(radar):
    from torchmm import (IMM, ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement,
                         run_filter)
    from torchmm.association import JPDA

    torch.set_default_dtype(torch.float64)
    motion = ConstantVelocity(2, dt=1.0, q=0.5)
    sensor = PositionMeasurement(4, [0, 2], 25.0)
    area = 1000.0 * 1000.0
    starts = torch.tensor([[0.0, 10.0, 0.0, 0.0], [300.0, 10.0, 300.0, 0.0]])
    bank = ConstantVelocity(2, dt=1.0, q=0.5, acceleration=[[0.0, 0.0], [2.0, 0.0], [-2.0, 0.0]])
    cov = torch.diag(torch.tensor([25.0, 4.0, 25.0, 4.0]))
    ns = {"torch": torch, "run_filter": run_filter, "IMM": IMM, "KalmanFilter": KalmanFilter,
          "sensor": sensor, "area": area, "bank": bank,
          "transition": torch.tensor([[0.9, 0.05, 0.05], [0.05, 0.9, 0.05], [0.05, 0.05, 0.9]]),
          "jpda": JPDA(KalmanFilter(motion, sensor), detection_probability=0.9, clutter_density=10 / area,
                       gate_probability=0.99, method="exact"),
          "tracks": GaussianBelief(starts.expand(2, 2, 4), cov.expand(2, 2, 4, 4))}
    blocks = _blocks("docs/tracking.md")
    read = next(b for b in blocks if "read_detections(" in b)
    mht = next(b for b in blocks if "ManagedMHT(IMM(" in b)
    exec(compile(read, "docs/tracking.md, read_detections", "exec"), ns)
    scans = ns["scans"]
    assert scans.z.shape[:2] == (9, 2) and scans.series == ["north", "south"]
    assert ns["trajectory"].belief.mean.shape == (9, 2, 2, 4)
    ns["runs"] = scans.z.shape[1]  # (as the example's comment says)
    exec(compile(mht, "docs/tracking.md, ManagedMHT", "exec"), ns)
    confirmed = ns["trajectory"].belief.confirmed()
    assert confirmed.shape[:2] == (9, 2) and bool(confirmed[-1].any(-1).all())  # each run has a track
    # passing the scans object itself is a TypeError that names the fix
    with pytest.raises(TypeError, match=r"^measurements: .*got DetectionScans; .*as_tensor\(scans\.z\)"):
        run_filter(ns["jpda"], ns["tracks"], scans)

"""The "bring your own model" tutorial runs as written (every python block, in order)."""

from __future__ import annotations

import re
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]


def test_tutorial_runs_and_learns(tmp_path, monkeypatch):
    text = (ROOT / "docs" / "tutorial-own-model.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) >= 6
    monkeypatch.chdir(tmp_path)  # the tutorial writes a checkpoint into the working directory
    previous = torch.get_default_dtype()
    namespace: dict = {"__name__": "tutorial"}
    try:
        for i, block in enumerate(blocks):
            exec(compile(block, f"tutorial-own-model.md[block {i}]", "exec"), namespace)
    finally:
        torch.set_default_dtype(previous)
    # the drag coefficient is learned from a 10x-off start (true 0.02)
    assert abs(namespace["c_learned"] - 0.02) < 0.002, namespace["c_learned"]
    assert namespace["history"][-1].loss < namespace["history"][0].loss
    assert (tmp_path / "drag_checkpoint.pt").exists()
    assert namespace["restored"].motion.net.log_c.exp().item() == namespace["c_learned"]
    assert namespace["after"] < namespace["before"]  # the MLP trained through the UKF improves
    probs = namespace["traj"].belief.mode_probs[-1].mean(0)
    assert probs[1] > probs[0]  # the learned drag mode explains the data better than CV

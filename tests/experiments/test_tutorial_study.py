"""docs/tutorial-study.md runs as written (every python block, in order, in a temporary folder)."""

from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_tutorial_study_runs(tmp_path, monkeypatch):
    text = (ROOT / "docs" / "tutorial-study.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.DOTALL)
    assert len(blocks) >= 6
    monkeypatch.chdir(tmp_path)  # the tutorial writes outputs/ and seeds/ into the working directory
    namespace: dict = {"__name__": "tutorial"}
    for i, block in enumerate(blocks):
        exec(compile(block, f"tutorial-study.md[block {i}]", "exec"), namespace)  # noqa: S102 - the doc's own code
    base = namespace["base"]
    assert base.dir.parent == Path("outputs") / "imm_baseline" and (tmp_path / base.dir / "results.json").exists()
    assert namespace["imm_low"] < namespace["imm_rmse"]  # R = 25 < 100: a smaller position error
    assert "- `scenario.R=25` (default: 100.0)" in namespace["low_noise"].markdown
    assert namespace["rmse_figure"].exists()
    report = json.loads((tmp_path / "seeds" / "report" / "report.json").read_text())["imm_baseline"]
    assert [g["replicates"] for g in report["groups"]] == [[0, 1, 2]]
    assert report["paired"]["rmse"]["reference"] == "IMM"
    tex = namespace["tex"]
    assert "\\toprule" in tex and "KF $-$ IMM" in tex and "pos\\_rmse" in tex

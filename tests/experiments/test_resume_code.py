"""Resuming never mixes code versions, and continuing a finished run keeps its provenance (docs/studies.md,
"Resuming" and "results.json")."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import torchmm
from experiments.folders import CodeChanged, code_difference
from experiments.provenance import code_version
from experiments.run import run_study
from tests.experiments.test_studies import _compose

STUDY = ["experiment=imm_baseline", "debug=imm_baseline", "logger=none", "figures=false", "progress=false", "mc_runs=4",
         "scenario.steps=30"]


def _cli(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(Path(sys.executable).with_name("torchmm-run")), *STUDY, *args], capture_output=True,
                          text=True, timeout=300, cwd=cwd, env={**os.environ, "OMP_NUM_THREADS": "1"})


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".torchmm.lock"}


def test_units_of_other_code_are_refused_in_one_line_naming_both_versions(tmp_path):
    """A checkpoint whose units another code version computed (here: its recorded torchmm version) is not
    continued - resume=latest (the command line), hydra.run.dir=<dir> (claim_folder, before Hydra) and
    run_study alike - and nothing in its folder changes (before: its units were kept and the run's
    provenance named the new code only)."""
    from experiments.run import claim_folder

    folder = tmp_path / "outputs" / "imm_baseline" / "2026-01-01_00-00-00"
    run_study(_compose("imm_baseline", *STUDY[1:]), folder)
    checkpoint = json.loads((folder / "checkpoint.json").read_text())
    assert checkpoint["code"] == code_version()  # recorded with the units
    checkpoint["code"]["torchmm"] = "0.0.0-other"
    (folder / "checkpoint.json").write_text(json.dumps(checkpoint))
    before = _files(folder)
    proc = _cli(tmp_path, "resume=latest")
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("torchmm-run: error: resume=latest: ") and "Traceback" not in proc.stderr
    assert "come from other code" in lines[0] and "torchmm 0.0.0-other" in lines[0]
    assert "this run: " in lines[0] and f"torchmm {torchmm.__version__}" in lines[0]
    assert "start a fresh run" in lines[0]
    assert _files(folder) == before
    with pytest.raises(CodeChanged, match="0.0.0-other"):
        claim_folder([*STUDY, f"hydra.run.dir={folder}"])
    with pytest.raises(CodeChanged, match="0.0.0-other"):
        run_study(_compose("imm_baseline", *STUDY[1:]), folder)
    assert _files(folder) == before


def test_code_difference_compares_version_commit_and_uncommitted_changes():
    code = {"torchmm": "0.1.0", "commit": "a" * 40, "dirty": False, "diff": None}
    assert code_difference(code, dict(code)) is None
    assert code_difference(None, code) is None  # an old checkpoint: nothing recorded to compare
    assert "commit bbbbbbbbbbbb" in code_difference({**code, "commit": "b" * 40}, code)
    assert "uncommitted changes 1234" in code_difference(code, {**code, "dirty": True, "diff": "1234"})
    assert code_difference({**code, "dirty": True, "diff": "1"}, {**code, "dirty": True, "diff": "2"})
    outside = {"torchmm": "0.1.0", "commit": None, "dirty": None, "diff": None}  # not a git checkout
    assert code_difference(outside, code) is None and code_difference({**outside, "torchmm": "0.2"}, code)


def test_continuing_a_finished_run_keeps_its_provenance_and_appends_the_resume(tmp_path):
    """run_study twice into one folder (resume=latest on a finished run): results.json's provenance is the
    first run's (start, end, wall_seconds, command) with the second in ``resumes`` (before: replaced by the
    second's)."""
    cfg = _compose("imm_baseline", *STUDY[1:])
    run_study(cfg, tmp_path / "run")
    first = json.loads((tmp_path / "run" / "results.json").read_text())
    units = len(json.loads((tmp_path / "run" / "checkpoint.json").read_text())["units"])
    for n in (1, 2):
        run_study(cfg, tmp_path / "run")
        again = json.loads((tmp_path / "run" / "results.json").read_text())
        assert again["tables"] == first["tables"]
        p = again["provenance"]
        for key in ("start", "end", "wall_seconds", "command", "git", "versions"):
            assert p[key] == first["provenance"][key], key
        assert len(p["resumes"]) == n and p["resumes"][-1]["units_kept"] == units
        assert p["resumes"][-1]["start"] >= first["provenance"]["end"]
    assert "Continued 2 time(s) since" in (tmp_path / "run" / "results.md").read_text()

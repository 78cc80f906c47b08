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
from experiments.folders import CodeChanged
from experiments.provenance import code_difference, code_version
from experiments.run import run_study
from tests.experiments.test_studies import _compose

STUDY = ["experiment=imm_baseline", "debug=imm_baseline", "logger=none", "figures=false", "progress=false",
         "mc_runs=4", "scenario.steps=30"]


def _cli(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(Path(sys.executable).with_name("torchmm-run")), *STUDY, *args],
                          capture_output=True, text=True, timeout=300, cwd=cwd,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})


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
    assert len(lines) == 1 and lines[0].startswith("torchmm-run: error: resume=latest: ")
    assert "Traceback" not in proc.stderr
    assert "come from other code" in lines[0] and "torchmm 0.0.0-other" in lines[0]
    assert "this run: " in lines[0] and f"torchmm {torchmm.__version__}" in lines[0]
    assert "start a fresh run" in lines[0]
    assert _files(folder) == before
    with pytest.raises(CodeChanged, match="0.0.0-other"):
        claim_folder([*STUDY, f"hydra.run.dir={folder}"])
    with pytest.raises(CodeChanged, match="0.0.0-other"):
        run_study(_compose("imm_baseline", *STUDY[1:]), folder)
    assert _files(folder) == before


def test_code_difference_compares_the_version_and_the_code_fingerprint():
    code = {"torchmm": "0.1.0", "commit": "a" * 40, "dirty": False, "changed": False, "source": "s1"}
    assert code_difference(code, dict(code)) is None
    assert code_difference(None, code) is None  # an old checkpoint: nothing recorded to compare
    assert code_difference({**code, "commit": "b" * 40}, code) is None  # a commit of docs alone: same code
    differ = code_difference({**code, "commit": "b" * 40, "source": "s2"}, code)
    assert "commit bbbbbbbbbbbb (code s2)" in differ and "this run: commit aaaaaaaaaaaa (code s1)" in differ
    assert "uncommitted code changes" in code_difference(code, {**code, "changed": True, "source": "s3"})
    outside = {"torchmm": "0.1.0", "commit": None, "dirty": None, "changed": None, "source": None}  # no git
    assert code_difference(outside, code) is None and code_difference({**outside, "torchmm": "0.2"}, code)


def test_the_code_fingerprint_follows_the_code_not_the_docs(tmp_path):
    """code_version on a small git repository: editing or committing docs keeps ``source``; an uncommitted
    edit of experiments/ changes it (``changed``), committing that edit keeps the edit's; a deleted code file
    changes it. Cross-checked against the blob ids git itself stores on commit."""
    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), "-c", "user.email=t@t", "-c", "user.name=t", *args],
                       check=True, capture_output=True)

    for name in ("torchmm/a.py", "experiments/b.py", "conf/c.yaml", "docs/d.md"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text("x = 1\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-qm", "one")
    first = code_version(tmp_path)
    assert first["commit"] and first["changed"] is False and first["source"]
    (tmp_path / "docs/d.md").write_text("more\n")
    docs = code_version(tmp_path)
    assert docs["dirty"] is True and docs["changed"] is False and docs["source"] == first["source"]
    git("commit", "-qam", "docs")
    assert code_version(tmp_path)["source"] == first["source"]
    (tmp_path / "experiments/b.py").write_text("x = 2\n")
    edited = code_version(tmp_path)
    assert edited["changed"] is True and edited["source"] != first["source"]
    git("commit", "-qam", "code")
    committed = code_version(tmp_path)
    assert committed["changed"] is False and committed["source"] == edited["source"] != first["source"]
    (tmp_path / "conf/c.yaml").unlink()
    assert code_version(tmp_path)["source"] not in (first["source"], edited["source"])


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
        for key in ("start", "end", "wall_seconds", "command", "git", "versions"):  # the first run's
            assert p[key] == first["provenance"][key], key
        assert len(p["resumes"]) == n and p["resumes"][-1]["units_kept"] == units
        assert p["resumes"][-1]["start"] >= first["provenance"]["end"]
    assert "Continued 2 time(s) since" in (tmp_path / "run" / "results.md").read_text()


def test_a_resume_that_reuses_no_unit_is_recorded_as_a_new_run(tmp_path):
    """Resuming a finished run with another ``unit_runs`` asks for other unit keys: nothing of the old run is
    used, and every unit is computed again. Its results.json kept the old run's provenance (its command, its
    kernels) with "16 units kept"; now the provenance is the new run's, ``replaced`` names the old one, and
    a resume that does reuse units still counts those it read back."""
    cfg = _compose("imm_baseline", *STUDY[1:], "mc_runs=7", "block_runs=2", "unit_runs=2")
    run_study(cfg, tmp_path / "run")
    first = json.loads((tmp_path / "run" / "results.json").read_text())
    other = _compose("imm_baseline", *STUDY[1:], "mc_runs=7", "block_runs=2", "unit_runs=4")  # no key in common
    run_study(other, tmp_path / "run")
    again = json.loads((tmp_path / "run" / "results.json").read_text())
    fresh_dir = tmp_path / "fresh"
    run_study(other, fresh_dir)
    fresh = json.loads((fresh_dir / "results.json").read_text())
    assert again["tables"] == fresh["tables"]
    p = again["provenance"]
    assert "resumes" not in p and "resumed" not in p
    assert p["replaced"]["start"] == first["provenance"]["start"] and p["start"] > first["provenance"]["end"]
    assert p["kernels"] == fresh["provenance"]["kernels"]
    run_study(other, tmp_path / "run")  # the same unit_runs again: every unit read back
    last = json.loads((tmp_path / "run" / "results.json").read_text())["provenance"]
    units = len(json.loads((tmp_path / "run" / "checkpoint.json").read_text())["units"])
    assert last["start"] == p["start"] and last["resumes"][-1]["units_kept"] < units  # (the old keys stay listed)

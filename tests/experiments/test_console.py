"""The command line and the provenance of a run: --help, --version, the run folder, Ctrl-C."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from experiments.run import run_study, study_summaries
from tests.experiments.test_studies import EXPERIMENTS, _compose


def _exe() -> str:
    return str(Path(sys.executable).with_name("torchmm-run"))


def test_provenance_records_versions_source_host_times_and_the_resolved_device(tmp_path):
    run_study(_compose("imm_baseline", "debug=imm_baseline", "logger=none", "device=auto"), tmp_path)
    data = json.loads((tmp_path / "results.json").read_text())
    p = data["provenance"]
    import numpy
    import torch

    import torchmm

    assert p["versions"]["torch"] == torch.__version__ and p["versions"]["numpy"] == numpy.__version__
    assert p["versions"]["torchmm"] == torchmm.__version__
    assert p["device"] in ("cpu", "cuda") or p["device"].startswith("cuda:")  # resolved, not "auto"
    assert data["config"]["device"] == "auto"  # the config keeps what was asked for
    assert p["dtype"] == "float64" and p["threads"] >= 1
    commit = p["git"]["commit"]
    assert commit is None or re.fullmatch(r"[0-9a-f]{40}", commit)
    assert p["start"] <= p["end"] and p["wall_seconds"] >= 0
    assert "## provenance" in (tmp_path / "results.md").read_text()


def test_help_lists_every_study_and_version_is_torchmms(tmp_path):
    out = subprocess.run([_exe(), "--help"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 0
    for name in EXPERIMENTS:
        assert re.search(rf"^  {name}\s+\S", out.stdout, re.M), name
    assert "mc_runs=100" in out.stdout and "mode_filter" in out.stdout
    assert all(summary for _, summary in study_summaries())
    import torchmm

    version = subprocess.run([_exe(), "--version"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert version.stdout.strip() == f"torchmm-run (torchmm {torchmm.__version__})"
    assert not list(tmp_path.iterdir())  # neither writes a run folder


def test_run_names_its_folder_first_and_prints_the_headline_table(tmp_path):
    out_dir = tmp_path / "run"
    proc = subprocess.run([_exe(), "experiment=imm_baseline", "debug=imm_baseline", "logger=none",
                           f"hydra.run.dir={out_dir}"], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    first = next(line for line in proc.stderr.splitlines() if line.startswith("torchmm-run:"))
    assert first == f"torchmm-run: imm_baseline -> {out_dir}"
    assert "imm_baseline: rmse" in proc.stdout and "| IMM |" in proc.stdout


def test_ctrl_c_ends_with_one_line_that_says_how_to_resume(tmp_path):
    out_dir = tmp_path / "run"
    proc = subprocess.Popen([_exe(), "experiment=imm_analysis", "mc_runs=200", "logger=none", "progress=false",
                             f"hydra.run.dir={out_dir}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1"})
    deadline = time.time() + 120
    while not (out_dir / ".hydra").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    time.sleep(3.0)  # inside the study
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[-1].startswith("torchmm-run: interrupted;") and f"hydra.run.dir={out_dir}" in lines[-1]
    assert "Traceback" not in err

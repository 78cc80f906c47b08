"""Sweeps through other Hydra launchers give the numbers of the basic launcher (docs/scaling.md).

The submitit launcher (the ``slurm`` extra) runs every sweep job in its own process, from a pickled
copy of the sweep's config: the jobs must land in the same sweep folder and give the same tables.
``submitit_local`` exercises that path on one machine, without a SLURM cluster.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("hydra_plugins.hydra_submitit_launcher")

SWEEP = ["experiment=imm_baseline", "debug=imm_baseline", "logger=none", "progress=false", "seed=0,1"]
JOBS = ["0_debug=imm_baseline,seed=0", "1_debug=imm_baseline,seed=1"]


def _sweep(launcher: str, sweep_dir: Path, cwd: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("torchmm-run")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([str(exe), "-m", *SWEEP, f"hydra/launcher={launcher}", f"hydra.sweep.dir={sweep_dir}"],
                          capture_output=True, text=True, timeout=180, cwd=cwd, env=env)


def _tables(sweep_dir: Path) -> list[dict]:
    return [json.loads((sweep_dir / job / "results.json").read_text())["tables"] for job in JOBS]


@pytest.mark.slow  # (the Hydra submitit launcher's whole sweep, 20 s: make test-slow; submitit itself stays in the
# fast set through the executors' tests, tests/experiments/test_executors.py)
def test_submitit_local_sweep_matches_the_basic_launcher(tmp_path):
    basic, local = tmp_path / "basic", tmp_path / "submitit"
    for launcher, folder in (("basic", basic), ("submitit_local", local)):
        proc = _sweep(launcher, folder, tmp_path)
        assert proc.returncode == 0, f"{launcher}:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    assert sorted(p.name for p in local.iterdir() if p.is_dir() and not p.name.startswith(".")) == JOBS
    assert (local / ".submitit").is_dir()  # submitit's pickled jobs and per-job logs
    logs = "".join(p.read_text() for p in (local / ".submitit").rglob("*_log.err"))
    assert f"-> {local / JOBS[0]}" in logs and f"-> {local / JOBS[1]}" in logs  # ran in submitit's jobs
    tables = _tables(local)
    assert all(tables) and tables == _tables(basic)
    assert not (tmp_path / "outputs").exists()  # nothing went to a second, default sweep folder


def test_slurm_launcher_config_extends_submitit_slurm():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from experiments.run import CONFIG_DIR

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            cfg = compose("config", overrides=["experiment=imm_baseline", "hydra/launcher=slurm",
                                               "hydra.launcher.partition=cpu"], return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("submitit_launcher.SlurmLauncher")
    assert launcher.cpus_per_task == 1 and launcher.partition == "cpu" and launcher.max_num_timeout > 0
    assert launcher.name == "torchmm-imm_baseline"
    assert launcher._get_node("submitit_folder")._value() == "${hydra.sweep.dir}/.submitit/%j"

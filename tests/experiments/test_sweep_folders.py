"""A sweep job's folder: a folder of another result config (an earlier sweep into the same hydra.sweep.dir)
is left as it was and the job goes to a fresh sibling, chosen before Hydra writes anything (docs/studies.md,
"Sweeps")."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from experiments.claim import job_folder
from experiments.folders import config_hash

ARGS = ["mc_runs=4", "scenario.steps=20", "logger=none", "figures=false", "progress=false", "seed=0",
        "hydra/launcher=basic"]


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".torchmm.lock"}


def test_job_folder_takes_the_first_name_holding_no_run_or_this_config(tmp_path):
    a, b = {"experiment_name": "a", "seed": 0}, {"experiment_name": "b", "seed": 0}
    (tmp_path / "0_seed=0").mkdir()
    (tmp_path / "0_seed=0" / "checkpoint.json").write_text(json.dumps(
        {"config_hash": config_hash(a), "config": a, "units": {}}))
    assert job_folder(tmp_path, "0_seed=0", a) == "0_seed=0"  # its own folder: continued
    assert job_folder(tmp_path, "0_seed=0", b) == "0_seed=0_1"  # another config's: a sibling, made here
    assert (tmp_path / "0_seed=0_1").is_dir()
    assert job_folder(tmp_path, "0_seed=0", b) == "0_seed=0_1"  # the same answer when asked again (requeued)
    assert job_folder(tmp_path, "1_seed=1", b) == "1_seed=1"  # nothing there: the name itself
    assert not (tmp_path / "1_seed=1").exists()  # (Hydra makes it)


def test_the_sweep_subdir_resolver_reads_the_jobs_config_and_sweep_folder(tmp_path):
    """``${torchmm.sweep_subdir:...}`` (hydra.sweep.subdir, conf/config.yaml) with the job's config: the
    sibling when the named folder holds another config's checkpoint."""
    import experiments.run  # noqa: F401 - registers the resolvers

    other = {"experiment_name": "a", "seed": 0}
    (tmp_path / "0_seed=0").mkdir()
    (tmp_path / "0_seed=0" / "checkpoint.json").write_text(json.dumps(
        {"config_hash": config_hash(other), "config": other, "units": {"u": 1}}))
    for name, want in (("a", "0_seed=0"), ("b", "0_seed=0_1")):
        cfg = OmegaConf.create({"hydra": {"sweep": {"dir": str(tmp_path),
                                                    "subdir": "${torchmm.sweep_subdir:0,'seed=0'}"}},
                                "experiment_name": name, "seed": 0})
        assert cfg.hydra.sweep.subdir == want


@pytest.mark.slow  # two sweeps on the command line (~30 s); the resolver's choice: the tests above
def test_a_second_sweep_whose_job_has_the_same_name_goes_to_a_sibling_and_the_first_is_untouched(tmp_path):
    """Two sweeps into one hydra.sweep.dir whose job folder names coincide (experiment is left out of the
    name): the second's job goes to <name>_1 before Hydra writes its .hydra/ and log, and the console names
    that folder (before: Hydra wrote the second job's .hydra/ and run.log into the first job's folder, and
    only the study moved to the sibling)."""
    run = [str(Path(sys.executable).with_name("torchmm-run")), "-m"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    sweep = tmp_path / "sw"
    first = subprocess.run([*run, "experiment=imm_baseline", *ARGS, f"hydra.sweep.dir={sweep}"],
                           capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert first.returncode == 0, first.stderr[-2000:]
    (job,) = [p for p in sweep.iterdir() if p.is_dir()]
    before = _files(job)
    second = subprocess.run([*run, "experiment=quickstart", *ARGS, f"hydra.sweep.dir={sweep}"],
                            capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert second.returncode == 0, second.stderr[-2000:]
    sibling = job.with_name(job.name + "_1")
    assert _files(job) == before  # its .hydra/, run.log, results: as the first sweep left them
    assert json.loads((sibling / "results.json").read_text())["experiment"] == "quickstart"
    assert "experiment_name: quickstart" in (sibling / ".hydra" / "config.yaml").read_text()
    assert f"torchmm-run: quickstart -> {sibling}" in second.stderr
    assert "this job goes to" in second.stderr and sibling.name in second.stderr

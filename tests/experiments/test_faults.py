"""Run folders under faults and under each other (docs/robustness.md, "Run folders and faults").

kill -9 at seeded moments (the command line, a process pool, inside a file write), corrupt and
missing checkpoint and unit files, a folder that cannot be written, two runs or two sweeps aimed at
one folder, malformed inputs of torchmm-report and torchmm-plot. Every check compares numbers with
an uninterrupted run of the same config (nothing lost or overwritten) and every error is one line
naming the file, without a traceback.
"""

from __future__ import annotations

import fcntl
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from experiments.harness import LOCK_FILE, TMP_SUFFIX, FolderInUse, RunFolderError, lock_folder, unlock_folder
from experiments.run import run_study
from tests.experiments.test_studies import _compose

ROOT = Path(__file__).resolve().parents[2]
#: the smallest study with units of runs: 4 estimators x 4 units of 2 runs (each unit has a units/*.npz)
STUDY = ["debug=imm_baseline", "logger=none", "figures=false", "progress=false", "mc_runs=8", "block_runs=2",
         "unit_runs=2"]
UNITS = 16


def _exe(name: str = "torchmm-run") -> str:
    return str(Path(sys.executable).with_name(name))


def _env() -> dict:
    return {**os.environ, "OMP_NUM_THREADS": "1"}


def _cli(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    flags = [a for a in args if a.startswith("-")]  # -m before the overrides
    overrides = [a for a in args if not a.startswith("-")]
    return subprocess.run([_exe(), *flags, "experiment=imm_baseline", *STUDY, *overrides],
                          capture_output=True, text=True, timeout=300, cwd=cwd, env=_env())


def _popen(cwd: Path, *args: str) -> subprocess.Popen:
    """The command line in a session of its own (its pool workers too: killed together by the group)."""
    return subprocess.Popen([_exe(), "experiment=imm_baseline", *STUDY, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=cwd, env=_env(), start_new_session=True)


def _tables(folder: Path) -> dict:
    return json.loads((folder / "results.json").read_text())["tables"]


def _one_line(stderr: str, *names: str) -> str:
    """stderr is one error line naming every one of ``names`` (and no traceback)."""
    assert "Traceback" not in stderr, stderr[-3000:]
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and ": error: " in lines[0], stderr[-3000:]
    for name in names:
        assert str(name) in lines[0], (name, lines[0])
    return lines[0]


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (the lock file aside) with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != LOCK_FILE}


def _units(folder: Path) -> dict:
    return json.loads((folder / "checkpoint.json").read_text())["units"]


def _assert_whole(folder: Path) -> None:
    """A finished run folder: every unit in the checkpoint, each unit file there with its recorded
    checksum, no temporary file left."""
    import hashlib

    units = _units(folder)
    assert len(units) == UNITS
    for ref in units.values():
        data = (folder / ref["__array__file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == ref["sha256"], ref["__array__file"]
    assert not list(folder.glob(f".*{TMP_SUFFIX}")) and not list(folder.glob(f"units/.*{TMP_SUFFIX}"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """``seed -> folder`` of an uninterrupted in-process run (made once per seed)."""
    made: dict[int, Path] = {}

    def get(seed: int = 0) -> Path:
        if seed not in made:
            folder = tmp_path_factory.mktemp(f"reference{seed}") / "run"
            run_study(_compose("imm_baseline", *STUDY, f"seed={seed}"), folder)
            made[seed] = folder
        return made[seed]

    return get


# -- kill -9 -------------------------------------------------------------------------------------------
def _kill_after(proc: subprocess.Popen, cwd: Path, units: int, delay: float) -> tuple[Path, int]:
    """SIGKILL ``proc``'s process group once its run folder's checkpoint holds ``units`` units (then
    ``delay`` s more); returns the folder and the units its checkpoint holds after the kill. Every
    read of checkpoint.json on the way must parse: it is replaced atomically, never seen half-written."""
    deadline, folder, seen = time.time() + 240, None, 0
    while time.time() < deadline and proc.poll() is None and seen < units:
        if folder is None:
            found = list((cwd / "outputs" / "imm_baseline").glob("*/"))
            folder = found[0] if found else None
        if folder is not None and (folder / "checkpoint.json").exists():
            seen = len(_units(folder))  # a JSONDecodeError here: a half-written checkpoint
        time.sleep(0.005)
    time.sleep(delay)
    assert proc.poll() is None, f"the run ended before the kill: {proc.stderr.read()[-2000:]}"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL and folder is not None
    return folder, len(_units(folder))


def _kill_and_resume(tmp_path: Path, reference, *args: str, seed: str) -> None:
    rng = random.Random(seed)  # a seeded moment: after a random number of units, plus a random delay
    # three quarters of the units left: still running on a fast machine too
    at, delay = rng.randint(1, UNITS // 4), rng.uniform(0.0, 0.02)
    folder, kept = _kill_after(_popen(tmp_path, *args), tmp_path, at, delay)
    assert at <= kept < UNITS
    again = _cli(tmp_path, *args, "resume=latest")
    assert again.returncode == 0, again.stderr[-3000:]
    assert "Traceback" not in again.stderr
    assert f"resume=latest: continuing {folder.resolve()}" in again.stderr
    assert f"resuming: {kept} finished units in the checkpoint" in again.stderr  # nothing that was finished is lost
    assert _tables(folder) == _tables(reference(0))  # the numbers of an uninterrupted run
    _assert_whole(folder)


def test_kill_9_at_a_seeded_moment_then_resume_gives_the_uninterrupted_numbers(tmp_path, reference):
    _kill_and_resume(tmp_path, reference, seed="local")


def test_kill_9_of_a_process_pool_study_then_resume_gives_the_uninterrupted_numbers(tmp_path, reference):
    """The study's process and its pool workers killed together (as a node failure or OOM kill would)."""
    _kill_and_resume(tmp_path, reference, "executor=processes", "executor.workers=2", seed="processes")


_KILL_INSIDE_A_WRITE = """
import os, signal, sys
from hydra import compose, initialize_config_dir
from experiments.run import CONFIG_DIR, run_study

target, folder, overrides = int(sys.argv[1]), sys.argv[2], sys.argv[3:]
calls, replace = [0], os.replace

def killing_replace(src, dst):  # the temporary written and fsynced, not yet in place: die here
    calls[0] += 1
    if calls[0] == target:
        os.kill(os.getpid(), signal.SIGKILL)
    return replace(src, dst)

os.replace = killing_replace
with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
    cfg = compose("config", overrides=["experiment=imm_baseline", *overrides])
run_study(cfg, folder)
"""


@pytest.mark.parametrize("parity", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_kill_9_inside_a_file_write_loses_nothing(parity, tmp_path, reference, monkeypatch, caplog):
    """Killed between writing a file's temporary and putting it in place - a unit's npz (odd write)
    or the checkpoint naming it (even write): the folder holds the previous, whole files; the resumed
    run removes the temporary, keeps every unit the checkpoint names and gives the same numbers."""
    import experiments.studies.imm_baseline as study

    n = 2 * random.Random(29).randint(2, UNITS - 2) - parity  # every unit writes its npz, then the checkpoint
    folder = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-c", _KILL_INSIDE_A_WRITE, str(n), str(folder), *STUDY],
                          capture_output=True, text=True, timeout=300, cwd=ROOT, env=_env())
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-3000:]
    assert list(folder.glob(f".*{TMP_SUFFIX}")) or list(folder.glob(f"units/.*{TMP_SUFFIX}"))  # left behind
    kept = len(_units(folder))
    assert kept == (n - 1) // 2
    computed = []
    unit = study.unit
    monkeypatch.setattr(study, "unit", lambda ctx, **args: computed.append(args) or unit(ctx, **args))
    run_study(_compose("imm_baseline", *STUDY), folder)
    assert len(computed) == UNITS - kept and "WARNING" not in caplog.text
    assert _tables(folder) == _tables(reference(0))
    _assert_whole(folder)


# -- corrupt and missing files ---------------------------------------------------------------------------
def test_corrupt_or_missing_unit_files_are_named_and_computed_again(tmp_path, reference, monkeypatch, caplog):
    import logging

    import experiments.studies.imm_baseline as study

    folder = tmp_path / "run"
    shutil.copytree(reference(0), folder)
    refs = _units(folder)
    keys = sorted(refs)
    truncated, deleted, changed = (folder / refs[k]["__array__file"] for k in keys[:3])
    truncated.write_bytes(truncated.read_bytes()[:100])
    deleted.unlink()
    data = bytearray(changed.read_bytes())
    data[len(data) // 2] ^= 0xFF  # same size, one byte changed: only the checksum tells
    changed.write_bytes(bytes(data))
    computed = []
    unit = study.unit
    monkeypatch.setattr(study, "unit", lambda ctx, **args: computed.append(args) or unit(ctx, **args))
    with caplog.at_level(logging.WARNING, logger="torchmm.experiments"):
        run_study(_compose("imm_baseline", *STUDY), folder)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 3 and all("\n" not in w for w in warnings)  # one line per file
    for path, key, warning in zip((truncated, deleted, changed), keys[:3], warnings):
        assert str(path) in warning and f"unit {key} is computed again" in warning
    assert sorted(f"{a['name']}/runs{a['start']}-{a['stop']}" for a in computed) == keys[:3]
    assert _tables(folder) == _tables(reference(0))
    _assert_whole(folder)


def test_a_corrupt_checkpoint_is_one_line_and_resume_latest_says_it_passes_it_over(
        tmp_path, reference, capsys, monkeypatch):
    from experiments.run import resolve_resume

    folder = tmp_path / "outputs" / "imm_baseline" / "2026-01-01_00-00-00"
    shutil.copytree(reference(0), folder)
    ckpt = folder / "checkpoint.json"
    ckpt.write_text(ckpt.read_text()[:200])  # truncated
    with pytest.raises(RunFolderError, match="checkpoint.json: not a valid checkpoint"):
        run_study(_compose("imm_baseline", *STUDY), folder)
    before = _snapshot(folder)
    proc = _cli(tmp_path, f"hydra.run.dir={folder}")
    assert proc.returncode == 2
    _one_line(proc.stderr, ckpt, "not a valid checkpoint")
    assert _snapshot(folder) == before  # nothing written: Hydra did not start
    # resume=latest (the command line's resolve_resume): one line names the unreadable checkpoint and
    # one says that a fresh run starts; the command line then has no folder (a fresh one is made)
    monkeypatch.chdir(tmp_path)
    args = ["experiment=imm_baseline", *STUDY, "resume=latest"]
    assert resolve_resume(args) == args
    lines = capsys.readouterr().err.splitlines()
    assert lines == [f"torchmm-run: resume=latest: skipping {ckpt.relative_to(tmp_path)}: "
                     f"not a valid checkpoint ({lines[0].split('(', 1)[1]}",
                     "torchmm-run: resume=latest: no readable earlier run of this config under "
                     "outputs/imm_baseline; starting a fresh one"]
    assert _snapshot(folder) == before
    # a checkpoint that is JSON but not a checkpoint, and a results.json that is not an object
    ckpt.write_text("[]\n")
    with pytest.raises(RunFolderError, match="checkpoint.json: not a valid checkpoint"):
        run_study(_compose("imm_baseline", *STUDY), folder)
    ckpt.unlink()
    (folder / "results.json").write_text("[]\n")
    with pytest.raises(RunFolderError, match="results.json: not a valid results file"):
        run_study(_compose("imm_baseline", *STUDY), folder)


# -- folders that cannot be written ---------------------------------------------------------------------
def test_a_folder_that_cannot_be_made_is_one_line(tmp_path, capsys):
    """As root every folder is writable: a path under a regular file is one that nobody can make."""
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder\n")
    proc = _cli(tmp_path, f"hydra.run.dir={blocker / 'run'}")
    assert proc.returncode == 2
    _one_line(proc.stderr, blocker / "run")
    # the default folder (made by the torchmm.unique_dir resolver inside Hydra): one line too
    from experiments.run import _unique_locked_dir

    with pytest.raises(SystemExit) as exit_:
        _unique_locked_dir(str(blocker / "outputs" / "now"))
    assert exit_.value.code == 2
    _one_line(capsys.readouterr().err, blocker)
    # a file the study writes cannot be written mid-run (units/ is a file): RunFolderError naming it
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "units").write_text("")
    with pytest.raises(RunFolderError, match=f"{folder / 'units'}.*cannot write"):
        run_study(_compose("imm_baseline", *STUDY), folder)


_NOBODY = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]


def _unprivileged() -> list[str] | None:
    """How to run the CLI where a read-only folder is read-only: as this user when it is not root;
    as root (CI, the developers' machines), as ``nobody`` through ``setpriv`` where that user can
    read the environment (probed); None where neither works."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return []
    if shutil.which("setpriv") is None:
        return None
    probe = subprocess.run([*_NOBODY, sys.executable, "-c", "import experiments.run"], capture_output=True,
                           cwd="/", env={**_env(), "HOME": "/tmp"})
    return _NOBODY if probe.returncode == 0 else None


def test_a_read_only_folder_is_one_line(tmp_path):
    prefix = _unprivileged()
    if prefix is None:  # pragma: no cover - a root without setpriv, or an environment nobody may read
        pytest.skip("cannot run the CLI unprivileged here (root writes into read-only folders); "
                    "test_a_folder_that_cannot_be_made_is_one_line covers unwritable folders")
    # a folder the unprivileged user can reach
    base = Path(tempfile.mkdtemp(prefix="torchmm-ro-", dir="/tmp"))
    try:
        base.chmod(0o755)
        for folder in (base / "ro", base / "ro_parent" / "run"):
            target = folder if folder.name == "ro" else folder.parent
            target.mkdir()
            target.chmod(0o555)
            proc = subprocess.run([*prefix, _exe(), "experiment=imm_baseline", *STUDY,
                                   f"hydra.run.dir={folder}"],
                                  capture_output=True, text=True, timeout=300, cwd=base,
                                  env={**_env(), "HOME": str(base)})
            assert proc.returncode == 2, proc.stderr[-3000:]
            _one_line(proc.stderr, folder)
            assert not list(target.iterdir()), "a refused run writes nothing"
    finally:
        for path in base.rglob("*"):
            if path.is_dir():
                path.chmod(0o755)
        shutil.rmtree(base, ignore_errors=True)


# -- two runs, two sweeps ------------------------------------------------------------------------------
def test_a_folder_in_use_is_refused_and_left_untouched(tmp_path, reference):
    from experiments.run import claim_folder

    folder = tmp_path / "run"
    shutil.copytree(reference(0), folder)
    before = _snapshot(folder)
    fd = os.open(folder / LOCK_FILE, os.O_RDWR | os.O_CREAT)  # another process's run holds it
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        proc = _cli(tmp_path, f"resume={folder}", "seed=1")  # resume=<dir>: hydra.run.dir=<dir>
        assert proc.returncode == 2
        assert "in use by another run" in _one_line(proc.stderr, folder)
        with pytest.raises(FolderInUse, match="in use by another run"):  # a sweep into it (as the CLI does)
            claim_folder(["-m", "experiment=imm_baseline", "seed=0,1", f"hydra.sweep.dir={folder}"])
        with pytest.raises(FolderInUse):
            run_study(_compose("imm_baseline", *STUDY), folder)
    finally:
        os.close(fd)
    assert _snapshot(folder) == before
    assert lock_folder(folder) is True  # released with its holder
    unlock_folder(folder)


def test_two_runs_started_into_one_folder_never_mix(tmp_path, reference):
    """Seeds 0 and 1 at once into one hydra.run.dir: one runs there and the other is refused (or,
    if the first had finished, goes to a fresh sibling); each folder holds one seed's whole run."""
    folder = tmp_path / "run"
    procs = {seed: _popen(tmp_path, f"hydra.run.dir={folder}", f"seed={seed}") for seed in (0, 1)}
    outcome = {}
    for seed, proc in procs.items():
        _, err = proc.communicate(timeout=300)
        assert proc.returncode in (0, 2) and "Traceback" not in err, err[-3000:]
        if proc.returncode == 2:
            assert "in use by another run" in _one_line(err, folder)
        outcome[seed] = proc.returncode
    assert 0 in outcome.values()
    runs = [f for f in (folder, tmp_path / "run_1") if (f / "results.json").exists()]
    assert len(runs) == list(outcome.values()).count(0)
    for run in runs:
        seed = json.loads((run / "results.json").read_text())["config"]["seed"]
        assert f"seed: {seed}" in (run / ".hydra" / "config.yaml").read_text()  # Hydra's record: the same run
        assert _tables(run) == _tables(reference(seed))
        _assert_whole(run)


def test_a_second_sweep_into_a_sweep_folder_keeps_the_first_ones_record(tmp_path, reference):
    sweep = tmp_path / "sweep"
    args = ["-m", "hydra/launcher=basic", f"hydra.sweep.dir={sweep}"]
    first = _cli(tmp_path, *args, "seed=0")
    assert first.returncode == 0, first.stderr[-3000:]
    record = (sweep / "multirun.yaml").read_text()
    job0 = next(p for p in sweep.iterdir() if p.is_dir())
    kept = _snapshot(job0)
    second = _cli(tmp_path, *args, "seed=1")
    assert second.returncode == 0 and "Traceback" not in second.stderr, second.stderr[-3000:]
    assert "its record is kept as multirun.1.yaml" in second.stderr
    assert (sweep / "multirun.1.yaml").read_text() == record  # the first sweep's record, unchanged
    assert "seed=1" in (sweep / "multirun.yaml").read_text() and "seed=1" not in record
    assert _snapshot(job0) == kept
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert len(jobs) == 2 and all((job / "results.json").exists() for job in jobs)
    assert _tables(job0) == _tables(reference(0))


# -- torchmm-report and torchmm-plot on malformed inputs -------------------------------------------------
@pytest.mark.parametrize("content", [
    "[]\n", '{"experiment": "x", "tab',
    '{"experiment": "x", "tables": {"t": {"columns": ["a"], "rows": [[1, 2]]}}}'])
def test_report_on_a_malformed_results_file_is_one_line(content, tmp_path, capsys):
    from experiments import report

    run = tmp_path / "run"
    run.mkdir()
    (run / "results.json").write_text(content)
    assert report.main([str(run)]) == 2
    _one_line(capsys.readouterr().err, run / "results.json")
    assert not (run / "report").exists()


def test_plot_on_a_truncated_curves_file_is_one_line(tmp_path, reference, capsys):
    from experiments import plot

    run = tmp_path / "run"
    shutil.copytree(reference(0), run)
    curves = run / "curves.npz"
    curves.write_bytes(curves.read_bytes()[:1000])
    assert plot.main([str(run)]) == 2
    _one_line(capsys.readouterr().err, curves)
    assert not (run / "figures").exists()  # nothing drawn from a broken file

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

import pytest

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


def test_help_imports_neither_torch_nor_hydra():
    """``torchmm-run --help`` is a fraction of a second (issue 30): experiments.run imports torch, Hydra
    and the harness when a run starts, and its lazily imported names still resolve."""
    code = ("import sys, io, contextlib; import experiments.run as r; out = io.StringIO()\n"
            "with contextlib.redirect_stdout(out): sys.argv[1:] = ['--help']; r.main()\n"
            "assert 'quickstart' in out.getvalue()\n"
            "print(sorted(m for m in ('torch', 'hydra', 'experiments.harness', 'experiments.context', 'torchmm') "
            "if m in sys.modules))\n"
            "assert r.unique_dir.__module__ == 'experiments.folders' and r.torch.__name__ == 'torch'")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[2])
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "[]"


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
    # mc_runs: a study that lasts well past the interrupt (200 runs took ~4 s once the engine got faster,
    # and the signal then came after the study had ended); interrupted after 3 s, it costs no more
    # the child with Ctrl-C's default action: a process started with SIGINT ignored (inherited: an earlier test
    # in this xdist worker - Ray, a launcher - can leave it ignored) never raises KeyboardInterrupt, and the
    # study then ran to its end with status 0 (seen once in the full suite)
    proc = subprocess.Popen([_exe(), "experiment=imm_analysis", "mc_runs=3000", "logger=none", "progress=false",
                             f"hydra.run.dir={out_dir}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1"},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    while not (out_dir / ".hydra").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    time.sleep(3.0)  # inside the study
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[-1].startswith("torchmm-run: interrupted;") and "Traceback" not in err
    # what it says is kept is what the folder holds (before: "the finished units are kept in
    # .../checkpoint.json" also when no unit had finished and there was no such file)
    checkpoint = out_dir / "checkpoint.json"
    if checkpoint.exists():
        units = len(json.loads(checkpoint.read_text())["units"])
        assert f"{units} finished unit" in lines[-1] and f"kept in {checkpoint}" in lines[-1]
        assert "resume=latest" in lines[-1] and f"resume={out_dir}" in lines[-1]
    else:
        assert "no unit had finished" in lines[-1] and "checkpoint.json" not in lines[-1]


def test_the_interrupted_line_says_what_is_kept_and_what_continues_it(tmp_path):
    """Ctrl-C's line (experiments.run.interrupted_line): the units the folder's checkpoint holds, or none;
    resume=latest for a single run, the sweep command with its hydra.sweep.dir in a -m sweep (where resume=
    is refused: before, a sweep's job suggested resume=latest)."""
    from experiments.run import interrupted_line

    folder = tmp_path / "sw" / "0_seed=0"
    folder.mkdir(parents=True)
    none = interrupted_line(folder)
    assert "no unit had finished" in none and "resume=" not in none and "checkpoint.json" not in none
    units = {"a": 1, "b": 2, "c": 3}
    (folder / "checkpoint.json").write_text(json.dumps({"config_hash": "x", "units": units}))
    single = interrupted_line(folder)
    assert f"3 finished units kept in {folder / 'checkpoint.json'}" in single
    assert "resume=latest" in single and f"resume={folder}" in single
    given = interrupted_line(folder, ("sw", True))
    assert "re-run the same command (it has hydra.sweep.dir=sw)" in given and "resume=" not in given
    assert "3 finished units kept" in given
    default = interrupted_line(folder, (str(tmp_path / "sw"), False))
    assert f"re-run the same command with hydra.sweep.dir={tmp_path / 'sw'}" in default
    assert "resume=" not in default


@pytest.mark.slow  # a sweep interrupted and continued on the command line (~10 s)
def test_ctrl_c_in_a_sweep_says_how_to_continue_it_and_that_command_continues_it(tmp_path):
    sweep = tmp_path / "sw"
    cmd = [_exe(), "-m", "experiment=imm_analysis", "mc_runs=20", "logger=none", "figures=false",
           "progress=false", "seed=0", "hydra/launcher=basic", f"hydra.sweep.dir={sweep}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            env=env, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    while not list(sweep.glob("0_*/checkpoint.json")) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    line = next(line for line in err.splitlines() if line.startswith("torchmm-run: interrupted;"))
    assert f"re-run the same command (it has hydra.sweep.dir={sweep})" in line and "resume=" not in line
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "torchmm-run: resuming:" in again.stderr and "finished units in the checkpoint" in again.stderr


def _run_cli(cwd, *args):
    return subprocess.run([_exe(), *args], capture_output=True, text=True, timeout=300, cwd=cwd,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})


def test_resume_latest_continues_the_newest_run_of_the_same_config(tmp_path):
    base = ["experiment=imm_baseline", "debug=imm_baseline", "logger=none", "progress=false", "figures=false"]
    first = _run_cli(tmp_path, *base)
    assert first.returncode == 0, first.stderr[-2000:]
    folders = sorted((tmp_path / "outputs" / "imm_baseline").iterdir())
    assert len(folders) == 1
    kept = json.loads((folders[0] / "checkpoint.json").read_text())["units"]
    # a non-result key changed: the same folder is continued and every unit is kept
    again = _run_cli(tmp_path, *base, "resume=latest", "progress=true")
    assert again.returncode == 0, again.stderr[-2000:]
    assert f"resume=latest: continuing {folders[0]}" in again.stderr
    assert sorted((tmp_path / "outputs" / "imm_baseline").iterdir()) == folders
    assert f"resuming: {len(kept)} finished units in the checkpoint" in again.stderr
    assert json.loads((folders[0] / "checkpoint.json").read_text())["units"] == kept
    # another seed: no earlier run of that config, so a fresh folder; the old one is left alone
    other = _run_cli(tmp_path, *base, "resume=latest", "seed=5")
    assert other.returncode == 0 and "no earlier run of this config" in other.stderr
    assert len(list((tmp_path / "outputs" / "imm_baseline").iterdir())) == 2
    assert json.loads((folders[0] / "checkpoint.json").read_text())["units"] == kept
    # user errors: one line, exit 2
    for bad, key in ((["resume=/no/such/folder"], "resume"), (["-m", "resume=latest", "seed=1,2"], "resume")):
        proc = _run_cli(tmp_path, *base, *bad)
        assert proc.returncode == 2 and proc.stderr.startswith(f"torchmm-run: error: {key}"), proc.stderr


def test_resume_keeps_units_across_non_result_keys_and_a_changed_seed_gets_a_new_folder(tmp_path, monkeypatch):
    import experiments.studies.imm_analysis as study

    base = ["debug=imm_analysis", "logger=none"]
    first = run_study(_compose("imm_analysis", *base), tmp_path / "run")

    def fail(*args, **kwargs):
        raise AssertionError("a finished unit was recomputed")

    monkeypatch.setattr(study, "_analyse", fail)
    # progress, logger, threads, chunk_runs do not change results: every unit is reused
    again = run_study(_compose("imm_analysis", *base, "progress=true", "logger=tensorboard", "threads=2",
                               "chunk_runs=2"), tmp_path / "run")
    assert again.tables["alpha_sweep"].rows == first.tables["alpha_sweep"].rows
    before = (tmp_path / "run" / "results.json").read_text()
    # a changed seed: a new folder next to the old one, which stays as it was
    with pytest.raises(AssertionError, match="recomputed"):
        run_study(_compose("imm_analysis", *base, "seed=7"), tmp_path / "run")
    assert (tmp_path / "run_1").is_dir()
    assert json.loads((tmp_path / "run" / "results.json").read_text()) == json.loads(before)
    monkeypatch.undo()
    moved = run_study(_compose("imm_analysis", *base, "seed=7"), tmp_path / "run")
    assert moved.output_dir.name.startswith("run_") and moved.output_dir != tmp_path / "run"
    assert json.loads((tmp_path / "run" / "results.json").read_text()) == json.loads(before)


def test_changed_result_keys_are_named(tmp_path, caplog):
    import logging

    base = ["debug=imm_baseline", "logger=none"]
    run_study(_compose("imm_baseline", *base), tmp_path / "run")
    with caplog.at_level(logging.WARNING, logger="torchmm.experiments"):
        run_study(_compose("imm_baseline", *base, "seed=3", "scenario.R=50"), tmp_path / "run")
    text = " ".join(r.getMessage() for r in caplog.records)
    assert "seed" in text and "scenario.R" in text and "the old one is kept" in text


def test_curves_are_data_and_torchmm_plot_redraws_them_from_the_file_alone(tmp_path):
    import csv

    import numpy as np

    run_study(_compose("imm_baseline", "debug=imm_baseline", "logger=none"), tmp_path / "run")
    run_dir = tmp_path / "run"
    data = json.loads((run_dir / "results.json").read_text())
    with np.load(run_dir / "curves.npz") as curves:
        keys = set(curves.files)
        imm = curves["pos_rmse/IMM"]
        steps = curves["pos_rmse/IMM#step"]
    assert {"pos_rmse/IMM", "pos_rmse/GPB1", "vel_rmse/KF"} <= keys
    assert steps[0] == 1 and len(steps) == len(imm)
    # the per-step RMSE averages to the table's figure (the papers' average RMSE)
    row = next(r for r in data["tables"]["rmse"]["rows"] if r[0] == "IMM")
    assert float(imm.mean()) == pytest.approx(row[1], rel=1e-12)
    with open(run_dir / "curves.csv") as f:
        rows = list(csv.DictReader(f))
    assert {"quantity", "series", "axis", "x", "value"} == set(rows[0])
    assert sum(1 for r in rows if r["quantity"] == "pos_rmse" and r["series"] == "IMM") == len(imm)
    assert (run_dir / "figures" / "curves" / "pos_rmse.png").exists()  # the run drew them from the file
    # redraw from the curves file alone (results, events and figures removed)
    import shutil

    shutil.rmtree(run_dir / "figures")
    for name in ("results.json", "results.md", "checkpoint.json"):
        (run_dir / name).unlink(missing_ok=True)
    out = subprocess.run([str(Path(sys.executable).with_name("torchmm-plot")), str(run_dir), "--format", "png,pdf"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    figures = run_dir / "figures" / "curves"
    assert (figures / "pos_rmse.png").exists() and (figures / "pos_rmse.pdf").exists()
    bad = subprocess.run([str(Path(sys.executable).with_name("torchmm-plot")), str(tmp_path / "nothing")],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.startswith("torchmm-plot: error: RUN_DIR")


def test_sweep_curves_keep_their_own_axis_and_are_logged_once(tmp_path):
    import numpy as np

    from experiments.plot import load_curves

    results = run_study(_compose("imm_analysis", "debug=imm_analysis", "logger=none"), tmp_path / "run")
    curves = load_curves(tmp_path / "run")
    rows = [r for r in results.tables["alpha_sweep"].rows if r[0] == 2 and r[2] == "IMM"]
    axis, x, values = curves["pos_rmse_vs_alpha/2_models/IMM"]
    assert axis == "alpha" and list(x) == [r[1] for r in rows]  # the alphas themselves, not alpha * 1000
    np.testing.assert_allclose(values, [r[3] for r in rows], rtol=1e-12)
    assert curves["pos_rmse_vs_alpha_se/2_models/IMM"][0] == "alpha"
    with np.load(tmp_path / "run" / "curves.npz") as data:
        assert "pos_rmse_vs_alpha/2_models/IMM#alpha" in data.files
    assert (tmp_path / "run" / "figures" / "curves" / "pos_rmse_vs_alpha.png").exists()


def test_tensorboard_has_the_config_text_hparams_and_headline_metrics(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from experiments.harness import Results
    from experiments.run import hparams

    run_study(_compose("imm_baseline", "debug=imm_baseline", "logger=tensorboard"), tmp_path / "run",
              overrides=["experiment=imm_baseline", "scenario.R=50", "progress=false"])
    tags, plugins = {}, set()
    for f in sorted((tmp_path / "run" / "tb").glob("events*")):
        acc = EventAccumulator(str(f), size_guidance={"tensors": 0})
        acc.Reload()
        tags.update({k: v for k, v in acc.Tags().items() if isinstance(v, list) and v})
        for plugin in ("hparams", "text"):
            try:
                plugins |= {f"{plugin}:{t}" for t in acc.PluginTagToContent(plugin)}
            except KeyError:
                pass
    assert "text:config/text_summary" in plugins and "hparams:_hparams_/experiment" in plugins
    assert "headline/IMM/pos_rmse" in tags["scalars"]
    settings, metrics = hparams({"seed": 0, "mc_runs": 4, "dtype": "float64", "device": "cpu"},
                                ["scenario.R=50", "progress=false", "+extra=abc", "hydra.verbose=true"],
                                Results(tmp_path, "x", {}))
    assert settings == {"experiment": "x", "seed": 0, "mc_runs": 4, "dtype": "float64", "device": "cpu",
                        "scenario.R": 50, "extra": "abc"}
    assert metrics == {}


def test_sweep_jobs_label_their_progress_bars(tmp_path):
    proc = _run_cli(tmp_path, "-m", "experiment=imm_baseline", "debug=imm_baseline", "seed=0,1", "progress=true",
                    "logger=none", "hydra/launcher=basic", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "[job 0] estimators" in proc.stderr and "[job 1] estimators" in proc.stderr
    assert sorted(p.name for p in (tmp_path / "sweep").iterdir() if p.is_dir()) == [
        "0_debug=imm_baseline,seed=0", "1_debug=imm_baseline,seed=1"]  # progress: not in the names
    # every job's Python log is run.log (docs/scaling.md; before: job 1 wrote app.log, the job name of the
    # last compose of conf/ in job 0, experiments/changes.py)
    for job in (p for p in (tmp_path / "sweep").iterdir() if p.is_dir()):
        assert not (job / "app.log").exists(), job.name
        assert "results written to" in (job / "run.log").read_text(), job.name

"""Defects 9 and 10: study keys are validated before anything runs; run folders never collide.

A user error on the command line is one line on stderr naming the key, the value and what is
allowed, exit status 2, no traceback, and no run folder left behind; ``run_study`` raises the same
:class:`~experiments.config.ConfigError` before writing anything. Run folders are created
atomically and are unique, also for runs started in the same second.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from experiments.config import ConfigError, validate
from experiments.run import CONFIG_DIR, run_study, unique_dir

EXPERIMENTS = sorted(p.stem for p in (Path(CONFIG_DIR) / "experiment").glob("*.yaml"))


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("torchmm-run")
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([str(exe), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_shipped_experiment_validates(name):
    validate(_compose(f"experiment={name}"))


# (overrides, the start of the one-line message)
BAD = [
    (["mc_runs=0"], "mc_runs=0: must be a positive integer"),
    (["mc_runs=-3"], "mc_runs=-3: must be a positive integer"),
    (["mc_runs=abc"], "mc_runs=abc: expected an integer"),
    (["mc_runs=2.5"], "mc_runs=2.5: expected an integer"),
    (["seed=abc"], "seed=abc: expected an integer"),
    (["seed=-5"], "seed=-5: must be an integer in [0, 2^63)"),
    (["chunk_runs=-2"], "chunk_runs=-2: must be a positive integer"),
    (["chunk_runs=0"], "chunk_runs=0: must be a positive integer"),
    (["threads=0"], "threads=0: must be a positive integer"),
    (["device=gpu"], "device=gpu: expected cpu, cuda, cuda:<index> or auto"),
    (["dtype=float16"], "dtype=float16: expected one of float64, float32"),
    (["progress=maybe"], "progress=maybe: expected true or false"),
    (["mc_run=5"], "mc_run=5: unknown key (did you mean mc_runs?"),
    (["experiment=imm_tf_quick", "source.ratio=1.5"], "source.ratio=1.5: must be a probability in [0, 1]"),
    (["experiment=imm_tf_quick", "source.ratioo=0.5"],
     "source.ratioo=0.5: unknown key (did you mean source.ratio?"),
    (["experiment=imm_baseline", "scenario=det_small"],
     "scenario=det_small: does not fit the imm_baseline study; choose one of maneuver2, maneuver3, maneuver_demo, paper000"),
    (["experiment=mevsmm", "scenario=paper000"], "scenario=paper000: does not fit the mevsmm study"),
    (["experiment=imm_analysis", "scenario=paper000"], "scenario=paper000: the imm_analysis study takes no scenario"),
    # (issue 30: it ran a unit, then printed a 20-line traceback and exited 1)
    (["experiment=imm_analysis", "analysis.alphas.two_model=[0.01,2]"],
     "analysis.alphas.two_model=[0.01, 2]: entries [2] exceed 1/(M-1) = 1 for M = 2 modes"),
    (["experiment=imm_analysis", "analysis.alphas.three_model=[0.6]"],
     "analysis.alphas.three_model=[0.6]: entries [0.6] exceed 1/(M-1) = 0.5 for M = 3 modes"),
    (["experiment=nope"], "experiment=nope: no such config; choose one of "),
    (["experiment=imm_baseline", "estimators.IMM.joseph=maybe"], "estimators.IMM.joseph=maybe: expected true or false"),
    (["experiment=mevsmm", "mevsmm.mixing=bogus"], "mevsmm.mixing=bogus: expected one of two_stage"),
    (["experiment=gimmaf", "noise=laplace"], "noise=laplace: expected one of skew_t"),
    (["experiment=imm_tf_quick", "scenario.transition=[[1,0],[0,1]]"],
     "scenario.transition=[[1, 0], [0, 1]]: must be 3 x 3"),
    (["scenario.transition=[[1,0,0],[0,1,0],[0,0,1]]"], "scenario.transition=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]: must be 2 x 2"),
    (["+foo=1"], "foo: not a key of the quickstart study"),
    (["logger=tb"], "logger=tb: no such config; choose one of none, tensorboard"),
    # issue 30: each of these ran the study (some a unit) and failed with a traceback or a Hydra error
    (["experiment=smoothing", "smoothing.scenarios.paper000.steps=-3"],
     "smoothing.scenarios.paper000.steps=-3: must be a positive integer"),
    (["experiment=smoothing", "smoothing.scenarios.paper001.q=abc"], "smoothing.scenarios.paper001.q=abc: expected a number"),
    (["experiment=smoothing", "smoothing.scenarios.turning.stay=1.5"], "smoothing.scenarios.turning.stay=1.5: must"),
    (["experiment=smoothing", "+smoothing.scenarios.turning.bogus=1"], "smoothing.scenarios.turning.bogus: unknown key"),
    (["experiment=smoothing", "smoothing.cv_mode.paper000=-3"],
     "smoothing.cv_mode.paper000=-3: must be a mode index in [0, 3)"),
    (["experiment=smoothing", "smoothing.speed=maybe"], "smoothing.speed=maybe: expected true or false"),
    (["experiment=imm_tf_quick", "tf_estimators.VSIMM.p_ee=abc"], "tf_estimators.VSIMM.p_ee=abc: expected a number"),
    (["experiment=imm_tf_quick", "tf_estimators.VSIMM.p_ee=1.5"], "tf_estimators.VSIMM.p_ee=1.5: must lie in [0, 1)"),
    (["experiment=imm_tf_quick", "tf_estimators.IF-TF.gate.mode=-3"], "tf_estimators.IF-TF.gate.mode=-3: must be non-negative"),
    (["experiment=mevsmm", "mevsmm.cm_passes=0"], "mevsmm.cm_passes=0: must be a positive integer"),
    # issue 30: the estimators of mevsmm and gimmaf are config nodes; a bad node is one line naming its key
    (["experiment=mevsmm", "mevsmm.estimators.PF-MEVSMM._target_=torch.nn.Linear"],
     "mevsmm.estimators.PF-MEVSMM._target_=torch.nn.Linear: expected one of experiments.studies.mevsmm.eqma"),
    (["experiment=mevsmm", "+mevsmm_estimator@mevsmm.estimators.T=topk", "mevsmm.estimators.T.selection.method=x"],
     "mevsmm.estimators.T.selection.method=x: expected one of cm, topk"),
    (["experiment=mevsmm", "+mevsmm.estimators.K=topk"], "mevsmm.estimators.K=topk: expected an estimator node"),
    (["experiment=mevsmm", "mevsmm.estimator_names=[PF-MEVSMM,X]"], "mevsmm.estimator_names=['PF-MEVSMM', 'X']: entry X"),
    (["experiment=gimmaf", "gimmaf.estimators.STVBF._target_=torch.nn.Linear"],
     "gimmaf.estimators.STVBF._target_=torch.nn.Linear: expected one of torchmm.multimodel.variational.imm_vbt"),
    (["experiment=gimmaf", "gimmaf.estimators.GIMMAF.iterations=0"],
     "gimmaf.estimators.GIMMAF.iterations=0: must be a positive integer"),
    (["experiment=fusion_radar", "radar.rho=[]"], "radar.rho=[]: expected 2 numbers"),
    (["experiment=fusion_radar", "radar.x0=[1]"], "radar.x0=[1.0]: expected 6 numbers"),
    (["experiment=fusion_ups", "ups.horizons=[-1]"], "ups.horizons=[-1]: must include 0"),
    (["experiment=fusion_ups", "ups.C=[]"], "ups.C=[]: expected 3 numbers (one per state)"),
    (["experiment=fusion_ups", "ups.d=[1]"], "ups.d=[1.0]: expected 3 numbers (one per sensor)"),
    (["scenario.initial_mean=[]"], "scenario.initial_mean=[]: expected the 2-state [position, velocity] mean"),
    (["experiment=tracking", "tracking.estimators=[IMM-JPDAF,MHT]"], "tracking.estimators=['IMM-JPDAF', 'MHT']: entry"),
    (["experiment=tracking", "tracking.detection_probability=1.5"], "tracking.detection_probability=1.5: must lie in (0, 1]"),
    (["experiment=tracking", "tracking.P0=[1.5,2.5]"], "tracking.P0=[1.5, 2.5]: expected 4 variances"),
    (["experiment=tracking", "tracking.P0=[1,1,1,inf]"], "tracking.P0[3]=inf: must be finite"),
    (["experiment=tracking", "tracking.P0=[1,nan,1,1]"], "tracking.P0[1]=nan: must be finite"),
    (["experiment=fusion_radar", "radar.eta_std=[[1000.0,0.01],[900.0,-inf],[800.0,0.01]]"],
     "radar.eta_std[1][1]=-inf: must be finite"),
    (["experiment=tracking", "tracking.targets=20"], "tracking.targets=20: the exact JPDA takes at most 12"),
    (["experiment=tracking", "tracking.lifetimes=[[0,60],[10,60],[0,30],[0,60]]"],
     "tracking.estimators=['IMM-JPDAF', 'JPDAF', 'IMM-PDAF', 'GNN-IMM', 'JIPDA-TM',...: IMM-JPDAF, JPDAF"),
    (["experiment=tracking", "tracking.lifetimes=[[0,60]]", "tracking.estimators=[JIPDA-TM]"],
     "tracking.lifetimes=[[0, 60]]: expected [first, stop] for each of the 4 targets"),
    (["experiment=tracking", "tracking.lifetimes=[[0,60],[10,5],[0,30],[0,60]]", "tracking.estimators=[JIPDA-TM]"],
     "tracking.lifetimes=[[0, 60], [10, 5], [0, 30], [0, 60]]: each [first, stop] needs 0 <= first < stop"),
    (["experiment=tracking", "tracking.management.method=exact", "tracking.management.capacity=20"],
     "tracking.management.capacity=20: the exact JIPDA takes at most 12"),
    (["experiment=tracking", "tracking.start=detections", "tracking.estimators=[GNN-IMM,IMM-JPDAF]",
      "tracking.management.capacity=13"],
     "tracking.management.capacity=13: with tracking.start: detections IMM-JPDAF runs the exact JPDA over the track "
     "slots, which takes at most 12"),
    (["experiment=tracking", "tracking.management.m_of_n=[4,3]"],
     "tracking.management.m_of_n=[4, 3]: expected [M, N] with 1 <= M <= N"),
    (["experiment=tracking", "tracking.management.max_misses=0"], "tracking.management.max_misses=0: must be a positive"),
    (["experiment=tracking", "tracking.management.confirm=0"], "tracking.management.confirm=0.0: must lie in (0, 1]"),
]


#: rejected while Hydra composes the config (unknown keys, missing configs): the command line's case
COMPOSITION = {"mc_run=5", "source.ratioo=0.5", "experiment=nope", "logger=tb"}
COMPOSED = [b for b in BAD if b[0][-1] not in COMPOSITION]


@pytest.mark.parametrize("overrides,message", COMPOSED, ids=[" ".join(o) for o, _ in COMPOSED])
def test_run_study_rejects_bad_keys_before_writing(overrides, message, tmp_path):
    cfg = _compose(*overrides)
    with pytest.raises(ConfigError) as err:
        run_study(cfg, tmp_path / "run")
    assert str(err.value).startswith(message)
    assert not (tmp_path / "run").exists()


COMPOSING = [b for b in BAD if b[0][-1] in COMPOSITION]


@pytest.mark.parametrize("overrides,message", COMPOSING, ids=[" ".join(o) for o, _ in COMPOSING])
def test_composition_errors_become_one_line_config_errors(overrides, message):
    from experiments.config import _precheck

    with pytest.raises(ConfigError) as err:
        _precheck(list(overrides), CONFIG_DIR, "config")
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


CLI_CASES = [b for b in BAD if b[0][-1] in ("mc_runs=abc", "mc_runs=2.5", "seed=-5", "device=gpu", "mc_run=5",
                                              "source.ratioo=0.5", "experiment=nope", "logger=tb")
             or b[0][-1] in ("scenario=det_small", "analysis.alphas.two_model=[0.01,2]",
                             "smoothing.scenarios.paper000.steps=-3", "tf_estimators.VSIMM.p_ee=abc")]


@pytest.mark.parametrize("overrides,message", CLI_CASES, ids=[" ".join(o) for o, _ in CLI_CASES])
def test_cli_user_errors_are_one_line_exit_2_and_leave_no_folder(overrides, message, tmp_path):
    proc = _cli(*overrides, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert lines == [f"torchmm-run: error: {lines[0].split('error: ', 1)[1]}"] and "Traceback" not in proc.stderr
    assert lines[0].split("error: ", 1)[1].startswith(message)
    assert list(tmp_path.iterdir()) == []  # no outputs/ or multirun/ folder, no empty TensorBoard run


def test_cli_sweep_validates_every_job_before_starting(tmp_path):
    proc = _cli("-m", "experiment=imm_baseline", "mc_runs=2,0", cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "torchmm-run: error: mc_runs=0: must be a positive integer"
    assert list(tmp_path.iterdir()) == []


def test_unique_dir_never_reuses_a_folder(tmp_path):
    base = str(tmp_path / "outputs" / "study" / "2026-12-01_12-00-00")
    made = [unique_dir(base) for _ in range(3)]
    assert made == [base, base + "_1", base + "_2"]
    assert all(Path(p).is_dir() for p in made)


def test_two_runs_started_together_write_into_their_own_folders(tmp_path):
    """Seeds 1 and 2 launched in the same second used to share (and overwrite) one folder."""
    exe = Path(sys.executable).with_name("torchmm-run")
    procs = [subprocess.Popen([str(exe), "mc_runs=2", f"seed={seed}", "progress=false", "logger=tensorboard",
                               "figures=false", "hydra.run.dir=${torchmm.unique_dir:outputs/same}"],
                              cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for seed in (1, 2)]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err[-2000:]
    folders = sorted((tmp_path / "outputs").iterdir())
    assert [f.name for f in folders] == ["same", "same_1"]
    seeds = sorted(json.loads((f / "results.json").read_text())["config"]["seed"] for f in folders)
    assert seeds == [1, 2]
    for f in folders:
        assert len(list((f / "tb").glob("events.out.tfevents.*"))) == 1  # one TensorBoard run each
        assert (f / ".hydra" / "config.yaml").exists()

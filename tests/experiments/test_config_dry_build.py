"""Config errors that only a constructor can judge are caught before any folder (issue 44): the run's
scenario, estimators and learn entries are built dry in the precheck (experiments.config.dry_build),
so each is one line naming the key, exit status 2 and no run folder (before: Hydra's "Error executing
job", a traceback, exit 1 and a folder holding only run.log)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments.config import precheck
from experiments.run import CONFIG_DIR


@pytest.fixture(scope="module")
def track(tmp_path_factory) -> Path:
    """A 2-D track of two series (x, y measured; px, vx, py, vy truth) with a time column."""
    rng = np.random.default_rng(0)
    rows = ["series,t,x,y,px,vx,py,vy"]
    for name, steps in (("a", 12), ("b", 9)):
        for k in range(steps):
            rows.append(f"{name},{k + 1},{k + rng.normal():.6f},{rng.normal():.6f},{k},1,0,0")
    path = tmp_path_factory.mktemp("data") / "track.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


def _data(track: Path, **extra) -> str:
    keys = {"path": str(track), "measurements": "[x,y]", "truth": "[px,vx,py,vy]", "series": "series", **extra}
    return "scenario.data={" + ",".join(f"{k}:{v}" for k, v in keys.items()) + "}"


CASES = [
    # (overrides, the start of the one line)
    (["scenario.sensors.0.R=-1"], "scenario.sensors[0]="),
    (["scenario.sensors.0.R=[[1,2],[3,4]]"], "scenario.sensors[0]="),
    (["scenario.sensors.0.R=[1,2,3]"], "scenario.sensors[0]="),
    (["scenario.modes.0.q=-1"], "scenario.modes[0]="),
    (["scenario.initial_cov=[[1,0,0,0],[0,-1,0,0],[0,0,1,0],[0,0,0,1]]"], "scenario.initial_cov="),
    (["scenario.groups={position:[0,7]}"], "scenario.groups.position="),
    (["MEASUREMENTS=[x]"], "scenario.data.measurements="),
    (["TRUTH=[px,py]"], "scenario.data.truth="),
    (["TIME=t", "scenario.modes=[" + ",".join(["{_target_:torchmm.LinearMotion,F:[[1,1,0,0],[0,1,0,0],[0,0,1,1],"
                                                "[0,0,0,1]],Q:[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"] * 3) + "]"],
     "scenario.modes[0]="),  # a time column: the modes are rebuilt with its dt, which LinearMotion has not
    (["learn={parameters:[{model:'modes[9]',name:Q}]}"], "learn.parameters[0].model=modes[9]: there are 3 modes"),
    (["learn={parameters:[{model:'modes[0]',name:Z}]}"], "learn.parameters[0].name=Z"),
    (["learn={parameters:[{model:'modes[0]',name:Q,kind:bogus}]}"], "learn.parameters[0].kind=bogus"),
    (["learn={parameters:[{model:'foo',name:Q}]}"], "learn.parameters[0].model=foo"),
    (["learn={parameters:[{model:'sensors[3]',name:R}]}"], "learn.parameters[0].model=sensors[3]"),
    (["learn={parameters:[{model:'sensors[0]',name:R}],estimators:[KF-CV-q],method:gradient}"], "learn.estimators=KF-CV-q"),
    (["learn={parameters:[{name:transition,kind:free}]}"], "learn.parameters[0].kind=free"),
    (["learn={parameters:[{name:H}]}"], "learn.parameters[0].model"),
    (["learn={parameters:[{model:'modes[0]',name:Q}],estimators:[nope]}"], "learn.estimators="),
    (["estimators.KF-CV.mode=7"], "estimators.KF-CV.mode=7: is not one of the scenario's 3 modes"),
    (["scenario.initial_mode_probs=[0.5,0.5]"], "scenario.initial_mode_probs=[0.5, 0.5]: expected 3 probabilities"),
    (["learn={parameters:[{model:'modes[0]',name:F}],method:gradient}"], "learn.parameters[0].name=F: method gradient"),
    (["learn={parameters:[{model:'modes[0]',name:Z}]}"], "learn.parameters[0].name=Z: no mode model"),
    # the second fuzz: no coercion of words into flags or numbers, repeated names, empty lists, a burn of everything
    (["figures=no"], "figures=no: expected true or false"),
    (["progress=no"], "progress=no: expected true or false"),
    (["update_first=no"], "update_first=no: expected true or false"),
    (["mc_runs='3'"], "mc_runs=3: expected an integer"),
    (["scenario.every=1.5"], "scenario.every=1.5: one value per sensor, integer periods"),
    (["scenario.labels=[a,a,b]"], "scenario.labels=['a', 'a', 'b']: the modes' names must differ"),
    (["scenario.groups={position:[0,0],velocity:[1,3]}"], "scenario.groups.position=[0, 0]: lists a state component twice"),
    (["metrics=[]"], "metrics=[]: must not be empty"),
    (["burn=50"], "burn=50: leaves out every step"),
    (["MEASUREMENTS=[x,x]"], "scenario.data.measurements=['x', 'x']: measurements[1]: column 'x' is named twice"),
    (["paired=3"], "paired=3: expected a mapping of reference"),
    (["learn={parameters:[{model:'modes[0]',name:Q}],method:em}"], "learn.parameters[0]=modes[0].Q: method em for "
                                                                     "switching models estimates"),
    (["learn={parameters:[{model:'sensors[0]',name:R,shared:true}],method:em,estimators:[KF-CV]}"],
     "learn.parameters[0].shared=True: method em takes fixed entries, not shared"),
    (["learn={parameters:[{model:'sensors[0]',name:R,fixed:[true,false]}],method:em,estimators:[KF-CV]}"],
     "learn.parameters[0].fixed=[True, False]: a covariance's mask must be symmetric"),  # (broadcast to 2 x 2)
    (["learn={parameters:[{model:'modes[0]',name:F,fixed:[[true,false,true,true],[true,true,true,true],"
      "[true,true,true,true],[true,true,true,true]]}],method:em,estimators:[KF-CV]}"],
     "learn.parameters[0].fixed=[[True, False, True, True], [True, True, True, True], [Tr...: with fixed entries "
     "the M-step of F is a least squares weighted by Q"),
    (["learn={parameters:[{model:'sensors[0]',name:R,fixed:[[true,false],[false,false]]}],method:em,"
      "estimators:[KF-CV]}"], "learn.parameters[0].fixed=[[True, False], [False, False]]: the free entries of a "
                              "covariance must form diagonal blocks"),
    # the start's entries (issue 45)
    (["learn={parameters:[{model:modes,name:initial_mean}]}"], "learn.parameters[0].model=modes: initial_mean belongs "
                                                               "to no model"),
    (["learn={parameters:[{name:initial_cov,kind:free}]}"], "learn.parameters[0].kind=free: the start's covariance"),
    (["learn={parameters:[{name:initial_mode_probs}],estimators:[KF-CV]}"], "learn.parameters[0]=initial_mode_probs: "
                                                                            "KF-CV is not a mode filter"),
    (["learn={parameters:[{name:initial_mean,fixed:[true,false]}]}"], "learn.parameters[0].fixed=[True, False]: "
                                                                      "expected a boolean mask of shape (4,)"),
    # a Param's own refusals and a singular covariance start (before: a ValueError or _LinAlgError traceback)
    (["learn={parameters:[{model:'sensors[0]',name:R,lower:5}]}"],
     "learn.parameters[0].lower=5: bounds are for kind 'free' entries, not 'variance'"),
    (["learn={parameters:[{model:'sensors[0]',name:H,lower:2,upper:1}]}"],
     "learn.parameters[0].upper=1: must exceed lower"),
    (["scenario.sensors.0.R=[[25.0,25.0],[25.0,25.0]]",
      "learn={parameters:[{model:sensors,name:R,kind:covariance}],estimator:KF-CV}"],
     "learn.parameters=sensors.R: a 'covariance' starts from a positive definite matrix"),
    # the transition's options: fixed and names honoured (tests/experiments/test_learn_entries_config.py),
    # the others refused
    (["learn={parameters:[{name:transition,shared:true}]}"],
     "learn.parameters[0].shared=True: the transition matrix takes no shared entries"),
    (["learn={parameters:[{name:transition,lower:0.1}]}"],
     "learn.parameters[0].lower=0.1: the transition matrix takes no bounds"),
    (["learn={parameters:[{name:transition,fixed:[true,false]}]}"],
     "learn.parameters[0].fixed=[True, False]: expected a boolean mask of shape (3, 3)"),
    (["learn={parameters:[{name:transition,names:[a,b]}]}"],
     "learn.parameters[0].names=['a', 'b']: expected 9 names"),
]


@pytest.mark.parametrize("overrides, start", CASES, ids=[c[1].split("=")[0] + f"-{i}" for i, c in enumerate(CASES)])
def test_each_config_error_is_one_line_before_any_folder(track, tmp_path, capsys, overrides, start):
    extra = {}
    rest = []
    for item in overrides:
        key, _, value = item.partition("=")
        if key in ("MEASUREMENTS", "TRUTH", "TIME"):
            extra[key.lower()] = value
        else:
            rest.append(item)
    argv = ["experiment=compare", "logger=none", _data(track, **extra), *rest, f"hydra.run.dir={tmp_path / 'run'}"]
    with pytest.raises(SystemExit) as stop:
        precheck(argv, CONFIG_DIR)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"torchmm-run: error: {start}"), err
    assert not (tmp_path / "run").exists()


def test_the_command_line_leaves_no_folder(track, tmp_path):
    """The console script end to end: exit 2, one line, no folder (one case; the rest in-process above)."""
    exe = str(Path(sys.executable).with_name("torchmm-run"))
    out = tmp_path / "run"
    proc = subprocess.run([exe, "experiment=compare", "logger=none", _data(track), "scenario.sensors.0.R=-1",
                           f"hydra.run.dir={out}"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().startswith("torchmm-run: error: scenario.sensors[0]=") and \
        len(proc.stderr.strip().splitlines()) == 1
    assert not out.exists()


def test_a_valid_config_passes_the_dry_build(track, tmp_path):
    precheck(["experiment=compare", "logger=none", _data(track, time="t"),
              "learn={parameters:[{model:'sensors[0]',name:R}],estimators:[IMM,KF-CV]}"], CONFIG_DIR)


def test_a_manoeuvre_that_ends_before_it_starts_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        precheck(["experiment=tracking", "tracking.maneuver_start=30", "tracking.maneuver_stop=20",
                  f"hydra.run.dir={tmp_path / 'run'}"], CONFIG_DIR)
    assert capsys.readouterr().err.startswith("torchmm-run: error: tracking.maneuver_start=30: is after maneuver_stop")


# -- every study's config built dry (the audit of the config errors: each case ran the study's code after
# creating its folder and failed with a traceback and exit 1, or was accepted and then ignored or lost)
def _study(name: str, *overrides: str) -> list[str]:
    return [f"experiment={name}", f"debug={name}", "logger=none", "figures=false", "progress=false",
            *overrides]


STUDY_CASES = [
    # (the command line, the start of the one line); before: a traceback after the run folder was made
    (_study("quickstart", "estimators.KF.mode=2"),
     "estimators.KF.mode=2: is not one of the scenario's 2 modes"),
    (_study("imm_baseline", "estimators.KF.mode=3"),
     "estimators.KF.mode=3: is not one of the scenario's 3 modes"),
    (_study("imm_baseline", "estimators.IMM.transition=[[0.5,0.5],[0.5,0.5]]"),
     "estimators.IMM.transition=[[0.5, 0.5], [0.5, 0.5]]: expected 3 x 3"),
    (_study("quickstart", "scenario.initial_mode_probs=[0.2,0.2]"),
     "scenario.initial_mode_probs=[0.2, 0.2]: must be non-negative and sum to 1"),
    (_study("imm_tf", "transfer.influence.mode=5"),
     "transfer.influence.mode=5: must be a mode index in [0, 3)"),
    (_study("imm_tf", "vsimm.extra_model=7"), "vsimm.extra_model=7: must be a mode index in [0, 3)"),
    (_study("imm_tf", "tf_estimators.VSIMM.extra_model=7"),
     "tf_estimators.VSIMM.extra_model=7: must be a mode index"),
    (_study("imm_tf", "tf_estimators.IF-TF.gate.mode=5"),
     "tf_estimators.IF-TF.gate.mode=5: must be a mode index"),
    (_study("imm_tf", "estimator_names=[IMM,IMM-TF,IMM-TF]"),  # (before: one IMM-TF row, no word)
     "estimator_names=['IMM', 'IMM-TF', 'IMM-TF']: IMM-TF given twice"),
    (_study("imm_tf", "transfer.influence.weight=process"),  # (the scenario's Q = q G G^T is singular)
     "tf_estimators.IF-TF.gate.weight=process: needs a non-singular process noise Q of the anchor mode 0"),
    (_study("compare", "mode_filter=particle"),  # (the IMM has smooth: true)
     "estimators.IMM.smooth=True: the multiple-model smoothers need Gaussian mode filters"),
    (_study("gimmaf", "gimmaf.segments=[[1,50,0.0,-0.01]]"),
     "gimmaf.segments[0]=[1, 50, 0.0, -0.01]: the process-noise variance -0.01 must be non-negative"),
    (_study("gimmaf", "gimmaf.segments=[[51,50,0.0,0.01]]"),
     "gimmaf.segments[0]=[51, 50, 0.0, 0.01]: needs whole"),
    (_study("fusion_radar", "radar.C=[[[1,0,0]]]"), "radar.C=[[[1, 0, 0]]]: expected 3 matrices"),
    (_study("fusion_radar", "radar.position_index=9"),
     "radar.position_index=9: must be a state index in [0, 6)"),
    (_study("fusion_radar", "radar.eta_std=[[1000.0,0.01],[900.0,0.02]]"),
     "radar.eta_std=[[1000.0, 0.01], [900.0, 0.02]]: expected 3 rows (one per sensor) of 2 numbers"),
    (_study("fusion_ups", "ups.Ct=[[8.0,12.0],[10.0,8.0],[8.0,6.0]]"),
     "ups.Ct=[[8.0, 12.0], [10.0, 8.0], [8.0, 6.0]]: expected rows of 3 numbers"),
    (_study("fusion_ups", "ups.Gamma=[[0.5],[0.0]]"), "ups.Gamma=[[0.5], [0.0]]: expected 3 rows"),
    (_study("learn_dynamics", "learn.scenario.initial_std=[10,2]"),
     "learn.scenario.initial_std=[10.0, 2.0]: expected 4 numbers"),
    (_study("learn_dynamics", "learn.scenario.initial_mean=[0,15]"),
     "learn.scenario.initial_mean=[0.0, 15.0]: expected 4 numbers"),
    (_study("mevsmm", "scenario.initial_state=[1,2]"),
     "scenario.initial_state=[1.0, 2.0]: expected 4 numbers"),
    # before: accepted, then replaced by another key or part of the output silently lost
    (_study("smoothing", "estimators.KF.mode=7"),
     "estimators.KF.mode=7: not used: the smoothing study runs each single filter on its scenario's "
     "smoothing.cv_mode"),
    (_study("imm_analysis", "estimators.IMM.transition=[[0.5,0.5,0.0],[0.5,0.5,0.0],[0,0,1]]"),
     "estimators.IMM.transition=[[0.5, 0.5, 0.0], [0.5, 0.5, 0.0], [0, 0, 1]]: not used: the imm_analysis "
     "study sweeps the transition matrix"),
    (_study("markov_switching", "scenario.labels=[a]"),
     "scenario.labels=['a']: needs one name per regime (2"),
    (_study("markov_switching", "scenario.labels=[a,a]"),
     "scenario.labels=['a', 'a']: the regimes' names must differ"),
    (_study("mevsmm", "scenario.maneuvers=[[31,20,[1.0,1.0]]]"),
     "scenario.maneuvers[0]=[31, 20, [1.0, 1.0]]: needs 1 <= first <= last"),
    # before: the line named another key (scenario.initial_mean), or suggested the refused key itself
    (_study("compare", "scenario.sensors.0.state_dim=6"),
     "scenario.sensors[0].state_dim=6: the sensor measures a 6-component state; the models' state and "
     "scenario.initial_mean have 4"),
    (_study("compare", "estimators.IMM.mode_filter._target_=torchmm.Foo"),
     "estimators.IMM.mode_filter._target_=torchmm.Foo: estimators.IMM.mode_filter is ${mode_filter}, which "
     "an override cannot reach into: choose the group, mode_filter=<extended|kalman|particle|unscented>"),
]


@pytest.mark.parametrize("argv, start", STUDY_CASES, ids=[" ".join(a[5:]) for a, _ in STUDY_CASES])
def test_each_study_config_error_is_one_line_before_any_folder(tmp_path, capsys, argv, start):
    with pytest.raises(SystemExit) as stop:
        precheck([*argv, f"hydra.run.dir={tmp_path / 'run'}"], CONFIG_DIR)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"torchmm-run: error: {start}"), err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("name", sorted(p.stem for p in (Path(CONFIG_DIR) / "debug").glob("*.yaml")))
def test_every_debug_config_passes_the_dry_build(name):
    """The small configs the fast tests run (debug=<study>) pass every check and dry build (mevsmm's
    histogram steps lie within its shortened scenario)."""
    precheck(_study(name), CONFIG_DIR)


def test_every_registered_study_names_its_dry_build():
    from experiments.schemas import BUILD_CHECKS, STUDIES

    assert set(STUDIES) <= set(BUILD_CHECKS)

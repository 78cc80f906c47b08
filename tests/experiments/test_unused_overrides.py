"""An override the study would ignore is refused before any folder (docs/studies.md, "a key whose values
would be lost"): ``mc_runs`` while the runs are a data file's series (compare's ``scenario.data``: nile,
fedfunds, markov_switching, one's own CSV; the tracking study's ``tracking.detections``). Before, such a run
exited 0 with the numbers of a run without it, while results.md listed ``mc_runs`` under "Differs from the
defaults" and results.json recorded it."""

from __future__ import annotations

from pathlib import Path

import pytest

from experiments.config import ConfigError, precheck
from experiments.run import CONFIG_DIR
from tests.experiments.test_config_dry_build import track  # noqa: F401 - (a fixture: two series in a CSV)


def _own_data(track: Path) -> str:
    return f"scenario.data={{path:{track},measurements:[x,y],truth:[px,vx,py,vy],series:series}}"


FILE_STUDIES = [(["experiment=nile"], "scenario.data"), (["experiment=fedfunds"], "scenario.data"),
                (["experiment=markov_switching"], "scenario.data"),
                (["experiment=tracking_detections"], "tracking.detections")]


@pytest.mark.parametrize("given", ["mc_runs=500", "++mc_runs=1"])
def test_mc_runs_with_ones_own_data_file_is_refused(track, tmp_path, capsys, given):
    argv = ["experiment=compare", "logger=none", _own_data(track), given, f"hydra.run.dir={tmp_path / 'run'}"]
    with pytest.raises(SystemExit) as stop:
        precheck(argv, CONFIG_DIR)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    value = given.split("=")[1]
    assert err == (f"torchmm-run: error: mc_runs={value}: not used: the runs are the series of scenario.data, "
                   "one run a series (leave mc_runs out)"), err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("argv, key", FILE_STUDIES, ids=[a[0] for a, _ in FILE_STUDIES])
def test_mc_runs_is_refused_by_every_study_that_reads_a_file(tmp_path, capsys, monkeypatch, argv, key):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        precheck([*argv, "logger=none", "mc_runs=7", f"hydra.run.dir={tmp_path / 'run'}"], CONFIG_DIR)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"torchmm-run: error: mc_runs=7: not used: the runs are "
                                                         f"the series of {key}"), err
    assert not (tmp_path / "run").exists()
    precheck([*argv, "logger=none"], CONFIG_DIR)  # without it: the same study passes


@pytest.mark.parametrize("argv", [["experiment=compare"], ["experiment=tracking", "debug=tracking"]])
def test_mc_runs_of_simulated_runs_is_kept(argv):
    precheck([*argv, "logger=none", "mc_runs=7"], CONFIG_DIR)


def test_the_python_api_refuses_it_before_any_folder(tmp_path):
    from experiments.api import study

    with pytest.raises(ConfigError, match=r"^mc_runs=3: not used: the runs are the series of scenario.data"):
        study("nile", out=tmp_path / "run", mc_runs=3, progress=False)
    assert not (tmp_path / "run").exists()


WAYPOINTS = "tracking.waypoints=[[[0,0,0],[10,100,0]],[[0,0,50],[10,100,50]]]"


@pytest.mark.parametrize("argv, given, why", [
    (["experiment=tracking_detections"], "tracking.targets=3", "the targets and scans are those of tracking.detections"),
    (["experiment=tracking_detections"], "tracking.steps=40", "the targets and scans are those of tracking.detections"),
    (["experiment=tracking_detections"], "tracking.maneuver_start=5",
     "the targets and scans are those of tracking.detections"),
    (["experiment=tracking", "debug=tracking", WAYPOINTS], "tracking.radius=200", "the targets fly tracking.waypoints"),
    (["experiment=tracking", "debug=tracking", WAYPOINTS], "tracking.targets=2", "the targets fly tracking.waypoints"),
], ids=["detections-targets", "detections-steps", "detections-maneuver", "waypoints-radius", "waypoints-targets"])
def test_the_simulated_scenarios_keys_are_refused_where_the_targets_come_from_elsewhere(tmp_path, capsys, monkeypatch,
                                                                                       argv, given, why):
    """docs/tracking.md: with a detections file the scenario keys (targets, steps, radius, the manoeuvre) are
    not read, nor targets, radius and the manoeuvre with waypoints; given on the command line they were
    recorded as changes that changed nothing."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        precheck([*argv, "logger=none", given, f"hydra.run.dir={tmp_path / 'run'}"], CONFIG_DIR)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    key = given.split("=")[0]
    assert err == f"torchmm-run: error: {given}: not used: {why} (leave {key} out)", err
    assert not (tmp_path / "run").exists()


def test_the_scenarios_keys_of_a_simulated_circle_are_kept():
    precheck(["experiment=tracking", "debug=tracking", "logger=none", "tracking.radius=200", "tracking.targets=3",
              "tracking.steps=30"], CONFIG_DIR)
    precheck(["experiment=tracking", "debug=tracking", "logger=none", WAYPOINTS, "tracking.steps=30"], CONFIG_DIR)

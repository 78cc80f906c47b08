"""experiments.study / experiments.load (the Python API) and results.md's command and changes."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

import experiments
from experiments import api
from experiments.config import ConfigError
from experiments.harness import Results
from experiments.run import CONFIG_DIR, run_study

QUIET = {"progress": False, "logger": "none", "figures": False}


def test_study_with_overrides_runs_and_results_md_names_them(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    res = experiments.study("imm_baseline", debug="imm_baseline", mode_filter="unscented", scenario__R=25,
                            **QUIET)
    assert isinstance(res, api.StudyResults)
    assert res.dir.parent == Path("outputs") / "imm_baseline" and (res.dir / "results.json").exists()
    assert res.json["config"]["scenario"]["R"] == 25 and res.config["mc_runs"] == 4
    assert res.json["config"]["mode_filter"]["_target_"] == "torchmm.UnscentedKalmanFilter"
    md = res.markdown
    command = "torchmm-run experiment=imm_baseline debug=imm_baseline mode_filter=unscented scenario.R=25"
    assert res.json["provenance"]["command"].startswith(command)
    head = md.split("## ")[0]  # before the first table: the command and the changes
    assert f"```bash\n{command}" in head
    assert "- `mode_filter=unscented` (default: kalman)" in head
    assert "- `debug=imm_baseline` (default: null)" in head
    assert "- `scenario.R=25` (default: 100.0)" in head
    assert "- `mc_runs=4` (default: 100)" in head
    assert "progress" not in head.split("```")[-1] and "logger" not in head.split("```")[-1]  # not result keys

    assert res.tables == ["rmse"]
    table = res.table("rmse")
    assert list(table["estimator"]) == ["IMM", "GPB1", "GPB2", "KF"]
    assert float(table["pos_rmse"][0]) == res.json["tables"]["rmse"]["rows"][0][1]
    with pytest.raises(KeyError, match="tables: rmse"):
        res.table("nope")
    assert res.figures == []  # figures=False
    assert res._repr_markdown_().endswith(md) and str(res.dir) in repr(res)

    again = experiments.load(res.dir)
    assert again.json == res.json and again.metrics == res.metrics and again.markdown == md


def test_run_without_overrides_says_it_ran_with_the_defaults(tmp_path):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("config", overrides=["experiment=imm_baseline", "progress=false", "logger=none",
                                           "figures=false", "threads=1"])
    run_study(cfg, tmp_path)  # no Hydra choices: every result key equals the study's default
    md = (tmp_path / "results.md").read_text()
    assert "Ran with the defaults of `imm_baseline`" in md
    assert "Differs from the defaults" not in md


def test_config_changes_infers_group_choices_without_hydra():
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("config", overrides=["experiment=imm_baseline", "mode_filter=unscented", "seed=3"])
    from omegaconf import OmegaConf

    changes = api.config_changes(OmegaConf.to_container(cfg, resolve=True))
    assert changes["experiment"] == "imm_baseline"
    assert changes["choices"] == {"mode_filter": ["kalman", "unscented"]}
    assert changes["keys"]["seed"] == [0, 3]
    assert changes["keys"]["mode_filter._target_"] == ["torchmm.KalmanFilter", "torchmm.UnscentedKalmanFilter"]
    results = Results(Path("."), "imm_baseline", {})
    results.changes = changes
    results.provenance = {"command": "torchmm-run experiment=imm_baseline mode_filter=unscented seed=3"}
    md = results.to_markdown()
    assert md.index("torchmm-run experiment") < md.index("`mode_filter=unscented`") < md.index("`seed=3`")
    assert api.config_changes({"experiment_name": "not_a_study"}) is None


def test_cli_results_md_names_the_overrides(tmp_path):
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "experiments.run", "experiment=imm_baseline", "debug=imm_baseline",
           "policy=all", "seed=2", "progress=false", "logger=none", "figures=false", f"hydra.run.dir={run_dir}"]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    head = (run_dir / "results.md").read_text().split("## ")[0]
    assert "experiment=imm_baseline debug=imm_baseline policy=all seed=2" in head
    assert "- `policy=all` (default: min_entropy)" in head  # from Hydra's own choices
    assert "- `seed=2` (default: 0)" in head and "- `debug=imm_baseline` (default: null)" in head


def test_overrides_dict_list_and_python_values(tmp_path):
    assert api._override_list({"scenario.R": 25.0, "figures": False}, {"table1_ratios": [0.3, 0.99], "x__y": None}) \
        == ["scenario.R=25.0", "figures=false", "table1_ratios=[0.3,0.99]", "x.y=null"]
    assert api._override_list(["+new=1"], {"name": "a b"}) == ["+new=1", "name='a b'"]
    res = api.study("imm_baseline", out=tmp_path / "run", overrides={"debug": "imm_baseline", "scenario.steps": 20},
                    **QUIET)
    assert res.dir == tmp_path / "run" and res.config["scenario"]["steps"] == 20


@pytest.mark.parametrize("call, error, words", [
    (lambda: api.study("nope"), ValueError, ["name", "imm_baseline"]),
    (lambda: api.study(3), TypeError, ["name"]),
    (lambda: api.study("imm_baseline", mc_runs=-1), ConfigError, ["mc_runs"]),
    (lambda: api.study("imm_baseline", mc_runz=5), ConfigError, ["mc_runz", "mc_runs"]),
    (lambda: api.study("imm_baseline", mode_filter="kalmann"), ConfigError, ["mode_filter", "unscented"]),
    (lambda: api.study("imm_baseline", overrides=5), TypeError, ["overrides"]),
    (lambda: api.study("imm_baseline", overrides=["seed"]), ValueError, ["overrides"]),
    (lambda: api.study("imm_baseline", experiment="imm_tf"), ValueError, ["experiment"]),
    (lambda: api.study("imm_baseline", out=3), TypeError, ["out"]),
    (lambda: api.study("imm_baseline", seed=object()), ConfigError, ["seed=<object", "expected a number"]),
    (lambda: api.study("imm_baseline", mc_runs=object()), ConfigError, ["mc_runs=<object"]),
    (lambda: api.study("imm_baseline", scenario__R=[1, object()]), ConfigError, ["scenario.R=[1, <object"]),
    (lambda: api.study("imm_baseline", overrides={"mc_runs": object()}), ConfigError, ["mc_runs=<object"]),
])
def test_user_errors_name_the_argument_and_write_nothing(tmp_path, monkeypatch, call, error, words):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(error) as info:
        call()
    for word in words:
        assert word in str(info.value)
    if error is ConfigError:  # the message starts with the key (issue 44: mc_runs=object() did not name it)
        assert str(info.value).startswith(words[0].split("=")[0]), str(info.value)
    assert not (tmp_path / "outputs").exists()


def test_load_errors(tmp_path):
    with pytest.raises(ValueError, match="run_dir"):
        api.load(tmp_path)
    (tmp_path / "results.json").write_text("{not json")
    with pytest.raises(ValueError, match="run_dir"):
        api.load(tmp_path)
    with pytest.raises(TypeError, match="run_dir"):
        api.load(3)
    (tmp_path / "results.json").write_text(json.dumps({"experiment": "toy", "tables": {
        "t": {"columns": ["a", "b"], "rows": [[1, 2]]}}}))
    assert api.load(tmp_path).table("t")["b"].tolist() == [2]


@pytest.mark.parametrize("content, message", [
    ("[]", r"results.json: not a results file \(a JSON list, not an object\)"),
    ('"done"', r"results.json: not a results file \(a JSON str, not an object\)"),
    ("{}", r"results.json: not a results file \(no 'experiment', 'tables'\)"),
    ('{"experiment": "toy"}', r"results.json: not a results file \(no 'tables'\)"),
    ('{"experiment": "toy", "tables": []}', r"results.json: not a results file \(tables: list, not an object\)"),
    ('{"experiment": "toy", "tables": {}, "metrics": 3}', r"not a results file \(metrics: int, not an object\)"),
    ('{"experiment": "toy", "tables": {"t": {"columns": ["a"]}}}', r"not a results file \(table 't': "),
    ('{"experiment": "toy", "tables": {"t": {"columns": ["a"], "rows": [[1, 2]]}}}', r"table 't': "),
])
def test_load_names_the_path_and_what_is_wrong(tmp_path, content, message):
    """A results.json that is not a results object was a raw AttributeError or KeyError later (issue 44)."""
    (tmp_path / "results.json").write_text(content)
    with pytest.raises(ValueError, match=r"^run_dir: " + re.escape(str(tmp_path)) + ".*" + message):
        api.load(tmp_path)


def test_load_of_a_file_or_a_missing_folder_names_the_path(tmp_path):
    """A file for the run folder was a raw NotADirectoryError (issue 44)."""
    file = tmp_path / "results.json"
    file.write_text(json.dumps({"experiment": "toy", "tables": {}}))
    with pytest.raises(ValueError, match=rf"^run_dir: {re.escape(str(file))} is a file, not a run folder"):
        api.load(file)
    with pytest.raises(ValueError, match=rf"^run_dir: {re.escape(str(tmp_path / 'none'))} does not exist"):
        api.load(tmp_path / "none")
    assert api.load(tmp_path).tables == []  # the folder holding it is fine


def test_study_out_that_is_a_file_names_out(tmp_path):
    file = tmp_path / "afile"
    file.write_text("x")
    with pytest.raises(ValueError, match=r"^out: .*afile is a file, not a folder"):
        api.study("imm_baseline", out=file)

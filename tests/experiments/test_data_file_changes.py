"""A study's data files are part of its result config (experiments/folders.py, ``with_data_files``): a run on a
file whose contents changed never continues a folder computed from the old contents (``resume=latest`` or the
same ``hydra.run.dir``), and the earlier results are kept as they were."""

from __future__ import annotations

import json

import numpy as np

from experiments.folders import DATA_FILES, config_hash, latest_run, with_data_files
from experiments.run import resolve_resume, run_study
from tests.experiments.test_studies import _compose

NILE = ["learn=null", "logger=none", "progress=false", "figures=false"]


def _write(path, scale):
    flows = np.array([1120.0, 1160.0, 963.0, 1210.0, 1160.0, 1160.0, 813.0, 1230.0, 1370.0, 1140.0])
    rows = "\n".join(f"{1871 + i},{scale * f:g}" for i, f in enumerate(flows))
    path.write_text("year,flow\n" + rows + "\n")


def test_a_changed_data_file_is_another_run_and_the_old_results_stay(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    data = tmp_path / "flow.csv"
    _write(data, 1.0)
    args = ["experiment=nile", f"scenario.data.path={data.name}", *NILE]
    run_study(_compose("nile", *args[1:]), tmp_path / "outputs" / "nile" / "a")
    old = (tmp_path / "outputs" / "nile" / "a" / "results.json").read_text()
    recorded = json.loads(old)["config"][DATA_FILES]
    assert list(recorded) == ["scenario.data.path"] and recorded["scenario.data.path"].startswith("sha256:")
    # the same contents: the same result config, and resume=latest finds the folder
    assert resolve_resume([*args, "resume=latest"])[-1] == f"hydra.run.dir={(tmp_path / 'outputs/nile/a').resolve()}"

    _write(data, 2.0)  # the same path, other contents
    assert resolve_resume([*args, "resume=latest"]) == [*args, "resume=latest"]  # no run of this config: fresh
    run_study(_compose("nile", *args[1:]), tmp_path / "outputs" / "nile" / "a")
    assert (tmp_path / "outputs" / "nile" / "a" / "results.json").read_text() == old  # kept as it was
    assert (tmp_path / "outputs" / "nile" / "a_1" / "results.json").exists()
    # the new run's numbers are the new data's: those of a run on the new file in a folder of its own
    run_study(_compose("nile", *args[1:]), tmp_path / "elsewhere")
    metrics = lambda folder: json.loads((folder / "results.json").read_text())["metrics"]  # noqa: E731
    new = metrics(tmp_path / "outputs" / "nile" / "a_1")
    assert new == metrics(tmp_path / "elsewhere") != metrics(tmp_path / "outputs" / "nile" / "a")


def test_the_fingerprint_follows_the_contents_not_the_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _write(tmp_path / "one.csv", 1.0)
    _write(tmp_path / "two.csv", 1.0)
    config = {"scenario": {"data": {"path": "one.csv"}}, "seed": 0}
    same = {"scenario": {"data": {"path": "two.csv"}}, "seed": 0}
    a, b = with_data_files(config), with_data_files(same)
    assert a[DATA_FILES]["scenario.data.path"] == b[DATA_FILES]["scenario.data.path"]
    _write(tmp_path / "two.csv", 1.5)
    assert with_data_files(same)[DATA_FILES] != a[DATA_FILES]
    assert config_hash(with_data_files(same)) != config_hash(b)
    # a file that does not exist is left to the study's reader to name; the shipped data is found as the
    # readers find it
    assert DATA_FILES not in with_data_files({"scenario": {"data": {"path": "missing.csv"}}})
    assert "scenario.data.path" in with_data_files({"scenario": {"data": {"path": "nile.csv"}}})[DATA_FILES]
    assert latest_run(tmp_path / "outputs", a) is None

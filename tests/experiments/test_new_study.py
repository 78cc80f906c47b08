"""A new study in a temporary directory, in two files and no library edit (docs/studies.md, "Adding a
study", is this test): its YAML declares its keys once - their defaults type them - and its module's
``CHECKS`` range them; ``torchmm-run`` validates them before anything runs, like any shipped study."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from experiments.config import precheck
from experiments.run import CONFIG_DIR

#: file 1 of 2: the study's config (its keys, their defaults and comments: the one place they are declared)
CONFIG = """\
# @package _global_
# summary: my study: a CV Kalman filter's position RMSE against the process noise it assumes
experiment_name: ball
study: ballstudy.run
mc_runs: 50
ball:
  steps: 40          # time steps per run
  q_true: 0.5        # the target's acceleration-noise variance
  q_assumed: [0.1, 0.5, 2.0]   # the filter's, one row each
  R: 4.0             # position-measurement noise variance
"""

#: file 2 of 2: the study's code, with the ranges of its keys
MODULE = '''\
"""My study: a CV Kalman filter's position RMSE against the process noise it assumes."""
import torch

from experiments.config import positive, positive_int, each
from torchmm import ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, run_filter
from torchmm.metrics import rmse
from torchmm.simulate import simulate_jump_system, simulate_measurements

CHECKS = {"ball.steps": positive_int, "ball.q_true": positive, "ball.q_assumed": each(positive),
          "ball.R": positive}


def run(ctx):
    cfg = ctx.cfg.ball
    sensor = PositionMeasurement(2, [0], cfg.R, dtype=torch.float64)
    prior = GaussianBelief.create([0.0, 1.0], [[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    truth = simulate_jump_system(ConstantVelocity(1, q=cfg.q_true, dtype=torch.float64), [[1.0]], prior,
                                 cfg.steps, (ctx.cfg.mc_runs,), generator=ctx.generator("data"))
    z = simulate_measurements(sensor, truth.states, generator=ctx.generator("noise"))
    table = ctx.results.table("rmse", ["q_assumed", "pos_rmse"])
    for q in cfg.q_assumed:
        kf = KalmanFilter(ConstantVelocity(1, q=q, dtype=torch.float64), sensor)
        est = run_filter(kf, prior.expand(ctx.cfg.mc_runs), z).estimate()
        table.rows.append([q, rmse(est.mean, truth.states, [0]).mean().item()])
    ctx.results.save()
'''


@pytest.fixture
def study(tmp_path):
    (tmp_path / "conf" / "experiment").mkdir(parents=True)
    (tmp_path / "conf" / "experiment" / "ball.yaml").write_text(CONFIG)
    (tmp_path / "ballstudy.py").write_text(MODULE)
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert len(files) == 2  # the whole study
    sys.path.insert(0, str(tmp_path))
    yield tmp_path
    sys.path.remove(str(tmp_path))
    sys.modules.pop("ballstudy", None)


def _args(folder: Path, *overrides: str) -> list[str]:
    return ["experiment=ball", f"hydra.searchpath=[file://{folder / 'conf'}]", "logger=none", *overrides]


def test_a_new_study_runs_from_two_files(study):
    env = {**os.environ, "PYTHONPATH": f"{study}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
           "OMP_NUM_THREADS": "1"}
    out = study / "out"
    proc = subprocess.run([sys.executable, "-m", "experiments.run", *_args(study, "mc_runs=20", "progress=false",
                                                                           f"hydra.run.dir={out}")],
                          capture_output=True, text=True, env=env, cwd=Path(CONFIG_DIR).parent, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads((out / "results.json").read_text())
    rows = res["tables"]["rmse"]["rows"]
    assert [r[0] for r in rows] == [0.1, 0.5, 2.0] and all(r[1] > 0 for r in rows)
    assert res["config"]["mc_runs"] == 20
    assert "mc_runs=20" in (out / "results.md").read_text()  # results.md names what differs from the defaults


@pytest.mark.parametrize("override, message", [
    ("ball.R=abc", "ball.R=abc: expected a number"),                  # typed by its default (4.0)
    ("ball.R=-1", "ball.R=-1: must be positive"),                     # ranged by the module's CHECKS
    ("ball.q_assumed=[0.1,x]", "ball.q_assumed[1]=x: expected a number"),
    ("ball.q_assumed=0.5", "ball.q_assumed=0.5: expected a list"),
    ("ball.steps=0", "ball.steps=0: must be a positive integer"),
    ("+ball.q_asumed=[1.0]", "ball.q_asumed: unknown key (did you mean ball.q_assumed?)"),
])
def test_its_keys_are_checked_before_anything_runs(study, override, message, capsys):
    with pytest.raises(SystemExit) as exit_:
        precheck(_args(study, override), CONFIG_DIR)
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err == f"torchmm-run: error: {message}", err

"""Variable-structure estimators in the studies' configs: a policy that does not fit its bank, a repeated EqMA
model and an unreachable challenge-match threshold are one line naming the key, exit 2 and no folder (before:
a traceback at step 1 after the folder was made, or a run that counted a model twice / always fell back);
a valid ``family`` is accepted; mevsmm names what it cannot report (a short scenario's maneuver window,
table2's base) and the fraction of steps at which a challenge match fell back."""

from __future__ import annotations

import json

import pytest
import torch

from experiments.config import precheck
from experiments.run import CONFIG_DIR, run_study
from experiments.studies.mevsmm import _merge
from tests.experiments.test_studies import _compose_numbers

RUN = ["mc_runs=2", "scenario.steps=5", "logger=none", "progress=false", "figures=false"]
VS = "+estimator@estimators.VS=vsmm"
POLICY = "estimators.VS.combinator.policy="
MEV = ["experiment=mevsmm", "debug=mevsmm"]

CASES = [
    # the auditor's command lines, each once a traceback after the folder was made
    (["experiment=imm_baseline", VS, "policy=challenge_match"],
     "estimators.VS.combinator.policy={'_target_': 'torchmm.multimodel.mevsmm.ChallengeMatch'"),
    (["experiment=imm_baseline", VS, "policy=challenge_match", "mode_filter=particle",
      "mode_filter.num_particles=50"],
     "estimators.VS.combinator.policy.num_winners=420: exceeds the bank's 3 x 50 = 150 particles"),
    ([*MEV, "+mevsmm_estimator@mevsmm.estimators.KF=vsmm", "policy=challenge_match",
      "mevsmm.estimator_names=[KF]"],
     "mevsmm.estimators.KF.policy={"),
    ([*MEV, "+mevsmm_estimator@mevsmm.estimators.PFV=vsmm", "policy=challenge_match", "mode_filter=particle",
      "mode_filter.num_particles=10", "mevsmm.estimator_names=[PFV]"],
     "mevsmm.estimators.PFV.policy.num_winners=420: exceeds the bank's 21 x 10 = 210 particles"),
    (["experiment=compare", VS, POLICY + "{_target_:torchmm.multimodel.FixedSet,members:[5]}"],
     "estimators.VS.combinator.policy.members=[5]: has model index 5, out of range for the bank's 3 models"),
    (["experiment=compare", VS,
      POLICY + "{_target_:torchmm.multimodel.DropBelow,threshold:0.1,candidates:[9]}"],
     "estimators.VS.combinator.policy.candidates=[9]: has model index 9"),
    (["experiment=imm_tf", "debug=imm_tf",
      "+tf_estimators.VS={_target_:torchmm.VariableStructureIMM,_partial_:true,"
      "policy:{_target_:torchmm.multimodel.FixedSet,members:[5]}}", "estimator_names=[IMM,VS]"],
     "tf_estimators.VS.policy.members=[5]: has model index 5"),
    (["experiment=compare", VS,
      POLICY + "{_target_:torchmm.multimodel.mevsmm.ExactMinimumEntropy,_convert_:all,family:[[0,1],[7]]}"],
     "estimators.VS.combinator.policy.family=[[0, 1], [7]]: entry 1 ([7]) has model index 7"),
    (["experiment=imm_baseline", VS, "policy.family=[[0,1],[3]]"],
     "estimators.VS.combinator.policy.family=[[0, 1], [3]]: entry 1 ([3]) has model index 3"),
    (["experiment=imm_baseline", VS, "policy.family=[[0,1],[]]"], "policy.family=[[0, 1], []]: entry 1 ([])"),
    (["experiment=imm_baseline", VS, "policy=challenge_match", "+policy.family=[[0]]"],
     "policy.family=[[0]]: only torchmm.multimodel.mevsmm.ExactMinimumEntropy takes family"),
    # EqMA's models once each (before: ran, table1 counted 4 models, m1 twice)
    ([*MEV, "+mevsmm_estimator@mevsmm.estimators.E=eqma9", "mevsmm.estimators.E.models=[1,1,2]",
      "mevsmm.estimator_names=[E]"],
     "mevsmm.estimators.E.models=[1, 1, 2]: model m1 is listed more than once"),
    ([*MEV, "+mevsmm_estimator@mevsmm.estimators.E=eqma9", "mevsmm.estimators.E.models=[]",
      "mevsmm.estimator_names=[E]"], "mevsmm.estimators.E.models=[]: must not be empty"),
    # a threshold no model can reach (before: every step fell back to one model, nothing said so)
    ([*MEV, "+mevsmm_estimator@mevsmm.estimators.T=topk", "mevsmm.estimators.T.selection.threshold=100",
      "mevsmm.estimator_names=[T]"], "mevsmm.estimators.T.selection.threshold=100: exceeds num_winners (42)"),
    ([*MEV, "mevsmm.threshold=43"], "mevsmm.threshold=43: exceeds num_winners (42)"),
    (["experiment=imm_baseline", VS, "policy=challenge_match", "policy.threshold=421", "mode_filter=particle",
      "mode_filter.num_particles=200"], "policy.threshold=421: exceeds num_winners (420)"),
]


@pytest.mark.parametrize("argv, start", CASES,
                         ids=[c[1].split("=")[0] + f"-{i}" for i, c in enumerate(CASES)])
def test_each_case_is_one_line_naming_the_key_before_any_folder(tmp_path, capsys, argv, start):
    with pytest.raises(SystemExit) as stop:
        precheck([*argv, *RUN, f"hydra.run.dir={tmp_path / 'run'}"], CONFIG_DIR)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"torchmm-run: error: {start}"), err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("argv", [
    ["experiment=imm_baseline", VS, "policy.family=[[0,1],[2]]"],
    ["experiment=compare", VS,
     POLICY + "{_target_:torchmm.multimodel.mevsmm.ExactMinimumEntropy,family:[[0,1],[2]]}"],
    [*MEV, "mevsmm.threshold=42"],  # (= num_winners: reachable)
    ["experiment=imm_baseline", VS, "policy=challenge_match", "mode_filter=particle",
     "mode_filter.num_particles=140"],
], ids=["policy.family", "node family (a ListConfig)", "threshold = num_winners", "num_winners = 3 x 140"])
def test_valid_configs_pass(argv):
    precheck([*argv, *RUN], CONFIG_DIR)


def _mevsmm(tmp_path, *overrides):
    cfg = _compose_numbers("mevsmm", "debug=mevsmm", "logger=none", "mc_runs=2", *overrides)
    run_study(cfg, tmp_path)
    return json.loads((tmp_path / "results.json").read_text())


def test_mevsmm_names_a_partial_maneuver_window_and_a_missing_timing_base(tmp_path):
    """100 steps cover 81-100 s of the 81-120 s window: maneuver_pos_rmse is null and named, as is table2's
    relative_time when its base (EqMA9+1) did not run (before: both blank, nothing said)."""
    data = _mevsmm(tmp_path, "scenario.steps=100", "mevsmm.estimator_names=[PF-MEVSMM]")
    rmse = data["tables"]["rmse"]
    row = dict(zip(rmse["columns"], rmse["rows"][0]))
    assert row["maneuver_pos_rmse"] is None and row["maneuver_pos_rmse_se"] is None
    assert "81-100 s of the 81-120 s" in data["dropped"]["maneuver_pos_rmse"]
    assert "maneuver_pos_rmse_se" in data["dropped"]
    assert data["tables"]["table2"]["rows"][0][2] is None
    assert "EqMA9+1" in data["dropped"]["relative_time"]


def test_mevsmm_drops_nothing_when_the_window_and_the_base_are_there(tmp_path):
    data = _mevsmm(tmp_path, "mevsmm.estimator_names=[EqMA9+1]")  # debug: 120 steps
    assert data["dropped"] == {}
    assert data["tables"]["rmse"]["rows"][0][3] is not None and data["tables"]["table2"]["rows"][0][2] == 1.0


def test_mevsmm_names_a_run_that_ends_before_the_maneuver_window(tmp_path):
    short = _mevsmm(tmp_path, "scenario.steps=60", "mevsmm.estimator_names=[EqMA9+1]")
    assert "ends before the 81-120 s maneuver window" in short["dropped"]["maneuver_pos_rmse"]


FALLBACK = ["scenario.steps=20", "+mevsmm_estimator@mevsmm.estimators.T=topk", "mevsmm.estimator_names=[T]"]


def test_mevsmm_reports_the_fallback_fraction_of_a_challenge_match(tmp_path):
    """threshold = num_winners (top-k): a step falls back unless one model holds all 42 winners; the note
    gives the fraction, and every set then has one model (table1's count 1)."""
    data = _mevsmm(tmp_path, *FALLBACK, "mevsmm.threshold=42")
    line = next(x for x in (tmp_path / "results.md").read_text().splitlines()
                if x.startswith("- T: the challenge match fell back at "))
    assert 0 < float(line.split("fell back at ")[1].split(" %")[0]) <= 100
    assert data["tables"]["table1"]["rows"][0][1] == 1.0


def test_mevsmm_reports_a_challenge_match_that_never_fell_back(tmp_path):
    data = _mevsmm(tmp_path, *FALLBACK, "mevsmm.threshold=0")
    assert "- T: the challenge match fell back at 0.00 % of the (run, step) pairs" in \
        (tmp_path / "results.md").read_text()
    assert data["tables"]["table1"]["rows"][0][1] == 21.0  # (threshold 0: every model active)


def test_the_fallback_fraction_is_the_share_of_run_steps_over_all_units():
    """_merge over two units of runs: the fraction is the fallback count summed over steps and units over
    steps x runs (a hand count), None when a unit has no fallback flag (a policy that cannot fall back)."""
    T = 4
    flags = [torch.tensor([[1, 0], [0, 0], [1, 1], [0, 0]], dtype=torch.float64),  # unit 1: 2 runs
             torch.tensor([[0], [1], [0], [0]], dtype=torch.float64)]  # unit 2: 1 run
    parts = []
    for f in flags:
        runs = f.shape[1]
        parts.append({"pos": torch.ones(T, runs).numpy(), "vel": torch.ones(T, runs).numpy(),
                      "run_counts": torch.ones(runs).numpy(), "runs": runs, "seconds": 1.0, "hists": {},
                      "sums": {"count": torch.full((T,), float(runs)).numpy(), "fallback": f.sum(1).numpy()},
                      "sq_sums": {"count": torch.full((T,), float(runs)).numpy()}})
    assert _merge(parts, 3, None)["fallback"] == pytest.approx(4 / (T * 3))
    for p in parts:
        del p["sums"]["fallback"]
    assert _merge(parts, 3, None)["fallback"] is None

"""Study smoothing: the smoother beats the filter where theory says it must (linear-Gaussian RTS),
the extended / unscented smoothers equal RTS on these linear scenarios, and the parallel scan
agrees with the sequential smoother."""

from __future__ import annotations

import json

import pytest

from experiments.checks import ConfigError
from experiments.config import validate
from experiments.run import run_study
from tests.experiments.test_studies import _compose_numbers as _compose


def test_smoothing_study_tables(tmp_path):
    run_study(_compose("smoothing", "debug=smoothing", "smoothing.speed=true", "logger=none", "mc_runs=20",
                       "smoothing.scenarios.paper000.steps=40", "smoothing.scenarios.turning.steps=40"), tmp_path)
    tables = json.loads((tmp_path / "results.json").read_text())["tables"]
    cols = tables["rmse"]["columns"]
    rows = {(r[0], r[1]): dict(zip(cols, r)) for r in tables["rmse"]["rows"] if r[2] != "Kim"}
    kim = {(r[0], r[1]): dict(zip(cols, r)) for r in tables["rmse"]["rows"] if r[2] == "Kim"}
    assert set(kim) == {(s, e) for s in ("paper000", "paper001", "turning") for e in ("IMM", "GPB2", "IMM-UKF")}
    assert {rows[(s, e)]["smoother"] for s, e in kim} == {"two-filter"}
    assert {r["smoother"] for key, r in rows.items() if key[1] in ("KF", "EKF")} == {"RTS", "extended RTS"}
    for scenario in ("paper000", "paper001", "turning"):
        kf = rows[(scenario, "KF")]
        # RTS is the posterior mean: on 20 runs its RMSE is below the filter's, with margin
        assert kf["smoother_pos_rmse"] < 0.95 * kf["filter_pos_rmse"], kf
        assert kf["smoother_vel_rmse"] < kf["filter_vel_rmse"], kf
        for mm in ("IMM", "GPB2"):  # the two-filter smoother gains on every scenario, Kim's loses on the maneuvers
            assert rows[(scenario, mm)]["smoother_pos_rmse"] < 0.9 * rows[(scenario, mm)]["filter_pos_rmse"]
            if scenario != "paper000":
                assert rows[(scenario, mm)]["smoother_pos_rmse"] < 0.8 * kim[(scenario, mm)]["smoother_pos_rmse"]
        for same, ref in (("EKF", "KF"), ("UKF", "KF"), ("IMM-UKF", "IMM")):  # linear scenarios
            for key in ("filter_pos_rmse", "smoother_pos_rmse", "smoother_vel_rmse"):
                assert abs(rows[(scenario, same)][key] - rows[(scenario, ref)][key]) <= 1e-8 * rows[(scenario, ref)][key]
    modes = tables["modes"]
    assert {r[1] for r in modes["rows"]} == {"IMM", "GPB2", "IMM-UKF"}
    assert {r[2] for r in modes["rows"]} == {"two-filter", "Kim"}
    assert all(0 <= r[3] <= 1 and 0 <= r[4] <= 1 for r in modes["rows"])
    speed = tables["parallel_speed"]
    assert [r[0] for r in speed["rows"]] == [16, 64]
    assert all(r[-1] < 1e-9 for r in speed["rows"])  # parallel == sequential smoothed means


def test_an_estimator_without_a_smoother_is_refused_before_the_run():
    """The study smooths every estimator: an IMM over particle modes was filtered on every run, its folder
    made, and then failed with a traceback; now it is one line naming the estimator at validation
    (torchmm.smooth_checks.why_not_smoothable, tests/smoothing/test_smoothable.py)."""
    particle = "estimators.IMM.mode_filter={_target_:torchmm.ParticleFilter,_partial_:true,num_particles:50}"
    with pytest.raises(ConfigError, match=r"^estimators.IMM=experiments.estimators.multiple_model: the smoothing "
                                          r"study smooths every estimator: .*IMM's are ParticleFilter"):
        validate(_compose("smoothing", "debug=smoothing", particle))
    validate(_compose("smoothing", "debug=smoothing"))  # the study as shipped passes

"""The generic study (``experiment=compare``): recorded data equal the library API, simulated scenarios of
any list of modes and sensors, metrics and paired differences checked against hand computations."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, open_dict

from experiments.config import ConfigError, validate
from experiments.datafile import DataFileError, read_series
from experiments.run import CONFIG_DIR, run_study
from torchmm import IMM, ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, run_filter
from torchmm.simulate import simulate_jump_system, simulate_measurements

MODES = [{"_target_": "torchmm.ConstantVelocity", "ndim": 1, "q": 0.05, "acceleration": [a]} for a in (0.0, 1.0)]
SENSOR = {"_target_": "torchmm.PositionMeasurement", "state_dim": 2, "indices": [0], "R": 4.0}
TRANSITION = [[0.9, 0.1], [0.2, 0.8]]
PRIOR_MEAN, PRIOR_COV = [0.0, 1.0], [[4.0, 0.0], [0.0, 1.0]]


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose("config", overrides=["experiment=compare", "logger=none", "progress=false", *overrides])


def _library_models():
    modes = [ConstantVelocity(1, q=0.05, acceleration=[a], dtype=torch.float64) for a in (0.0, 1.0)]
    sensor = PositionMeasurement(2, [0], 4.0, dtype=torch.float64)
    return modes, sensor


def _write_csv(path: Path, z: np.ndarray, x: np.ndarray) -> None:
    """``z (T, R, 1)``, ``x (T, R, 2)`` as rows ``series, t, pos_meas, pos, vel`` (NaN: an empty cell);
    series 1 one step shorter (padding)."""
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["series", "t", "y", "pos", "vel"])
        T, R, _ = z.shape
        for r in range(R):
            for k in range(T - (1 if r == 1 else 0)):
                w.writerow([f"s{r}", k + 1, "" if math.isnan(z[k, r, 0]) else repr(float(z[k, r, 0])),
                            repr(float(x[k, r, 0])), repr(float(x[k, r, 1]))])


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A 2-mode CSV of 3 series x 25 steps with missing data, and the same data as tensors."""
    modes, sensor = _library_models()
    g = torch.Generator().manual_seed(3)
    prior = GaussianBelief.create(PRIOR_MEAN, PRIOR_COV, dtype=torch.float64)
    sim = simulate_jump_system(modes, torch.tensor(TRANSITION, dtype=torch.float64), prior, 25, (3,), generator=g)
    z = simulate_measurements(sensor, sim.states, generator=g)
    z[4, 0] = torch.nan
    z[10:13, 2] = torch.nan
    folder = tmp_path_factory.mktemp("data")
    path = folder / "track.csv"
    _write_csv(path, z.numpy(), sim.states.numpy())
    return path, z, sim.states


def _data_config(path: Path, *overrides: str):
    cfg = _compose(*overrides)
    with open_dict(cfg):
        cfg.scenario.modes = MODES
        cfg.scenario.sensors = [SENSOR]
        cfg.scenario.labels = ["a=0", "a=1"]
        cfg.scenario.transition = TRANSITION
        cfg.scenario.initial_mean = PRIOR_MEAN
        cfg.scenario.initial_cov = PRIOR_COV
        cfg.scenario.initial_mode_probs = None
        cfg.scenario.groups = {"position": [0], "velocity": [1]}
        cfg.scenario.data = {"path": str(path), "measurements": ["y"], "truth": ["pos", "vel"], "time": "t",
                             "series": "series"}
        cfg.estimators = {
            "IMM": {"_target_": "experiments.estimators.multiple_model", "_partial_": True,
                    "combinator": {"_target_": "torchmm.IMM", "_partial_": True}, "mode_filter": None},
            "KF": {"_target_": "experiments.estimators.kalman", "_partial_": True, "mode": 0},
        }
    return cfg


def test_read_series_pads_and_reads_missing(recorded):
    path, z, x = recorded
    data = read_series(path, measurements=["y"], truth=["pos", "vel"], time="t", series="series")
    assert data.measurements.shape == (25, 3, 1) and data.series == ["s0", "s1", "s2"]
    assert data.present[:, 1].sum() == 24 and not data.present[24, 1]
    np.testing.assert_array_equal(np.isnan(data.measurements[:24]), np.isnan(z.numpy()[:24]))
    np.testing.assert_array_equal(data.measurements[:24][~np.isnan(data.measurements[:24])],
                                  z.numpy()[:24][~np.isnan(z.numpy()[:24])])
    np.testing.assert_array_equal(data.times, np.arange(1, 26))


@pytest.mark.parametrize("content, message", [
    ("a,b\n1,2\n3,x\n", "column 'b', row 3: 'x' is not a number"),
    ("a,c\n1,2\n", "column 'b', row 1: not in the header"),
    ("a,b\n1,2\n3\n", "row 3: 1 cells, the header has 2"),
    ("a,b,t\n1,2,1\n3,4,1\n", "column 't', row 3: time stamps must increase"),
])
def test_malformed_file_names_file_column_and_row(tmp_path, content, message):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(DataFileError, match="bad.csv: " + message.replace("(", r"\(").replace(")", r"\)")):
        read_series(path, measurements=["a", "b"], time="t" if ",t" in content else None)


def test_malformed_file_is_a_config_error_before_anything_runs(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("series,t,y,pos,vel\ns0,1,1.0,0,0\ns0,2,oops,0,0\n")
    cfg = _data_config(path)
    with pytest.raises(ConfigError, match=r"scenario.data=.*bad.csv: column 'y', row 3: 'oops' is not a number"):
        validate(cfg)


@pytest.mark.parametrize("key", ["truth", "measurements"])
def test_a_string_for_a_list_of_columns_is_a_config_error(tmp_path, key):
    """``truth: pos`` (a string for ``[pos]``) in a study config is refused naming the key, before
    read_series (which refuses it too, naming the argument: tests/robustness/test_data_specs.py)."""
    path = tmp_path / "data.csv"
    path.write_text("series,t,y,pos,vel\ns0,1,1.0,0,0\ns0,2,2.0,0,0\n")
    cfg = _data_config(path)
    cfg.scenario.data[key] = "pos"
    with pytest.raises(ConfigError, match=rf"^scenario.data.{key}='pos': .*list"):
        validate(cfg)


def test_csv_run_equals_the_library_api(recorded, tmp_path):
    """The study on a CSV gives the log-likelihood and RMSE of the same data filtered by hand (1e-12)."""
    path, z, x = recorded
    cfg = _data_config(path, "figures=false")
    validate(cfg)
    run_study(cfg, tmp_path)
    res = json.loads((tmp_path / "results.json").read_text())
    modes, sensor = _library_models()
    transition = torch.tensor(TRANSITION, dtype=torch.float64)
    prior = GaussianBelief.create(PRIOR_MEAN, PRIOR_COV, dtype=torch.float64).expand(3)
    z_lib = z.clone()
    z_lib[24, 1] = torch.nan  # series 1 is a step shorter: its last step is padding (missing)
    imm = IMM([KalmanFilter(m, sensor) for m in modes], transition)
    traj = run_filter(imm, imm.initial_belief(prior), z_lib)
    ll = traj.log_likelihood.sum(0)
    assert res["metrics"]["IMM"]["loglik"] == pytest.approx(float(ll.mean()), rel=1e-12, abs=1e-12)
    est = traj.estimate().mean.numpy()
    sq = (est[..., 0] - x.numpy()[..., 0]) ** 2  # (T, R); the padded step is not scored
    sq[24, 1] = np.nan
    armse = np.mean(np.sqrt(np.nanmean(sq, 1)))
    assert res["metrics"]["IMM"]["rmse_position"] == pytest.approx(armse, rel=1e-12)
    kf = KalmanFilter(modes[0], sensor)
    ll_kf = run_filter(kf, prior, z_lib).log_likelihood.sum(0)
    # the paired difference of the log-likelihood: the mean of the per-run differences, with a t interval
    paired = {(r[0], r[1]): r for r in res["tables"]["paired"]["rows"]}
    d = (ll_kf - ll).numpy()
    row = paired[("loglik", "KF")]
    assert row[3] == pytest.approx(d.mean(), rel=1e-12)
    assert row[4] == pytest.approx(d.std(ddof=1) / math.sqrt(3), rel=1e-10)
    from scipy.stats import t
    assert row[6] - row[3] == pytest.approx(t.ppf(0.975, 2) * row[4], rel=1e-10)


def test_simulated_multirate_sensors_and_missing(tmp_path):
    """Two sensors (every step, and every 3rd step with 20 % missing) stacked into one stream."""
    cfg = _compose("debug=compare", "figures=false", "scenario.steps=30", "mc_runs=50")
    with open_dict(cfg):
        cfg.scenario.sensors = [
            {"_target_": "torchmm.PositionMeasurement", "state_dim": 4, "indices": [0, 2], "R": 25.0},
            {"_target_": "torchmm.RangeBearing", "state_dim": 4, "R": [[1.0, 0.0], [0.0, 1e-4]]},
        ]
        cfg.scenario.every = [1, 3]
        cfg.scenario.missing = [0.0, 0.2]
        cfg.estimators = {"IMM": {"_target_": "experiments.estimators.multiple_model", "_partial_": True,
                                  "combinator": {"_target_": "torchmm.IMM", "_partial_": True},
                                  "mode_filter": {"_target_": "torchmm.ExtendedKalmanFilter", "_partial_": True}}}
    validate(cfg)
    from experiments.harness import open_context
    config = OmegaConf.to_container(cfg, resolve=True)
    ctx = open_context(cfg, tmp_path, config, "compare")
    from experiments.studies import compare
    _, _, z, _ = compare._data(ctx, 0, 50)
    assert z.shape == (30, 50, 4)
    assert not torch.isnan(z[..., :2]).any()
    steps = torch.arange(1, 31)
    off = steps % 3 != 0
    assert torch.isnan(z[off][..., 2:]).all()
    on = z[~off][..., 2:]
    frac = torch.isnan(on[..., 0]).double().mean().item()
    assert 0.1 < frac < 0.3  # 500 draws at p = 0.2
    assert torch.equal(torch.isnan(on[..., 0]), torch.isnan(on[..., 1]))
    run_study(cfg, tmp_path / "run")
    res = json.loads((tmp_path / "run" / "results.json").read_text())
    assert math.isfinite(res["metrics"]["IMM"]["loglik"]) and math.isfinite(res["metrics"]["IMM"]["nis"])
    # NIS of 2 or 4 degrees of freedom by step: each step's band is chi2(D_t) / N_t for its runs' dofs D_t (scipy),
    # no one band in the summary (before: the band of dof 3 = the rounded mean, which no step has), said in a note
    from scipy.stats import chi2
    curves = np.load(tmp_path / "run" / "curves.npz")
    d_t = torch.isfinite(z).sum(-1).sum(1).double().numpy()  # (T,) every run has a datum at every step
    np.testing.assert_allclose(curves["nis_low/IMM"], chi2.ppf(0.025, d_t) / 50, rtol=1e-10)
    np.testing.assert_allclose(curves["nis_high/IMM"], chi2.ppf(0.975, d_t) / 50, rtol=1e-10)
    assert "nis_dof" not in res["metrics"]["IMM"] and "nis_low" not in res["metrics"]["IMM"]
    assert "IMM: nis: the steps' degrees of freedom differ (2, 4" in (tmp_path / "run" / "results.md").read_text()


def test_gpb2s_innovation_metrics_are_named_as_dropped(tmp_path):
    """GPB2 records its innovations per mode pair: no nis or whiteness_lag1, named in `dropped` (was {})."""
    cfg = _compose("debug=compare", "figures=false", "scenario.steps=10", "mc_runs=4")
    validate(cfg)
    run_study(cfg, tmp_path)
    res = json.loads((tmp_path / "results.json").read_text())
    assert "nis" not in res["metrics"]["GPB2"] and "nis" in res["metrics"]["IMM"]
    assert {"nis (GPB2)", "whiteness_lag1 (GPB2)"} <= set(res["dropped"])
    assert not any("IMM" in key or "KF" in key for key in res["dropped"])


def test_bad_estimator_and_reference_are_config_errors():
    with pytest.raises(ConfigError, match="paired.reference"):
        validate(_compose("paired.reference=nope"))
    with pytest.raises(ConfigError, match="metrics"):
        validate(_compose("metrics=[rmse,bogus]"))
    with pytest.raises(ConfigError, match="estimators.IMM.smooth"):
        validate(_compose("estimators.IMM.smooth=rts"))
    # "<name> smoothed" names the smoothed trajectory of an estimator that smooths, no other (before: any name
    # ending in " smoothed" passed, and the study failed after filtering with a traceback and a folder left)
    validate(_compose("paired.reference=IMM smoothed"))  # (compare.yaml: IMM smooths)
    for ref in ("KF-CV smoothed", "nope smoothed"):
        with pytest.raises(ConfigError, match=f"^paired.reference={ref}: .*needs its smooth: true"):
            validate(_compose(f"paired.reference={ref}"))


def test_the_information_form_smoother_from_config(tmp_path):
    """``smooth: two_filter_info`` scores the information-form two-filter smoother
    (torchmm/two_filter_info.py; its own tests in tests/smoothing/test_two_filter_info.py) as
    ``IMM smoothed``, whose figures differ from the default two-filter reading's on the turning modes; a mode
    filter it cannot take, or a smoother's method on one filter, is one line naming the key before any
    folder (a single filter's smooth: kim failed after the filtering with a traceback)."""
    base = ("debug=compare", "figures=false", "scenario.steps=12", "mc_runs=6")
    runs = {}
    for method in ("two_filter", "two_filter_info"):
        cfg = _compose(*base, f"estimators.IMM.smooth={method}")
        validate(cfg)
        run_study(cfg, tmp_path / method)
        runs[method] = json.loads((tmp_path / method / "results.json").read_text())["metrics"]["IMM smoothed"]
    assert runs["two_filter"]["rmse_position"] != runs["two_filter_info"]["rmse_position"]
    with pytest.raises(ConfigError, match=r"^estimators.IMM.smooth=two_filter_info: needs IMM, GPB1 or GPB2 over "
                                          r"Kalman mode filters, not .*ExtendedKalmanFilter"):
        validate(_compose(*base, "estimators.IMM.smooth=two_filter_info", "mode_filter=extended"))
    with pytest.raises(ConfigError, match=r"^estimators.KF-CV-q.smooth=kim: picks a multiple-model smoother"):
        validate(_compose(*base, "+estimators.KF-CV-q.smooth=kim"))


def test_particle_estimators_do_not_depend_on_unit_runs(tmp_path):
    """Each block of ``block_runs`` runs is filtered on its own stream, as the other studies do
    (experiments.estimators.random_blocks): the same figures whatever ``unit_runs``. Before, a unit's runs
    shared its first block's stream (IMM position RMSE 6.2846 at unit_runs=2, 5.3970 at 4). A particle filter
    smoothed by FFBSm (each block with its own record) too."""
    pf = ("+estimators.PF={_target_:experiments.estimators.custom,_partial_:true,filter:{_target_:torchmm."
          "ParticleFilter,motion:{_target_:torchmm.LinearMotion,F:[[1,1,0,0],[0,1,0,0],[0,0,1,1],[0,0,0,1]],"
          "Q:[[0.5,0.1,0,0],[0.1,0.4,0,0],[0,0,0.5,0.1],[0,0,0.1,0.4]]},measurement:${scenario.sensors.0},"
          "num_particles:40},smooth:true}")
    base = ("debug=compare", "figures=false", "scenario.steps=10", "mc_runs=4", "block_runs=2",
            "mode_filter=particle", "mode_filter.num_particles=40", "estimators.IMM.smooth=false",
            "metrics=[rmse,loglik]", pf)
    tables = []
    for units in (2, 4):
        run_study(_compose(*base, f"unit_runs={units}"), tmp_path / str(units))
        tables.append(json.loads((tmp_path / str(units) / "results.json").read_text())["tables"]["summary"])
    drop = [i for i, c in enumerate(tables[0]["columns"]) if "time" in c or "second" in c]
    rows = [[[v for i, v in enumerate(r) if i not in drop] for r in t["rows"]] for t in tables]
    assert rows[0] == rows[1]
    assert {r[0] for r in tables[0]["rows"]} >= {"IMM", "PF", "PF smoothed"}


def test_a_smoother_that_does_not_exist_is_refused_before_the_run():
    """``smooth: true`` over filters torchmm.smooth has no backward pass for (an IMM over particle modes: the
    default study with ``mode_filter=particle``; a variable-structure IMM; FFBSm over a singular process
    noise) is one line naming the key at validation (they filtered every run, made the folder, then failed
    with a traceback: torchmm.smooth_checks.why_not_smoothable, tests/smoothing/test_smoothable.py)."""
    base = ("debug=compare", "figures=false", "scenario.steps=12", "mc_runs=2")
    with pytest.raises(ConfigError, match=r"^estimators.IMM.smooth=True: the multiple-model smoothers need "
                                          r"Gaussian mode filters .*IMM's are ParticleFilter"):
        validate(_compose(*base, "mode_filter=particle"))
    validate(_compose(*base, "mode_filter=particle", "estimators.IMM.smooth=false"))  # the way out it names
    with pytest.raises(ConfigError, match=r"^estimators.VS.smooth=True: no smoother for VariableStructureIMM"):
        validate(_compose(*base, "+estimator@estimators.VS=vsmm", "+estimators.VS.smooth=true"))
    pf = ("+estimators.PF={_target_:experiments.estimators.custom,_partial_:true,filter:{_target_:torchmm."
          "ParticleFilter,motion:${scenario.modes.0},measurement:${scenario.sensors.0},num_particles:50},"
          "smooth:true}")
    with pytest.raises(ConfigError, match=r"^estimators.PF.smooth=True: FFBSm .* positive-definite process noise"):
        validate(_compose(*base, pf))


def _irregular(tmp_path: Path, seed: int, T: int) -> tuple[list[float], torch.Tensor, Any]:
    """Two series of ``T`` irregularly stamped measurements (steps of 0.5, 1 or 2) in a CSV without truth:
    ``(dts, z (T, 2, 1), the study's config over it)``."""
    g = torch.Generator().manual_seed(seed)
    dts = [1.0] + [float(d) for d in torch.tensor([0.5, 1.0, 2.0])[torch.randint(0, 3, (T - 1,), generator=g)]]
    t = np.cumsum(dts)
    z = torch.randn(T, 2, 1, generator=g, dtype=torch.float64) * 3
    path = tmp_path / "irregular.csv"
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["series", "t", "y"])
        for r in range(2):
            for k in range(T):
                w.writerow([r, repr(float(t[k])), repr(float(z[k, r, 0]))])
    cfg = _data_config(path, "figures=false", "metrics=[loglik]")
    with open_dict(cfg):
        cfg.scenario.data.truth = None
    return dts, z, cfg


def _per_step_loglik(sensor, dts: list[float], z: torch.Tensor) -> float:
    """The library's IMM log-likelihood of ``z`` (summed over the series) with one motion model per step
    (step 0: the first step's length)."""
    def bank(dt):
        return [ConstantVelocity(1, dt=dt, q=0.05, acceleration=[a], dtype=torch.float64) for a in (0.0, 1.0)]

    imm = IMM([KalmanFilter(m, sensor) for m in bank(1.0)], torch.tensor(TRANSITION, dtype=torch.float64))
    prior = GaussianBelief.create(PRIOR_MEAN, PRIOR_COV, dtype=torch.float64).expand(2)
    traj = run_filter(imm, imm.initial_belief(prior), z, motions=[bank(dts[1])] + [bank(d) for d in dts[1:]])
    return float(traj.log_likelihood.sum())


def test_irregular_time_stamps_become_per_step_motions(tmp_path):
    """Irregular time stamps: step k predicts over t_k - t_{k-1}, step 0 over the first step's length
    t_1 - t_0 (as on a regular grid); equal to per-step models by hand."""
    dts, z, cfg = _irregular(tmp_path, 5, 15)
    validate(cfg)
    run_study(cfg, tmp_path / "run")
    res = json.loads((tmp_path / "run" / "results.json").read_text())
    _, sensor = _library_models()

    def bank(dt):
        return [ConstantVelocity(1, dt=dt, q=0.05, acceleration=[a], dtype=torch.float64) for a in (0.0, 1.0)]

    imm = IMM([KalmanFilter(m, sensor) for m in bank(1.0)], torch.tensor(TRANSITION, dtype=torch.float64))
    prior = GaussianBelief.create(PRIOR_MEAN, PRIOR_COV, dtype=torch.float64).expand(2)
    traj = run_filter(imm, imm.initial_belief(prior), z, motions=[bank(dts[1])] + [bank(d) for d in dts[1:]])
    assert res["metrics"]["IMM"]["loglik"] == pytest.approx(float(traj.log_likelihood.sum(0).mean()), rel=1e-12)
    regular = run_filter(imm, imm.initial_belief(prior), z).log_likelihood.sum(0).mean()
    assert abs(float(regular) - res["metrics"]["IMM"]["loglik"]) > 1e-3  # the time stamps mattered
    assert set(res["metrics"]["IMM"]) >= {"loglik"} and "rmse_position" not in res["metrics"]["IMM"]


def test_a_learned_module_mode_by_target(tmp_path):
    """A mode that is an ``nn.Module`` given by ``_target_`` (LearnedMotion over a torch module), simulated
    and filtered by an extended-Kalman IMM: the study's log-likelihood equals the library API's on its data."""
    from torchmm import ExtendedKalmanFilter, LearnedMotion

    q = [[0.01, 0, 0, 0], [0, 0.04, 0, 0], [0, 0, 0.01, 0], [0, 0, 0, 0.04]]
    cfg = _compose("debug=compare", "figures=false", "scenario.steps=20", "mc_runs=6", "metrics=[loglik,rmse]")
    with open_dict(cfg):
        cfg.scenario.modes = [
            {"_target_": "torchmm.ConstantVelocity", "ndim": 2, "q": 0.01},
            {"_target_": "torchmm.LearnedMotion", "net": {"_target_": "torch.nn.Identity"}, "state_dim": 4,
             "Q": q, "noise": "fixed"},
        ]
        cfg.scenario.labels = ["CV", "learned"]
        cfg.scenario.transition = [[0.9, 0.1], [0.1, 0.9]]
        cfg.scenario.initial_mode_probs = None
        cfg.estimators = {"IMM-EKF": {"_target_": "experiments.estimators.multiple_model", "_partial_": True,
                                      "combinator": {"_target_": "torchmm.IMM", "_partial_": True},
                                      "mode_filter": {"_target_": "torchmm.ExtendedKalmanFilter", "_partial_": True}}}
    validate(cfg)
    from experiments.context import open_context
    from experiments.studies import compare

    ctx = open_context(cfg, tmp_path, OmegaConf.to_container(cfg, resolve=True), "compare")
    _, _, z, _ = compare._data(ctx, 0, 6)
    run_study(cfg, tmp_path / "run")
    res = json.loads((tmp_path / "run" / "results.json").read_text())
    sensor = PositionMeasurement(4, [0, 2], 25.0, dtype=torch.float64)
    learned = LearnedMotion(torch.nn.Identity(), 4, torch.tensor(q, dtype=torch.float64), noise="fixed")
    modes = [ConstantVelocity(2, q=0.01, dtype=torch.float64), learned]
    imm = IMM([ExtendedKalmanFilter(m, sensor) for m in modes], torch.tensor([[0.9, 0.1], [0.1, 0.9]],
                                                                             dtype=torch.float64))
    prior = GaussianBelief.create(list(cfg.scenario.initial_mean), [list(r) for r in cfg.scenario.initial_cov],
                                  dtype=torch.float64).expand(6)
    ll = run_filter(imm, imm.initial_belief(prior), z).log_likelihood.sum(0).mean()
    assert res["metrics"]["IMM-EKF"]["loglik"] == pytest.approx(float(ll), rel=1e-12)


def test_learning_the_sensor_with_irregular_time_stamps(tmp_path):
    """Irregular time stamps and `learn:` (issue 45: refused before): the per-step motion models stay fixed and
    the sensor's R is estimated through them - the fit's log-likelihood is the library's with per-step models
    at the learned R, above the one at the start R; a motion model's tensors are refused with the reason."""
    from experiments.config import ConfigError

    dts, z, cfg = _irregular(tmp_path, 6, 40)
    with open_dict(cfg):
        cfg.learn = {"parameters": [{"model": "sensors[0]", "name": "R"}], "estimators": ["IMM"], "method": "mle"}
    validate(cfg)
    run_study(cfg, tmp_path / "run")
    res = json.loads((tmp_path / "run" / "results.json").read_text())
    learned = [row for row in res["tables"]["learned"]["rows"] if row[0] == "IMM"]
    assert len(learned) == 1
    r = learned[0][2]
    fit = dict(zip(res["tables"]["fit"]["columns"], res["tables"]["fit"]["rows"][0]))

    def loglik(variance):
        return _per_step_loglik(PositionMeasurement(2, [0], variance, dtype=torch.float64), dts, z)

    assert fit["loglik"] == pytest.approx(loglik(r), rel=1e-9)
    assert loglik(r) > loglik(4.0) and loglik(r) >= max(loglik(0.9 * r), loglik(1.1 * r))
    with open_dict(cfg):
        cfg.learn.parameters = [{"model": "modes[0]", "name": "Q"}]
    with pytest.raises(ConfigError, match="learn.parameters=modes\\[0\\]: a motion model's tensors with irregular"):
        validate(cfg)  # (the dry build: before any folder)


def test_trailing_rows_without_a_measurement_leave_the_smoother_as_it_is(tmp_path):
    """Rows after a series' last measurement (their truth kept: scored as the filter's predictions) carry
    nothing about the earlier steps: Kim's smoother on 25 rows with data and 15 empty ones gives, over the 25,
    the numbers of the 25 rows alone (it ran back through the empty rows: at the last row with data an
    audit's study measured a position error of 93.8 for 3.7)."""
    modes, sensor = _library_models()
    g = torch.Generator().manual_seed(11)
    prior = GaussianBelief.create(PRIOR_MEAN, PRIOR_COV, dtype=torch.float64)
    transition = torch.tensor(TRANSITION, dtype=torch.float64)
    sim = simulate_jump_system(modes, transition, prior, 40, (2,), generator=g)
    z = simulate_measurements(sensor, sim.states, generator=g).numpy()
    z[25:] = np.nan
    curves = {}
    x = sim.states.numpy()
    for label, steps in (("short", 25), ("long", 40)):
        path = tmp_path / f"{label}.csv"
        with path.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["series", "t", "y", "pos", "vel"])
            w.writerows([f"s{r}", k + 1, "" if math.isnan(z[k, r, 0]) else repr(float(z[k, r, 0])),
                         repr(float(x[k, r, 0])), repr(float(x[k, r, 1]))]
                        for r in range(2) for k in range(steps))
        cfg = _data_config(path, "figures=false")
        with open_dict(cfg):
            cfg.estimators.IMM.smooth = "kim"
            del cfg.estimators["KF"]
        run_study(cfg, tmp_path / label)
        curves[label] = pd.read_csv(tmp_path / label / "curves.csv")

    def smoothed(frame):
        rows = frame[(frame.quantity == "rmse_position") & (frame.series == "IMM smoothed")].set_index("x")
        return rows["value"].loc[:25].to_numpy()

    np.testing.assert_allclose(smoothed(curves["long"]), smoothed(curves["short"]), rtol=1e-9, atol=1e-9)
    assert len(smoothed(curves["long"])) == 25

"""Every conf/experiment/*.yaml composes and runs with a tiny mc_runs; CLI, sweeps and resume."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from experiments.run import CONFIG_DIR, run_study
from tests.regression.compare import mismatches
from tests.regression.record import COMMON

EXPERIMENTS = sorted(p.stem for p in (Path(CONFIG_DIR) / "experiment").glob("*.yaml"))
SCHEMA = {"experiment", "config", "metrics", "tables", "timing", "provenance", "dropped"}
#: per-study overrides that keep the fast suite fast (the structure is unchanged)
#: every study's tiny sizes: the conf/debug group (the structure is unchanged)
FAST = {name: [f"debug={name}"] for name in EXPERIMENTS}
FAST["smoothing"] += ["smoothing.speed=true"]  # the parallel scan's table at its debug sizes (16 and 64 steps)
TF_TABLES = {
    "table1": ["source_ratio", "estimator", "pos_rmse", "vel_rmse"],
    "rs_sweep": ["R_S", "estimator", "pos_rmse", "vel_rmse"],
}
REQUIRED_TABLES = {
    "imm_baseline": {"rmse": ["estimator", "pos_rmse", "vel_rmse"]},
    "quickstart": {"rmse": ["estimator", "pos_rmse", "vel_rmse", "nees", "mode_accuracy"]},
    "imm_analysis": {
        "conclusions": ["conclusion", "premise_steps", "holds_fraction"],
        "alpha_sweep": ["alpha", "estimator", "pos_rmse", "vel_rmse"],
    },
    "imm_tf": TF_TABLES,
    "imm_tf_quick": TF_TABLES,
    "fusion_radar": {"ex1_rmse": ["estimator", "pos_rmse"]},
    "fusion_ups": {"ex2_variance": ["estimator", "comp1", "comp2", "comp3"],
                   "ex2_mc": ["estimator", "comp1", "comp2", "comp3"],
                   "ex2_horizon": ["N", "comp1", "comp2", "comp3"]},
    "gimmaf": {"table2": ["estimator", "pos_armse", "vel_armse"],
               "table4": ["noise", "estimator", "pos_armse"],
               "srnfn": ["estimator", "srnfn_P", "srnfn_R"]},
    "vbakf_huang": {"table1": ["estimator", "pos_armse", "vel_armse"]},
    "learn_dynamics": {"learn": ["quantity", "true", "learned", "initial"],
                       "rmse": ["estimator", "pos_rmse", "vel_rmse"]},
    "mevsmm": {"rmse": ["estimator", "pos_rmse", "vel_rmse", "maneuver_pos_rmse"],
               "table1": ["estimator", "avg_model_count"],
               "table2": ["estimator", "seconds_per_step", "relative_time"]},
    "tracking": {"gospa": ["estimator", "gospa", "gospa_se", "localisation", "missed", "false", "label_switches",
                           "lost_fraction", "first_track_delay"]},
    "smoothing": {"rmse": ["scenario", "estimator", "filter_pos_rmse", "smoother_pos_rmse"],
                  "modes": ["scenario", "estimator", "filter_mode_accuracy", "smoother_mode_accuracy"],
                  "parallel_speed": ["steps", "runs", "sequential_seconds", "parallel_seconds"]},
}


#: curves without a Monte Carlo uncertainty partner, per study: ``(regex on the tag, reason)``. Every
#: other curve ``<q>/<s>`` of every study must come with ``<q>_se/<s>`` (a 95 % band) or with
#: ``<q>_low/<s>`` and ``<q>_high/<s>`` (an interval), or be such a partner itself (issue 30)
RUN_ZERO = "one run (run 0), shown as an example: no Monte Carlo uncertainty"
EXEMPT: dict[str, list[tuple[str, str]]] = {
    "compare": [(r"^mode_probability/", RUN_ZERO)],
    "fedfunds": [(r"^mode_probability/", "one recorded series (real data): no Monte Carlo runs")],
    "markov_switching": [(r"^mode_probability/", "one recorded series (real data): no Monte Carlo runs")],
    "fusion_ups": [(r"^variance/comp[123]/", ("the filters' computed variances P(t|t): exact (no Monte Carlo); "
                                              "the Monte Carlo variances are tables with their _se"))],
    "smoothing": [(r"^parallel_time_ratio/", ("wall-clock timing (best of repeats) over the swept step count, "
                                             "not a Monte Carlo mean (smoothing.speed)"))],
    "learn_dynamics": [(r"^training_(loss|grad_norm)/part_[ab]$", "training curve over the iterations (one fit)"),
                       (r"^training_param/part_[ab]/", "a learned parameter over the iterations (one fit)")],
}


def uncovered_curves(name: str, curves) -> list[str]:
    """The curves of study ``name`` without an uncertainty partner and not in :data:`EXEMPT`."""
    import re

    def partner(tag: str) -> bool:  # is an uncertainty of a curve (its _se, _low or _high)
        base, _, series = tag.partition("/")
        return any(base.endswith(suffix) and f"{base[:-len(suffix)]}/{series}" in curves
                   for suffix in ("_se", "_low", "_high"))

    exempt = EXEMPT.get(name, [])
    missing = []
    for tag in curves:
        base, _, series = tag.partition("/")
        if partner(tag) or any(re.search(pattern, tag) for pattern, _ in exempt):
            continue
        if f"{base}_se/{series}" in curves or (f"{base}_low/{series}" in curves and f"{base}_high/{series}" in curves):
            continue
        missing.append(tag)
    return missing


def test_uncertainty_exemptions_are_studies_with_reasons():
    assert set(EXEMPT) <= set(EXPERIMENTS)
    assert all(pattern and len(reason) > 20 for rules in EXEMPT.values() for pattern, reason in rules)


def _compose(name: str, *overrides: str):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose("config", overrides=[f"experiment={name}", *overrides])


def _compose_numbers(name: str, *overrides: str):
    """:func:`_compose` with ``figures=false``, for tests of numbers, not artefacts (drawing a study's
    figures costs about as much as its filtering at test sizes)."""
    return _compose(name, "figures=false", *overrides)


def test_every_experiment_has_required_tables_listed():
    assert set(EXPERIMENTS) >= set(REQUIRED_TABLES)


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_composes_and_runs(name, tmp_path):
    """Every study runs, writes every artefact, and gives the recorded numbers (tests/regression)."""
    cfg = _compose(name, *COMMON, "logger=tensorboard", *FAST.get(name, []))
    results = run_study(cfg, tmp_path)
    data = json.loads((tmp_path / "results.json").read_text())
    assert set(data) == SCHEMA
    assert data["experiment"] == name
    assert data["config"]["mc_runs"] == 4
    for table, columns in REQUIRED_TABLES.get(name, {}).items():
        assert table in data["tables"], table
        got = data["tables"][table]["columns"]
        assert got[: len(columns)] == columns or set(columns) <= set(got), (table, got)
        assert data["tables"][table]["rows"], f"{table} is empty"
    assert (tmp_path / "results.md").read_text().startswith(f"# {name}")
    assert list((tmp_path / "figures").glob("*.png"))
    assert len(list((tmp_path / "tb").glob("events.out.tfevents.*"))) == 1  # one event file per run
    assert results.tables
    assert not mismatches(name, data), "\n".join(mismatches(name, data)[:20])
    # every study writes its curves as data, each with its axis, and figures drawn from them
    from experiments.plot import load_curves

    curves = load_curves(tmp_path)
    assert curves, f"{name} writes no curves"
    for tag, (axis, x, values) in curves.items():
        assert len(x) == len(values) > 0, tag
        assert axis != "step" or list(x) == list(range(int(x[0]), int(x[0]) + len(x))), tag
        base, _, series = tag.partition("/")
        if base.endswith("_se") and f"{base[:-3]}/{series}" in curves:  # a band: same x as its curve
            assert list(curves[f"{base[:-3]}/{series}"][1]) == list(x), tag
    # every Monte Carlo curve shows its uncertainty: a band, an interval, or a listed reason (EXEMPT)
    missing = uncovered_curves(name, curves)
    assert not missing, f"{name}: curves without _se or _low/_high partner and not in EXEMPT: {missing[:10]}"
    for pattern, reason in EXEMPT.get(name, []):  # an exemption that matches nothing is stale
        import re

        assert any(re.search(pattern, tag) for tag in curves), (name, pattern, reason)
    assert list((tmp_path / "figures" / "curves").glob("*.png"))


def test_figures_false_draws_nothing_and_changes_no_number(tmp_path):
    """``figures=false``: no PNG/PDF and no TensorBoard image, the same numbers; with figures, the
    TensorBoard image is the saved PNG itself (its bytes, not a second rendering)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    base = ["mc_runs=3", "progress=false", "logger=tensorboard", *FAST["imm_baseline"]]
    drawn = run_study(_compose("imm_baseline", *base), tmp_path / "drawn")
    bare = run_study(_compose("imm_baseline", *base, "figures=false"), tmp_path / "bare")
    assert drawn.tables["rmse"].rows == bare.tables["rmse"].rows
    assert not (tmp_path / "bare" / "figures").exists()
    assert (tmp_path / "bare" / "curves.npz").exists()  # the curves are data, figures or not
    png = tmp_path / "drawn" / "figures" / "rmse_over_time.png"
    assert png.exists() and png.with_suffix(".pdf").exists()
    images = {}
    for name in ("drawn", "bare"):
        events = EventAccumulator(str(tmp_path / name / "tb"), size_guidance={"images": 0})
        events.Reload()
        images[name] = {tag: events.Images(tag) for tag in events.Tags()["images"]}
    assert images["bare"] == {}
    logged = images["drawn"]["figures/rmse_over_time"][-1]
    assert logged.encoded_image_string == png.read_bytes()
    from PIL import Image

    with Image.open(png) as im:
        assert (logged.width, logged.height) == im.size


def test_imm_analysis_conclusions_hold(tmp_path):
    cfg = _compose_numbers("imm_analysis", "mc_runs=6", "progress=false", "logger=none", *FAST["imm_analysis"])
    results = run_study(cfg, tmp_path)
    rows = {row[0]: row for row in results.tables["conclusions"].rows}
    for conclusion in (1, 2, 3, 4, 5):
        premise, fraction = rows[conclusion][1], rows[conclusion][2]
        assert premise > 0, f"Conclusion {conclusion}: premise never held"
        assert fraction == 1.0, f"Conclusion {conclusion} held on {fraction:.4f} of premise steps"
    estimators = {row[2] for row in results.tables["alpha_sweep"].rows}
    assert {"IMM", "GPB1"} <= estimators


def test_imm_baseline_estimators_and_timing(tmp_path):
    cfg = _compose_numbers("imm_baseline", "mc_runs=5", "progress=false", "logger=none")
    results = run_study(cfg, tmp_path)
    names = [row[0] for row in results.tables["rmse"].rows]
    assert names == ["IMM", "GPB1", "GPB2", "KF"]
    assert set(results.timing) == set(names) and all(t > 0 for t in results.timing.values())
    for row in results.tables["rmse"].rows:
        assert 0 < row[1] < 50 and 0 < row[2] < 20  # finite, sane RMSEs


def test_same_seed_same_numbers_and_chunking_is_transparent(tmp_path):
    a = run_study(_compose_numbers("imm_baseline", "mc_runs=6", "progress=false", "logger=none"), tmp_path / "a")
    b = run_study(_compose_numbers("imm_baseline", "mc_runs=6", "progress=false", "logger=none", "chunk_runs=4"),
                  tmp_path / "b")
    c = run_study(_compose_numbers("imm_baseline", "mc_runs=6", "progress=false", "logger=none", "seed=1"),
                  tmp_path / "c")
    rows_a, rows_b = a.tables["rmse"].rows, b.tables["rmse"].rows
    for ra, rb in zip(rows_a, rows_b):
        assert ra[1] == pytest.approx(rb[1], rel=1e-12) and ra[2] == pytest.approx(rb[2], rel=1e-12)
    assert rows_a[0][1] != c.tables["rmse"].rows[0][1]


def test_resume_skips_finished_units(tmp_path, monkeypatch):
    overrides = ["mc_runs=3", "progress=false", "logger=none", *FAST["imm_analysis"]]
    first = run_study(_compose("imm_analysis", *overrides), tmp_path)
    assert json.loads((tmp_path / "checkpoint.json").read_text())["units"]

    import experiments.studies.imm_analysis as study

    def fail(*args, **kwargs):
        raise AssertionError("a finished unit was recomputed")

    monkeypatch.setattr(study, "_analyse", fail)
    second = run_study(_compose("imm_analysis", *overrides), tmp_path)
    assert second.tables["alpha_sweep"].rows == first.tables["alpha_sweep"].rows
    # a different config does not reuse the checkpoint
    with pytest.raises(AssertionError, match="recomputed"):
        run_study(_compose("imm_analysis", *overrides, "seed=5"), tmp_path)


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("torchmm-run")
    env = {**os.environ, "HYDRA_FULL_ERROR": "1"}
    return subprocess.run([str(exe), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def test_cli_default_study_writes_every_artefact(tmp_path):
    out = tmp_path / "run"
    proc = _cli("mc_runs=3", "progress=false", f"hydra.run.dir={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    data = json.loads((out / "results.json").read_text())
    assert data["experiment"] == "quickstart"  # IMM against a Kalman filter on a maneuvering target, seconds
    assert {"rmse"} <= set(data["tables"])
    assert (out / "results.md").exists()
    assert (out / "figures" / "rmse_over_time.png").exists()
    assert list((out / "tb").glob("events.out.tfevents.*"))
    assert (out / ".hydra" / "config.yaml").exists()


def test_python_module_entry_point(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.run", "mc_runs=2", "progress=false", "logger=none",
         f"hydra.run.dir={out}"],
        cwd=Path(CONFIG_DIR).parent, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (out / "results.json").exists()


def test_joblib_multirun_sweep(tmp_path):
    sweep = tmp_path / "sweep"
    proc = _cli("-m", "experiment=imm_baseline", "mc_runs=2,3", "progress=false", "logger=none",
                f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Joblib" in proc.stdout + proc.stderr
    runs = sorted(json.loads(p.read_text())["config"]["mc_runs"] for p in sweep.glob("*/results.json"))
    assert runs == [2, 3]


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="needs CUDA (runs where a GPU is present)")
@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_runs_on_cuda(name, tmp_path):
    """Every study runs with ``device=cuda`` at its debug sizes (the data are simulated on the CPU and
    moved, so the numbers agree with the CPU record within the Monte Carlo tolerance of 4 runs)."""
    cfg = _compose(name, *COMMON, "device=cuda", *FAST.get(name, []))
    run_study(cfg, tmp_path)
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["provenance"]["device"].startswith("cuda"), data["provenance"]
    for table in REQUIRED_TABLES.get(name, {}):
        assert data["tables"][table]["rows"], f"{table} is empty on CUDA"

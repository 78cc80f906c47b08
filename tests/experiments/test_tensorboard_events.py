"""A run's TensorBoard events (docs/studies.md, "tb/"): every finite headline metric as a scalar and in the
HPARAMS row (before: the first 64 only), and one event file per run also when the run is continued in its
folder (before: a second SummaryWriter in tb/ showed every point and the hparams row twice)."""

from __future__ import annotations

import math
from collections import Counter

import pytest

from experiments.loggers import SUPERSEDED, TensorBoardLogger
from experiments.results import Results
from experiments.run import hparams, run_study
from tests.experiments.test_studies import _compose


def _scalars(folder):
    """``{tag: [(step, value), ...]}`` of every scalar event under ``folder`` (the files directly in it,
    as TensorBoard reads one run's folder)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(folder), size_guidance={"scalars": 0, "tensors": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def _session_starts(folder) -> int:
    """How many hparams rows (``_hparams_/session_start_info`` summaries) the event files in ``folder``
    hold."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    return sum(value.tag == "_hparams_/session_start_info" for path in folder.glob("*tfevents*")
               for event in EventFileLoader(str(path)).Load() for value in event.summary.value)


def test_every_finite_headline_metric_is_logged(tmp_path):
    """100 finite metrics over 5 estimators (the compare study has 80) and 3 that are not finite numbers:
    hparams() returns the 100, and TensorBoardLogger.hparams writes each as a scalar (before: 64)."""
    results = Results(tmp_path, "toy", {})
    want = {}
    for e in range(5):
        for m in range(20):
            value = (e + 1) * 0.5 + m / 7
            results.metric(f"E{e}", f"m{m}", value)
            want[f"headline/E{e}/m{m}"] = value
    results.metric("E0", "nan", float("nan"))
    results.metric("E1", "none", None)
    results.metric("E2", "inf", float("inf"))
    settings, metrics = hparams({"seed": 3}, [], results)
    assert settings == {"experiment": "toy", "seed": 3}
    assert metrics == want
    logger = TensorBoardLogger(tmp_path / "tb", flush_secs=1)
    logger.hparams(settings, metrics)
    logger.close()
    scalars = _scalars(tmp_path / "tb")
    got = {tag: points for tag, points in scalars.items() if tag.startswith("headline/")}
    assert set(got) == set(want)
    assert all(len(got[t]) == 1 and got[t][0][1] == pytest.approx(want[t], rel=1e-6) for t in want)


def test_a_continued_run_has_each_point_once_and_keeps_the_earlier_events(tmp_path):
    """run_study twice into one folder (what resume=latest on a finished run and a sweep re-run into its
    hydra.sweep.dir do): tb/ holds one event file, each scalar once per step and one hparams row; the
    first execution's events are kept under tb/superseded/1/, under names TensorBoard does not read."""
    cfg = _compose("imm_baseline", "debug=imm_baseline", "logger=tensorboard", "figures=false",
                   "progress=false")
    run_study(cfg, tmp_path / "run")
    first = _scalars(tmp_path / "run" / "tb")
    run_study(cfg, tmp_path / "run")
    tb = tmp_path / "run" / "tb"
    assert len([p for p in tb.iterdir() if "tfevents" in p.name]) == 1
    second = _scalars(tb)
    assert set(second) == set(first) and "pos_rmse/IMM" in second
    for tag, points in second.items():
        steps = Counter(step for step, _ in points)
        assert max(steps.values()) == 1, (tag, steps.most_common(1))
        assert len(points) == len(first[tag])
        assert all(math.isclose(a, b, rel_tol=1e-6) or (math.isnan(a) and math.isnan(b))
                   for (_, a), (_, b) in zip(points, first[tag]))
    assert _session_starts(tb) == 1  # one HPARAMS row (before: 2)
    kept = sorted((tb / SUPERSEDED).rglob("*"))
    assert [p.relative_to(tb).parts[:2] for p in kept if p.is_file()] == [(SUPERSEDED, "1")]
    assert not any("tfevents" in p.name for p in kept)  # TensorBoard reads files named *tfevents* only
    restored = tmp_path / "restored"
    restored.mkdir()
    (file,) = [p for p in kept if p.is_file()]
    (restored / file.name.replace(SUPERSEDED, "tfevents")).write_bytes(file.read_bytes())
    assert _scalars(restored) == first  # the earlier execution's events, kept whole


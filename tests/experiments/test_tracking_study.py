"""The tracking study's births and deaths and its managed tracker (issue 32; docs/tracking.md)."""

from __future__ import annotations

import json

import pytest
import torch
from omegaconf import OmegaConf

from experiments.plot import load_curves
from experiments.run import run_study
from experiments.studies import tracking
from tests.experiments.test_studies import _compose
from tests.regression.record import COMMON

LIVES = [[0, 24], [6, 24], [0, 16]]  # target 1 appears at scan 6, target 2 disappears after scan 15


def _section(**changes):
    cfg = _compose("tracking", "debug=tracking")
    section = OmegaConf.to_container(cfg.tracking)
    section.update(changes)
    return OmegaConf.create(section)


def test_a_target_outside_its_lifetime_makes_no_detection():
    """With P_D = 1 and (practically) no clutter, every scan holds exactly the targets that exist."""
    t = _section(steps=24, lifetimes=LIVES, detection_probability=1.0, clutter_rate=1e-12)
    truth, z, x0, present = tracking.simulate(t, 5, torch.Generator().manual_seed(3))
    expected = torch.tensor([[k in range(a, b) for a, b in LIVES] for k in range(24)])
    assert torch.equal(present, expected.unsqueeze(1).expand(24, 5, 3))
    detected = torch.isfinite(z).all(-1).sum(-1)  # (T, runs)
    assert torch.equal(detected, present.sum(-1))
    # and each detection lies near an existing target (within 6 sigma of R), none near an absent one
    gap = (z.unsqueeze(-2) - truth[..., [0, 2]].unsqueeze(-3)).norm(dim=-1)  # (T, runs, D, N)
    near = (gap < 6 * t.R**0.5) & torch.isfinite(z).all(-1, keepdim=True)
    assert not bool((near & ~present.unsqueeze(-2)).any())


def test_managed_tracker_follows_births_and_deaths(tmp_path):
    overrides = ["debug=tracking", "tracking.steps=24", "tracking.management.velocity_variance=900",
                 f"tracking.lifetimes={LIVES}".replace(" ", ""), "tracking.estimators=[JIPDA-TM]"]
    run_study(_compose("tracking", *COMMON, "figures=false", *overrides), tmp_path)
    curves = load_curves(tmp_path)
    truth = torch.as_tensor(curves["tracks/truth"][2])
    shown = torch.as_tensor(curves["tracks/JIPDA-TM"][2])
    assert truth.tolist() == [float(sum(k in range(a, b) for a, b in LIVES)) for k in range(24)]
    assert float(shown[0]) == 0.0  # a track born at a scan has the birth existence (0.1): not confirmed
    # while all three live (scans 10-15) about three confirmed tracks; after the death, about two
    assert abs(float(shown[10:16].mean()) - 3.0) < 0.6, shown.tolist()
    assert abs(float(shown[-5:].mean()) - 2.0) < 0.5, shown.tolist()
    row = json.loads((tmp_path / "results.json").read_text())["tables"]["gospa"]
    record = dict(zip(row["columns"], row["rows"][0]))
    assert 1.0 <= record["first_track_delay"] <= 6.0, record
    assert record["lost_fraction"] <= 0.25, record


def test_the_association_methods_side_by_side(tmp_path):
    """tracking.jpda.method, the IMM-JPDAF-LBP / IMM-JPDAF-kbest estimators and the IMM-MHT (issue 46):
    with every joint event the k-best IMM-JPDAF is the exact one, GOSPA for GOSPA; the IMM-MHT with one
    hypothesis is the GNN-IMM; loopy belief propagation runs beside them; more than 12 targets are
    refused for the exact method only."""
    from experiments.config import validate

    overrides = ["debug=tracking", "tracking.steps=12", "tracking.clutter_rate=2",
                 "tracking.estimators=[IMM-JPDAF,IMM-JPDAF-LBP,IMM-JPDAF-kbest,IMM-MHT,GNN-IMM]", "tracking.jpda.k=5000",
                 "tracking.mht.hypotheses=1", "tracking.mht.n_scan=0"]
    run_study(_compose("tracking", *COMMON, "figures=false", *overrides), tmp_path)
    rows = json.loads((tmp_path / "results.json").read_text())["tables"]["gospa"]
    table = {row[0]: dict(zip(rows["columns"], row)) for row in rows["rows"]}
    assert set(table) == {"IMM-JPDAF", "IMM-JPDAF-LBP", "IMM-JPDAF-kbest", "IMM-MHT", "GNN-IMM"}
    # the IMM-MHT with one hypothesis (and one event) is the GNN-IMM
    for key, value in table["GNN-IMM"].items():
        if key not in ("estimator", "seconds_per_track_scan") and isinstance(value, float):
            assert table["IMM-MHT"][key] == pytest.approx(value, rel=1e-9, abs=1e-9), key
    exact, kbest = table["IMM-JPDAF"], table["IMM-JPDAF-kbest"]
    for key, value in exact.items():
        if key not in ("estimator", "seconds_per_track_scan") and isinstance(value, float):
            assert kbest[key] == pytest.approx(value, rel=1e-9, abs=1e-9), key
    validate(_compose("tracking", "tracking.targets=20", "tracking.jpda.method=kbest",
                      "tracking.estimators=[IMM-JPDAF,JPDAF]"))
    with pytest.raises(ValueError, match="tracking.targets=20: the exact JPDA takes at most 12"):
        validate(_compose("tracking", "tracking.targets=20", "tracking.estimators=[IMM-JPDAF]"))


def test_the_xy_figure_of_one_run(tmp_path):
    """figures/tracks_xy.png: run 0's truth, detections and every estimator's tracks (issue 46's picture);
    the picture drawn is run 0's own data (its truth the simulation's)."""
    overrides = ["debug=tracking", "figures=true", "tracking.estimators=[IMM-JPDAF,JIPDA-TM]"]
    run_study(_compose("tracking", *COMMON, *overrides), tmp_path)
    assert (tmp_path / "figures" / "tracks_xy.png").stat().st_size > 10_000
    assert (tmp_path / "figures" / "tracks_xy.pdf").exists()


def test_track_quality_without_clutter_or_misses(tmp_path):
    """The track_quality table (SIAP-style, issue 46) where the answer is known: P_D = 1 and no clutter,
    tracks started on their targets - every target covered at every scan (completeness 1, no break), no
    spurious track; with a one-run-in-two miss rate the completeness falls below 1."""
    overrides = ["debug=tracking", "figures=false", "tracking.estimators=[IMM-JPDAF]", "tracking.detection_probability=1.0",
                 "tracking.clutter_rate=1e-9"]
    run_study(_compose("tracking", *COMMON, *overrides), tmp_path / "clean")
    table = json.loads((tmp_path / "clean" / "results.json").read_text())["tables"]["track_quality"]
    row = dict(zip(table["columns"], table["rows"][0]))
    assert row["completeness"] == 1.0 and row["track_breaks"] == 0.0 and row["spuriousness"] == 0.0
    assert row["ambiguity"] >= 1.0
    overrides[-1] = "tracking.management.velocity_variance=900"
    run_study(_compose("tracking", *COMMON, "debug=tracking", "figures=false", "tracking.steps=24",
                       f"tracking.lifetimes={LIVES}".replace(" ", ""), "tracking.estimators=[JIPDA-TM]"), tmp_path / "tm")
    table = json.loads((tmp_path / "tm" / "results.json").read_text())["tables"]["track_quality"]
    row = dict(zip(table["columns"], table["rows"][0]))
    assert 0.0 < row["completeness"] < 1.0 and 0.0 <= row["spuriousness"] < 1.0  # (a track confirms late)


def test_gospa_with_the_track_switching_penalty(tmp_path):
    """tracking.gospa_switching (issue 46): a `switching` column, GOSPA with it at least GOSPA without it
    (equal parts otherwise); zero exactly where no label ever switched or was lost and regained."""
    common = [*COMMON, "debug=tracking", "figures=false", "tracking.estimators=[IMM-JPDAF,JIPDA-TM]"]
    run_study(_compose("tracking", *common), tmp_path / "off")
    run_study(_compose("tracking", *common, "tracking.gospa_switching=5.0"), tmp_path / "on")
    off, on = ({row[0]: dict(zip(t["columns"], row)) for row in t["rows"]}
               for t in (json.loads((tmp_path / d / "results.json").read_text())["tables"]["gospa"]
                         for d in ("off", "on")))
    assert "switching" not in off["IMM-JPDAF"] and "switching" in on["IMM-JPDAF"]
    for name in off:
        for key in ("localisation", "missed", "false", "label_switches"):
            assert on[name][key] == off[name][key]
        assert on[name]["gospa"] >= off[name]["gospa"] - 1e-12
        assert (on[name]["switching"] > 0) == (on[name]["gospa"] > off[name]["gospa"] + 1e-12)
    assert on["JIPDA-TM"]["switching"] > 0  # its tracks are gained (and lost) over the run


WAYS = "[[[0,-200,0],[10,0,0],[20,0,200]],[[4,200,-100],[20,-120,-100]]]"


def test_targets_from_waypoints():
    """tracking.waypoints (issue 46): each target is at its waypoints at their scans, flies each leg at
    constant velocity, exists from its first waypoint's scan to its last; with P_D = 1 and no clutter
    every scan holds one detection per existing target; the tracks' start is the state one period before
    scan 0 (the first leg extrapolated back) plus N(0, P0)."""
    t = _section(steps=24, detection_probability=1.0, clutter_rate=1e-12, waypoints=json.loads(WAYS),
                 P0=[0.0, 0.0, 0.0, 0.0])
    truth, z, x0, present = tracking.simulate(t, 3, torch.Generator().manual_seed(1))
    assert truth.shape == (24, 3, 2, 4)
    assert truth[10, 0, 0, [0, 2]].tolist() == pytest.approx([0.0, 0.0]) and truth[20, 1, 0, [0, 2]].tolist() == \
        pytest.approx([0.0, 200.0])
    assert truth[7, 0, 0, [1, 3]].tolist() == pytest.approx([20.0, 0.0])  # 200 m in 10 scans of 1 s
    assert truth[15, 0, 0, [1, 3]].tolist() == pytest.approx([0.0, 20.0])
    assert truth[12, 0, 1, [0, 1]].tolist() == pytest.approx([200.0 - 8 * 20.0, -20.0])
    expected = torch.tensor([[k <= 20, 4 <= k <= 20] for k in range(24)])
    assert torch.equal(present[:, 0], expected)
    assert torch.equal(torch.isfinite(z).all(-1).sum(-1), present.sum(-1))
    assert x0[0, 0].tolist() == pytest.approx([-220.0, 20.0, 0.0, 0.0])  # (P0 = 0: the true state at scan -1)


def test_waypoint_study_with_a_birth_and_its_checks(tmp_path):
    from experiments.config import validate

    run_study(_compose("tracking", *COMMON, "debug=tracking", "figures=false", "tracking.steps=24",
                       f"tracking.waypoints={WAYS}", "tracking.estimators=[JIPDA-TM]",
                       "tracking.management.velocity_variance=900"), tmp_path)
    curves = load_curves(tmp_path)
    truth = torch.as_tensor(curves["tracks/truth"][2])
    assert truth.tolist() == [float(k <= 20) + float(4 <= k <= 20) for k in range(24)]
    assert "2 targets flying straight between their waypoints" in (tmp_path / "results.md").read_text()
    with pytest.raises(ValueError, match=r"tracking.estimators=.*target\(s\) \[1\] start later"):
        validate(_compose("tracking", f"tracking.waypoints={WAYS}", "tracking.estimators=[IMM-JPDAF]"))
    with pytest.raises(ValueError, match=r"tracking.waypoints\[0\]=.*increasing"):
        validate(_compose("tracking", "tracking.waypoints=[[[0,0,0],[0,1,1]]]", "tracking.estimators=[JIPDA-TM]"))
    with pytest.raises(ValueError, match=r"tracking.waypoints\[0\]=.*0 .. steps - 1 = 59"):
        validate(_compose("tracking", "tracking.waypoints=[[[0,0,0],[60,1,1]]]", "tracking.estimators=[JIPDA-TM]"))
    validate(_compose("tracking", "tracking.waypoints=[[[0,0,0],[59,1,1]]]", "tracking.estimators=[IMM-JPDAF]"))


def test_managed_trackers_take_the_k_best_events(tmp_path):
    """tracking.management.method=kbest (issue 46: the association choice for the managed trackers): with k
    above every joint event of the slots it is the exact JIPDA, table for table."""
    common = [*COMMON, "debug=tracking", "figures=false", "tracking.estimators=[JIPDA-TM]", "tracking.clutter_rate=2",
              "tracking.management.capacity=4"]
    run_study(_compose("tracking", *common, "tracking.management.method=exact"), tmp_path / "exact")
    run_study(_compose("tracking", *common, "tracking.management.method=kbest", "tracking.management.k=100000"),
              tmp_path / "kbest")
    a, b = (json.loads((tmp_path / d / "results.json").read_text())["tables"] for d in ("exact", "kbest"))
    for name in ("gospa", "track_quality"):
        for x, y, column in zip(a[name]["rows"][0], b[name]["rows"][0], a[name]["columns"]):
            if isinstance(x, float) and "seconds" not in column:
                assert y == pytest.approx(x, rel=1e-9, abs=1e-9), (name, column)


MOTIONS = ("[{start:[0,10,0,0],legs:[{scans:5},{scans:10,turn_rate:0.1},{scans:4,acceleration:[0,2]}]},"
           "{start:[100,0,50,-5],first:3,legs:[{scans:12}]}]")


def test_targets_from_motion_schedules():
    """tracking.motions (issue 46): constant velocity, a coordinated turn (speed kept, heading turned by
    w n dt), an acceleration (velocity changed by a n dt); a target exists from its first scan to the end of
    its last leg; the tracks' start is the first leg run back one period (P0 = 0)."""
    motions = [{"start": [0, 10, 0, 0], "legs": [{"scans": 5}, {"scans": 10, "turn_rate": 0.1},
                                                 {"scans": 4, "acceleration": [0, 2]}]},
               {"start": [100, 0, 50, -5], "first": 3, "legs": [{"scans": 12}]}]  # (MOTIONS)
    t = _section(steps=24, detection_probability=1.0, clutter_rate=1e-12, motions=motions, P0=[0.0, 0.0, 0.0, 0.0])
    truth, z, x0, present = tracking.simulate(t, 2, torch.Generator().manual_seed(1))
    a = truth[:, 0, 0]
    assert a[5, [0, 1, 2, 3]].tolist() == pytest.approx([50.0, 10.0, 0.0, 0.0])
    heading = torch.atan2(a[15, 3], a[15, 1])
    assert float(a[15, [1, 3]].norm()) == pytest.approx(10.0) and float(heading) == pytest.approx(0.1 * 10)
    assert (a[19, [1, 3]] - a[15, [1, 3]]).tolist() == pytest.approx([0.0, 8.0])
    b = truth[:, 0, 1]
    assert b[3].tolist() == pytest.approx([100.0, 0.0, 50.0, -5.0]) and b[15, 2].item() == pytest.approx(-10.0)
    expected = torch.tensor([[k <= 19, 3 <= k <= 15] for k in range(24)])
    assert torch.equal(present[:, 0], expected)
    assert torch.equal(torch.isfinite(z).all(-1).sum(-1), present.sum(-1))
    assert x0[0, 0].tolist() == pytest.approx([-10.0, 10.0, 0.0, 0.0])


def test_motion_study_with_a_birth_and_its_checks(tmp_path):
    from experiments.config import validate

    run_study(_compose("tracking", *COMMON, "debug=tracking", "figures=false", "tracking.steps=24",
                       f"tracking.motions={MOTIONS}", "tracking.start=detections",
                       "tracking.estimators=[IMM-JPDAF,JIPDA-TM]", "tracking.management.velocity_variance=100"),
              tmp_path)
    assert "2 targets flying their legs" in (tmp_path / "results.md").read_text()
    curves = load_curves(tmp_path)
    assert torch.as_tensor(curves["tracks/truth"][2]).tolist() == [float(k <= 19) + float(3 <= k <= 15)
                                                                   for k in range(24)]
    with pytest.raises(ValueError, match=r"tracking.estimators=.*target\(s\) \[1\] start later"):
        validate(_compose("tracking", f"tracking.motions={MOTIONS}", "tracking.estimators=[IMM-JPDAF]"))
    with pytest.raises(ValueError, match=r"tracking.motions\[0\].legs\[1\]=.*not both"):
        validate(_compose("tracking", "tracking.motions=[{start:[0,0,0,0],legs:[{scans:2},{scans:2,turn_rate:0.1,"
                          "acceleration:[0,1]}]}]", "tracking.estimators=[JIPDA-TM]"))
    with pytest.raises(ValueError, match=r"tracking.motions\[0\]=.*end at scan 60"):
        validate(_compose("tracking", "tracking.motions=[{start:[0,0,0,0],legs:[{scans:60}]}]",
                          "tracking.estimators=[JIPDA-TM]"))
    with pytest.raises(ValueError, match=r"tracking.motions\[0\].start=.*\[x, vx, y, vy\]"):
        validate(_compose("tracking", "tracking.motions=[{start:[0,0,0],legs:[{scans:6}]}]",
                          "tracking.estimators=[JIPDA-TM]"))


def test_the_mht_from_detections_takes_its_initiation_keys():
    """tracking.start: detections makes IMM-MHT a ManagedMHT with tracking.initiation's keys."""
    from torchmm.association import ManagedMHT

    t = _section(start="detections", estimators=["IMM-MHT"], initiation={
        "m_of_n": [3, 5], "max_misses": 4, "birth_rate": 0.2, "confirm_score": 12.0, "delete_drop": 6.0})
    mht = tracking.estimators(t, torch.float64)["IMM-MHT"].filter
    assert isinstance(mht, ManagedMHT) and mht.m_of_n == (3, 5) and mht.max_misses == 4
    assert mht.confirm_score == 12.0 and mht.delete_drop == 6.0
    assert mht.birth_density == pytest.approx(0.2 / (2 * float(t.region)) ** 2)


def test_one_run_names_gospa_se_as_dropped(tmp_path):
    """With one run (series) the standard error has no value: null in results.json, named in dropped with
    the reason (it was an unexplained empty cell); with more runs it is a number and not dropped."""
    run_study(_compose("tracking", "mc_runs=1", "progress=false", "logger=none", "debug=tracking",
                       "figures=false", "tracking.estimators=[IMM-PDAF]"), tmp_path / "one")
    results = json.loads((tmp_path / "one" / "results.json").read_text())
    gospa = results["tables"]["gospa"]
    assert gospa["rows"][0][gospa["columns"].index("gospa_se")] is None
    assert "no standard error" in results["dropped"]["gospa_se"]
    assert "`gospa_se`: one run (series): no standard error" in (tmp_path / "one" / "results.md").read_text()
    run_study(_compose("tracking", "mc_runs=2", "progress=false", "logger=none", "debug=tracking",
                       "figures=false", "tracking.estimators=[IMM-PDAF]"), tmp_path / "two")
    results = json.loads((tmp_path / "two" / "results.json").read_text())
    assert "gospa_se" not in results["dropped"]
    assert isinstance(results["tables"]["gospa"]["rows"][0][2], float)


def test_a_non_finite_waypoint_value_is_named():
    from experiments.config import validate

    for given, name, value in (("[5,nan,1]", "x", "nan"), ("[inf,1,1]", "scan", "inf")):
        want = rf"^tracking\.waypoints\[0\]\[1\]=.*its {name} is {value}: expected a finite number"
        with pytest.raises(ValueError, match=want):
            validate(_compose("tracking", f"tracking.waypoints=[[[0,0,0],{given}]]",
                              "tracking.estimators=[JIPDA-TM]"))


def test_runs_whose_tracker_failed_are_counted_and_said(tmp_path, monkeypatch):
    """A run whose tracker flagged extras["failed"] (here run 1's flag is raised at every scan, as a tracker's
    failed update raises it) is counted (metric failed_runs) and named in a note, not scored silently as a
    tracker that lost every target; a tracker that never failed has neither."""
    real = tracking.run_filter

    def run_filter(filt, belief, scans, record=None):
        def flag(out):
            failed = out.extras["failed"].clone()
            failed[1] = True
            out = out._replace(extras={**out.extras, "failed": failed})
            return out if record is None else record(out)
        return real(filt, belief, scans, record=flag if type(filt).__name__ != "ManagedTracks" else record)

    monkeypatch.setattr(tracking, "run_filter", run_filter)
    run_study(_compose("tracking", *COMMON, "debug=tracking", "figures=false",
                       "tracking.estimators=[IMM-JPDAF,IMM-PDAF,IMM-MHT,JIPDA-TM]"), tmp_path)
    results = json.loads((tmp_path / "results.json").read_text())
    notes = (tmp_path / "results.md").read_text()
    for name in ("IMM-JPDAF", "IMM-PDAF", "IMM-MHT"):
        assert results["metrics"][name]["failed_runs"] == 1, name
        assert f"- {name}: 1 of 4 runs failed" in notes, name
    assert "failed_runs" not in results["metrics"]["JIPDA-TM"]  # (its flags left as they were: none raised)
    assert "JIPDA-TM: 1 of 4" not in notes and "JIPDA-TM: 0 of" not in notes


def test_label_switches_compare_with_the_last_track_across_gaps():
    """label_switches counts a target's change of track against its last one, across scans without a track
    (A, none, B: 1; A, none, A: 0; gained or lost: 0), as a plain loop over the scans does."""
    import itertools

    label = torch.tensor([[0, 0, 1], [-1, 0, 1], [2, 0, -1], [2, 1, -1], [-1, -1, 1], [0, -1, 3]]).view(6, 1, 3)
    assert tracking.label_switches(label).tolist() == [4.0]  # target 0: 0 -> 2 -> 0; 1: 0 -> 1; 2: 1 -> 3
    gen = torch.Generator().manual_seed(3)
    label = torch.randint(-1, 3, (9, 5, 4), generator=gen)
    want = []
    for r in range(5):
        count = 0
        for i in range(4):
            known = [int(v) for v in label[:, r, i] if v >= 0]
            count += sum(a != b for a, b in itertools.pairwise(known))
        want.append(float(count))
    assert tracking.label_switches(label).tolist() == want

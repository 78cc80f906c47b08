"""Crossing, manoeuvring targets in clutter: IMM-JPDAF, JPDAF, IMM-PDAF, GNN-IMM and managed tracks (issue 32;
docs/tracking.md, "The tracking study").

``targets`` targets start evenly on a circle of radius ``radius`` and head for its centre, which they
all cross at mid-run; from ``maneuver_start`` to ``maneuver_stop`` each accelerates sideways (``+a``
for even targets, ``-a`` for odd ones; ``a = maneuver_acceleration``), then flies on. Constant velocity
with white-acceleration noise ``q`` otherwise (2-D, state ``[x, vx, y, vy]``). A position sensor (``R``
per axis) detects each target with probability ``P_D``; Poisson clutter (``clutter_rate`` a scan) is
uniform over the square ``[-region, region]^2``. With ``lifetimes`` (``[[first, stop], ...]``, one per
target) a target exists only over scans ``first..stop-1`` (births and deaths): it makes no detection
and is not scored outside them.

The first four estimators start one track per target from the true initial state perturbed by
``N(0, P0)`` (the number of targets is known; they refuse ``lifetimes``); ``JIPDA-TM`` starts with
no track and initiates, confirms and deletes its own, as does ``IMM-JIPDA-TM``. With ``tracking.start:
detections`` every estimator but IMM-PDAF starts with no track (the JPDAs and GNN as ``ManagedTracks`` over
a JIPDA whose tracks exist for sure with ``tracking.initiation``'s M-of-N logic; IMM-MHT as ``ManagedMHT``).

Targets may also come from ``tracking.waypoints`` or ``tracking.motions`` (legs of constant velocity,
coordinated turns and accelerations), and several sensors (``tracking.sensors``: each its ``R``, ``P_D``,
clutter rate, period and offset) update the tracks in turn (``SequentialSensors``); a detections file may
name each row's sensor (docs/tracking.md).

Estimators (``tracking.estimators``):

* ``IMM-JPDAF``: ``JPDA(IMM(KalmanFilter(bank)))``: the joint association over an IMM of the truth's
  three acceleration modes (Blom & Bloem 2000); ``tracking.jpda.method``: ``exact`` (default, at most
  12 targets), ``lbp`` or ``kbest`` (the ``tracking.jpda.k`` most likely joint events: Murty).
* ``IMM-JPDAF-LBP``, ``IMM-JPDAF-kbest``: the same with loopy belief propagation, and with the k best
  joint events, whatever ``tracking.jpda.method`` says: the methods side by side in one study.
* ``IMM-MHT``: ``MHT(IMM(KalmanFilter(bank)))`` (``tracking.mht``: hypotheses, k, n_scan): the best
  hypothesis's tracks.
* ``JPDAF``: ``JPDA(KalmanFilter(cv))``: one constant-velocity model with the inflated noise ``q_cv``.
* ``IMM-PDAF``: ``IMM(PDA(KalmanFilter(bank)))`` per target (Houles & Bar-Shalom 1989): every track
  associates alone, the scan shared.
* ``GNN-IMM``: ``GNN(IMM(KalmanFilter(bank)))``: the best joint event.
* ``JIPDA-TM``: ``ManagedTracks(JIPDA(KalmanFilter(cv)))`` (``tracking.management``): a table of
  ``capacity`` track slots a run, empty at the start; an unexplained detection starts a track, the
  JIPDA's existence confirms it (``confirm``) or deletes it (``delete``); or, with ``m_of_n: [M, N]``,
  M detections in its gate among its first N scans confirm it and a track unconfirmed after N scans
  is deleted (``max_misses``: consecutive misses that delete a track). Only confirmed tracks are
  shown and scored.
* ``IMM-JIPDA-TM``: the same over ``JIPDA(IMM(KalmanFilter(bank)))``: the IMM-JIPDA, a new track in
  every mode with equal probabilities.

Tables: ``gospa`` (estimator; time-averaged GOSPA (``c``, ``p``, ``alpha = 2``) with its standard
error over the runs; its localisation / missed / false parts; label switches a run; the fraction of
targets lost at the end (no track within ``c``); scans from a target's first scan to its first track
within ``c``; seconds per track-scan). Figures: GOSPA and the number of tracks shown over time, with
95 % bands; ``tracks_xy``: run 0 in the plane (truth, detections, each estimator's labelled tracks with
2-sigma ellipses). TensorBoard: the same curves. Sweeps: ``-m tracking.clutter_rate=2,10,30`` or
``tracking.detection_probability=0.7,0.9,0.99``.

Every scan the trackers see, simulated or read, is first put in one canonical order of its detections
(:func:`experiments.studies.tracking_data.canonical_order`; docs/tracking.md, "Detection order"), so that
a file's row order and padding change no number.

The targets, sensors and simulated scans: :mod:`experiments.studies.tracking_scenario`; detection files:
:mod:`experiments.studies.tracking_data`; the trackers built: :mod:`experiments.studies.tracking_estimators`.
"""

from __future__ import annotations

import math
import time

import torch
import torch.utils._pytree as pytree
from torch import Tensor

from experiments.arrays import join_runs, per_run
from experiments.executors import Unit
from experiments.harness import StudyContext
from experiments.studies import plots, tracking_data
from experiments.studies.tracking_estimators import estimators, unstarted
from experiments.studies.tracking_scenario import lifetimes, schedule, sensor_list, simulate
from torchmm import GaussianBelief, run_filter
from torchmm.association import SensorScans
from torchmm.metrics import gospa, gospa_switching

UNIT = "experiments.studies.tracking:unit"



def _data(ctx: StudyContext, start: int, stop: int):
    """Runs ``start..stop-1``: truth positions ``(T, runs, N, 2)`` (None: no truth), detections
    ``(T, runs, D, 2)``, the tracks' start ``x0 (runs, K, 4)``, ``P0 (runs, K, 4, 4)`` and which targets
    exist ``(T, runs, N)`` (None with no truth): simulated, or read from ``tracking.detections``. Every
    scan's detections in the canonical order (:func:`experiments.studies.tracking_data.canonical_order`),
    here where both pass: the file's row order and padding, and the simulation's draw order, change no
    number, and a simulation exported and read back is the same scans."""
    t = ctx.cfg.tracking
    if t.detections is not None:
        got = ctx.memo(("recorded",), lambda: _read(t))
        cut = slice(start, stop)
        z = tracking_data.canonical_order(got.z[:, cut])
        return (None if got.truth is None else got.truth[:, cut], z, got.x0[cut], got.P0[cut],
                None if got.present is None else got.present[:, cut])

    def simulate_block():
        return ctx.simulate_runs(lambda n, gen: simulate(t, n, gen), stop, "tracking", axes=(1, 1, 0, 1), start=start)
    truth, z, x0, present = ctx.memo(("data", start, stop), simulate_block)
    P0 = torch.diag(torch.tensor(list(t.P0), dtype=x0.dtype)).expand(*x0.shape, 4)
    return truth[..., [0, 2]], tracking_data.canonical_order(z), x0, P0, present


def _read(t) -> tracking_data.Recorded:
    """``tracking.detections``'s files (with ``tracking.sensors``: each sensor's scans on its schedule)."""
    sensors = None if t.get("sensors") is None else [s["name"] for s in sensor_list(t)]
    return tracking_data.read(t.detections, dt=float(t.dt), P0=list(t.P0), sensors=sensors,
                              schedule=None if sensors is None else lambda T: schedule(t, T))


def runs_of(ctx: StudyContext) -> int:
    """The runs: ``mc_runs``, or the detections file's series."""
    t = ctx.cfg.tracking
    if t.detections is None:
        return int(ctx.cfg.mc_runs)
    return len(ctx.memo(("recorded",), lambda: _read(t)).series)


def check_build(cfg, scenario) -> None:
    """Before any folder (:func:`experiments.config.dry_build`): ``tracking.detections``'s files read, every
    error one line naming the key; the exact JPDA's limit on the start file's tracks."""
    from experiments.config import ConfigError

    t = cfg.tracking
    if t.detections is None:
        return
    got = _read(t)
    K = got.x0.shape[-2]
    method = str((t.get("jpda") or {}).get("method", "exact"))
    if K > 12 and method == "exact" and any(name in ("IMM-JPDAF", "JPDAF") for name in t.estimators):
        raise ConfigError("tracking.detections.start", t.detections.start.path,
                          f"{K} tracks: the exact JPDA takes at most 12 (tracking.jpda.method: lbp or kbest)")


def unit(ctx: StudyContext, *, name: str, start: int, stop: int) -> dict:
    """Estimator ``name`` on runs ``start..stop-1``: per-run GOSPA curves and parts ``(T, runs)``,
    label switches, lost targets and the scans to a target's first track ``(runs,)``, and the seconds
    it took."""
    t = ctx.cfg.tracking
    truth, z, x0, P0, present = (None if v is None else v.to(ctx.dtype) if v.is_floating_point() else v
                                 for v in _data(ctx, start, stop))
    K = x0.shape[-2]
    est = estimators(t, ctx.dtype, targets=K)[name]
    belief = est.initial(GaussianBelief(x0, P0))
    scans = _scans_for(t, z, est.per_track)
    filt, belief = est.filter.to(ctx.device), belief.to(ctx.device)
    scans = pytree.tree_map(lambda v: v.to(ctx.device), scans)
    tic = time.perf_counter()
    with torch.no_grad():
        traj = run_filter(filt, belief, scans, record=est.record if est.managed else _estimate_and_failed)
    seconds = time.perf_counter() - tic
    if est.managed:  # the confirmed tracks, each with its label
        table = traj.belief
        shown, labels = table.confirmed().cpu(), table.label.cpu()
    else:  # one track per target, its index the label
        shown, labels = None, torch.arange(K).expand(traj.belief.mean.shape[:-1])
    position = traj.belief.estimate().mean[..., [0, 2]].cpu().double()  # (T, runs, K, 2)
    # the runs where some update failed (extras["failed"]: a NaN prediction or association,
    # docs/robustness.md)
    flags = (traj.extras or {}).get("failed")
    failed = (torch.zeros(position.shape[1], dtype=torch.bool) if flags is None
              else flags.cpu().reshape(*flags.shape[:2], -1).any(-1).any(0))
    visible = shown if shown is not None else torch.ones(position.shape[:-1], dtype=torch.bool)
    picture = None
    if start == 0:  # run 0 for the x-y figure: its tracks (position block), truth and detections
        est_b = traj.belief.estimate()
        cov = est_b.cov[:, 0].expand(*position[:, 0].shape[:-1], 4, 4)
        picture = {"mean": position[:, 0], "cov": cov[..., [0, 2], :][..., :, [0, 2]].cpu().double(),
                   "shown": visible[:, 0], "labels": labels[:, 0],
                   "truth": (truth[:, 0] if truth is not None else position.new_zeros(len(position), 0, 2)).cpu().double(),
                   "present": present[:, 0] if truth is not None else torch.zeros(len(position), 0, dtype=torch.bool),
                   "detections": z[:, 0].reshape(len(z), -1, 2).cpu().double()}  # (every sensor's)
    common = {"picture": picture, "seconds": seconds, "failed": per_run(failed),
              # a managed tracker's new tracks it could not start for lack of slots, a run
              "unstarted": per_run(unstarted(traj.extras).sum(0).double()) if est.managed else None,
              "tracks": per_run(visible.sum(-1).double()),
              "track_scans": int(position.shape[0] * position.shape[1] * position.shape[2])}
    if truth is None:  # nothing to score: the tracks, their number and the time
        return common
    truth_xy = truth.cpu().double()
    out = gospa(position, truth_xy, c=float(t.gospa_c), p=float(t.gospa_p), estimate_present=shown,
                truth_present=present)
    assigned = out["assigned"]  # (T, runs, N): the track on each target, -1 none within c
    label = torch.where(assigned >= 0, labels.gather(-1, assigned.clamp(min=0)), -1)
    penalty = float(t.get("gospa_switching") or 0.0)
    if penalty > 0:  # GOSPA with its track-switching term (Stone Soup's switching_penalty)
        term = gospa_switching(label, penalty=penalty, p=float(t.gospa_p), truth_present=present)
        out["distance"] = (out["distance"] ** 2 + term ** 2).sqrt()
        out["switching"] = term
    switches = label_switches(label)  # (runs,)
    # a figure over targets counts only the targets that exist (a truth file may give a series fewer
    # targets, or none): NaN where a run has none to count, left out of the average over runs
    last = present[-1]
    lost = _ratio(((assigned[-1] < 0) & last).sum(-1), last.sum(-1))  # (runs,)
    steps = torch.arange(len(present)).view(-1, 1, 1)
    never = torch.full_like(steps, len(present))
    appears = torch.where(present, steps, never).amin(0)  # (runs, N)
    tracked = torch.where(assigned >= 0, steps, never).amin(0)
    exists = present.any(0)  # (runs, N): the target exists in the run
    # (runs,): scans from appearing to a track within c, over the targets of the run
    delay = _ratio(torch.where(exists, tracked - appears, 0).sum(-1), exists.sum(-1))
    # SIAP-style quality (Votruba, Naval Research Lab, 2001): a track "covers" a target it lies within c of
    # (any number of tracks a target, unlike GOSPA's one-to-one assignment)
    gap = (position.unsqueeze(-2) - truth_xy.unsqueeze(-3)).norm(dim=-1)  # (T, runs, K, N)
    near = (gap < float(t.gospa_c)) & visible.unsqueeze(-1) & present.unsqueeze(-2)
    covered = near.any(-2)  # (T, runs, N): the target has a track
    quality = {
        "completeness": per_run(_ratio(covered.sum((0, 2)), present.sum((0, 2)))),
        "ambiguity": per_run(_ratio(near.sum((0, 2, 3)), covered.sum((0, 2)))),
        "spuriousness": per_run(_ratio((visible & ~near.any(-1)).sum((0, 2)), visible.sum((0, 2)))),
        "breaks": per_run((covered[:-1] & ~covered[1:] & present[1:]).sum((0, 2)).double()),
    }
    return common | {key: per_run(out[key]) for key in ("distance", "localisation", "missed", "false", "switching")
                     if key in out} | {
        "switches": per_run(switches), "lost": per_run(lost), "delay": per_run(delay), **quality,
        "targets": per_run(present.sum(-1).double())}


def label_switches(label: Tensor) -> Tensor:
    """Times a target's track changed, a run: ``label (T, runs, N)`` the label of each target's GOSPA-assigned
    track (-1: none) -> ``(runs,)`` float64. Each step with a track compares it with the target's last one
    (across steps without: A, none, B counts 1; A, none, A counts 0), as the full switches of
    :func:`torchmm.metrics.gospa_switching`; gaining or losing a track is not a switch."""
    T = label.shape[0]
    steps = torch.arange(T, device=label.device).view(-1, *[1] * (label.dim() - 1))
    seen = torch.where(label >= 0, steps, -1).cummax(0).values  # the last step with a track, up to each step
    before = torch.cat([torch.full_like(seen[:1], -1), seen[:-1]])  # ... before each step
    last = torch.where(before >= 0, label.gather(0, before.clamp(min=0)), -1)
    return ((label >= 0) & (last >= 0) & (label != last)).sum((0, 2)).double()


def _estimate_and_failed(out):
    """``record`` of a fixed-track estimator: the point estimate, the log-likelihood and
    ``extras["failed"]``."""
    failed = (out.extras or {}).get("failed")
    return type(out)(out.belief.estimate(), None, out.log_likelihood,
                     extras=None if failed is None else {"failed": failed})


def _ratio(count: Tensor, total: Tensor) -> Tensor:
    """``count / total`` per run (float64), NaN where ``total`` is 0 (nothing to count: not 0)."""
    return torch.where(total > 0, count.double() / total.clamp(min=1).double(), math.nan)


#: why a track-quality figure has no run to average over (every run NaN)
_UNDEFINED = {
    "lost_fraction": "no target exists at the last scan of any series (truth)",
    "first_track_delay": "no target exists in any series (truth)",
    "completeness": "no target exists in any series (truth)",
    "ambiguity": "no target-scan is covered by a track in any series",
    "spuriousness": "no track is shown in any series",
}


def _average(ctx: StudyContext, name: str, column: str, runs) -> float:
    """The mean over the runs where ``column`` is defined (a run without the targets it counts is NaN and
    left out); NaN, and named in ``dropped``, where no run has it."""
    finite = runs[torch.isfinite(runs)]
    if not len(finite):
        ctx.results.dropped[f"{column} ({name})"] = _UNDEFINED[column]
        return math.nan
    return float(finite.mean())


def _sensing(t) -> str:
    """The sensors in words, for the description."""
    region = f"[-{t.region}, {t.region}]^2"
    if t.get("sensors") is None:
        return (f"P_D = {t.detection_probability}, {t.clutter_rate} clutter points a scan over {region}, "
                f"R = {t.R}")
    return f"{len(t.sensors)} sensors in turn (clutter over {region}): " + ", ".join(
        f"{s['name']} (P_D = {s['detection_probability']}, {s['clutter_rate']} clutter points, R = {s['R']}, every "
        f"{s['period']:g} from {s['offset']:g})" for s in sensor_list(t))


def _scans_for(t, z: Tensor, per_track: bool):
    """The estimators' data: the scans ``z (T, runs, D, 2)`` (IMM-PDAF: every track sees the run's scan),
    or with ``tracking.sensors`` ``z (T, runs, S, D, 2)`` as :class:`SensorScans` with the schedule."""
    if t.get("sensors") is None:
        return z.unsqueeze(-3) if per_track else z
    T, runs, S = z.shape[:3]
    scans = tuple(z[:, :, s].unsqueeze(-3) if per_track else z[:, :, s] for s in range(S))
    return SensorScans(scans, schedule(t, T).unsqueeze(1).expand(T, runs, S).to(z.device))


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    t = cfg.tracking
    runs = runs_of(ctx)
    names = list(t.estimators)
    ranges = ctx.run_ranges(runs)
    if t.export:  # the simulated scenario as the files tracking.detections reads
        truth, z, x0, _, _ = _data(ctx, 0, runs)
        sensors = None if t.get("sensors") is None else [s["name"] for s in sensor_list(t)]
        tracking_data.export(ctx.output_dir / "scenario", z=z, truth=truth,
                             present=lifetimes(t).unsqueeze(1).expand(truth.shape[:-1]), x0=x0, dt=float(t.dt),
                             sensors=sensors, reports=None if sensors is None else schedule(t, len(z)))
    parts = ctx.map_units([Unit(f"tracking/{name}/runs{a}-{b}", UNIT, {"name": name, "start": a, "stop": b})
                           for name in names for a, b in ranges], desc="estimators")
    scored = "distance" in parts[0] if parts else True
    d = t.detections
    if d is not None:
        got = ctx.memo(("recorded",), lambda: _read(t))
        ctx.results.description = (
            f"detections from `{d.path}` ({runs} series, {len(got.times)} scans every {t.dt}"
            + (f", {got.truth.shape[2]} targets in the truth file `{d.truth.path}`" if d.truth is not None else
               ", no truth file: nothing scored")
            + (f", {got.x0.shape[1]} tracks started from `{d.start.path}`" if d.start is not None else "")
            + f"). Trackers' model: {_sensing(t)}; {cfg.dtype}." + (f" GOSPA with c = {t.gospa_c}, p = "
                                                                        f"{t.gospa_p}, alpha = 2." if scored else ""))
    elif t.get("motions") is not None:
        ctx.results.description = (
            f"{len(t.motions)} targets flying their legs (tracking.motions: constant velocity, coordinated turns, "
            f"accelerations), each from its start at its first scan to the end of its last leg; {t.steps} scans, "
            f"{_sensing(t)}; {runs} Monte Carlo runs (seed {cfg.seed}, {cfg.dtype}). GOSPA with c = {t.gospa_c}, "
            f"p = {t.gospa_p}, alpha = 2.")
    elif t.get("waypoints") is not None:
        ctx.results.description = (
            f"{len(t.waypoints)} targets flying straight between their waypoints ([scan, x, y]: "
            f"{[list(map(list, w)) for w in t.waypoints]}), each existing from its first waypoint's scan to its "
            f"last; {t.steps} scans, {_sensing(t)}; {runs} Monte Carlo runs (seed {cfg.seed}, {cfg.dtype}). GOSPA "
            f"with c = {t.gospa_c}, p = {t.gospa_p}, alpha = 2.")
    else:
        ctx.results.description = (
            f"{t.targets} crossing targets, {t.steps} scans, manoeuvre {t.maneuver_start}-{t.maneuver_stop} "
            f"(+-{t.maneuver_acceleration} m/s^2), {_sensing(t)}; {runs} Monte Carlo runs (seed {cfg.seed}, "
            f"{cfg.dtype}). GOSPA with c = {t.gospa_c}, p = {t.gospa_p}, alpha = 2."
            + ("" if t.lifetimes is None else f" Targets exist over scans [first, stop) = "
                                              f"{list(map(list, t.lifetimes))}."))
    if t.export:
        ctx.results.description += (" The scenario is in scenario/ (detections.csv, truth.csv, start.csv: "
                                     "tracking.detections reads them back, docs/tracking.md).")
    panels = ("GOSPA", "localisation", "missed", "false", "tracks shown") if scored else ("tracks shown",)
    curves, bands = {k: {} for k in panels}, {k: {} for k in panels}

    def mean_and_band(runs_curves, panel: str, series: str, tag: str) -> None:  # (T, runs) -> curve, 95 % band
        curve = runs_curves.mean(1)
        curves[panel][series] = curve
        ctx.logger.series(f"{tag}/{series}", curve)
        if runs_curves.shape[1] > 1:
            bands[panel][series] = band = runs_curves.std(1) / math.sqrt(runs_curves.shape[1])
            ctx.logger.series(f"{tag}_se/{series}", band)

    n = len(ranges)
    if scored:
        _score_tables(ctx, names, parts, n, mean_and_band)
    else:
        why = "no truth (tracking.detections.truth is null)"
        ctx.results.dropped.update({"gospa": why, "track_quality": why})
        table = ctx.results.table(
            "tracks", ["estimator", "tracks_shown", "seconds_per_track_scan"],
            note="tracks_shown: the tracks shown a scan (every track of the fixed-track estimators; the confirmed "
                 "ones of the managed trackers), averaged over scans and series. Without truth nothing is scored.")
        for i, name in enumerate(names):
            mine = parts[i * n:(i + 1) * n]
            seconds = sum(p["seconds"] for p in mine) / sum(p["track_scans"] for p in mine)
            table.rows.append([name, float(join_runs([p["tracks"] for p in mine]).mean()), seconds])
            ctx.results.timing[name] = seconds
    for i, name in enumerate(names):
        mean_and_band(join_runs([p["tracks"] for p in parts[i * n:(i + 1) * n]]), "tracks shown", name, "tracks")
        failed = int(join_runs([p["failed"] for p in parts[i * n:(i + 1) * n]], dim=0).sum())
        if failed:  # said, never scored silently as a tracker that lost everything
            ctx.results.metric(name, "failed_runs", failed)
            ctx.results.notes.append(
                f"{name}: {failed} of {runs} runs failed (the tracker flagged extras['failed'] at some "
                "scan: a NaN prediction or association, docs/robustness.md); from that scan on their tracks "
                "are NaN, scored as no track (every target missed), so its figures measure the failure, not "
                "its accuracy (metric failed_runs).")
        if parts[i * n]["unstarted"] is not None:  # capacity: said wherever it bound
            lost = float(join_runs([p["unstarted"] for p in parts[i * n:(i + 1) * n]], dim=0).mean())
            ctx.results.metric(name, "unstarted_tracks", lost)
            if lost > 0:
                ctx.results.notes.append(
                    f"{name}: {lost:.4g} unexplained detections a run (mean over the runs) could start no "
                    f"track, every slot taken (tracking.management.capacity = {t.management.capacity}); the "
                    "first ones in detection order took the free slots (metric unstarted_tracks). A larger "
                    "capacity lifts it.")
    if names and scored:
        mean_and_band(join_runs([p["targets"] for p in parts[:n]]), "tracks shown", "truth", "tracks")
    ctx.results.save()
    if ctx.figures and names:  # one run in the plane: truth, detections, each estimator's tracks
        pics = {name: {k: torch.as_tensor(v) for k, v in parts[i * n]["picture"].items()}  # (units: lists)
                for i, name in enumerate(names)}
        first = pics[names[0]]
        label = f"series {got.series[0]!r} of {runs}" if d is not None else f"run 0 of {runs}"
        ctx.save_figure("tracks_xy", plots.tracks_xy(
            first["truth"].reshape(len(first["present"]), -1, 2), first["present"].reshape(len(first["present"]), -1),
            first["detections"], {name: (p["mean"], p["cov"], p["shown"], p["labels"]) for name, p in pics.items()},
            title=label))
    what = f"{d.path}, {runs} series" if d is not None else (
        f"{len(t.waypoints)} targets from waypoints, {runs} runs" if t.get("waypoints") is not None else
        f"{len(t.motions)} targets from their motions, {runs} runs" if t.get("motions") is not None else
        f"{t.targets} crossing targets in clutter, {runs} runs")
    ctx.save_figure("gospa_over_time" if scored else "tracks_over_time", plots.rmse_over_time(curves, what, bands=bands))


def _score_tables(ctx: StudyContext, names: list[str], parts: list[dict], n: int, mean_and_band) -> None:
    """The gospa and track_quality tables and the GOSPA curves (the study has truth)."""
    switching = float(ctx.cfg.tracking.get("gospa_switching") or 0.0) > 0
    table = ctx.results.table(
        "gospa", ["estimator", "gospa", "gospa_se", "localisation", "missed", "false",
                  *(["switching"] if switching else []), "label_switches",
                  "lost_fraction", "first_track_delay", "seconds_per_track_scan"],
        note="gospa: the GOSPA distance averaged over steps and runs, gospa_se its standard error over the "
             "runs (95 %: +- 1.96 se). localisation / missed / false: the parts of GOSPA^p (units of "
             "distance^p), averaged the same way. label_switches: times a target's track changed, a run (against "
             "its last track, across scans without one: A, none, B counts 1; gaining or losing one is not a "
             "switch). "
             "lost_fraction: targets without a track within c at the last scan (of those that exist then). "
             "first_track_delay: scans from a target's first scan to its first track within c (a target "
             "never tracked counts the scans to the end), over the targets that exist in a run. Both average "
             "over the runs that have such targets (a run with none is left out; with none at all the figure "
             "is not computed, see below). JIPDA-TM and IMM-JIPDA-TM show their confirmed "
             "tracks only (existence >= tracking.management.confirm, or by tracking.management.m_of_n)."
             + (" switching: GOSPA's track-switching term (tracking.gospa_switching times the p-th root of the "
                "step's switches: 1 for a target's track changing to another, 0.5 for one gained or lost), "
                "averaged over steps and runs; gospa then includes it, (d^2 + switching^2)^(1/2) at each step, "
                "as Stone Soup's GOSPAMetric(switching_penalty)." if switching else ""))
    quality = ctx.results.table(
        "track_quality", ["estimator", "completeness", "ambiguity", "spuriousness", "track_breaks", "label_switches",
                          "first_track_delay"],
        note="SIAP-style track quality, a track covering a target it lies within c of (any number of tracks a "
             "target): completeness, the target-scans covered over those that exist; ambiguity, the covering "
             "tracks per covered target-scan (1: one track each); spuriousness, the shown track-scans that "
             "cover no target over all shown; track_breaks, times a target lost its cover while it existed, a "
             "run; label_switches and first_track_delay as in the gospa table. Averages over the runs; a run "
             "where a ratio has nothing to count (no target for completeness, no covered target-scan for "
             "ambiguity, no shown track for spuriousness) is left out of its average, never counted as 0.")
    if names and len(join_runs([p["distance"] for p in parts[:n]]).mean(0)) < 2:
        ctx.results.dropped["gospa_se"] = "one run (series): no standard error over the runs"
    for i, name in enumerate(names):
        mine = parts[i * n:(i + 1) * n]
        dist = join_runs([p["distance"] for p in mine])  # (T, runs)
        per_run_mean = dist.mean(0)
        parts_mean = {k: float(join_runs([p[k] for p in mine]).mean()) for k in ("localisation", "missed", "false")}
        overflow = [k for k, v in parts_mean.items() if math.isinf(v)]
        if overflow:  # (the parts are in distance^p; GOSPA itself is computed without forming them)
            ctx.results.notes.append(
                f"{name}: {', '.join(overflow)} {'is' if len(overflow) == 1 else 'are'} beyond the float "
                "range (inf): the parts are in units of distance^p and c^p = "
                f"{ctx.cfg.tracking.gospa_c}^{ctx.cfg.tracking.gospa_p} is beyond it; gospa is exact "
                "(computed on d / c, docs/tracking.md).")
        switches = float(join_runs([p["switches"] for p in mine], dim=0).mean())
        lost = _average(ctx, name, "lost_fraction", join_runs([p["lost"] for p in mine], dim=0))
        delay = _average(ctx, name, "first_track_delay", join_runs([p["delay"] for p in mine], dim=0))
        seconds = sum(p["seconds"] for p in mine) / sum(p["track_scans"] for p in mine)
        se = float(per_run_mean.std() / math.sqrt(len(per_run_mean))) if len(per_run_mean) > 1 else None
        term = [float(join_runs([p["switching"] for p in mine]).mean())] if switching else []
        table.rows.append([name, float(per_run_mean.mean()), se, parts_mean["localisation"], parts_mean["missed"],
                           parts_mean["false"], *term, switches, lost, delay, seconds])
        ctx.results.metric(name, "gospa", float(per_run_mean.mean()))
        if math.isfinite(lost):
            ctx.results.metric(name, "lost_fraction", lost)
        ctx.results.timing[name] = seconds
        quality.rows.append([name, *(_average(ctx, name, key, join_runs([p[key] for p in mine], dim=0))
                                     for key in ("completeness", "ambiguity", "spuriousness")),
                             float(join_runs([p["breaks"] for p in mine], dim=0).mean()), switches, delay])
        mean_and_band(dist, "GOSPA", name, "gospa")
        for part in ("localisation", "missed", "false"):  # GOSPA^p's parts over time
            mean_and_band(join_runs([p[part] for p in mine]), part, name, f"gospa_{part}")

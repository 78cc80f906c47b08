"""Crossing, manoeuvring targets in clutter: IMM-JPDAF, JPDAF, IMM-PDAF and GNN-IMM (issue 32;
docs/tracking.md, "The tracking study").

``targets`` targets start evenly on a circle of radius ``radius`` and head for its centre, which they
all cross at mid-run; from ``maneuver_start`` to ``maneuver_stop`` each accelerates sideways (``+a``
for even targets, ``-a`` for odd ones; ``a = maneuver_acceleration``), then flies on. Constant velocity
with white-acceleration noise ``q`` otherwise (2-D, state ``[x, vx, y, vy]``). A position sensor (``R``
per axis) detects each target with probability ``P_D``; Poisson clutter (``clutter_rate`` a scan) is
uniform over the square ``[-region, region]^2``. Tracks start from the true initial states perturbed
by ``N(0, P0)``, one per target (no track initiation or deletion: the number of targets is known).

Estimators (``tracking.estimators``):

* ``IMM-JPDAF``: ``JPDA(IMM(KalmanFilter(bank)))``: the joint association over an IMM of the truth's
  three acceleration modes (Blom & Bloem 2000), exact.
* ``JPDAF``: ``JPDA(KalmanFilter(cv))``: one constant-velocity model with the inflated noise ``q_cv``.
* ``IMM-PDAF``: ``IMM(PDA(KalmanFilter(bank)))`` per target (Houles & Bar-Shalom 1989): every track
  associates alone, the scan shared.
* ``GNN-IMM``: ``GNN(IMM(KalmanFilter(bank)))``: the best joint event.

Tables: ``gospa`` (estimator; time-averaged GOSPA (``c``, ``p``, ``alpha = 2``) with its standard
error over the runs; its localisation / missed / false parts; label switches a run; the fraction of
targets lost at the end (no track within ``c``); seconds per track-scan). Figures: GOSPA over time
with 95 % bands. TensorBoard: the GOSPA curves. Sweeps: ``-m tracking.clutter_rate=2,10,30`` or
``tracking.detection_probability=0.7,0.9,0.99``.
"""

from __future__ import annotations

import math
import time

import torch

from experiments.arrays import join_runs, per_run
from experiments.executors import Unit
from experiments.harness import StudyContext
from experiments.studies import plots
from torchmm import IMM, GaussianBelief, KalmanFilter, run_filter
from torchmm.association import GNN, JPDA, PDA
from torchmm.beliefs import psd_sqrt
from torchmm.metrics import gospa
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.simulate import simulate_detections

ESTIMATORS = ("IMM-JPDAF", "JPDAF", "IMM-PDAF", "GNN-IMM")
UNIT = "experiments.studies.tracking:unit"


def _bank(t, dtype) -> ConstantVelocity:
    a = float(t.maneuver_acceleration)
    return ConstantVelocity(2, dt=float(t.dt), q=float(t.q), acceleration=[[0.0, 0.0], [0.0, a], [0.0, -a]],
                            dtype=dtype)


def simulate(t, runs: int, generator: torch.Generator, dtype=torch.float64):
    """Truth ``(T, runs, N, 4)``, detections ``(T, runs, D, 2)`` and the tracks' start ``(runs, N, 4)``."""
    N, T, dt = int(t.targets), int(t.steps), float(t.dt)
    bank = _bank(t, dtype)
    F, Q, offset = bank.F, bank.Q, bank.offset  # offset (3, 4): each mode's G a
    angle = 2 * math.pi * torch.arange(N, dtype=dtype) / N
    speed = float(t.radius) / (T / 2 * dt)  # at the centre at mid-run
    start = torch.stack([float(t.radius) * angle.cos(), -speed * angle.cos(),
                         float(t.radius) * angle.sin(), -speed * angle.sin()], -1).expand(runs, N, 4)
    push = torch.where(torch.arange(N) % 2 == 0, 1, 2)  # the mode each target takes in the manoeuvre
    LQ = psd_sqrt(Q)  # q G G^T: singular
    x, states = start, []
    for k in range(T):
        turning = int(t.maneuver_start) <= k < int(t.maneuver_stop)
        x = x @ F.mT + (offset[push] if turning else 0.0) + torch.randn(runs, N, 4, generator=generator,
                                                                          dtype=dtype) @ LQ.mT
        states.append(x)
    truth = torch.stack(states)
    sensor = PositionMeasurement(4, [0, 2], float(t.R), dtype=dtype)
    L = float(t.region)
    rate = float(t.clutter_rate)
    det = simulate_detections(sensor, truth, detection_probability=float(t.detection_probability),
                              clutter_rate=rate, region=torch.tensor([[-L, L], [-L, L]], dtype=dtype),
                              max_clutter=int(rate + 6 * math.sqrt(rate) + 5), generator=generator)
    P0 = torch.tensor(list(t.P0), dtype=dtype)
    x0 = start + torch.randn(runs, N, 4, generator=generator, dtype=dtype) * P0.sqrt()
    return truth, det.z, x0


def estimators(t, dtype) -> dict:
    """The configured estimators: name -> (filter, initial-belief maker, whether scans go per track)."""
    bank = _bank(t, dtype)
    cv = ConstantVelocity(2, dt=float(t.dt), q=float(t.q_cv), dtype=dtype)
    sensor = PositionMeasurement(4, [0, 2], float(t.R), dtype=dtype)
    M, stay = 3, float(t.stay)
    off = (1 - stay) / (M - 1)
    Pi = torch.full((M, M), off, dtype=dtype) + (stay - off) * torch.eye(M, dtype=dtype)
    opts = {"detection_probability": float(t.detection_probability),
            "clutter_density": float(t.clutter_rate) / (2 * float(t.region)) ** 2,
            "gate_probability": float(t.gate_probability)}
    imm = IMM(KalmanFilter(bank, sensor), Pi)
    per_track = IMM(PDA(KalmanFilter(bank, sensor), **opts), Pi)
    made = {
        "IMM-JPDAF": (JPDA(imm, **opts), imm.initial_belief, False),
        "JPDAF": (JPDA(KalmanFilter(cv, sensor), **opts), lambda b: b, False),
        "IMM-PDAF": (per_track, per_track.initial_belief, True),
        "GNN-IMM": (GNN(imm, **opts), imm.initial_belief, False),
    }
    return {name: made[name] for name in t.estimators}


def _data(ctx: StudyContext, start: int, stop: int):
    t = ctx.cfg.tracking

    def simulate_block():
        return ctx.simulate_runs(lambda n, gen: simulate(t, n, gen), stop, "tracking", axes=(1, 1, 0), start=start)
    return ctx.memo(("data", start, stop), simulate_block)


def unit(ctx: StudyContext, *, name: str, start: int, stop: int) -> dict:
    """Estimator ``name`` on runs ``start..stop-1``: per-run GOSPA curves and parts ``(T, runs)``,
    label switches and lost targets ``(runs,)``, and the seconds it took."""
    t = ctx.cfg.tracking
    truth, z, x0 = (v.to(ctx.dtype) for v in _data(ctx, start, stop))
    filt, initial, per_track = estimators(t, ctx.dtype)[name]
    P0 = torch.diag(torch.tensor(list(t.P0), dtype=ctx.dtype))
    belief = initial(GaussianBelief(x0, P0))
    scans = z.unsqueeze(-3) if per_track else z  # IMM-PDAF: every track sees the run's scan
    filt, belief, scans = filt.to(ctx.device), belief.to(ctx.device), scans.to(ctx.device)
    tic = time.perf_counter()
    with torch.no_grad():
        traj = run_filter(filt, belief, scans, record="estimate")
    seconds = time.perf_counter() - tic
    est = traj.belief.mean[..., [0, 2]].cpu().double()  # (T, runs, N, 2)
    out = gospa(est, truth[..., [0, 2]].double(), c=float(t.gospa_c), p=float(t.gospa_p))
    assigned = out["assigned"]  # (T, runs, N): the track on each target, -1 none within c
    both = (assigned[1:] >= 0) & (assigned[:-1] >= 0)
    switches = (both & (assigned[1:] != assigned[:-1])).sum((0, 2)).double()  # (runs,)
    lost = (assigned[-1] < 0).double().mean(-1)  # (runs,)
    return {key: per_run(out[key]) for key in ("distance", "localisation", "missed", "false")} | {
        "switches": per_run(switches), "lost": per_run(lost), "seconds": seconds,
        "track_scans": int(est.shape[0] * est.shape[1] * est.shape[2])}


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    t = cfg.tracking
    runs = int(cfg.mc_runs)
    names = list(t.estimators)
    ranges = ctx.run_ranges(runs)
    parts = ctx.map_units([Unit(f"tracking/{name}/runs{a}-{b}", UNIT, {"name": name, "start": a, "stop": b})
                           for name in names for a, b in ranges], desc="estimators")
    ctx.results.description = (
        f"{t.targets} crossing targets, {t.steps} scans, manoeuvre {t.maneuver_start}-{t.maneuver_stop} "
        f"(+-{t.maneuver_acceleration} m/s^2), P_D = {t.detection_probability}, {t.clutter_rate} clutter "
        f"points a scan over [-{t.region}, {t.region}]^2, R = {t.R}; {runs} Monte Carlo runs (seed {cfg.seed}, "
        f"{cfg.dtype}). GOSPA with c = {t.gospa_c}, p = {t.gospa_p}, alpha = 2.")
    table = ctx.results.table(
        "gospa", ["estimator", "gospa", "gospa_se", "localisation", "missed", "false", "label_switches",
                  "lost_fraction", "seconds_per_track_scan"],
        note="gospa: the GOSPA distance averaged over steps and runs, gospa_se its standard error over the "
             "runs (95 %: +- 1.96 se). localisation / missed / false: the parts of GOSPA^p (units of "
             "distance^p), averaged the same way. label_switches: times a target's track changed, a run. "
             "lost_fraction: targets without a track within c at the last scan.")
    curves, bands = {"GOSPA": {}}, {"GOSPA": {}}
    n = len(ranges)
    for i, name in enumerate(names):
        mine = parts[i * n:(i + 1) * n]
        dist = join_runs([p["distance"] for p in mine])  # (T, runs)
        per_run_mean = dist.mean(0)
        curve, band = dist.mean(1), dist.std(1) / math.sqrt(dist.shape[1]) if dist.shape[1] > 1 else None
        parts_mean = {k: float(join_runs([p[k] for p in mine]).mean()) for k in ("localisation", "missed", "false")}
        switches = float(join_runs([p["switches"] for p in mine], dim=0).mean())
        lost = float(join_runs([p["lost"] for p in mine], dim=0).mean())
        seconds = sum(p["seconds"] for p in mine) / sum(p["track_scans"] for p in mine)
        se = float(per_run_mean.std() / math.sqrt(len(per_run_mean))) if len(per_run_mean) > 1 else None
        table.rows.append([name, float(per_run_mean.mean()), se, parts_mean["localisation"], parts_mean["missed"],
                           parts_mean["false"], switches, lost, seconds])
        ctx.results.metric(name, "gospa", float(per_run_mean.mean()))
        ctx.results.metric(name, "lost_fraction", lost)
        ctx.results.timing[name] = seconds
        curves["GOSPA"][name] = curve
        ctx.logger.series(f"gospa/{name}", curve)
        if band is not None:
            bands["GOSPA"][name] = band
            ctx.logger.series(f"gospa_se/{name}", band)
    ctx.results.save()
    ctx.save_figure("gospa_over_time", plots.rmse_over_time(curves, f"{t.targets} crossing targets in clutter, "
                                                                    f"{runs} runs", bands=bands))

"""Study ``smoothing``: filter against fixed-interval smoother, and the parallel-in-time scan's speed.

For every scenario of ``smoothing.scenarios`` (by default paper 000's 1-D target, paper 001's
two-model maneuvering target and a 2-D CV/CT maneuvering target) and every estimator (a Kalman,
an extended and an unscented Kalman filter on the constant-velocity model, IMM and GPB2 over the
scenario's mode bank, IMM over unscented mode filters), the runs are filtered and then smoothed
with :func:`torchmm.smooth` (RTS, extended RTS, unscented RTS, the two-filter IMM smoother, and Kim's
smoother beside it for the multiple-model estimators: docs/smoothing.md).

Tables: ``rmse`` (scenario, estimator, smoother, filter and smoother position / velocity RMSE with
their delta-method standard errors, the smoother's position gain and NEES), ``modes`` (filter and
smoother mode accuracy of the multiple-model estimators), ``parallel_speed`` (sequential against associative-scan
Kalman filtering + smoothing, ``torchmm.parallel``, for ``smoothing.speed_steps`` and ``speed_runs``; only with
``smoothing.speed=true``: at T = 10^4 it takes most of a full run, whatever ``mc_runs``). Curves: position
RMSE over time, filter and smoother, per scenario; figures of them and of the speed table.
"""

from __future__ import annotations

import logging
import time

import torch
from hydra.utils import instantiate

from experiments.estimators import evaluate_runs, reduce_runs
from experiments.executors import Unit
from experiments.harness import StudyContext, per_run
from experiments.studies import plots
from torchmm import GaussianBelief, KalmanFilter, UnscentedKalmanFilter, parallel, run_filter, smooth
from torchmm.metrics import mode_hits, nees, squared_error
from torchmm.models import ConstantVelocity, PositionMeasurement

log = logging.getLogger("torchmm.experiments")

#: the builder of single-filter estimators (they get the scenario's constant-velocity mode)
SINGLE = "experiments.estimators.kalman"


def _data(ctx: StudyContext, key: str, start: int, stop: int):
    """``(scenario, sim, z)`` of ``smoothing.scenarios[key]``, runs ``start..stop-1``, once per process."""
    def simulate():
        scenario, data_scenario = ctx.scenarios(ctx.cfg.smoothing.scenarios[key])
        sim, z = ctx.simulate_runs(data_scenario.simulate, stop, "data", key, start=start)
        return scenario, sim.to(ctx.dtype), z.to(ctx.dtype)  # the same data in any dtype

    return ctx.memo(("data", key, start, stop), simulate)


def _estimator(ctx: StudyContext, key: str, name: str, scenario):
    node = ctx.cfg.estimators[name]
    options = {"mode": int(ctx.cfg.smoothing.cv_mode[key])} if node.get("_target_") == SINGLE else {}
    return instantiate(node)(scenario, name=name, **options)


#: the study's unit function (what an executor ships)
UNIT = "experiments.studies.smoothing:unit"


def _smoother_label(est) -> str:
    """The smoother torchmm.smooth picks for the estimator's filter."""
    if est.multiple_model:
        return "two-filter"
    if isinstance(est.filter, UnscentedKalmanFilter):
        return "unscented RTS"
    return "RTS" if isinstance(est.filter, KalmanFilter) else "extended RTS"


def unit(ctx: StudyContext, *, scenario: str, name: str, start: int, stop: int) -> dict:
    """Estimator ``name`` on runs ``start..stop-1`` of ``scenario``: per-run values of the filter and
    of its smoothers (:func:`~experiments.estimators.evaluate_runs`'s format, merged by ``reduce_runs``):
    ``smoother`` (RTS, extended or unscented RTS, or the two-filter IMM smoother) and, for the
    multiple-model estimators, ``kim`` (Kim's smoother)."""
    scen, sim, z = _data(ctx, scenario, start, stop)
    est = _estimator(ctx, scenario, name, scen)
    filtered, traj = evaluate_runs(est, scen, sim, z, keep_trajectory="all", block_runs=ctx.block_runs,
                                   generators=ctx.block_generators("filter", scenario, name), first_run=start)
    out = {"filter": filtered}
    for key, method in (("smoother", None), ("kim", "kim")) if est.multiple_model else (("smoother", None),):
        tic = time.perf_counter()
        smoothed = smooth(est.filter, traj, z, method=method)
        seconds = time.perf_counter() - tic
        est_s = smoothed.estimate()
        truth = sim.states
        hits = None
        if est.multiple_model:
            hits = per_run(mode_hits(smoothed.belief.mode_log_probs, sim.modes).to(est_s.mean.dtype).sum(1))
        out[key] = {
            "pos": per_run(squared_error(est_s.mean, truth, scen.position)),
            "vel": per_run(squared_error(est_s.mean, truth, scen.velocity)),
            "nees_sum": per_run(nees(est_s, truth).sum(1)), "hits_sum": hits, "sums": {},
            "runs": filtered["runs"], "seconds": seconds, "state_dim": filtered["state_dim"],
        }
    return out


def _speed_table(ctx: StudyContext):
    """Sequential against associative-scan Kalman filtering + RTS smoothing (a 2-D CV target)."""
    cfg = ctx.cfg.smoothing
    dtype, device = ctx.dtype, ctx.device
    kf = KalmanFilter(ConstantVelocity(2, q=0.1, dtype=dtype), PositionMeasurement(4, [0, 2], 4.0, dtype=dtype)).to(device)
    runs = int(cfg.speed_runs)
    table = ctx.results.table(
        "parallel_speed", ["steps", "runs", "sequential_seconds", "parallel_seconds", "time_ratio", "max_abs_diff"],
        note="run_filter + torchmm.smooth (T steps one after another) against torchmm.parallel.smooth (two "
             "associative scans, ~2 log2 T levels); time_ratio = sequential / parallel (best of 3); "
             f"max_abs_diff: of the smoothed means. {ctx.device}, {ctx.cfg.dtype}, one thread unless threads=.")
    for steps in ctx.progress_bar([int(s) for s in cfg.speed_steps], desc="parallel scan"):
        g = ctx.generator("speed", steps)
        z = torch.cumsum(torch.randn(steps, runs, 2, generator=g, dtype=torch.float64, device=device), 0).to(dtype)
        b0 = GaussianBelief(torch.zeros(runs, 4, dtype=dtype, device=device),
                            10 * torch.eye(4, dtype=dtype, device=device).expand(runs, 4, 4))
        times = {}
        with torch.no_grad():
            for label, fn in (("sequential", lambda: smooth(kf, run_filter(kf, b0, z)).belief.mean),
                              ("parallel", lambda: parallel.smooth(kf, b0, z).belief.mean)):
                best = float("inf")
                for _ in range(3 if steps <= 10000 else 1):
                    if device.type == "cuda":
                        torch.cuda.synchronize()
                    tic = time.perf_counter()
                    out = fn()
                    if device.type == "cuda":
                        torch.cuda.synchronize()
                    best = min(best, time.perf_counter() - tic)
                times[label] = (best, out)
        diff = (times["sequential"][1] - times["parallel"][1]).abs().max().item()
        seq, par = times["sequential"][0], times["parallel"][0]
        table.rows.append([steps, runs, seq, par, seq / par, diff])
    if table.rows:
        ctx.logger.sweep("parallel_time_ratio/sequential_over_parallel", [r[0] for r in table.rows],
                         [r[4] for r in table.rows], "steps")
    return table


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    scfg = cfg.smoothing
    keys, names = list(scfg.scenarios), list(cfg.estimators)  # smoothing.cv_mode: checked by the schema
    ranges = ctx.run_ranges(cfg.mc_runs)
    scenarios = {k: _data(ctx, k, *ranges[0])[0] for k in keys}
    for k in keys:  # a bad estimator config: an error before any unit runs
        for name in names:
            _estimator(ctx, k, name, scenarios[k])
    ctx.results.description = (
        f"Filter against fixed-interval smoother (torchmm.smooth) on {len(keys)} scenarios, {cfg.mc_runs} Monte "
        f"Carlo runs each (seed {cfg.seed}, {cfg.dtype}); RMSE per step over the runs, averaged over time. "
        "Single filters run on the scenario's constant-velocity mode; the multiple-model ones over its mode bank "
        "(the two-filter IMM smoother, and Kim's beside it). Every scenario here is linear: the extended and "
        "unscented filters and smoothers equal the Kalman ones to rounding."
    )
    units = [Unit(f"{k}/{name}/runs{a}-{b}", UNIT, {"scenario": k, "name": name, "start": a, "stop": b})
             for k in keys for name in names for a, b in ranges]
    parts = ctx.map_units(units, desc="estimators")
    rmse = ctx.results.table(
        "rmse", ["scenario", "estimator", "smoother", "filter_pos_rmse", "smoother_pos_rmse", "filter_vel_rmse",
                 "smoother_vel_rmse", "filter_pos_rmse_se", "smoother_pos_rmse_se", "filter_vel_rmse_se",
                 "smoother_vel_rmse_se", "pos_gain", "smoother_nees"],
        note="smoother: RTS, extended / unscented RTS, the two-filter IMM smoother (the default for multiple-model "
             "filters) or Kim's (a second row). _se: delta-method standard errors over the runs (95 %: +- 1.96 "
             "se; filter and smoother are computed on the same runs, so their difference is far more certain "
             "than either). pos_gain: 1 - smoother / filter position RMSE. smoother_nees: mean NEES of the "
             "smoothed estimate (its state dimension when the covariance is consistent).")
    modes = ctx.results.table(
        "modes", ["scenario", "estimator", "smoother", "filter_mode_accuracy", "smoother_mode_accuracy"],
        note="Fraction of (step, run) pairs whose most probable mode is the true one.")
    n = len(ranges)
    for i, (k, name) in enumerate((k, name) for k in keys for name in names):
        mine = parts[i * n:(i + 1) * n]
        ev_f = reduce_runs([p["filter"] for p in mine])
        f = ev_f.summary()
        est = _estimator(ctx, k, name, scenarios[k])
        smoothers = [("smoother", _smoother_label(est))] + ([("kim", "Kim")] if est.multiple_model else [])
        for key, smoother in smoothers:
            ev_s = reduce_runs([p[key] for p in mine])
            s = ev_s.summary()
            rmse.rows.append([k, name, smoother, f["pos_rmse"], s["pos_rmse"], f["vel_rmse"], s["vel_rmse"],
                              f["pos_rmse_se"], s["pos_rmse_se"], f["vel_rmse_se"], s["vel_rmse_se"],
                              1 - s["pos_rmse"] / f["pos_rmse"], s["nees"]])
            if ev_f.mode_accuracy is not None:
                modes.rows.append([k, name, smoother, f["mode_accuracy"], s["mode_accuracy"]])
            label = "smoother" if key == "smoother" else "Kim smoother"
            ctx.results.metric(f"{k}/{name} {label}", "pos_rmse", s["pos_rmse"])
            ctx.logger.series(f"pos_rmse_{k}/{name} {label}", ev_s.pos_rmse)  # one figure per scenario
            ctx.logger.series(f"pos_rmse_{k}_se/{name} {label}", ev_s.pos_rmse_band)
            ctx.results.timing[f"{k}/{name} {label}"] = ev_s.seconds_per_step
        ctx.results.metric(f"{k}/{name} filter", "pos_rmse", f["pos_rmse"])
        ctx.logger.series(f"pos_rmse_{k}/{name} filter", ev_f.pos_rmse)
        ctx.logger.series(f"pos_rmse_{k}_se/{name} filter", ev_f.pos_rmse_band)
    ctx.results.save()
    for k in keys:
        rows = [r for r in rmse.rows if r[0] == k]
        ctx.save_figure(f"rmse_{k}", _bars(rows, k, int(cfg.mc_runs)))
    if not cfg.smoothing.speed:  # smoothing.speed=false (debug=smoothing): no speed table
        return
    speed = _speed_table(ctx)
    ctx.results.save()
    if speed.rows:
        ctx.save_figure("parallel_speed", plots.lines(
            [r[0] for r in speed.rows], {"sequential / parallel": [r[4] for r in speed.rows]}, xlabel="steps T",
            ylabel="time ratio", logx=True, title=f"parallel-in-time Kalman smoother, {speed.rows[0][1]} runs"))


def _bars(rows, key: str, runs: int):
    """Filter and smoother position RMSE per estimator, with 95 % intervals."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 3.4))
    names = [r[1] if r[2] != "Kim" else f"{r[1]} (Kim)" for r in rows]
    xs = torch.arange(len(rows), dtype=torch.float64)
    for offset, (label, col, se) in zip((-0.2, 0.2), (("filter", 3, 7), ("smoother", 4, 8))):
        ax.bar((xs + offset).tolist(), [r[col] for r in rows], width=0.4, label=label,
               yerr=[1.96 * (r[se] or 0.0) for r in rows], capsize=3)
    ax.set_xticks(xs.tolist(), names, rotation=20)
    ax.set_ylabel("position RMSE")
    ax.set_title(f"{key}, {runs} runs")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig

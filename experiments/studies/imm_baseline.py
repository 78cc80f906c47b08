"""Default study: IMM, GPB1, GPB2 and a single Kalman filter on one Markov-jump scenario.

The paper-000 target (accelerations {0.25, 0, -0.25}, R = 100) without source data, by default.
Tables: ``rmse`` (estimator, pos_rmse, vel_rmse, nees, mode_accuracy); metrics per estimator;
timing; figures RMSE over time (95 % bands), NEES over time (95 % chi-square band), run 0's mode
probabilities (one panel per multiple-model estimator) and run 0's trajectory (+- 2 sigma bands);
TensorBoard per-step scalars.
"""

from __future__ import annotations

import logging

import torch
from hydra.utils import instantiate

from experiments.estimators import evaluate_runs, reduce_runs
from experiments.uncertainty import nees_consistency
from experiments.executors import Unit
from experiments.harness import StudyContext, per_run
from experiments.studies import plots

log = logging.getLogger("torchmm.experiments")


def _data(ctx: StudyContext, start: int = 0, stop: int | None = None):
    """``(scenario, sim, z)``: the scenario and its run-indexed data of runs ``start..stop-1`` (all
    by default), simulated once per process."""
    stop = int(ctx.cfg.mc_runs) if stop is None else stop

    def simulate():
        scenario, data_scenario = ctx.scenarios(ctx.cfg.scenario)
        sim, z = ctx.simulate_runs(data_scenario.simulate, stop, "data", scenario.name, start=start)
        return scenario, sim.to(ctx.dtype), z.to(ctx.dtype)  # the same data in any dtype

    return ctx.memo(("data", start, stop), simulate)


#: the study's unit function (what an executor ships: this path, the config and the arguments)
UNIT = "experiments.studies.imm_baseline:unit"


def unit(ctx: StudyContext, *, name: str, start: int, stop: int) -> dict:
    """Estimator ``name`` on runs ``start..stop-1`` (``ctx.run_ranges``): per-run values
    (:func:`~experiments.estimators.evaluate_runs`), and in the first unit run 0's mode probabilities
    and estimates (mean and covariance, for the trajectory figure)."""
    scenario, sim, z = _data(ctx, start, stop)
    est = instantiate(ctx.cfg.estimators[name])(scenario, name=name)
    stats = {"mode_probs": lambda traj: traj.belief.mode_probs} if est.multiple_model else {}
    values, kept = evaluate_runs(est, scenario, sim, z, chunk_runs=ctx.cfg.get("chunk_runs"),
                                 keep_trajectory=start == 0, per_step=stats, block_runs=ctx.block_runs,
                                 generators=ctx.block_generators("filter", scenario.name, est.name), first_run=start)
    values["example"] = kept.belief.mode_probs[:, 0] if est.multiple_model and kept is not None else None  # (T, M)
    estimate = kept.estimate() if kept is not None else None  # run 0: (T, n), (T, n, n)
    values["example_mean"] = per_run(estimate.mean[:, 0]) if estimate is not None else None
    values["example_cov"] = per_run(estimate.cov[:, 0]) if estimate is not None else None
    return values


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    ranges = ctx.run_ranges(cfg.mc_runs)
    scenario, sim, z = _data(ctx, *ranges[0])  # run-indexed streams (here: the first unit's runs, for run 0)
    names = list(cfg.estimators)
    for name in names:  # a bad estimator config: an error before any unit runs
        instantiate(cfg.estimators[name])(scenario, name=name)
    ctx.results.description = (
        f"Scenario `{scenario.name}`: {scenario.num_modes} modes, {scenario.steps} steps, "
        f"{cfg.mc_runs} Monte Carlo runs (seed {cfg.seed}, {cfg.dtype}). RMSE is per step over runs, "
        "then averaged over time (the papers' average RMSE)."
    )
    table = ctx.results.table(
        "rmse", ["estimator", "pos_rmse", "vel_rmse", "nees", "mode_accuracy", "pos_rmse_se", "vel_rmse_se",
                 "nees_low", "nees_high", "nees_steps_inside"],
        note="_se: delta-method standard errors of the average RMSE over runs (95 % interval: +- 1.96 se). "
             "nees_low/high: the 95 % chi-square interval of a step's NEES averaged over the runs; "
             "nees_steps_inside: the fraction of steps inside it (0.95 for a consistent filter).")
    curves = {"position RMSE": {}, "velocity RMSE": {}}
    bands = {"position RMSE": {}, "velocity RMSE": {}}  # per-step standard errors of the curves
    examples = {}  # run 0's mode probabilities of each multiple-model estimator, (T, M)
    estimates = {}  # run 0's estimate of each estimator: mean (T, n), covariance (T, n, n)
    consistency = {}  # each estimator's 95 % chi-square band of the run-averaged NEES
    # every estimator x range of runs is a unit, all at once: an executor (executor=processes|slurm|ray)
    # runs them side by side; each estimator's ranges are reduced in run order
    units = [Unit(f"{name}/runs{a}-{b}", UNIT, {"name": name, "start": a, "stop": b})
             for name in names for a, b in ranges]
    parts = ctx.map_units(units, desc="estimators")

    def f64(values):
        return torch.as_tensor(values, dtype=torch.float64)

    for i, name in enumerate(names):
        mine = parts[i * len(ranges):(i + 1) * len(ranges)]
        ev = reduce_runs(mine)
        summary = ev.summary()
        lo, hi, inside = nees_consistency(ev.nees, ev.runs, ev.state_dim)  # 95 % band of the run-averaged NEES
        consistency[name] = (f64(ev.nees), (lo, hi))
        table.rows.append([name, summary["pos_rmse"], summary["vel_rmse"], summary["nees"],
                           summary.get("mode_accuracy"), summary["pos_rmse_se"], summary["vel_rmse_se"], lo, hi,
                           inside])
        for key, value in summary.items():
            ctx.results.metric(name, key, value)
        ctx.results.timing[name] = ev.seconds_per_step
        curves["position RMSE"][name], curves["velocity RMSE"][name] = f64(ev.pos_rmse), f64(ev.vel_rmse)
        bands["position RMSE"][name], bands["velocity RMSE"][name] = f64(ev.pos_rmse_band), f64(ev.vel_rmse_band)
        ctx.logger.series(f"pos_rmse/{name}", ev.pos_rmse)
        ctx.logger.series(f"vel_rmse/{name}", ev.vel_rmse)
        ctx.logger.series(f"pos_rmse_se/{name}", ev.pos_rmse_band)
        ctx.logger.series(f"vel_rmse_se/{name}", ev.vel_rmse_band)
        ctx.logger.series(f"nees/{name}", ev.nees)
        ctx.logger.series(f"nees_low/{name}", [lo] * len(ev.nees))  # the band torchmm-plot shades
        ctx.logger.series(f"nees_high/{name}", [hi] * len(ev.nees))
        if mine[0].get("example_mean") is not None:
            estimates[name] = (f64(mine[0]["example_mean"]), f64(mine[0]["example_cov"]))
        if ev.mode_accuracy is not None:  # a multiple-model estimator
            ctx.logger.series(f"mode_accuracy/{name}", ev.mode_accuracy)
            if ev.mode_accuracy_se is not None:  # sd over runs / sqrt(N) (none: a unit checkpointed without it)
                ctx.logger.series(f"mode_accuracy_se/{name}", ev.mode_accuracy_se)
            probs = f64(ev.means["mode_probs"])  # average over all runs, (T, M)
            probs_se = ev.means_se.get("mode_probs")  # its standard error, (T, M)
            for j, label in enumerate(scenario.mode_labels):
                ctx.logger.series(f"mode_probability/{name}/{label}", probs[:, j])
                if probs_se is not None:
                    ctx.logger.series(f"mode_probability_se/{name}/{label}", f64(probs_se)[:, j])
            if mine[0].get("example") is not None:
                examples[name] = f64(mine[0]["example"])  # run 0, (T, M)
        log.info("%s: %s", name, {k: round(val, 4) for k, val in summary.items() if isinstance(val, float)})
    ctx.results.save()
    ctx.save_figure("rmse_over_time", plots.rmse_over_time(curves, f"{scenario.name}, {cfg.mc_runs} runs",
                                                                  bands=bands))
    ctx.save_figure("nees", plots.nees_over_time({n: v for n, (v, _) in consistency.items()},
                                                 {n: b for n, (_, b) in consistency.items()},
                                                 f"{scenario.name}, {cfg.mc_runs} runs"))
    if examples:
        ctx.save_figure("mode_probabilities", plots.mode_probabilities(
            examples, sim.modes[:, 0], scenario.mode_labels, "run 0"))
    if estimates:
        position = list(scenario.position)[:2]  # x (and y)
        # the measurements as dots where they are the position itself (a position sensor)
        direct = list(getattr(scenario.measurement, "indices", ())) == position
        ctx.save_figure("trajectory", plots.trajectory(
            sim.states[:, 0], z[:, 0] if direct else None, estimates, components=position, run=None,
            title=f"{scenario.name}, run 0"))

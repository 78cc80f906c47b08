"""Default study: IMM, GPB1, GPB2 and a single Kalman filter on one Markov-jump scenario.

The paper-000 target (accelerations {0.25, 0, -0.25}, R = 100) without source data, by default.
Tables: ``rmse`` (estimator, pos_rmse, vel_rmse, nees, mode_accuracy); metrics per estimator;
timing; figures RMSE over time and one run's mode probabilities; TensorBoard per-step scalars.
"""

from __future__ import annotations

import logging

from hydra.utils import instantiate

from experiments.estimators import evaluate
from experiments.uncertainty import chi2_interval
from experiments.harness import StudyContext
from experiments.studies import plots

log = logging.getLogger("torchmm.experiments")


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    scenario, data_scenario = ctx.scenarios(cfg.scenario)
    estimators = [instantiate(ecfg)(scenario, name=name) for name, ecfg in cfg.estimators.items()]
    sim, z = ctx.simulate_runs(data_scenario.simulate, int(cfg.mc_runs), "data", scenario.name)  # run-indexed
    sim, z = sim.to(ctx.dtype), z.to(ctx.dtype)  # the same data in float32 and float64
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
    example = None
    for est in ctx.progress_bar(estimators, desc="estimators"):
        stats = {"mode_probs": lambda traj: traj.belief.mode_probs} if est.multiple_model else {}
        ev = evaluate(est, scenario, sim, z, chunk_runs=cfg.get("chunk_runs"), keep_trajectory=True,
                      per_step=stats, block_runs=ctx.block_runs,
                      generators=ctx.block_generators("filter", scenario.name, est.name))
        summary = ev.summary()
        lo, hi = chi2_interval(ev.runs * ev.state_dim)
        lo, hi = lo * ev.state_dim, hi * ev.state_dim  # the interval of the run-averaged NEES
        inside = ((ev.nees >= lo) & (ev.nees <= hi)).double().mean().item()
        table.rows.append([est.name, summary["pos_rmse"], summary["vel_rmse"], summary["nees"],
                           summary.get("mode_accuracy"), summary["pos_rmse_se"], summary["vel_rmse_se"], lo, hi,
                           inside])
        for key, value in summary.items():
            ctx.results.metric(est.name, key, value)
        ctx.results.timing[est.name] = ev.seconds_per_step
        curves["position RMSE"][est.name] = ev.pos_rmse
        curves["velocity RMSE"][est.name] = ev.vel_rmse
        bands["position RMSE"][est.name] = ev.pos_rmse_band
        bands["velocity RMSE"][est.name] = ev.vel_rmse_band
        ctx.logger.series(f"pos_rmse/{est.name}", ev.pos_rmse)
        ctx.logger.series(f"vel_rmse/{est.name}", ev.vel_rmse)
        ctx.logger.series(f"pos_rmse_se/{est.name}", ev.pos_rmse_band)
        ctx.logger.series(f"vel_rmse_se/{est.name}", ev.vel_rmse_band)
        ctx.logger.series(f"nees/{est.name}", ev.nees)
        if est.multiple_model:
            ctx.logger.series(f"mode_accuracy/{est.name}", ev.mode_accuracy)
            probs = ev.means["mode_probs"]  # average over all runs (every chunk), (T, M)
            for j, label in enumerate(scenario.mode_labels):
                ctx.logger.series(f"mode_probability/{est.name}/{label}", probs[:, j])
            if example is None:
                example = (est.name, ev.trajectory.belief.mode_probs[:, 0])  # run 0 (first chunk)
        log.info("%s: %s", est.name, {k: round(v, 4) for k, v in summary.items()})
        ctx.results.save()
    ctx.save_figure("rmse_over_time", plots.rmse_over_time(curves, f"{scenario.name}, {cfg.mc_runs} runs",
                                                                  bands=bands))
    if example is not None:
        name, probs = example
        ctx.save_figure("mode_probabilities", plots.mode_probabilities(
            probs, sim.modes[:, 0], scenario.mode_labels, f"{name}, run 0"))

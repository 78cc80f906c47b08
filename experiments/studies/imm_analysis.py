"""Paper 001 study: IMM input-interaction analysis over an alpha sweep (docs/specification.md §3.2).

For each scenario (a 2- and a 3-model maneuvering target) and each ``alpha`` of the symmetric
transition matrix (2.2) (``alpha_j = alpha`` for every mode), the estimators run on the same
simulated data. From the IMM run's internals, every step ``k`` and run is checked against the
premises and claims of Conclusions 1-5 and the mode-probability bounds (3.2)/(3.3), (3.8)
(library functions in :mod:`torchmm.analysis`).

Tables: ``conclusions`` (conclusion, premise_steps, holds_fraction, ...), ``conclusions_by_alpha``,
``bounds``, ``alpha_sweep`` (models, alpha, estimator, pos_rmse, vel_rmse, mode_accuracy) and
``compression`` (models, alpha, mean_delta, mean_zeta).
"""

from __future__ import annotations

import logging
import math

import torch
from hydra.utils import instantiate

from experiments.estimators import evaluate_runs, reduce_runs
from experiments.executors import Unit
from experiments.harness import StudyContext
from experiments.studies import plots
from experiments.uncertainty import mean_se_per_step
from torchmm import alpha_transition
from torchmm.analysis import (
    check_conclusions,
    check_probability_bounds,
    delta_ratio,
    matched_model,
    zeta_ratio,
)

log = logging.getLogger("torchmm.experiments")


STATEMENTS = {
    1: "sum(alpha) < 1: the matched model's interacted estimate is closer than the output (delta < 1)",
    2: "sum(alpha) <= 1, output closer than model j: interaction improves model j",
    3: "2 models, pi_ij > 0: interaction improves the mismatched model (zeta < 1)",
    4: "2 models, diagonally dominant: matched start better than output, mismatched start worse",
    5: "3 models, pi_ij > 0: some mismatched model is improved by the interaction",
}


def _analyse(ctx: StudyContext, scenario, sim, z, alpha: float, start: int = 0) -> dict:
    """One (scenario, alpha) unit on the runs of ``sim``/``z`` (runs ``start..``): every estimator's
    per-run values (:func:`~experiments.estimators.evaluate_runs`), conclusion and bound counts, and
    sums of delta(k) and zeta(k) - all additive over units of runs (:func:`_merge`)."""
    cfg, acfg = ctx.cfg, ctx.cfg.analysis
    M = scenario.num_modes
    alphas = torch.full((M,), float(alpha), dtype=ctx.dtype, device=ctx.device)
    transition = alpha_transition(alphas)
    out: dict = {"runs": {}, "bounds": {}}
    for name, ecfg in cfg.estimators.items():
        est = instantiate(ecfg)(scenario, name=name, transition=transition)
        out["runs"][name], traj = evaluate_runs(est, scenario, sim, z, keep_trajectory="all",  # every run
                                                block_runs=ctx.block_runs, first_run=start,
                                                generators=ctx.block_generators("filter", alpha, name))
        # (3.2)/(3.3) and (3.8): posterior u(k) and predicted u^0(k) of the next cycle
        probs = traj.belief.mode_probs[:-1]
        predicted = traj.prior.mode_log_probs[1:].exp()
        for bound, check in check_probability_bounds(alphas, probs, predicted, tol=acfg.tol).items():
            out["bounds"][f"{bound}|{name}"] = [int(check.premise.sum()), int((check.premise & check.holds).sum())]
        if name != acfg.interaction_estimator:
            continue
        means = traj.belief.components.mean[:-1]  # x_j(k|k), k = 1..T-1
        mixed = traj.extras["mixed"].components.mean[1:]  # x_j^0(k|k): start of cycle k+1
        if acfg.matched == "closest":
            matched = matched_model(means, sim.states[:-1])
        elif acfg.matched == "true_mode":
            matched = sim.modes[:-1]
        else:
            raise ValueError(f"analysis.matched: expected 'closest' or 'true_mode', got {acfg.matched!r}")
        checks = check_conclusions(transition, probs, means, mixed, matched, tol=acfg.tol)
        out["conclusions"] = {}
        for c, chk in checks.items():
            outside = chk.applicable & ~chk.premise
            out["conclusions"][str(c)] = [int(chk.premise.sum()), int((chk.premise & chk.holds).sum()),
                                          int(outside.sum()), int((outside & chk.holds).sum())]
        delta = delta_ratio(alphas, probs, matched)  # (T-1, runs)
        out["delta_sum"], out["delta_count"] = delta.sum().item(), delta.numel()
        out["delta_over_time_sum"] = delta.sum(-1).tolist()
        out["delta_over_time_sq"] = delta.to(torch.float64).square().sum(-1).tolist()  # the per-step SE
        out["delta_run_means"] = delta.mean(0).tolist()  # per run: the standard error of mean_delta
        out["zeta_sum"] = zeta_ratio(transition, probs, matched).sum().item() if M == 2 else None
    return out


def _merge(parts: list[dict]) -> dict:
    """A (scenario, alpha) setting's units of runs, in run order, as one value: RMSE summaries,
    conclusion and bound counts, mean delta and zeta, delta(k) over time."""
    first = parts[0]
    runs = sum(int(p["runs"][next(iter(p["runs"]))]["runs"]) for p in parts)
    evaluations = {name: reduce_runs([p["runs"][name] for p in parts]) for name in first["runs"]}
    out: dict = {"rmse": {name: ev.summary() for name, ev in evaluations.items()},
                 "bounds": {key: [sum(p["bounds"][key][i] for p in parts) for i in range(2)]
                            for key in first["bounds"]}}
    for name, ev in evaluations.items():  # the curves' band of the time-averaged mode accuracy (not a table column)
        if ev.mode_accuracy is not None and math.isfinite(ev.mode_accuracy_avg_se):
            out["rmse"][name]["mode_accuracy_se"] = ev.mode_accuracy_avg_se
    if "conclusions" in first:
        out["conclusions"] = {c: [sum(p["conclusions"][c][i] for p in parts) for i in range(4)]
                              for c in first["conclusions"]}
        count = sum(p["delta_count"] for p in parts)
        out["mean_delta"] = sum(p["delta_sum"] for p in parts) / count
        out["mean_zeta"] = sum(p["zeta_sum"] for p in parts) / count if first["zeta_sum"] is not None else None
        steps = len(first["delta_over_time_sum"])
        out["delta_over_time"] = [sum(p["delta_over_time_sum"][k] for p in parts) / runs for k in range(steps)]
        if all("delta_over_time_sq" in p for p in parts):  # sd over runs / sqrt(N) at each step
            out["delta_over_time_se"] = mean_se_per_step(
                [sum(p["delta_over_time_sum"][k] for p in parts) for k in range(steps)],
                [sum(p["delta_over_time_sq"][k] for p in parts) for k in range(steps)], runs).tolist()
        per_run = [v for p in parts for v in p.get("delta_run_means", [])]
        # every run has the same steps: mean_delta is the mean of the runs' means, se = sd_r / sqrt(N)
        out["mean_delta_se"] = (torch.tensor(per_run, dtype=torch.float64).std().item() / len(per_run) ** 0.5
                                if len(per_run) == runs and runs > 1 else None)
    return out


#: the study's unit function (what an executor ships: this path, the config and the arguments)
UNIT = "experiments.studies.imm_analysis:unit"


def _data(ctx: StudyContext, key: str, start: int = 0, stop: int | None = None):
    """``(scenario, sim, z)`` of ``analysis.scenarios[key]``, runs ``start..stop-1`` (all by default),
    simulated once per process from the seed."""
    stop = int(ctx.cfg.mc_runs) if stop is None else stop

    def simulate():
        scenario, data_scenario = ctx.scenarios(ctx.cfg.analysis.scenarios[key])
        sim, z = ctx.simulate_runs(data_scenario.simulate, stop, "data", scenario.name, start=start)
        return scenario, sim.to(ctx.dtype), z.to(ctx.dtype)  # the same data in any dtype

    return ctx.memo(("data", key, start, stop), simulate)


def unit(ctx: StudyContext, *, scenario: str, alpha: float, start: int, stop: int) -> dict:
    """One (scenario, alpha) setting on runs ``start..stop-1``; a function of the config and these
    arguments only."""
    scen, sim, z = _data(ctx, scenario, start, stop)
    return _analyse(ctx, scen, sim, z, float(alpha), start)


def run(ctx: StudyContext) -> None:
    cfg, acfg = ctx.cfg, ctx.cfg.analysis
    if acfg.interaction_estimator not in cfg.estimators:
        raise ValueError(f"analysis.interaction_estimator: {acfg.interaction_estimator!r} is not among "
                         f"the estimators {list(cfg.estimators)}")
    results = ctx.results
    results.description = (
        "Paper 001 (Liang et al. 2001): IMM input interaction under the alpha-parametrised transition "
        f"matrix (2.2), alpha_j = alpha for all modes. {cfg.mc_runs} Monte Carlo runs per scenario "
        f"(seed {cfg.seed}); the matched model is the one {'closest to the truth' if acfg.matched == 'closest' else 'in force'} "
        "at each step. A conclusion holds on a (step, run) when its claim holds up to rounding "
        f"(tol {acfg.tol}); premise_steps counts the (step, run) pairs where its premise held "
        "(Conclusion 2: (step, run, mismatched model) triples)."
    )
    # one unit per (scenario, alpha), all at once: an executor (executor=processes|slurm|ray) runs them
    # side by side; each simulates (or reuses, per process) its scenario's data from the seed
    # (and each range of runs, unit_runs=...)
    todo = [(key, float(alpha)) for key in acfg.scenarios for alpha in acfg.alphas[key]]
    ranges = ctx.run_ranges(cfg.mc_runs)
    values = ctx.map_units([Unit(f"{key}/alpha={alpha}/runs{a}-{b}", UNIT,
                                 {"scenario": key, "alpha": alpha, "start": a, "stop": b})
                            for key, alpha in todo for a, b in ranges], desc="alpha sweep")
    n = len(ranges)
    units = [(ctx.scenarios(acfg.scenarios[key])[0].num_modes, alpha, _merge(values[i * n:(i + 1) * n]))
             for i, (key, alpha) in enumerate(todo)]
    _tables(ctx, units)
    _curves(ctx, units)
    _figures(ctx, units)


def _curves(ctx: StudyContext, units) -> None:
    """The sweep as data (curves.npz, over alpha): RMSEs and their standard errors, delta(k)
    averaged over steps and runs, and delta(k) over time at every alpha; logged once per study."""
    for models in sorted({m for m, _, _ in units}):
        rows = [(a, v) for m, a, v in units if m == models]
        alphas = [a for a, _ in rows]
        for name in rows[0][1]["rmse"]:
            for key in ("pos_rmse", "vel_rmse", "pos_rmse_se", "vel_rmse_se", "mode_accuracy", "mode_accuracy_se"):
                values = [v["rmse"][name].get(key) for _, v in rows]
                quantity = f"{key[:-3]}_vs_alpha_se" if key.endswith("_se") else f"{key}_vs_alpha"  # se: bands
                if all(x is not None for x in values):
                    ctx.logger.sweep(f"{quantity}/{models}_models/{name}", alphas, values, "alpha")
        if all("mean_delta" in v for _, v in rows):
            ctx.logger.sweep(f"mean_delta_vs_alpha/{models}_models", alphas, [v["mean_delta"] for _, v in rows],
                             "alpha")
            se = [v.get("mean_delta_se") for _, v in rows]
            if all(x is not None for x in se):  # its standard error: a band in torchmm-plot
                ctx.logger.sweep(f"mean_delta_vs_alpha_se/{models}_models", alphas, se, "alpha")
        for alpha, v in rows:
            if v.get("delta_over_time"):
                ctx.logger.series(f"delta/{models}_models/alpha={alpha:g}", v["delta_over_time"])
                if v.get("delta_over_time_se"):
                    ctx.logger.series(f"delta_se/{models}_models/alpha={alpha:g}", v["delta_over_time_se"])


def _tables(ctx: StudyContext, units) -> None:
    results = ctx.results
    sweep = results.table("alpha_sweep", ["models", "alpha", "estimator", "pos_rmse", "vel_rmse", "mode_accuracy",
                                           "pos_rmse_se", "vel_rmse_se"])
    by_alpha = results.table("conclusions_by_alpha", ["models", "alpha", "conclusion", "premise_steps", "holds_fraction"])
    compression = results.table(
        "compression", ["models", "alpha", "mean_delta", "mean_zeta"],
        note="delta(k) (4.10) of the matched model and zeta(k) (4.14, two models) averaged over steps and runs.",
    )
    totals = {c: [0, 0, 0, 0] for c in range(1, 6)}
    bound_totals: dict[str, list[int]] = {}
    for models, alpha, value in units:
        for name, r in value["rmse"].items():
            sweep.rows.append([models, alpha, name, r["pos_rmse"], r["vel_rmse"], r.get("mode_accuracy"),
                               r.get("pos_rmse_se"), r.get("vel_rmse_se")])
        for c, counts in value.get("conclusions", {}).items():
            totals[int(c)] = [t + n for t, n in zip(totals[int(c)], counts)]
            premise, holds = counts[:2]
            by_alpha.rows.append([models, alpha, int(c), premise, holds / premise if premise else None])
        for key, (premise, holds) in value["bounds"].items():
            entry = bound_totals.setdefault(key, [0, 0])
            entry[0] += premise
            entry[1] += holds
        if "mean_delta" in value:
            compression.rows.append([models, alpha, value["mean_delta"], value["mean_zeta"]])
    table = results.table(
        "conclusions",
        ["conclusion", "premise_steps", "holds_fraction", "outside_steps", "holds_fraction_outside", "statement"],
        note="Pooled over both scenarios and every alpha. Conclusions 1-5 are proven: holds_fraction must be 1. "
             "outside_*: the (step, run) pairs the conclusion speaks about (its model count; for 2 the "
             "mismatched models) where its premise failed, and how often the claim held there anyway.",
    )
    for c, (premise, holds, outside, holds_outside) in totals.items():
        table.rows.append([c, premise, holds / premise if premise else None, outside,
                           holds_outside / outside if outside else None, STATEMENTS[c]])
        results.metric("IMM", f"conclusion_{c}_holds_fraction", holds / premise if premise else None)
    bounds = results.table("bounds", ["bound", "estimator", "premise_steps", "holds_fraction"],
                           note="(3.2)/(3.3): predicted mode probability inside its interval; (3.8): ratio bound.")
    for key, (premise, holds) in bound_totals.items():
        bound, name = key.split("|")
        bounds.rows.append([bound, name, premise, holds / premise if premise else None])


def _figures(ctx: StudyContext, units) -> None:
    """``rmse_vs_alpha`` and ``delta_vs_alpha``: Monte Carlo means over alpha, each point with its
    95 % error bar (+- 1.96 se: the delta-method se of the average RMSE; sd / sqrt(N) of the runs'
    mean delta)."""
    import matplotlib.pyplot as plt

    model_counts = sorted({m for m, _, _ in units})
    fig, axes = plt.subplots(1, len(model_counts), figsize=(5.5 * len(model_counts), 3.8), squeeze=False)
    for ax, models in zip(axes[0], model_counts):
        rows = [(a, v) for m, a, v in units if m == models]
        xs = [a for a, _ in rows]
        names = list(rows[0][1]["rmse"])
        series = {n: [v["rmse"][n]["pos_rmse"] for _, v in rows] for n in names}
        errors = {n: [v["rmse"][n].get("pos_rmse_se") for _, v in rows] for n in names}  # 95 % error bars
        plots.lines(xs, series, xlabel="alpha", ylabel="position RMSE", title=f"{models} models", logx=True, ax=ax,
                    errors=errors)
    fig.tight_layout()
    ctx.save_figure("rmse_vs_alpha", fig)
    series = {f"{m} models": [v["mean_delta"] for mm, _, v in units if mm == m] for m in model_counts}
    errors = {f"{m} models": [v.get("mean_delta_se") for mm, _, v in units if mm == m] for m in model_counts}
    xs = [a for m, a, _ in units if m == model_counts[0]]
    if all(len(s) == len(xs) for s in series.values()):
        ctx.save_figure("delta_vs_alpha", plots.lines(
            xs, series, xlabel="alpha", ylabel="mean delta(k), eq. (4.10)", logx=True,
            title="interaction error compression of the matched model", errors=errors))

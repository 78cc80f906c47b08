"""Paper 000 study: IMM-TF with slow, irregular source measurements (docs/specification.md §3.1).

Scenario (section 3 of the paper): 1-D target ``[p, v]`` whose acceleration jumps in
``{0.25, 0, -0.25}`` (transition matrix (38)), ``w ~ N(0, 1)`` on the acceleration, target sensor
``y = p + v`` with ``R = 100`` every step, source sensor ``y_S = p + v_S`` with ``R_S`` present
with probability ``source.ratio`` (Bernoulli, or periodic). Estimators (``torchmm.multimodel``):
IMM (target only), IMM-TF, IF-TF, IMM-FU, VSIMM, IMM-SU.

Work units (each on its own simulated data, shared by all estimators of the unit):

* ``default``: ``source.ratio`` (0.6) and ``source.R`` (10): table ``metrics`` per estimator
  (pos_rmse, vel_rmse, nees), RMSE over time (Fig. 4), influence value over time (Fig. 3);
* ``table1/<ratio>``: the source ratios of Table 1 -> table ``table1``;
* ``rs_sweep/<R_S>``: source noise variances of Fig. 5 / Fig. 6 at the default ratio -> ``rs_sweep``.

Data depend on the source ratio only: every ``R_S`` of the sweep (and the default setting) sees the
same truth, target data and source times, and source noise ``sqrt(R_S) e`` with the same ``e``
(common random numbers), so the IMM reference is one line and the sweep isolates the source quality.
"""

from __future__ import annotations

import logging
import inspect
import time

import torch
from hydra.utils import instantiate

from experiments.estimators import Estimator, build_mode_filter, evaluate_runs, reduce_runs, starter
from experiments.executors import Unit
from experiments.harness import StudyContext
from experiments.uncertainty import Z95, inside, nees_consistency
from experiments.studies import plots
from torchmm import PositionMeasurement
from torchmm.multimodel import TransferIMM
from torchmm.simulate import simulate_jump_system, simulate_multirate

log = logging.getLogger("torchmm.experiments")

ESTIMATORS = ("IMM", "IMM-TF", "IF-TF", "IMM-FU", "VSIMM", "IMM-SU")

PUBLISHED_TABLE1 = {
    "columns": ["source_ratio", "estimator", "pos_rmse", "vel_rmse"],
    "rows": [[0.1, "IMM-TF", 5.8755, 2.0266], [0.3, "IMM-TF", 5.4070, 1.9567], [0.5, "IMM-TF", 4.8868, 1.8798],
             [0.7, "IMM-TF", 4.5314, 1.8465], [0.99, "IMM-TF", 4.0999, 1.7674]],
    "source": "Gao et al. 2023, Table 1 (IMM-TF only; the 99 % row is the paper's '99')",
}


def build_estimators(scenario, source_R: float, cfg, names=ESTIMATORS) -> list[Estimator]:
    """The multi-rate estimators ``names`` of ``cfg.tf_estimators`` for a source sensor with noise
    ``source_R``, over the configured mode filters (``conf/mode_filter``).

    Each ``tf_estimators`` entry is a partial of a torchmm class, called as
    ``cls(mode_filters, transition, source_sensor)`` when the class takes a ``source`` argument
    (IMM-TF, IF-TF, IMM-SU, IMM-FU, VSIMM) and as ``cls(mode_filters, transition)`` otherwise (the
    target-only IMM, which then filters the target stream only).
    """
    bank = build_mode_filter(instantiate(cfg.mode_filter) if cfg.get("mode_filter") else None,
                             scenario.motion, scenario.measurement)  # the mode filters (conf/mode_filter)
    P = scenario.transition
    source = PositionMeasurement(scenario.motion.state_dim, scenario.position,
                                 torch.tensor(float(source_R), dtype=P.dtype), dtype=P.dtype).to(P.device)
    nodes = cfg.tf_estimators
    unknown = [n for n in names if n not in nodes]
    if unknown:
        raise ValueError(f"estimators: unknown {sorted(unknown)}; choose from {list(nodes)}")
    out = []
    for name in names:
        make = instantiate(nodes[name])
        takes_source = "source" in inspect.signature(make.func).parameters
        filt = make(bank, P, source) if takes_source else make(bank, P)
        select = None if takes_source else (lambda z: z.target)
        out.append(Estimator(name, filt, starter(filt, scenario.initial_mode_probs), True, select))
    return out


def simulate(ctx: StudyContext, scenario, ratio: float, source_R: float, key: str, start: int = 0,
             stop: int | None = None):
    """Truth, target stream and source stream (NaN where ``gamma_k = 0``) for runs ``start..stop-1``
    (all ``mc_runs`` by default)."""
    cfg = ctx.cfg
    runs = int(cfg.mc_runs) if stop is None else int(stop)
    scenario = _data_scenario(ctx, scenario)  # float64 draws: the same data in float32 and float64
    dtype = scenario.transition.dtype
    sensor = PositionMeasurement(scenario.motion.state_dim, scenario.position,
                                 torch.tensor(float(source_R), dtype=dtype), dtype=dtype).to(ctx.device)
    if cfg.source.availability not in ("bernoulli", "periodic"):
        raise ValueError(f"source.availability: expected 'bernoulli' or 'periodic', got {cfg.source.availability!r}")

    def draw(n: int, g: torch.Generator):
        sim = simulate_jump_system(scenario.motion, scenario.transition, scenario.initial, scenario.steps, (n,),
                                   initial_mode_probs=scenario.initial_mode_probs, generator=g)
        if cfg.source.availability == "bernoulli":
            z = simulate_multirate(scenario.measurement, sensor, sim.states, probability=float(ratio), generator=g)
        else:
            z = simulate_multirate(scenario.measurement, sensor, sim.states, period=int(cfg.source.period),
                                   generator=g)
        return sim, z

    sim, z = ctx.simulate_runs(draw, runs, "data", key, start=start)  # run-indexed streams: blocks of block_runs runs
    sim, z = sim.to(ctx.dtype), type(z)(z.target.to(ctx.dtype), z.source.to(ctx.dtype))
    return sim, z, torch.isfinite(z.source).all(-1)


def _data_scenario(ctx: StudyContext, scenario):
    """The scenario in the data dtype (float64), built from the config like the filters' one."""
    if ctx.dtype == ctx.data_dtype:
        return scenario
    return instantiate(ctx.cfg.scenario, dtype=ctx.data_dtype, device=ctx.device)


def _log_sweep(ctx: StudyContext, rows: list, axis: str) -> None:
    """A sweep table's RMSEs (and standard errors) as curves over the swept value (curves.npz), once."""
    for name in dict.fromkeys(r[1] for r in rows):
        mine = [r for r in rows if r[1] == name]
        xs = [r[0] for r in mine]
        for column, key in ((2, "pos_rmse"), (3, "vel_rmse"), (4, "pos_rmse_se"), (5, "vel_rmse_se")):
            values = [r[column] for r in mine]
            if all(v is not None for v in values):
                quantity = f"{key[:-3]}_vs_{axis}_se" if key.endswith("_se") else f"{key}_vs_{axis}"
                ctx.logger.sweep(f"{quantity}/{name}", xs, values, axis)


def _unit(ctx: StudyContext, scenario, ratio: float, source_R: float, key: str, names, curves: bool,
          start: int, stop: int) -> dict:
    """Every estimator of ``names`` on runs ``start..stop-1`` of ``key``'s data: per-run values
    (:func:`~experiments.estimators.evaluate_runs`) and the count of source measurements present."""
    sim, z, mask = simulate(ctx, scenario, ratio, source_R, key, start, stop)
    out: dict = {"present": [int(mask.sum()), mask.numel()], "runs": {}}
    for est in build_estimators(scenario, source_R, ctx.cfg, names):
        transfer = isinstance(est.filter, TransferIMM)
        stats = {}  # per-run values (T, chunk, ...) of each chunk, averaged over all runs by evaluate
        if transfer:
            stats["transfer_used"] = lambda traj: traj.extras["transfer_used"].double()
        if curves:
            stats["mode_probs"] = lambda traj: traj.belief.mode_probs
            if transfer:  # influence value (33), m = 1 here
                stats["influence_abs"] = lambda traj: traj.extras["influence"][..., 0].abs()
                stats["influence_mean"] = lambda traj: traj.extras["influence"][..., 0]
                # the second moment: the standard error of the mean |L_k| over the runs (the figure's band)
                stats["influence_abs_sq"] = lambda traj: traj.extras["influence"][..., 0].square()
        out["runs"][est.name], _ = evaluate_runs(
            est, scenario, sim, z, chunk_runs=ctx.cfg.get("chunk_runs"), per_step=stats, block_runs=ctx.block_runs,
            generators=ctx.block_generators("filter", key, est.name), first_run=start)
    return out


def _merge(parts: list[dict], curves: bool) -> dict:
    """A setting's units of runs (in run order) as one value: each estimator's summary and, with
    ``curves``, its per-step curves."""
    present = [sum(p["present"][i] for p in parts) for i in range(2)]
    out: dict = {"summary": {}, "present_fraction": present[0] / present[1]}
    for name in parts[0]["runs"]:
        ev = reduce_runs([p["runs"][name] for p in parts])
        summary = ev.summary()
        summary["seconds_per_step"] = ev.seconds_per_step
        summary["nees_low"], summary["nees_high"], summary["nees_steps_inside"] = nees_consistency(
            ev.nees, ev.runs, ev.state_dim)
        if "transfer_used" in ev.means:
            summary["transfer_fraction"] = ev.means["transfer_used"].mean().item()
        out["summary"][name] = summary
        if curves:
            curve = {"pos_rmse": ev.pos_rmse.tolist(), "vel_rmse": ev.vel_rmse.tolist(), "nees": ev.nees.tolist(),
                     "mode_probs": ev.means["mode_probs"].tolist(),
                     "pos_rmse_se": ev.pos_rmse_band.tolist(), "vel_rmse_se": ev.vel_rmse_band.tolist()}
            if "mode_probs" in ev.means_se:  # sd over runs / sqrt(N) (none: a unit checkpointed without it)
                curve["mode_probs_se"] = ev.means_se["mode_probs"].tolist()
            if "influence_abs" in ev.means:
                curve["influence_abs"] = ev.means["influence_abs"].tolist()
                curve["influence_mean"] = ev.means["influence_mean"].tolist()
                if "influence_mean" in ev.means_se:  # sd over runs / sqrt(N)
                    curve["influence_mean_se"] = ev.means_se["influence_mean"].tolist()
                if "influence_abs_sq" in ev.means:  # se of a mean over N runs: sd / sqrt(N)
                    curve["influence_abs_se"] = _mean_se(ev.means["influence_abs"], ev.means["influence_abs_sq"],
                                                         ev.runs).tolist()
            out.setdefault("curves", {})[name] = curve
    return out


def _mean_se(mean: torch.Tensor, mean_sq: torch.Tensor, runs: int) -> torch.Tensor:
    """Standard error ``sd / sqrt(N)`` of a per-step mean over ``N`` runs from the means of the value
    and of its square (``sd`` with the ``N - 1`` divisor); NaN for one run."""
    mean, mean_sq = mean.to(torch.float64), mean_sq.to(torch.float64)
    if runs < 2:
        return torch.full_like(mean, float("nan"))
    var = (mean_sq - mean.square()).clamp_min(0) * runs / (runs - 1)
    return (var / runs).sqrt()


#: the study's unit function (what an executor ships: this path, the config and the arguments)
UNIT = "experiments.studies.imm_tf:unit"


def unit(ctx: StudyContext, *, ratio: float, source_R: float, key: str, curves: bool, start: int, stop: int) -> dict:
    """One unit: every estimator of ``estimator_names`` on runs ``start..stop-1`` of the data of
    ``key`` (source ratio ``ratio``, source noise ``source_R``); a function of the config and these
    arguments only."""
    scenario = ctx.memo("scenario", lambda: instantiate(ctx.cfg.scenario, dtype=ctx.dtype, device=ctx.device))
    return _unit(ctx, scenario, float(ratio), float(source_R), key, list(ctx.cfg.estimator_names),
                 curves=curves, start=start, stop=stop)


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    tic = time.perf_counter()
    scenario = ctx.memo("scenario", lambda: instantiate(cfg.scenario, dtype=ctx.dtype, device=ctx.device))
    ratio, source_R = float(cfg.source.ratio), float(cfg.source.R)
    build_estimators(scenario, source_R, cfg, list(cfg.estimator_names))  # a bad name: an error before any unit
    R = float(scenario.measurement.R.reshape(-1)[0])
    ctx.results.description = (
        f"Paper 000 (IMM-TF), scenario `{scenario.name}`: {scenario.num_modes} modes, {scenario.steps} steps, "
        f"{cfg.mc_runs} Monte Carlo runs (seed {cfg.seed}, {cfg.dtype}); target R = {R:g}, source R_S = "
        f"{source_R:g} present with probability {ratio:g} ({cfg.source.availability}). RMSE per step over runs, "
        "averaged over time. Each source ratio has its own simulated data, shared by all estimators; the R_S "
        "sweep reuses the data of its ratio with the source noise rescaled (common random numbers)."
    )

    # -- the default setting: metrics, Fig. 3 and Fig. 4 --------------------------------------------
    # every unit at once, so an executor (executor=processes|slurm|ray) runs them side by side
    ratios = [float(r) for r in cfg.table1_ratios]
    rs_values = [float(v) for v in cfg.rs_sweep]
    # (and each range of runs, unit_runs=...; a setting's ranges are merged in run order)
    settings = {"default": {"ratio": ratio, "source_R": source_R, "key": f"source/{ratio}", "curves": True}}
    settings.update({f"table1/{r}": {"ratio": r, "source_R": source_R, "key": f"source/{r}", "curves": False}
                     for r in ratios})
    settings.update({f"rs_sweep/{rs}": {"ratio": ratio, "source_R": rs, "key": f"source/{ratio}", "curves": False}
                     for rs in rs_values})
    ranges = ctx.run_ranges(cfg.mc_runs)
    units = [Unit(f"{name}/runs{a}-{b}", UNIT, {**args, "start": a, "stop": b})
             for name, args in settings.items() for a, b in ranges]
    parts = ctx.map_units(units, desc="units")
    n = len(ranges)
    values = {name: _merge(parts[i * n:(i + 1) * n], args["curves"]) for i, (name, args) in enumerate(settings.items())}
    default = values["default"]
    for name, summary in default["summary"].items():
        for key in ("pos_rmse", "vel_rmse", "nees", "mode_accuracy", "transfer_fraction", "nees_low", "nees_high",
                    "nees_steps_inside"):
            if key in summary:
                ctx.results.metric(name, key, summary[key])
        ctx.results.timing[name] = summary["seconds_per_step"]
    curves = default["curves"]
    for name, curve in curves.items():
        ctx.logger.series(f"pos_rmse/{name}", curve["pos_rmse"])
        ctx.logger.series(f"vel_rmse/{name}", curve["vel_rmse"])
        for key in ("pos_rmse_se", "vel_rmse_se"):  # the per-step standard errors (bands)
            if key in curve:
                ctx.logger.series(f"{key}/{name}", curve[key])
        ctx.logger.series(f"nees/{name}", curve["nees"])
        steps = len(curve["nees"])  # the 95 % chi-square band of the run-averaged NEES (torchmm-plot shades it)
        ctx.logger.series(f"nees_low/{name}", [default["summary"][name]["nees_low"]] * steps)
        ctx.logger.series(f"nees_high/{name}", [default["summary"][name]["nees_high"]] * steps)
        for j, label in enumerate(scenario.mode_labels):
            ctx.logger.series(f"mode_probability/{name}/{label}", [p[j] for p in curve["mode_probs"]])
            if "mode_probs_se" in curve:
                ctx.logger.series(f"mode_probability_se/{name}/{label}", [p[j] for p in curve["mode_probs_se"]])
        if "influence_abs" in curve:
            ctx.logger.series(f"influence/{name}", curve["influence_mean"])
            if "influence_mean_se" in curve:
                ctx.logger.series(f"influence_se/{name}", curve["influence_mean_se"])
            ctx.logger.series(f"influence_abs/{name}", curve["influence_abs"])
            if "influence_abs_se" in curve:
                ctx.logger.series(f"influence_abs_se/{name}", curve["influence_abs_se"])
    as_tensor = {panel: {n: torch.tensor(c[key]) for n, c in curves.items()}
                 for panel, key in (("position RMSE", "pos_rmse"), ("velocity RMSE", "vel_rmse"))}
    bands = {panel: {n: torch.tensor(c[f"{key}_se"]) for n, c in curves.items() if f"{key}_se" in c}
             for panel, key in (("position RMSE", "pos_rmse"), ("velocity RMSE", "vel_rmse"))}
    ctx.save_figure("rmse_over_time", plots.rmse_over_time(
        as_tensor, f"{cfg.mc_runs} runs, source ratio {ratio:g}, R_S = {source_R:g}", bands=bands))
    ctx.save_figure("nees", plots.nees_over_time(
        {n: torch.tensor(c["nees"]) for n, c in curves.items()},
        {n: (s["nees_low"], s["nees_high"]) for n, s in default["summary"].items()},
        f"{cfg.mc_runs} runs, source ratio {ratio:g}, R_S = {source_R:g}"))
    if "IMM-TF" in curves:
        ctx.save_figure("influence", _influence_figure(curves, ratio, source_R))
    ctx.results.save()

    # -- Table 1: source ratios -------------------------------------------------------------------
    table1 = ctx.results.table("table1", ["source_ratio", "estimator", "pos_rmse", "vel_rmse", "pos_rmse_se",
                                          "vel_rmse_se"],
                               note=f"R_S = {source_R:g}; every estimator at every ratio, each ratio on its own data.",
                               published=PUBLISHED_TABLE1)
    for r in ratios:
        unit = values[f"table1/{r}"]
        for name, s in unit["summary"].items():
            table1.rows.append([r, name, s["pos_rmse"], s["vel_rmse"], s.get("pos_rmse_se"), s.get("vel_rmse_se")])
        ctx.results.save()
    _log_sweep(ctx, table1.rows, "source_ratio")
    ctx.save_figure("table1", _sweep_figure(table1.rows, "source ratio", logx=False,
                                            published=PUBLISHED_TABLE1["rows"]))
    _published_vs_ours(ctx, table1)

    # -- R_S sweep (Fig. 5, Fig. 6) ---------------------------------------------------------------
    sweep = ctx.results.table("rs_sweep", ["R_S", "estimator", "pos_rmse", "vel_rmse", "pos_rmse_se", "vel_rmse_se"],
                              note=f"source ratio {ratio:g}, target R = {R:g}; IMM (no source) is the reference.")
    for rs in rs_values:
        unit = values[f"rs_sweep/{rs}"]
        for name, s in unit["summary"].items():
            sweep.rows.append([rs, name, s["pos_rmse"], s["vel_rmse"], s.get("pos_rmse_se"), s.get("vel_rmse_se")])
        ctx.results.save()
    _log_sweep(ctx, sweep.rows, "R_S")
    ctx.save_figure("rs_sweep", _sweep_figure(sweep.rows, "source noise variance R_S", logx=True))
    ctx.results.notes.append(f"wall time of the study: {time.perf_counter() - tic:.1f} s")


def _published_vs_ours(ctx: StudyContext, table1) -> None:
    """Table ``table1_vs_published``: each published Table 1 figure beside ours with our 95 % interval."""
    ours = {(row[0], row[1]): row for row in table1.rows}
    rows = []
    for ratio, name, pub_pos, pub_vel in PUBLISHED_TABLE1["rows"]:
        row = ours.get((ratio, name))
        if row is None:
            continue
        rows.append([ratio, name, pub_pos, row[2], row[4], inside(pub_pos, row[2], row[4]),
                     pub_vel, row[3], row[5], inside(pub_vel, row[3], row[5])])
    if rows:
        table = ctx.results.table(
            "table1_vs_published",
            ["source_ratio", "estimator", "published_pos_rmse", "pos_rmse", "pos_rmse_se", "pos_inside_95",
             "published_vel_rmse", "vel_rmse", "vel_rmse_se", "vel_inside_95"],
            note="Whether the published figure lies inside our 95 % interval (+- 1.96 se over the Monte Carlo "
                 "runs): a gap outside it is not Monte Carlo noise.")
        table.rows.extend(rows)


def _influence_figure(curves: dict, ratio: float, source_R: float):
    """Fig. 3: the influence value over time next to the RMSE, IMM-TF (and IF-TF).

    Both are Monte Carlo quantities: each line has its 95 % band (+- 1.96 se) - the RMSE's delta-method
    standard error per step (``pos_rmse_se``) and the mean |L_k|'s ``sd / sqrt(N)`` over the runs
    (``influence_abs_se``)."""
    import matplotlib.pyplot as plt
    import numpy as np

    def draw(ax, values, se, label):
        steps = np.arange(1, len(values) + 1)
        (line,) = ax.plot(steps, values, label=label, lw=1.2)
        if se is not None and len(se) == len(values):
            values, se = np.asarray(values, dtype=float), np.asarray(se, dtype=float)
            ax.fill_between(steps, values - Z95 * se, values + Z95 * se, color=line.get_color(), alpha=0.2, lw=0)

    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(7.5, 5.5), sharex=True)
    for name in ("IMM", "IMM-TF", "IF-TF"):
        if name in curves:
            draw(ax0, curves[name]["pos_rmse"], curves[name].get("pos_rmse_se"), name)
    ax0.set_ylabel("position RMSE")
    ax0.legend(fontsize=8)
    ax0.grid(alpha=0.3)
    for name in ("IMM-TF", "IF-TF"):
        if name in curves and "influence_abs" in curves[name]:
            draw(ax1, curves[name]["influence_abs"], curves[name].get("influence_abs_se"), f"{name}: mean |L_k|")
    ax1.set_ylabel("influence value (33)")
    ax1.set_xlabel("time step k")
    ax1.legend(fontsize=8)
    ax1.grid(alpha=0.3)
    ax0.set_title(f"influence of the source data (ratio {ratio:g}, R_S = {source_R:g}; bands: 95 %)")
    fig.tight_layout()
    return fig


def _sweep_figure(rows: list, xlabel: str, *, logx: bool, published: list | None = None):
    """Position and velocity RMSE against the swept quantity, one line per estimator, each point with
    its 95 % error bar (+- 1.96 se, the table's ``pos_rmse_se``/``vel_rmse_se``: columns 4 and 5)."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    names = list(dict.fromkeys(r[1] for r in rows))
    xs = sorted({r[0] for r in rows})
    for col, (ax, label) in enumerate(zip(axes, ("position RMSE", "velocity RMSE"))):
        series = {n: [next(r[2 + col] for r in rows if r[0] == x and r[1] == n) for x in xs] for n in names}
        errors = {n: [next(r[4 + col] for r in rows if r[0] == x and r[1] == n) for x in xs] for n in names}
        plots.lines(xs, series, xlabel=xlabel, ylabel=label, logx=logx, ax=ax, errors=errors)
        if published:
            ax.plot([r[0] for r in published], [r[2 + col] for r in published], "k--", marker="x",
                    label="IMM-TF (published)")
            ax.legend(fontsize=8)
    fig.tight_layout()
    return fig

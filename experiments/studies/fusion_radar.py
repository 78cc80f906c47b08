"""Paper 002, Example 1: three-sensor radar tracking with time-correlated multiplicative noise.

Local filters of the three sensors (Theorem 3, N = 0), the augmented method (12)-(15) for each
sensor, and the distributed matrix-weighted fusion filter of the position ``s(t)`` with the
position blocks ``P^s_ij(t|t)`` of Theorem 6 (the paper's target), plus the centralized filter
(Remark 10) as the bound. Table ``ex1_rmse`` (estimator, pos_rmse = time average of the RMSE over
runs, computed_rmse = time average of the square root of the computed variance, the last step's
both, and the standard errors ``pos_rmse_se``, ``final_rmse_se``); figures: the tracking of one run
(Fig. 1) and the RMSE over time with 95 % bands (Fig. 2). Readings: ``docs/reproduction-002.md``.
"""

from __future__ import annotations

import logging
import math
import time

import torch

from experiments.harness import StudyContext
from experiments.studies import plots  # noqa: F401  (sets the Agg backend)
from experiments.uncertainty import Z95, armse_se, rmse_se_per_step
from torchmm.fusion import (
    MultiSensorSystem,
    augmented_local_estimates,
    centralized_estimates,
    cross_covariances,
    cross_predictor_stats,
    fuse,
    local_estimates,
    local_predictor_stats,
    simulate_fusion,
)

log = logging.getLogger("torchmm.experiments")


def radar_system(cfg, dtype, device) -> MultiSensorSystem:
    """System (56)-(58) from the ``radar`` config block."""
    T = float(cfg.T)
    rho1, rho2 = (float(v) for v in cfg.rho)
    A = [[1, T, 0, 0, 0, 0], [0, 1, 1, 0, 0, 0], [0, 0, rho1, 0, 0, 0],
         [0, 0, 0, 1, T, 0], [0, 0, 0, 0, 1, 1], [0, 0, 0, 0, 0, rho2]]
    kw = dict(dtype=dtype, device=device)
    C = torch.tensor(cfg.C, **kw)
    Ct = torch.tensor(cfg.Ct, **kw)
    tau = float(cfg.tau)
    h = math.exp(float(cfg.h_sign) * T / tau)
    q = 1 - math.exp(-2 * T / tau)
    sig = torch.tensor(cfg.sigma_r, **kw)
    Qp = sig**2 * q
    hs = torch.tensor(cfg.h_factor, **kw) * h
    Q_eta = torch.diag_embed(torch.tensor(cfg.eta_std, **kw) ** 2)
    P0 = torch.diag(torch.tensor(cfg.P0_diag, **kw))
    Qr0 = None if cfg.Qr0 is None else torch.tensor(cfg.Qr0, **kw)
    return MultiSensorSystem.from_correlation(
        A=torch.tensor(A, **kw), Gamma=torch.eye(6, **kw), Qw=torch.diag(torch.tensor(cfg.Qw_diag, **kw)),
        C=C, Ct=Ct, h=hs, Qp=Qp, d=torch.tensor(cfg.d, **kw), Q_eta=Q_eta,
        mu0=torch.tensor(cfg.x0, **kw), P0=P0, Qr0=Qr0)


def _tracking_figure(t, truth, est, meas, title):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(t, meas, ".", ms=3, color="0.6", label="sensor 1 position measurement")
    ax.plot(t, truth, "k-", lw=1.5, label="true position s(t)")
    ax.plot(t, est, "r--", lw=1.3, label="MF fusion filter")
    ax.set_xlabel("time step t")
    ax.set_ylabel("position")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    return fig


def _rmse_figure(curves, title, bands=None):
    """RMSE over time, linear and log scale; ``bands[name] = (T,)`` per-step standard errors, drawn as
    +- 1.96 se (95 %) bands in the line's colour."""
    import matplotlib.pyplot as plt

    bands, fills = bands or {}, []
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for ax, logy in zip(axes, (False, True)):
        if logy:
            ax.set_yscale("log")
        for name, values in curves.items():
            v = values.cpu()
            if logy:  # the position is deterministic for the first steps when P0 = 0
                v = torch.where(v > 1e-6, v, torch.nan)
            (line,) = ax.plot(range(len(v)), v, label=name, lw=1.2, ls="--" if name.startswith("AUG") else "-")
            if name in bands:
                se = bands[name].cpu().to(v.dtype)
                lo = (v - Z95 * se).clamp_min(1e-300) if logy else v - Z95 * se
                fills.append((ax, v, lo, v + Z95 * se, line.get_color()))
    limits = [ax.get_ylim() for ax in axes]  # the lines' ranges: a wide band does not rescale the axes
    for ax, v, lo, hi, color in fills:
        ax.fill_between(range(len(v)), lo, hi, color=color, alpha=0.2, lw=0)
    for ax, limit in zip(axes, limits):
        ax.set_ylim(*limit)
    for ax in axes:
        ax.set_xlabel("time step t")
        ax.set_ylabel("position RMSE")
        ax.grid(alpha=0.3)
    axes[0].set_ylim(0, 1.3 * max(float(v.max()) for k, v in curves.items() if k != "LF3"))
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    rc = cfg.radar
    system = radar_system(rc, ctx.dtype, ctx.device)
    steps, runs = int(rc.steps), int(cfg.mc_runs)
    # simulated with the system in float64 and cast: float32 and float64 runs see the same data
    data_system = system if ctx.dtype == ctx.data_dtype else radar_system(rc, ctx.data_dtype, ctx.device)
    sim = ctx.simulate_runs(lambda n, g: simulate_fusion(data_system, steps, (n,), g), runs,
                            "fusion_radar", "data").to(ctx.dtype)  # run-indexed streams (blocks of block_runs)
    ctx.results.description = (
        f"Paper 002 Example 1: 3-sensor radar, {steps} steps, {runs} Monte Carlo runs (seed {cfg.seed}, "
        f"{cfg.dtype}); h = exp({float(rc.h_sign):+g} T/{float(rc.tau):g}). "
        "Position RMSE per step over runs, "
        "averaged over time. MF fuses the position with the position blocks of Theorem 6 (N = 0)."
    )
    pos = int(rc.position_index)
    truth = sim.x[..., pos]
    curves, bands, rows = {}, {}, []

    def record(name, est_pos, var_pos, seconds):
        rmse = ((truth - est_pos) ** 2).mean(1).sqrt()
        curves[name] = rmse
        computed = var_pos.clamp_min(0).sqrt()
        sq = ((truth - est_pos) ** 2).to(torch.float64)  # (T, runs): the Monte Carlo standard errors
        band = bands[name] = rmse_se_per_step(sq)
        rows.append([name, float(rmse.mean()), float(computed.mean()), float(rmse[-1]), float(computed[-1]),
                     armse_se(sq), float(band[-1])])
        ctx.results.metric(name, "pos_rmse", float(rmse.mean()))
        ctx.results.timing[name] = seconds / steps
        ctx.logger.series(f"pos_rmse/{name}", rmse, start=0)
        ctx.logger.series(f"pos_rmse_se/{name}", band, start=0)

    state: dict = {}

    def local_filters():
        t0 = time.perf_counter()
        state["stats"] = local_predictor_stats(system, steps)
        state["mean"], cov = local_estimates(system, sim.y, 0, state["stats"])
        state["t_local"] = time.perf_counter() - t0
        for i in range(system.num_sensors):
            record(f"LF{i + 1}", state["mean"][:, :, i, pos], cov[:, i, pos, pos], state["t_local"])

    def augmented():
        t0 = time.perf_counter()
        amean, acov = augmented_local_estimates(system, sim.y, 0)
        t_aug = time.perf_counter() - t0
        for i in range(system.num_sensors):
            record(f"AUG{i + 1}", amean[:, :, i, pos], acov[:, i, pos, pos], t_aug)
        ctx.results.metric("AUG", "max_abs_diff_vs_LF", float((amean - state["mean"]).abs().max()))

    def matrix_fusion():
        t0 = time.perf_counter()
        stats = state["stats"]
        Pij = cross_covariances(system, stats, cross_predictor_stats(system, stats), 0)
        state["fused"] = fuse(state["mean"], Pij, "matrix", components=[pos])
        t_mf = time.perf_counter() - t0 + state["t_local"]
        record("MF", state["fused"].mean[..., 0], state["fused"].cov[:, 0, 0], t_mf)

    def centralized():
        t0 = time.perf_counter()
        cmean, ccov = centralized_estimates(system, sim.y, 0)
        record("CF", cmean[..., pos], ccov[:, pos, pos], time.perf_counter() - t0)

    for stage in ctx.progress_bar([local_filters, augmented, matrix_fusion, centralized], desc="estimators"):
        stage()
    fused = state["fused"]
    table = ctx.results.table(
        "ex1_rmse", ["estimator", "pos_rmse", "computed_rmse", "final_rmse", "final_computed_rmse", "pos_rmse_se",
                     "final_rmse_se"],
        note=("pos_rmse: RMSE over runs per step, averaged over all steps; computed_rmse: the same "
              "average of "
              "sqrt(P(t|t)) from the estimator's own covariance. The paper gives only curves (Fig. 2): "
              "local filter = [11] filter (sensor 1, d_1 = 0) = augmented method, all less accurate "
              "than MF. pos_rmse_se, final_rmse_se: delta-method standard errors of pos_rmse and final_rmse "
              "over the runs (95 % interval: +- 1.96 se); the computed values are exact (no Monte Carlo "
              "error)."),
    )
    table.rows.extend(rows)
    ctx.results.save()
    run0 = 0
    t = list(range(steps))
    y_pos = sim.y[:, run0, 0, 0].cpu()
    ctx.save_figure("fig1_tracking", _tracking_figure(
        t, truth[:, run0].cpu(), fused.mean[:, run0, 0].cpu(), y_pos, "MF fusion filter, run 0 (Fig. 1)"))
    shown = {k: v for k, v in curves.items() if k in ("LF1", "LF2", "LF3", "AUG1", "MF", "CF")}
    ctx.save_figure("fig2_rmse", _rmse_figure(shown, f"position RMSE, {runs} runs (Fig. 2)", bands=bands))
    log.info("ex1_rmse: %s", [(r[0], round(r[1], 2)) for r in rows])

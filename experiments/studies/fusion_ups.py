"""Paper 002, Example 2: 1 kVA uninterruptible power supply with three sensors.

Local filters (LF1-3), scalar- (SF), diagonal-matrix- (DF) and matrix-weighted (MF) distributed
fusion and centralized fusion (CF). Tables:

* ``ex2_variance``: steady-state computed error variances per state component (Theorems 7-8 and
  Remark 9 for the local and distributed estimators; the converged time-varying Riccati recursion
  for CF);
* ``ex2_mc``: Monte Carlo error variances of the time-varying estimators, averaged over runs and the
  steps ``burn_in..T-1``, with the largest |z| against the computed variances (SE from the runs'
  time-averaged squared errors; runs are independent) and those SEs (``comp*_se``);
* ``ex2_horizon``: MF fused predictor (N = -2, -1), filter (0) and smoother (1, 2), steady-state
  computed variances, with the Monte Carlo ones and their SEs (``mc*_se``) beside them (Fig. 4);
* ``ex2_steady``: the steady-state (offline-gain) MF estimators' Monte Carlo variance against their
  computed variance.

Figures: variance over time per component (Fig. 3) and MF for N = -2..2 (Fig. 4).
"""

from __future__ import annotations

import logging
import time

import torch

from experiments.harness import StudyContext
from experiments.studies import plots  # noqa: F401  (sets the Agg backend)
from torchmm.fusion import (
    MultiSensorSystem,
    centralized_estimates,
    cross_covariances,
    cross_predictor_stats,
    fuse,
    fusion_weights,
    local_estimates,
    local_predictor_stats,
    simulate_fusion,
    steady_fused_estimates,
    steady_state,
    theorem6_cross_covariances,
)

log = logging.getLogger("torchmm.experiments")

METHODS = {"SF": "scalar", "DF": "diagonal", "MF": "matrix"}


def ups_system(cfg, dtype, device) -> MultiSensorSystem:
    kw = dict(dtype=dtype, device=device)
    t = lambda v: torch.tensor(v, **kw)  # noqa: E731
    L = len(cfg.Ct)
    return MultiSensorSystem.from_correlation(
        A=t(cfg.A), Gamma=t(cfg.Gamma), Qw=t([[float(cfg.Qw)]]), C=t([[cfg.C]] * L),
        Ct=t([[c] for c in cfg.Ct]),
        h=t(cfg.h), Qp=t(cfg.Qp), d=t(cfg.d).reshape(L, 1, 1), Q_eta=t(cfg.Q_eta).reshape(L, 1, 1),
        mu0=t(cfg.mu0), P0=float(cfg.P0_scale) * torch.eye(3, **kw),
        Qr0=None if cfg.Qr0 is None else t(cfg.Qr0))


def _se(err2: torch.Tensor) -> torch.Tensor:
    """Standard error of the Monte Carlo variance ``err2.mean((0, 1))`` from squared errors ``(steps, runs,
    3)``: the sd over the runs of a run's window-averaged squared error over sqrt(runs) (runs are
    independent; a run's errors are correlated over time). ``(3,)``; the SE that :func:`_z` divides by."""
    per_run = err2.mean(0)
    return per_run.std(0) / per_run.shape[0] ** 0.5


def _z(err2: torch.Tensor, computed: torch.Tensor) -> torch.Tensor:
    per_run = err2.mean(0)
    se = per_run.std(0) / per_run.shape[0] ** 0.5
    return (per_run.mean(0) - computed) / se.clamp_min(1e-300)


def _panels(series: dict, title: str, ylabel: str = "error variance"):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 3.8))
    for c, ax in enumerate(axes):
        for name, values in series.items():
            ax.plot(range(values.shape[0]), values[:, c].cpu(), label=name, lw=1.2)
        ax.set_xlabel("time step t")
        ax.set_ylabel(ylabel)
        ax.set_title(f"state component {c + 1}")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    uc = cfg.ups
    system = ups_system(uc, ctx.dtype, ctx.device)
    steps, runs, burn = int(uc.steps), int(cfg.mc_runs), int(uc.burn_in)
    if not 0 <= burn < steps - 2:
        raise ValueError(f"ups.burn_in: expected 0 <= burn_in < steps - 2, got {burn} (steps = {steps})")
    horizons = [int(n) for n in uc.horizons]
    ctx.results.description = (
        f"Paper 002 Example 2 (UPS): 3 sensors, {steps} steps, {runs} Monte Carlo runs (seed {cfg.seed}, "
        f"{cfg.dtype}); Monte Carlo variances averaged over t = {burn}..{steps - 1} (smoothers: up to "
        f"{steps - 1} - N). Steady state: Theorems 7-8, Remark 9."
    )
    # simulated with the system in float64 and cast: float32 and float64 runs see the same data
    data_system = system if ctx.dtype == ctx.data_dtype else ups_system(uc, ctx.data_dtype, ctx.device)
    sim = ctx.simulate_runs(lambda n, g: simulate_fusion(data_system, steps, (n,), g), runs,
                            "fusion_ups", "data").to(ctx.dtype)  # run-indexed streams (blocks of block_runs)
    diag = dict(dim1=-2, dim2=-1)

    # ---- time-varying estimators --------------------------------------------------------------
    t0 = time.perf_counter()
    stats = local_predictor_stats(system, steps)
    cross = cross_predictor_stats(system, stats)
    local, fused, cent = {}, {}, {}
    for N in ctx.progress_bar(horizons, desc="horizons N"):
        local[N] = local_estimates(system, sim.y, N, stats)
        Pij = cross_covariances(system, stats, cross, N)
        fused[N] = {name: fuse(local[N][0], Pij, method) for name, method in METHODS.items()}
        cent[N] = centralized_estimates(system, sim.y, N)
    label = "all estimators, N = " + ",".join(map(str, horizons))
    ctx.results.timing[label] = (time.perf_counter() - t0) / steps
    window = {N: slice(burn, steps - max(N, 0)) for N in horizons}

    # ---- steady state -------------------------------------------------------------------------
    ss = steady_state(system, tol=float(uc.ss_tol))
    ctx.results.metric("steady_state", "riccati_iterations", ss.iterations)
    ctx.results.metric("steady_state", "cross_iterations", ss.cross_iterations)
    dummy = torch.zeros(int(uc.cf_ss_steps), 1, system.num_sensors, system.meas_dim, dtype=ctx.dtype,
                        device=ctx.device)

    def steady_vars(N):
        out = {f"LF{i + 1}": v for i, v in enumerate(ss.local_covariances(system, N).diagonal(**diag))}
        Pij = ss.cross_covariances(system, N)
        for name, method in METHODS.items():
            out[name] = fusion_weights(Pij, method)[1].diagonal()
        out["CF"] = centralized_estimates(system, dummy, N)[1][-1 - max(N, 0)].diagonal()
        return out

    ss_vars = {N: steady_vars(N) for N in horizons}
    names = [f"LF{i + 1}" for i in range(system.num_sensors)] + ["SF", "DF", "MF", "CF"]
    cols = ["estimator", "comp1", "comp2", "comp3"]
    t_var = ctx.results.table(
        "ex2_variance", cols,
        note="Steady-state computed filter (N = 0) error variances per state component.",
        published={"columns": ["ordering"], "rows": [["CF < MF < DF < SF < LF (Fig. 3, curves only)"]],
                   "source": "paper 002, Fig. 3"})
    for name in names:
        t_var.rows.append([name, *ss_vars[0][name].tolist()])

    # ---- Monte Carlo --------------------------------------------------------------------------
    def mc(mean, N, computed_tv):
        w = window[N]
        err2 = (sim.x[w] - mean[w]) ** 2
        mcv = err2.mean((0, 1))
        z = _z(err2, computed_tv[w].diagonal(**diag).mean(0))
        return mcv, z, _se(err2)

    t_mc = ctx.results.table(
        "ex2_mc", cols + ["computed1", "computed2", "computed3", "max_abs_z", "comp1_se", "comp2_se", "comp3_se"],
        note=("Monte Carlo error variances of the time-varying filters (N = 0) against the computed ones "
              "(window averages). max_abs_z: largest |MC - computed| / SE over components; SE from the "
              f"{runs} runs' time-averaged squared errors. Consistency: |z| < 4.5. comp*_se: that SE of the "
              "Monte Carlo variances comp* (sd over the runs of a run's window-averaged squared error / "
              "sqrt(runs); 95 % interval: +- 1.96 se). The computed columns are exact."))
    series = {}
    for name in names:
        if name.startswith("LF"):
            i = int(name[2:]) - 1
            mean, cov = local[0][0][:, :, i], local[0][1][:, i]
        elif name == "CF":
            mean, cov = cent[0]
        else:
            mean, cov = fused[0][name].mean, fused[0][name].cov
        mcv, z, se = mc(mean, 0, cov)
        comp = cov[window[0]].diagonal(**diag).mean(0)
        t_mc.rows.append([name, *mcv.tolist(), *comp.tolist(), float(z.abs().max()), *se.tolist()])
        series[name] = cov.diagonal(**diag)
        for c in range(3):
            ctx.logger.series(f"variance/comp{c + 1}/{name}", cov.diagonal(**diag)[:, c], start=0)
    t_h = ctx.results.table(
        "ex2_horizon", ["N", "comp1", "comp2", "comp3", "mc1", "mc2", "mc3", "max_abs_z", "mc1_se", "mc2_se",
                        "mc3_se"],
        note="MF fused estimator x_o(t|t+N): steady-state computed variances and Monte Carlo variances "
             "of the time-varying MF (window averages). mc*_se: standard errors of the Monte Carlo "
             "variances (as in ex2_mc).",
        published={"columns": ["ordering"], "rows": [["N = 2 smallest, N = -2 largest (Fig. 4, curves)"]],
                   "source": "paper 002, Fig. 4"})
    horizon_series = {}
    for N in horizons:
        f = fused[N]["MF"]
        mcv, z, se = mc(f.mean, N, f.cov)
        t_h.rows.append([N, *ss_vars[N]["MF"].tolist(), *mcv.tolist(), float(z.abs().max()), *se.tolist()])
        horizon_series[f"N = {N}"] = f.cov.diagonal(**diag)
    t_p = ctx.results.table(
        "ex2_horizon_printed_thm6", ["N", "comp1", "comp2", "comp3", "mc1", "mc2", "mc3", "max_abs_z", "mc1_se",
                                     "mc2_se", "mc3_se"],
        note=("MF with the cross-covariances of Theorem 6 as printed ((42) without E[eps_i xi_i^T], exact "
              "only for N <= 1): its computed fused variance vs the Monte Carlo variance of that fused "
              "estimator (window averages), N >= 0. Shows what the printed theorem reports. mc*_se: "
              "standard errors of the Monte Carlo variances (as in ex2_mc)."))
    for N in [n for n in horizons if n >= 0]:
        Pij = theorem6_cross_covariances(system, stats, cross, N, xi_term=False)
        f = fuse(local[N][0], Pij, "matrix")
        w = window[N]
        err2 = (sim.x[w] - f.mean[w]) ** 2
        z = _z(err2, f.cov[w].diagonal(**diag).mean(0))
        t_p.rows.append([N, *f.cov[w].diagonal(**diag).mean(0).tolist(), *err2.mean((0, 1)).tolist(),
                         float(z.abs().max()), *_se(err2).tolist()])
    t_s = ctx.results.table(
        "ex2_steady", ["N", "comp1", "comp2", "comp3", "mc1", "mc2", "mc3", "max_abs_z", "mc1_se", "mc2_se",
                       "mc3_se"],
        note="Steady-state MF estimators (offline gains and weights): computed vs Monte Carlo variance. "
             "mc*_se: standard errors of the Monte Carlo variances (as in ex2_mc).")
    for N in horizons:
        mean, Po, _ = steady_fused_estimates(system, ss, sim.y, N, "matrix")
        err2 = (sim.x - mean)[window[N]] ** 2
        z = _z(err2, Po.diagonal())
        t_s.rows.append([N, *Po.diagonal().tolist(), *err2.mean((0, 1)).tolist(), float(z.abs().max()),
                         *_se(err2).tolist()])
    for name in names:
        ctx.results.metric(name, "steady_trace", float(ss_vars[0][name].sum()))
    ctx.results.save()
    ctx.save_figure("fig3_variances", _panels(series, "filter error variances (Fig. 3)"))
    ctx.save_figure("fig4_horizon", _panels(horizon_series, "MF predictor / filter / smoother (Fig. 4)"))
    log.info("ex2_variance: %s", [(r[0], [round(v, 4) for v in r[1:]]) for r in t_var.rows])

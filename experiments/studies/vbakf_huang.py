"""VBAKF-PR on its authors' scenario (Huang et al., IEEE TAC 2018; docs/baselines.md §6).

2-D constant velocity, state ``[x, y, vx, vy]``, ``H = [I 0]``, 1000 steps,
``Q_k = (6.5 + 0.5 cos(pi k / 1000)) q [dt^3/3 I, dt^2/2 I; dt^2/2 I, dt I]``,
``R_k = (0.1 + 0.05 cos(pi k / 1000)) r [[1, .5], [.5, 1]]``; ``x_0 = [100, 100, 10, 10]``,
``P_0 = 100 I``, ``x^_0 ~ N(x_0, P_0)``. Filters: the KF with the nominal ``R~ = beta I`` (and
``Q~``), the KF with the true ``Q_k, R_k``, and VBAKF-PR (``Q~``, ``R~_0 = beta I``, tau = 3,
rho = 1 - exp(-4), N = 10). ``nominal_q: true`` is the setting of the paper's Table I
(``Q~ = Q_k``); ``nominal_q: <alpha>`` uses ``Q~ = alpha I`` (the paper's Fig. 1 setting).

Table ``table1``: estimator, pos_armse / vel_armse over the last 100 s and over all steps, their
delta-method standard errors (``*_se``) and whether the published Table I value (last 100 s, beside
them) lies inside our 95 % interval (``*_inside_95``).
"""

from __future__ import annotations

import math

import torch

from experiments.executors import Unit
from experiments.harness import StudyContext, join_runs, per_run
from experiments.studies import plots
from experiments.uncertainty import armse_se, inside, rmse_se_per_step
from torchmm import GaussianBelief, KalmanFilter, LinearMeasurement, LinearMotion, run_filter
from torchmm.filters.variational import VBAKFPR

#: Huang et al. 2018, Table I (last 100 s; KF nominal, KF true, VBAKF-PR)
PUBLISHED = {"KF-nominal": (4.63, 4.58), "KF-true": (2.77, 3.38), "VBAKF-PR": (2.81, 3.45)}


def huang_scenario(runs: int, generator: torch.Generator, *, steps: int = 1000, dtype=torch.float64,
                   device=None, q: float = 1.0, r: float = 100.0, period: float = 1000.0):
    """Truth ``(T, runs, 4)``, measurements ``(T, runs, 2)``, ``Q_k (T, 4, 4)``, ``R_k (T, 2, 2)``,
    ``x0 (4,)`` and the initial estimates ``(runs, 4)``; the noise levels vary as ``cos(pi k / period)``
    (the paper's 1000 s, whatever ``steps`` is)."""
    kw = {"dtype": dtype, "device": device}
    dt = 1.0
    eye2 = torch.eye(2, **kw)
    F = torch.eye(4, **kw)
    F[:2, 2:] = dt * eye2
    Q1 = q * torch.cat([torch.cat([dt**3 / 3 * eye2, dt**2 / 2 * eye2], 1),
                        torch.cat([dt**2 / 2 * eye2, dt * eye2], 1)], 0)
    k = torch.arange(1, steps + 1, **kw)
    Qs = (6.5 + 0.5 * torch.cos(math.pi * k / period))[:, None, None] * Q1
    R1 = r * torch.tensor([[1.0, 0.5], [0.5, 1.0]], **kw)
    Rs = (0.1 + 0.05 * torch.cos(math.pi * k / period))[:, None, None] * R1
    x0 = torch.tensor([100.0, 100.0, 10.0, 10.0], **kw)
    P0 = 100.0 * torch.eye(4, **kw)
    x = x0.expand(runs, 4)
    xs, zs = [], []
    LQ, LR = torch.linalg.cholesky(Qs), torch.linalg.cholesky(Rs)
    for t in range(steps):
        x = x @ F.mT + torch.randn(runs, 4, generator=generator, **kw) @ LQ[t].mT
        xs.append(x)
        zs.append(x[:, :2] + torch.randn(runs, 2, generator=generator, **kw) @ LR[t].mT)
    xhat0 = x0 + torch.randn(runs, 4, generator=generator, **kw) @ torch.linalg.cholesky(P0).mT
    return torch.stack(xs), torch.stack(zs), F, Qs, Rs, P0, xhat0


#: where huang_scenario's outputs hold the runs (truth, z: time-major; F, Q_k, R_k, P0: shared; x̂0: first)
HUANG_AXES = (1, 1, None, None, None, None, 0)


def run_huang(runs: int, generator: torch.Generator | None, *, steps: int = 1000, nominal_q="true",
              beta: float = 100.0,
              tau: float = 3.0, rho: float = 1 - math.exp(-4), iterations: int = 10, dtype=torch.float64,
              device=None, progress: bool = False, simulate_runs=None, names=None) -> dict:
    """Run the three filters; returns per-estimator ``{"pos": (T,), "vel": (T,)}`` RMSE curves, the
    SRNFN-free summary ``{"estimator": (pos_last100, vel_last100, pos_all, vel_all)}``, its delta-method
    standard errors ``"se"`` (the same four) and the per-step standard errors ``"pos_band"``,
    ``"vel_band"`` ``(T,)`` (experiments/uncertainty.py). ``simulate_runs(draw, runs, start)`` (e.g.
    the study's run-indexed blocks) simulates instead of one stream from ``generator``; ``names``:
    only these filters (default all three)."""
    errors = huang_errors(runs, generator, steps=steps, nominal_q=nominal_q, beta=beta, tau=tau, rho=rho,
                          iterations=iterations, dtype=dtype, device=device, progress=progress,
                          simulate_runs=simulate_runs, names=names)
    return {name: summarize(*map(torch.as_tensor, sq)) for name, sq in errors.items()}


def huang_errors(runs: int, generator: torch.Generator | None, *, steps: int = 1000, nominal_q="true",
                 beta: float = 100.0, tau: float = 3.0, rho: float = 1 - math.exp(-4), iterations: int = 10,
                 dtype=torch.float64, device=None, progress: bool = False, simulate_runs=None, names=None,
                 start: int = 0) -> dict:
    """Per-run squared position and velocity errors ``(T, runs - start)`` (numpy) of each filter on runs
    ``start..runs-1``: what :func:`summarize` reduces (arguments: :func:`run_huang`)."""
    # simulated in float64 and cast: float32 and float64 runs see the same data
    def draw(n, gen):
        return huang_scenario(n, gen, steps=steps, dtype=torch.float64, device=device)

    data = draw(runs - start, generator) if simulate_runs is None else simulate_runs(draw, runs, start)
    truth, z, F, Qs, Rs, P0, xhat0 = (t.to(dtype) for t in data)
    kw = {"dtype": dtype, "device": device}
    H = torch.cat([torch.eye(2, **kw), torch.zeros(2, 2, **kw)], 1)
    R_nom = beta * torch.eye(2, **kw)
    if nominal_q == "true":
        Q_nom = Qs
    else:
        Q_nom = float(nominal_q) * torch.eye(4, **kw).expand(steps, 4, 4)
    belief0 = GaussianBelief(xhat0, P0.expand(truth.shape[1], 4, 4))
    nominal_meas = LinearMeasurement(H, R_nom)
    # the time-varying Q~_k, Q_k, R_k: per-step models through run_filter (no filter rebuilt, no buffer rewritten)
    nominal_motions = [LinearMotion(F, Q_nom[t]) for t in range(steps)]
    true_motions = [LinearMotion(F, Qs[t]) for t in range(steps)]
    true_sensors = [LinearMeasurement(H, Rs[t]) for t in range(steps)]
    vbakf = VBAKFPR(nominal_motions[0], nominal_meas, tau=tau, rho=rho, iterations=iterations)
    runs_of = {
        "KF-nominal": lambda: run_filter(KalmanFilter(nominal_motions[0], nominal_meas), belief0, z,
                                         motions=nominal_motions, record=_means_only,
                                         progress="KF-nominal" if progress else False),
        "KF-true": lambda: run_filter(KalmanFilter(true_motions[0], true_sensors[0]), belief0, z,
                                      motions=true_motions, sensors=true_sensors, record=_means_only,
                                      progress="KF-true" if progress else False),
        "VBAKF-PR": lambda: run_filter(vbakf, vbakf.initial_belief(belief0, R_nom), z, motions=nominal_motions,
                                       record=_means_only, progress="VBAKF-PR" if progress else False),
    }
    out = {}
    for name, go in runs_of.items():
        if names is None or name in names:
            err = go().belief.mean - truth
            out[name] = (per_run(err[..., :2].square().sum(-1)), per_run(err[..., 2:].square().sum(-1)))
    return out


def summarize(sq_pos: torch.Tensor, sq_vel: torch.Tensor) -> dict:
    """RMSE curves, Table I summary (last 100 steps and all steps), standard errors and bands from the
    squared errors ``(T, runs)`` of all runs."""
    steps, runs = sq_pos.shape
    pos, vel = (sq_pos.sum(1) / runs).sqrt(), (sq_vel.sum(1) / runs).sqrt()
    tail = slice(max(steps - 100, 0), steps)
    sq_pos, sq_vel = sq_pos.to(torch.float64), sq_vel.to(torch.float64)  # the standard errors
    return {"pos": pos, "vel": vel,
            "summary": (pos[tail].mean().item(), vel[tail].mean().item(), pos.mean().item(), vel.mean().item()),
            "se": (armse_se(sq_pos[tail]), armse_se(sq_vel[tail]), armse_se(sq_pos), armse_se(sq_vel)),
            "pos_band": rmse_se_per_step(sq_pos), "vel_band": rmse_se_per_step(sq_vel)}


def _means_only(out):
    """Keep the posterior means (the study reports RMSEs only)."""
    return out._replace(prior=None, innovation=None, innovation_cov=None, extras=None)


#: the filters of Table I, and the study's unit function (what an executor ships)
FILTERS = ("KF-nominal", "KF-true", "VBAKF-PR")
UNIT = "experiments.studies.vbakf_huang:unit"


def unit(ctx: StudyContext, *, name: str, start: int, stop: int) -> dict:
    """Filter ``name`` of Table I on runs ``start..stop-1`` of the run-indexed data (simulated once per
    process): its per-run squared errors."""
    h = ctx.cfg.huang

    def simulate_runs(draw, n, a):
        return ctx.memo(("data", a, n), lambda: ctx.simulate_runs(draw, n, "huang", axes=HUANG_AXES, start=a))

    out = huang_errors(stop, None, steps=int(h.steps), nominal_q=h.nominal_q, beta=float(h.beta),
                       tau=float(h.tau), rho=float(h.rho), iterations=int(h.iterations), dtype=ctx.dtype,
                       device=ctx.device, progress=ctx.progress, simulate_runs=simulate_runs, names=[name],
                       start=start)
    sq_pos, sq_vel = out[name]
    return {"pos": sq_pos, "vel": sq_vel}


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    h = cfg.huang
    runs = int(cfg.mc_runs)
    # one unit per filter, all at once: an executor (executor=processes|slurm|ray) runs them side by side
    # (and each range of runs, unit_runs=...; a filter's ranges are joined in run order)
    names = list(FILTERS)
    ranges = ctx.run_ranges(runs)
    parts = ctx.map_units([Unit(f"huang/{name}/runs{a}-{b}", UNIT, {"name": name, "start": a, "stop": b})
                           for name in names for a, b in ranges], desc="filters")
    n = len(ranges)
    res = {}
    for i, name in enumerate(names):
        mine = parts[i * n:(i + 1) * n]
        v = summarize(*(join_runs([p[k] for p in mine]) for k in ("pos", "vel")))
        res[name] = {"pos": v["pos"].tolist(), "vel": v["vel"].tolist(), "summary": list(v["summary"]),
                     "se": list(v["se"]), "pos_band": v["pos_band"].tolist(), "vel_band": v["vel_band"].tolist()}
    ctx.results.description = (
        f"Huang et al. 2018 scenario, {h.steps} steps, {runs} Monte Carlo runs "
        f"(seed {cfg.seed}, {cfg.dtype}), "
        f"nominal Q = {h.nominal_q}, R~ = {h.beta} I, tau = {h.tau}, rho = {h.rho:.4f}, N = {h.iterations}."
    )
    table = ctx.results.table(
        "table1", ["estimator", "pos_armse", "vel_armse", "pos_armse_all", "vel_armse_all", "pos_armse_se",
                   "vel_armse_se", "pos_armse_all_se", "vel_armse_all_se", "pos_armse_inside_95",
                   "vel_armse_inside_95"],
        note="ARMSE over the last 100 s (the paper's Table I) and over all steps. _se: delta-method standard "
             "errors of the ARMSE over the runs (95 % interval: +- 1.96 se); _inside_95: whether the "
             "published Table I figure lies inside that interval (null without one).",
        published={"columns": ["estimator", "pos_armse", "vel_armse"],
                   "rows": [[k, *v] for k, v in PUBLISHED.items()], "source": "Huang et al. 2018, Table I"},
    )
    curves = {"position RMSE": {}, "velocity RMSE": {}}
    bands = {"position RMSE": {}, "velocity RMSE": {}}  # per-step standard errors of the curves
    for name, v in res.items():
        se = v.get("se", [None] * 4)
        pub_pos, pub_vel = PUBLISHED.get(name, (None, None))
        table.rows.append([name, *v["summary"], *se, inside(pub_pos, v["summary"][0], se[0]),
                           inside(pub_vel, v["summary"][1], se[1])])
        ctx.results.metric(name, "pos_armse_last100", v["summary"][0])
        ctx.results.metric(name, "vel_armse_last100", v["summary"][1])
        curves["position RMSE"][name] = torch.tensor(v["pos"], dtype=torch.float64)
        curves["velocity RMSE"][name] = torch.tensor(v["vel"], dtype=torch.float64)
        ctx.logger.series(f"pos_rmse/{name}", v["pos"])
        ctx.logger.series(f"vel_rmse/{name}", v["vel"])
        if "pos_band" in v:
            bands["position RMSE"][name] = torch.tensor(v["pos_band"], dtype=torch.float64)
            bands["velocity RMSE"][name] = torch.tensor(v["vel_band"], dtype=torch.float64)
            ctx.logger.series(f"pos_rmse_se/{name}", v["pos_band"])
            ctx.logger.series(f"vel_rmse_se/{name}", v["vel_band"])
    ctx.results.save()
    ctx.save_figure("rmse_over_time", plots.rmse_over_time(curves, f"Huang et al. scenario, {runs} runs",
                                                                  bands=bands))

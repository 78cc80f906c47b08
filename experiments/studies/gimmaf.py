"""Paper 004 (GIMMAF): the section-3.1 CT/CV scenario with skew-t noise; Tables 2 and 4, SRNFN.

Truth: Table 1 segments (turn rate, process noise ``G diag(q, q) G^T``), ``T = 1``, 250 steps,
start ``[1000, 10, 1000, 10]``. Measurements ``z = [x, y] + e`` with ``e`` skew-t (independent
axes, eq. (2)), Student-t or Gaussian. Estimators (all with the nominal ``Q_0``; the config nodes of
``gimmaf.estimators``, :func:`build_estimators`):

* ``IMM-VBT`` — IMM over Student-t VB filters on the model set {CV, CT(pi/400), CT(-pi/600)};
* ``STVBF`` — skew-t VB filter (Nurminen et al.), CV model;
* ``VBAKF-PR`` — Huang et al.'s adaptive KF, CV model, ``R~_0 = R``;
* ``GIMMAF`` — IMM over skew-t + inverse-Wishart VB filters, ELBO mode likelihood;
* ``KF-oracle`` (reference, not in the paper) — KF with the true ``F_k``, ``Q_k`` and the noise's
  true mean and covariance.

Tables: ``table2`` (estimator, pos_armse, vel_armse, finite, their standard errors ``*_se`` and
whether the published Table 2 figure beside lies inside our 95 % interval), ``table4`` (noise,
estimator, pos_armse, pos_armse_se), ``srnfn`` (estimator, srnfn_P, srnfn_R, time-averaged). Figures: position
and velocity RMSE over time (Figs. 1-2), SRNFN over time (Fig. 3), mean mode probabilities.
"""

from __future__ import annotations

import inspect
import logging
import math
import time

import torch

from experiments.executors import Unit
from experiments.harness import StudyContext, add_runs, join_runs, per_run
from experiments.studies import plots
from experiments.uncertainty import armse_se, inside, mean_se_per_step, rmse_se_per_step
from torchmm import GaussianBelief, KalmanFilter, LinearMotion, run_filter
from torchmm.distributions import SkewT
from torchmm.models import ConstantVelocity, CoordinatedTurn, PositionMeasurement
from torchmm.models.motion import turn_matrix

log = logging.getLogger("torchmm.experiments")

#: the paper's estimators: the default keys of ``gimmaf.estimators`` (conf/experiment/gimmaf.yaml)
ESTIMATORS = ["IMM-VBT", "STVBF", "VBAKF-PR", "GIMMAF"]
#: Table 2 of paper 004 (position m, velocity m/s)
PUBLISHED_T2 = {
    "IMM-VBT": (100.76, 3.16), "STVBF": (137.74, 2.18), "VBAKF-PR": (103.03, 2.63), "GIMMAF": (4.67, 1.53),
}
#: Table 4 of paper 004 (position ARMSE, robot experiment of section 3.2)
PUBLISHED_T4 = {
    "skew_t": {"IMM-VBT": 13.10, "STVBF": 22.79, "VBAKF-PR": 14.40, "GIMMAF": 8.61},
    "student_t": {"IMM-VBT": 3.78, "STVBF": 19.05, "VBAKF-PR": 7.93, "GIMMAF": 3.45},
    "gaussian": {"IMM-VBT": 6.53, "STVBF": 17.05, "VBAKF-PR": 6.12, "GIMMAF": 6.38},
}


def _gain(dt: float, **kw) -> torch.Tensor:
    G = torch.zeros(4, 2, **kw)
    G[0, 0] = G[2, 1] = dt**2 / 2
    G[1, 0] = G[3, 1] = dt
    return G


def noise_distribution(kind: str, R: float, delta: float, nu: float, **kw) -> SkewT:
    """The measurement-noise law per axis: skew-t, Student-t (``delta = 0``) or Gaussian."""
    loc = torch.zeros(2, **kw)
    if kind == "skew_t":
        return SkewT(loc, torch.full((2,), R, **kw), torch.full((2,), delta, **kw), nu)
    if kind == "student_t":
        return SkewT(loc, torch.full((2,), R, **kw), torch.zeros(2, **kw), nu)
    if kind == "gaussian":
        return None
    raise ValueError(f"gimmaf.noise.kind: expected skew_t | student_t | gaussian, got {kind!r}")


def simulate(g, runs: int, generator: torch.Generator, kind: str, R: float, delta: float, nu: float, *,
             dtype, device):
    """Truth ``(T, runs, 4)``, measurements ``(T, runs, 2)``, per-step ``F_k``, ``Q_k``, the noise mean and
    covariance, and the initial estimates ``(runs, 4)``."""
    kw = {"dtype": dtype, "device": device}
    steps, dt = int(g.steps), float(g.dt)
    G = _gain(dt, **kw)
    omegas = torch.zeros(steps, **kw)
    qs = torch.zeros(steps, **kw)
    for first, last, omega, q in g.segments:
        omegas[int(first) - 1:int(last)] = float(omega)
        qs[int(first) - 1:int(last)] = float(q)
    Fs = turn_matrix(omegas, dt)
    Qs = qs[:, None, None] * (G @ G.mT)
    x0 = torch.tensor(list(g.x0), **kw)
    P0 = torch.diag(torch.tensor(list(g.P0), **kw))
    noise = noise_distribution(kind, R, delta, nu, **kw)
    x = x0.expand(runs, 4)
    states, meas = [], []
    for k in range(steps):
        w = torch.randn(runs, 2, generator=generator, **kw) * qs[k].sqrt()
        x = x @ Fs[k].mT + w @ G.mT
        e = (torch.randn(runs, 2, generator=generator, **kw) * math.sqrt(R) if noise is None
             else noise.sample((runs,), generator=generator))
        states.append(x)
        meas.append(x[:, [0, 2]] + e)
    xhat0 = x0 + torch.randn(runs, 4, generator=generator, **kw) * P0.diagonal().sqrt()
    if noise is None:
        e_mean, e_cov = torch.zeros(2, **kw), R * torch.eye(2, **kw)
    else:
        e_mean, e_cov = noise.mean, noise.covariance_matrix
    return {"truth": torch.stack(states), "z": torch.stack(meas), "F": Fs, "Q": Qs, "e_mean": e_mean,
            "e_cov": e_cov, "xhat0": xhat0, "P0": P0}


def build_estimators(g, R: float, delta: float, nu: float, *, dtype, device) -> dict:
    """The estimators of ``g.estimators`` (name -> config node) for the measurement noise ``R``,
    ``delta``, ``nu`` of a setting (Table 2's or a Table 4 noise), in the map's order.

    Each node is a partial of a torchmm function or class, called as
    ``make(bank, sensor, transition, **noise)`` when it takes a ``transition`` (an IMM over the
    ``model_rates`` bank: ``imm_vbt``, ``gimmaf``) and as ``make(cv, sensor, **noise)`` otherwise (a
    single filter on the CV model: ``SkewTVBFilter``, ``VBAKFPR``), all with the nominal ``Q_0``;
    ``noise`` is ``skewness=delta``, ``df=nu``, as far as the target takes them (they change with the
    setting, so they are not node options).
    """
    from hydra.utils import instantiate

    kw = {"dtype": dtype, "device": device}
    q0 = float(g.nominal_q)
    # the models are modules: built on the CPU, then moved with their tensors (F, Q, H, R) to the device
    rates = torch.tensor(list(g.model_rates), dtype=dtype)
    bank = CoordinatedTurn(rates, dt=float(g.dt), q=q0, dtype=dtype).to(device)
    cv = ConstantVelocity(2, dt=float(g.dt), q=q0, dtype=dtype).to(device)
    meas = PositionMeasurement(4, [0, 2], torch.tensor(R, dtype=dtype)).to(device)
    transition = torch.tensor([list(r) for r in g.transition], **kw)
    noise = {"skewness": delta, "df": nu}
    out = {}
    for name, node in g.estimators.items():
        make = instantiate(node)
        params = inspect.signature(make.func).parameters
        models = (bank, meas, transition) if "transition" in params else (cv, meas)
        out[str(name)] = make(*models, **{k: v for k, v in noise.items() if k in params})
    return out


def _oracle(data, steps: int):
    """KF with the true F_k, Q_k, noise mean (subtracted) and covariance; its predicted covariances."""
    H = torch.zeros(2, 4, dtype=data["z"].dtype, device=data["z"].device)
    H[0, 0] = H[1, 2] = 1.0
    meas = PositionMeasurement(4, [0, 2], data["e_cov"])
    belief = GaussianBelief(data["xhat0"], data["P0"].expand(*data["xhat0"].shape, 4))
    motions = [LinearMotion(data["F"][k], data["Q"][k]) for k in range(steps)]  # the true F_k, Q_k per step
    traj = run_filter(KalmanFilter(motions[0], meas), belief, data["z"][:steps] - data["e_mean"], motions=motions)
    return traj.belief.mean, traj.prior.cov


#: where simulate()'s outputs hold the runs (time-major truth and z, x̂0 runs first; the rest shared)
SIM_AXES = {"truth": 1, "z": 1, "F": None, "Q": None, "e_mean": None, "e_cov": None, "xhat0": 0, "P0": None}


def run_unit(g, noise_kind: str, noise_params, runs: int, generator, *, dtype, device,
             with_oracle: bool, progress: bool = False, simulate_runs=None, start: int = 0) -> dict:
    """Every filter on runs ``start..runs-1`` of the data: per-run squared errors and sums over these
    runs of the per-step statistics, per estimator (one value of a setting's units: :func:`merge`).
    ``simulate_runs(draw, runs, start)`` (the study's run-indexed blocks) simulates instead of one
    stream from ``generator``."""
    R, delta, nu = float(noise_params.R), float(noise_params.delta), float(noise_params.nu)
    steps = int(g.steps)
    # simulated in float64 and cast: float32 and float64 runs see the same data
    def draw(n, gen):
        return simulate(g, n, gen, noise_kind, R, delta, nu, dtype=torch.float64, device=device)

    data = draw(runs - start, generator) if simulate_runs is None else simulate_runs(draw, runs, start)
    data = {k: v.to(dtype) if isinstance(v, torch.Tensor) and v.is_floating_point() else v for k, v in data.items()}
    truth = data["truth"]
    n = truth.shape[1]
    oracle_mean, oracle_pred = _oracle(data, steps)
    estimators = build_estimators(g, R, delta, nu, dtype=dtype, device=device)
    start_belief = GaussianBelief(data["xhat0"], data["P0"].expand(n, 4, 4))

    def errors(mean):
        err = mean - truth
        return {"pos": per_run(err[..., [0, 2]].square().sum(-1)), "vel": per_run(err[..., [1, 3]].square().sum(-1)),
                "runs": n, "finite": bool(torch.isfinite(mean).all())}

    def frobenius(estimate, reference):  # per step, summed over these runs: (T,)
        return per_run((estimate - reference).square().sum((-1, -2)).sum(-1))

    def frobenius_sq(estimate, reference):  # the squares' sum (the per-step standard errors): (T,)
        return per_run((estimate - reference).square().sum((-1, -2)).to(torch.float64).square().sum(-1))

    out = {}
    for name, est in estimators.items():
        b0 = est.initial_belief(start_belief)  # mode beliefs, adaptive noise; a plain filter: the prior itself
        tic = time.perf_counter()
        traj = run_filter(est, b0, data["z"], record=lambda o: o._replace(prior=None),
                          progress=f"{noise_kind}: {name}" if progress else False)
        mean = traj.estimate().mean
        seconds = time.perf_counter() - tic
        extras = traj.extras.get("modes", traj.extras)
        if "modes" in traj.extras:
            w = traj.belief.mode_probs[..., None, None]
            P_hat = (w * extras["predicted_cov"]).sum(-3)
            R_hat = (w * extras["noise_cov"]).sum(-3)
            mode_probs = per_run(traj.belief.mode_probs.sum(1))
            mode_probs_sq = per_run(traj.belief.mode_probs.to(torch.float64).square().sum(1))
        else:
            P_hat, R_hat, mode_probs, mode_probs_sq = extras["predicted_cov"], extras["noise_cov"], None, None
        entry = {**errors(mean), "srnfn_P_sum": frobenius(P_hat, oracle_pred),
                 "srnfn_R_sum": frobenius(R_hat, data["e_cov"].expand_as(R_hat)),
                 "srnfn_P_sq": frobenius_sq(P_hat, oracle_pred),
                 "srnfn_R_sq": frobenius_sq(R_hat, data["e_cov"].expand_as(R_hat)),
                 "d": [int(P_hat.shape[-1]), int(R_hat.shape[-1])],
                 "seconds": seconds, "steps": steps}
        if mode_probs is not None:
            entry["mode_probs_sum"], entry["mode_probs_sq"] = mode_probs, mode_probs_sq
        if "elbo" in extras:
            elbo = extras["elbo"].flatten(0, -2)
            entry["elbo_sum"], entry["elbo_count"] = per_run(elbo.sum(0)), elbo.shape[0]
        out[name] = entry
    if with_oracle:
        out["KF-oracle"] = errors(oracle_mean)
        out["KF-oracle"]["finite"] = True
    return out


def merge(parts: list[dict]) -> dict:
    """A setting's units of runs (in run order) as one value per estimator: RMSE curves, standard
    errors, SRNFN curves, finiteness, mean mode probabilities and ELBO, seconds per step."""
    out = {}
    for name, first in parts[0].items():
        mine = [p[name] for p in parts]
        runs = sum(m["runs"] for m in mine)

        def add(key):
            return add_runs([m[key] for m in mine])

        sq_pos, sq_vel = (join_runs([m[k] for m in mine]) for k in ("pos", "vel"))
        entry = {"pos": (sq_pos.sum(1) / runs).sqrt(), "vel": (sq_vel.sum(1) / runs).sqrt(),
                 **_uncertainty(sq_pos, sq_vel), "finite": all(m["finite"] for m in mine)}
        if "srnfn_P_sum" in first:
            d_P, d_R = first["d"]  # SRNFN: (1/(d^2 runs) sum_runs ||est - truth||_F^2)^(1/4) per step
            entry["srnfn_P"] = (add("srnfn_P_sum") / runs / d_P**2) ** 0.25
            entry["srnfn_R"] = (add("srnfn_R_sum") / runs / d_R**2) ** 0.25
            if all("srnfn_P_sq" in m for m in mine):  # delta method: se(m^(1/4)) = m^(1/4) se(m) / (4 m)
                for key in ("srnfn_P", "srnfn_R"):
                    mean = add(f"{key}_sum").to(torch.float64) / runs
                    se = mean_se_per_step(add(f"{key}_sum"), add(f"{key}_sq"), runs)
                    entry[f"{key}_se"] = torch.where(mean > 0, entry[key].to(torch.float64) * se
                                                     / (4 * mean.clamp_min(torch.finfo(mean.dtype).tiny)), 0.0)
            entry["seconds_per_step"] = sum(m["seconds"] for m in mine) / first["steps"]
        if "mode_probs_sum" in first:
            entry["mode_probs"] = add("mode_probs_sum") / runs
            if all(m.get("mode_probs_sq") is not None for m in mine):
                entry["mode_probs_se"] = mean_se_per_step(add("mode_probs_sum"), add("mode_probs_sq"), runs)
        if "elbo_sum" in first:
            entry["elbo_iterations"] = add("elbo_sum") / sum(m["elbo_count"] for m in mine)
        out[name] = {k: (v.tolist() if torch.is_tensor(v) else v) for k, v in entry.items()}
    return out


def _uncertainty(sq_pos: torch.Tensor, sq_vel: torch.Tensor) -> dict:
    """Monte Carlo standard errors from the squared position / velocity errors ``(T, runs)``: the
    delta-method SE of the ARMSEs (floats) and of each step's RMSE (``(T,)`` bands)."""
    sq_pos, sq_vel = sq_pos.to(torch.float64), sq_vel.to(torch.float64)
    return {"pos_se": armse_se(sq_pos), "vel_se": armse_se(sq_vel),
            "pos_band": rmse_se_per_step(sq_pos), "vel_band": rmse_se_per_step(sq_vel)}


def _segments_labels(g) -> list[str]:
    if len(g.model_rates) == 3:
        return ["CV", "CT(pi/400)", "CT(-pi/600)"]
    return [f"w={w:.4f}" for w in g.model_rates]


#: the study's unit function (what an executor ships: this path, the config and the arguments)
UNIT = "experiments.studies.gimmaf:unit"


def unit(ctx: StudyContext, *, table: str, kind: str, start: int, stop: int) -> dict:
    """Table 2 (``table="table2"``, the main noise) or one Table 4 noise ``kind``: every filter on runs
    ``start..stop-1`` of its run-indexed data; a function of the config and these arguments only."""
    g = ctx.cfg.gimmaf
    params = g.noise if table == "table2" else g.table4.noise
    return run_unit(g, kind, params, stop, None, dtype=ctx.dtype, device=ctx.device, start=start,
                    progress=ctx.progress, with_oracle=bool(g.oracle),
                    simulate_runs=lambda draw, n, a: ctx.simulate_runs(draw, n, "data", kind, table, axes=SIM_AXES,
                                                                      start=a))


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    g = cfg.gimmaf
    runs = int(cfg.mc_runs)
    main_kind = str(g.noise.kind)
    ctx.results.description = (
        f"Paper 004 section 3.1: {g.steps} steps, {runs} Monte Carlo runs (seed {cfg.seed}, {cfg.dtype}); "
        f"noise {main_kind} (R = {g.noise.R}, delta = {g.noise.delta}, nu = {g.noise.nu}); nominal Q_0 = "
        f"{g.nominal_q} G G^T, tau = {g.tau}, {g.iterations} VB iterations, gamma shape {g.gamma_shape}. "
        "ARMSE = time average of the per-step RMSE over runs (position: x and y together). "
        "KF-oracle is a reference (true F_k, Q_k, noise mean and covariance), not in the paper."
    )
    # Table 2 and every Table 4 noise are units, all at once: an executor (executor=processes|slurm|ray)
    # runs them side by side
    # (and each range of runs, unit_runs=...; a setting's ranges are merged in run order)
    todo = [("table2", main_kind)] + [("table4", str(kind)) for kind in g.table4.noises]
    ranges = ctx.run_ranges(runs)
    parts = ctx.map_units([Unit(f"{table}/{kind}/runs{a}-{b}", UNIT, {"table": table, "kind": kind, "start": a,
                                                                      "stop": b})
                           for table, kind in todo for a, b in ranges], desc="units")
    n = len(ranges)
    value_of = {setting: merge(parts[i * n:(i + 1) * n]) for i, setting in enumerate(todo)}
    main = value_of[("table2", main_kind)]
    t2 = ctx.results.table(
        "table2", ["estimator", "pos_armse", "vel_armse", "finite", "pos_armse_se", "vel_armse_se",
                   "pos_armse_inside_95", "vel_armse_inside_95"],
        note="Position ARMSE in m, velocity ARMSE in m/s. _se: delta-method standard errors of the ARMSE "
             "over the runs (95 % interval: +- 1.96 se); _inside_95: whether the published figure lies "
             "inside that interval (null without one).",
        published={"columns": ["estimator", "pos_armse", "vel_armse"],
                   "rows": [[k, *v] for k, v in PUBLISHED_T2.items()], "source": "paper 004, Table 2"},
    )
    srnfn = ctx.results.table("srnfn", ["estimator", "srnfn_P", "srnfn_R"],
                              note="Time-averaged SRNFN of P_{k|k-1} (vs the oracle KF's) and of R "
                                   "(vs the noise covariance).")
    curves = {"position RMSE": {}, "velocity RMSE": {}}
    bands = {"position RMSE": {}, "velocity RMSE": {}}  # per-step standard errors of the curves
    sr_curves = {"SRNFN of P_k|k-1": {}, "SRNFN of R": {}}
    sr_bands = {"SRNFN of P_k|k-1": {}, "SRNFN of R": {}}  # their per-step standard errors
    for name, e in main.items():
        pos, vel = torch.tensor(e["pos"], dtype=torch.float64), torch.tensor(e["vel"], dtype=torch.float64)
        pub_pos, pub_vel = PUBLISHED_T2.get(name, (None, None))
        pos_se, vel_se = e.get("pos_se"), e.get("vel_se")
        t2.rows.append([name, pos.mean().item(), vel.mean().item(), e["finite"], pos_se, vel_se,
                        inside(pub_pos, pos.mean().item(), pos_se), inside(pub_vel, vel.mean().item(), vel_se)])
        if "seconds_per_step" in e:
            ctx.results.timing[name] = e["seconds_per_step"]
        ctx.results.metric(name, "pos_armse", pos.mean().item())
        ctx.results.metric(name, "vel_armse", vel.mean().item())
        curves["position RMSE"][name], curves["velocity RMSE"][name] = pos, vel
        ctx.logger.series(f"pos_rmse/{name}", pos)
        ctx.logger.series(f"vel_rmse/{name}", vel)
        if "pos_band" in e:  # per-step standard errors of the RMSE curves
            bands["position RMSE"][name] = torch.tensor(e["pos_band"], dtype=torch.float64)
            bands["velocity RMSE"][name] = torch.tensor(e["vel_band"], dtype=torch.float64)
            ctx.logger.series(f"pos_rmse_se/{name}", e["pos_band"])
            ctx.logger.series(f"vel_rmse_se/{name}", e["vel_band"])
        if "srnfn_P" in e:
            sp, sr = torch.tensor(e["srnfn_P"], dtype=torch.float64), torch.tensor(e["srnfn_R"], dtype=torch.float64)
            srnfn.rows.append([name, sp.mean().item(), sr.mean().item()])
            sr_curves["SRNFN of P_k|k-1"][name], sr_curves["SRNFN of R"][name] = sp, sr
            ctx.logger.series(f"srnfn_P/{name}", sp)
            ctx.logger.series(f"srnfn_R/{name}", sr)
            if "srnfn_P_se" in e:  # per-step standard errors (delta method over the runs)
                ctx.logger.series(f"srnfn_P_se/{name}", e["srnfn_P_se"])
                ctx.logger.series(f"srnfn_R_se/{name}", e["srnfn_R_se"])
                sr_bands["SRNFN of P_k|k-1"][name] = torch.tensor(e["srnfn_P_se"], dtype=torch.float64)
                sr_bands["SRNFN of R"][name] = torch.tensor(e["srnfn_R_se"], dtype=torch.float64)
        if "elbo_iterations" in e:
            ctx.logger.series(f"elbo_per_iteration/{name}", e["elbo_iterations"])
        if "mode_probs" in e:
            probs = torch.tensor(e["mode_probs"], dtype=torch.float64)
            for j, label in enumerate(_segments_labels(g)):
                ctx.logger.series(f"mode_probability/{name}/{label}", probs[:, j])
            if "mode_probs_se" in e:  # sd over runs / sqrt(N)
                probs_se = torch.tensor(e["mode_probs_se"], dtype=torch.float64)
                for j, label in enumerate(_segments_labels(g)):
                    ctx.logger.series(f"mode_probability_se/{name}/{label}", probs_se[:, j])
    ctx.results.save()
    title = f"paper 004 scenario, {main_kind} noise, {runs} runs"
    ctx.save_figure("rmse_over_time", plots.rmse_over_time(curves, title, bands=bands))
    ctx.save_figure("srnfn_over_time", plots.rmse_over_time(sr_curves, title, bands=sr_bands))
    mm = {n: torch.tensor(e["mode_probs"], dtype=torch.float64) for n, e in main.items() if "mode_probs" in e}
    if mm:
        ctx.save_figure("mode_probabilities", _mode_figure(mm, g))

    t4 = ctx.results.table(
        "table4", ["noise", "estimator", "pos_armse", "pos_armse_se"],
        note=f"Simulation scenario of section 3.1 with the Table-4 noise parameters {dict(g.table4.noise)} "
             "(the paper's Table 4 is from the robot experiment of section 3.2, whose data are not "
             "available: no interval check against it). pos_armse_se: delta-method standard error of the "
             "ARMSE over the runs (95 % interval: +- 1.96 se).",
        published={"columns": ["noise", "estimator", "pos_armse"],
                   "rows": [[n, e, v] for n, d in PUBLISHED_T4.items() for e, v in d.items()],
                   "source": "paper 004, Table 4 (robot experiment)"},
    )
    for kind in g.table4.noises:
        kind = str(kind)
        res = value_of[("table4", kind)]
        for name, e in res.items():
            t4.rows.append([kind, name, torch.tensor(e["pos"], dtype=torch.float64).mean().item(), e.get("pos_se")])
        ctx.results.save()


def _mode_figure(mode_probs: dict, g):
    import matplotlib.pyplot as plt

    labels = _segments_labels(g)
    fig, axes = plt.subplots(len(mode_probs), 1, figsize=(8, 2.6 * len(mode_probs)), sharex=True,
                             squeeze=False)
    for ax, (name, probs) in zip(axes[:, 0], mode_probs.items()):
        for j, label in enumerate(labels):
            ax.plot(range(1, probs.shape[0] + 1), probs[:, j], label=label)
        for first, _, omega, _ in g.segments:
            ax.axvline(int(first), color="k", lw=0.5, alpha=0.4)
        ax.set_ylabel(f"{name}\nmean mode prob.")
        ax.set_ylim(0, 1)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time step k")
    fig.tight_layout()
    return fig

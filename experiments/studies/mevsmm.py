"""Paper 003 (minimum-entropy VSMM), section 4: PF-MEVSMM vs EqMA9+1 / EqMA21+1 on particle filters.

Scenarios (``conf/scenario/det_small.yaml``, ``det_large.yaml``, ``random.yaml``): a 2-D target
``X = [x, vx, y, vy]`` with ``X(k) = F X(k-1) + D A(k)`` (35), ``X(1) = [10000, 150, 10000, 100]``,
180 steps; deterministic maneuvers ``A = [10, -12]`` (31-80 s) and ``[-30, 30]`` (81-120 s) with
``R = 25^2 I`` or ``150^2 I``, or random maneuvers (probability 0.7 per step of a new
``A ~ N(0, 30^2 I)``) with ``R = 150^2 I``. The 21 acceleration models of section 4.

Tables: ``rmse`` (estimator, pos_rmse, vel_rmse, maneuver_pos_rmse, and their standard errors
``*_se``), ``table1`` (estimator, avg_model_count, avg_model_count_se, published_inside_95),
``table2`` (estimator, seconds_per_step, relative_time). Figures: position RMSE over time (with
95 % bands), selected model count over time, model-set membership (time x model). TensorBoard: ESS,
model count and RMSE (and its standard error) per step, particle-weight histograms.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from experiments.executors import Unit
from experiments.harness import StudyContext, add_runs, join_runs, per_run
from experiments.studies import plots
from experiments.estimators import build_mode_filter
from experiments.uncertainty import armse_se, inside, mean_se_per_step, rmse_se_per_step
from torchmm import GaussianBelief, LinearMotion, PositionMeasurement, run_filter
from torchmm.filters import StepOutput
from torchmm.multimodel import VariableStructureIMM
from torchmm.multimodel.mevsmm import (
    EqMAParticleFilter,
    ExactMinimumEntropy,
    MinimumEntropyVSMM,
    uniform_transition,
)

log = logging.getLogger("torchmm.experiments")

#: the 21 models of section 4 (accelerations in m/s^2, [a_x, a_y]); m1 .. m21
MODELS = [
    [0, 0], [0, 10], [0, -10], [10, 0], [-10, 0], [10, 10], [10, -10], [-10, 10], [-10, -10],
    [0, 20], [0, -20], [20, 0], [-20, 0], [20, 20], [20, -20], [-20, 20], [-20, -20],
    [0, 40], [0, -40], [40, 0], [-40, 0],
]
#: EqMA9+1 centres {m1, m6..m13} (0-based indices; conf/mevsmm_estimator/eqma9.yaml lists them 1-based)
EQMA9 = [0, 5, 6, 7, 8, 9, 10, 11, 12]

PUBLISHED_TABLE1 = {"det_small": 6.6, "det_large": 6.3}
PUBLISHED_TABLE2 = [["EqMA9+1", 1.000], ["EqMA21+1", 1.874], ["PF-MEVSMM", 2.143]]


@dataclass
class Paper003Scenario:
    name: str
    F: Tensor
    D: Tensor
    R: float
    steps: int
    initial_state: Tensor
    initial_std: tuple[float, float]
    maneuvers: list
    random: dict | None
    d_reading: str

    @property
    def measurement(self) -> PositionMeasurement:
        return PositionMeasurement(4, [0, 2], torch.tensor(self.R**2, dtype=self.F.dtype, device=self.F.device),
                                   dtype=self.F.dtype).to(self.F.device)

    def simulate(self, runs: int, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
        """Truth ``(T, runs, 4)``, accelerations ``(T, runs, 2)`` and measurements ``(T, runs, 2)``."""
        dtype, device = self.F.dtype, self.F.device
        T = self.steps
        acc = torch.zeros(T, runs, 2, dtype=dtype, device=device)
        if self.random is None:
            for start, stop, a in self.maneuvers:  # 1-based inclusive seconds
                acc[start - 1 : stop] = torch.tensor(a, dtype=dtype, device=device)
        else:
            p, std = float(self.random["maneuver_prob"]), float(self.random["accel_std"])
            hold = str(self.random.get("hold", "previous"))
            draws = std * torch.randn(T, runs, 2, dtype=dtype, device=device, generator=generator)
            new = torch.rand(T, runs, 1, dtype=dtype, device=device, generator=generator) < p
            for k in range(1, T):  # loop over time only
                keep = acc[k - 1] if hold == "previous" else torch.zeros_like(acc[k - 1])
                acc[k] = torch.where(new[k], draws[k], keep)
        states = [self.initial_state.expand(runs, 4)]
        for k in range(1, T):
            states.append(states[-1] @ self.F.mT + acc[k] @ self.D.mT)
        truth = torch.stack(states)
        z = truth[..., [0, 2]] + self.R * torch.randn(T, runs, 2, dtype=dtype, device=device, generator=generator)
        return truth, acc, z

    def prior(self, runs: int) -> GaussianBelief:
        pos, vel = self.initial_std
        var = torch.tensor([pos**2, vel**2, pos**2, vel**2], dtype=self.F.dtype, device=self.F.device)
        return GaussianBelief(self.initial_state.expand(runs, 4), torch.diag(var).expand(runs, 4, 4))


def paper003_scenario(*, name: str, R: float, steps: int = 180, initial_state=(10000.0, 150.0, 10000.0, 100.0),
                      initial_std=None, maneuvers=(), random=None, D: str = "kinematic",
                      dtype: torch.dtype = torch.float64, device="cpu") -> Paper003Scenario:
    """The section-4 scenario. ``D="kinematic"`` uses ``[[1/2, 0], [1, 0], [0, 1/2], [0, 1]]``
    (``T^2/2`` on positions, ``T`` on velocities for the state order ``[x, vx, y, vy]``);
    ``D="printed"`` uses the matrix as printed, ``[[1, 0], [1/2, 0], [0, 1], [0, 1/2]]``."""
    F = torch.tensor([[1.0, 1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]], dtype=dtype, device=device)
    if D == "kinematic":
        Dm = torch.tensor([[0.5, 0], [1, 0], [0, 0.5], [0, 1]], dtype=dtype, device=device)
    elif D == "printed":
        Dm = torch.tensor([[1.0, 0], [0.5, 0], [0, 1], [0, 0.5]], dtype=dtype, device=device)
    else:
        raise ValueError(f"scenario.D: expected 'kinematic' or 'printed', got {D!r}")
    std = (float(R), 10.0) if initial_std is None else tuple(float(s) for s in initial_std)
    return Paper003Scenario(
        name=name, F=F, D=Dm, R=float(R), steps=int(steps),
        initial_state=torch.tensor(list(initial_state), dtype=dtype, device=device), initial_std=std,
        maneuvers=[list(m) for m in maneuvers], random=None if random is None else dict(random), d_reading=D,
    )


# -- estimator builders (conf/mevsmm_estimator/*.yaml: the nodes of ``mevsmm.estimators``) ------------
#: node keys the study reads itself (not builder options): ``runs`` (at most this many of the runs,
#: e.g. ``${mevsmm.exact_runs}``) and ``timing_base`` (table2's relative_time is relative to it)
STUDY_KEYS = ("runs", "timing_base")


def _accelerations(scenario: Paper003Scenario, accel_std: float) -> tuple[Tensor, Tensor]:
    """The 21 model accelerations ``(21, 2)`` and the filter acceleration-noise covariance ``(2, 2)``."""
    dtype, device = scenario.F.dtype, scenario.F.device
    acc = torch.tensor(MODELS, dtype=dtype, device=device)
    return acc, float(accel_std) ** 2 * torch.eye(2, dtype=dtype, device=device)


def _selection_motion(scenario: Paper003Scenario, accel_std: float, stay_prob: float | None):
    """The 21-model bank as one :class:`LinearMotion` (offsets ``D a_j``) and its transition matrix
    (``stay_prob`` null: uniform ``1/21``, the "maximum-likelihood" competition of section 3.4.3)."""
    dtype, device = scenario.F.dtype, scenario.F.device
    acc, qa = _accelerations(scenario, accel_std)
    motion = LinearMotion(scenario.F, scenario.D @ qa @ scenario.D.mT, offset=acc @ scenario.D.mT)
    stay = 1.0 / len(MODELS) if stay_prob is None else float(stay_prob)
    return motion, uniform_transition(len(MODELS), stay, dtype=dtype, device=device)


def eqma(scenario: Paper003Scenario, *, models=None, num_particles: int, stay_prob: float = 0.9,
         accel_std: float = 5.0, mixing: str = "two_stage", noise_dtype: str | None = None) -> EqMAParticleFilter:
    """EqMA ``N+1`` on particle filters (docs/baselines.md §2.2) over the section-4 models ``models``
    (``m_j``, 1-based; null: all 21): ``conf/mevsmm_estimator/eqma9.yaml``, ``eqma21.yaml``."""
    acc, qa = _accelerations(scenario, accel_std)
    grid = acc if models is None else acc[[int(m) - 1 for m in models]]
    return EqMAParticleFilter(scenario.F, scenario.D, grid, qa, scenario.measurement, int(num_particles),
                              stay=float(stay_prob), mixing=str(mixing), innovation_stats=False,
                              noise_dtype=noise_dtype)


def pf_mevsmm(scenario: Paper003Scenario, *, selection, num_particles: int, feedback: bool = True,
              stay_prob: float | None = None, accel_std: float = 5.0, mixing: str = "two_stage",
              noise_dtype: str | None = None) -> MinimumEntropyVSMM:
    """PF-MEVSMM over the 21 models with a model-set ``selection`` (a ``ChallengeMatch`` or
    ``ExactMinimumEntropy`` node): ``conf/mevsmm_estimator/cm.yaml``, ``topk``, ``nofeedback``,
    ``exact``, ``mmpf``."""
    motion, transition = _selection_motion(scenario, accel_std, stay_prob)
    return MinimumEntropyVSMM(motion, scenario.measurement, transition, int(num_particles), selection=selection,
                              feedback=bool(feedback), mixing=str(mixing), innovation_stats=False,
                              noise_dtype=noise_dtype)


def vsmm(scenario: Paper003Scenario, *, mode_filter=None, policy=None, entropy: str = "joint",
         feedback: bool = True, stay_prob: float | None = None, accel_std: float = 5.0) -> VariableStructureIMM:
    """The model-set ``policy`` (conf/policy; null: the exact minimum-entropy set with ``entropy``)
    over a bank of ``mode_filter`` filters (conf/mode_filter) of the 21 models:
    ``conf/mevsmm_estimator/vsmm.yaml``."""
    motion, transition = _selection_motion(scenario, accel_std, stay_prob)
    bank = build_mode_filter(mode_filter, motion, scenario.measurement)
    return VariableStructureIMM(bank, transition, policy or ExactMinimumEntropy(entropy=str(entropy)),
                                feedback=bool(feedback))


def _node(opts, name: str) -> dict:
    """Estimator ``name``'s node of ``mevsmm.estimators``, resolved (a plain dict)."""
    from omegaconf import OmegaConf

    node = opts.estimators[name]
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else dict(node)


def _build(node: dict, scenario: Paper003Scenario):
    """The estimator of a ``mevsmm.estimators`` node: its builder called with the scenario; its
    random stream is an argument of every call (:func:`_run`)."""
    from hydra.utils import instantiate

    make = instantiate({k: v for k, v in node.items() if k not in STUDY_KEYS})
    return make(scenario)


def _warm_up(filt, scenario: Paper003Scenario, z: Tensor) -> None:
    """One untimed run of the estimator over two steps of at most two runs, with a generator of its own
    (the study's streams are not touched, so no number changes): what a process's first call loads or
    compiles (the Numba particle stages, ~4 s) is then not charged to whichever estimator runs first in
    table2 (it made EqMA9+1's relative time 0.03 at small sizes). ``z``: ``(T, runs, m)``."""
    g = torch.Generator(device=z.device).manual_seed(0)
    belief0 = filt.initial_belief(scenario.prior(min(z.shape[1], 2)), generator=g)
    run_filter(filt, belief0, z[:2, :2], generator=g, update_first=True,
               record=lambda out: StepOutput(None, None, out.log_likelihood, None, None, {}))


def _run(filt, scenario: Paper003Scenario, z: Tensor, hist_steps: set[int], generator: torch.Generator) -> dict:
    """Filter all runs (:func:`~torchmm.run_filter`, the first datum at the prior's time: update only);
    returns per-step estimates, model counts, membership, ESS, weight histograms and the time per step."""
    runs = z.shape[1]
    hists: dict[int, Tensor] = {}
    step = iter(range(1, z.shape[0] + 1))

    def record(out):  # keep only what the study reports (the particle sets are too large to keep)
        k, belief, extras = next(step), out.belief, out.extras
        kept = {"mean": _estimate_mean(belief),
                "count": extras["model_count"].to(z.dtype) if "active" in extras
                else torch.full((runs,), float(filt.num_modes), dtype=z.dtype, device=z.device)}
        if "active" in extras:
            kept["active"] = extras["active"]
        if "fallback" in extras:  # (a challenge match: no model reached the threshold)
            kept["fallback"] = extras["fallback"]
        if "ess" in extras:
            kept["ess"] = extras["ess"]
        if k in hist_steps and hasattr(belief.components, "log_weights"):
            lw = belief.mode_log_probs[0].unsqueeze(-1) + belief.components.log_weights[0]
            hists[k] = lw.flatten().detach().clamp_min(-700.0)  # JSON-safe (no -inf)
        return StepOutput(None, None, out.log_likelihood, None, None, kept)

    tic = time.perf_counter()
    belief0 = filt.initial_belief(scenario.prior(runs), generator=generator)
    traj = run_filter(filt, belief0, z, generator=generator, update_first=True, record=record)
    elapsed = time.perf_counter() - tic
    kept = traj.extras
    return {
        "mean": kept["mean"], "count": kept["count"], "members": kept.get("active"),
        "ess": kept.get("ess"),  # particle estimators only
        "fallback": kept.get("fallback"),  # a policy that can fall back (the challenge match) only
        "hists": hists, "seconds_per_step": elapsed / z.shape[0],
    }


def _estimate_mean(belief) -> Tensor:
    """The output estimate's mean (31) without its covariance: one batched matmul. ``(*B, n)``."""
    if not hasattr(belief.components, "log_weights"):  # Gaussian mode filters (the vsmm builder)
        return belief.estimate().mean
    lp = belief.mode_log_probs
    if hasattr(belief, "active"):
        lp = torch.where(belief.active, lp, torch.full_like(lp, -float("inf")))
    lp = lp - torch.logsumexp(lp, -1, keepdim=True)
    comps = belief.components
    w = (lp.unsqueeze(-1) + comps.log_weights).exp().flatten(-2)  # within-model weights are normalised
    return (w.unsqueeze(-2) @ comps.particles.flatten(-3, -2)).squeeze(-2)


def _data(ctx: StudyContext, start: int = 0, stop: int | None = None):
    """``(scenario, truth, z)``: the scenario and its run-indexed data of runs ``start..stop-1`` (all
    by default), simulated once per process."""
    stop = int(ctx.cfg.mc_runs) if stop is None else stop

    def simulate():
        scenario, data_scenario = ctx.scenarios(ctx.cfg.scenario)
        truth, _, z = ctx.simulate_runs(data_scenario.simulate, stop, "data", scenario.name, start=start)
        return scenario, truth.to(ctx.dtype), z.to(ctx.dtype)  # float64 draws: the same data in any dtype

    return ctx.memo(("data", start, stop), simulate)


#: the study's unit function (what an executor ships: this path, the config and the arguments)
UNIT = "experiments.studies.mevsmm:unit"


def unit(ctx: StudyContext, *, name: str, start: int, stop: int) -> dict:
    """Estimator ``name`` (its node of ``mevsmm.estimators``) on runs ``start..stop-1``: per-run
    squared errors and model counts, and sums over these runs of the per-step statistics (merged
    over units by :func:`_merge`); a function of the config and these arguments only."""
    opts = ctx.cfg.mevsmm
    scenario, truth, z = _data(ctx, start, stop)
    hist_steps = {int(s) for s in opts.histogram_steps}
    # the particle filters draw from one stream per block of runs (run-indexed): any chunking or
    # split over workers gives the same numbers; every figure is reduced over all runs at once
    values: dict[str, list] = {k: [] for k in ("pos", "vel", "count", "ess", "members", "fallback")}
    seconds, hists = 0.0, {}
    filt = _build(_node(opts, name), scenario)
    _warm_up(filt, scenario, z)
    stream, first = ctx.block_generators("filter", scenario.name, name), start // ctx.block_runs
    for b, sl in enumerate(ctx.blocks(stop - start)):
        res = _run(filt, scenario, z[:, sl], hist_steps if first + b == 0 else set(), stream(first + b))
        err = res["mean"] - truth[:, sl]
        values["pos"].append(err[..., [0, 2]].square().sum(-1).detach())  # (T, block)
        values["vel"].append(err[..., [1, 3]].square().sum(-1).detach())
        values["count"].append(res["count"].detach().to(ctx.dtype))
        if res["ess"] is not None:
            values["ess"].append(res["ess"].detach())
        if res["members"] is not None:
            values["members"].append(res["members"].to(ctx.dtype))
        if res["fallback"] is not None:
            values["fallback"].append(res["fallback"].to(ctx.dtype))
        seconds += res["seconds_per_step"]
        hists = hists or {str(k): v.tolist() for k, v in res["hists"].items()}
    joined = {k: torch.cat(v, 1) for k, v in values.items() if v}  # (T, runs here, ...)
    return {
        "pos": per_run(joined["pos"]), "vel": per_run(joined["vel"]),
        "run_counts": per_run(joined["count"].to(torch.float64).mean(0)),  # a run's time-averaged model count
        "sums": {k: per_run(v.sum(1)) for k, v in joined.items() if k not in ("pos", "vel")},
        # sums of squares: each step's standard error of the mean count and ESS over the runs
        "sq_sums": {k: per_run(joined[k].to(torch.float64).square().sum(1)) for k in ("count", "ess") if k in joined},
        "runs": stop - start, "seconds": seconds, "hists": hists,
    }


def _merge(parts: list[dict], runs: int, window: slice | None) -> dict:
    """An estimator's units of runs (in run order) as one value: RMSE curves, mean model count, ESS
    and membership, timing (scaled to all ``runs``), standard errors."""
    est_runs = sum(int(p["runs"]) for p in parts)

    def add(key):
        return add_runs([p["sums"][key] for p in parts]) / est_runs if key in parts[0]["sums"] else None

    pos, vel = (join_runs([p[k] for p in parts]) for k in ("pos", "vel"))
    e_pos, e_vel = pos.to(torch.float64), vel.to(torch.float64)
    run_counts = join_runs([p["run_counts"] for p in parts], 0)
    count, ess, members = add("count"), add("ess"), add("members")
    # the fraction of (run, step) pairs at which the challenge match fell back (None: no such policy, or
    # units checkpointed before it was kept)
    fallback = add("fallback") if all("fallback" in p["sums"] for p in parts) else None

    def band(key):  # sd over runs / sqrt(N) of each step's per-run values (None: no squares kept)
        if key not in parts[0]["sums"] or any(key not in p.get("sq_sums", {}) for p in parts):
            return None
        return mean_se_per_step(add_runs([p["sums"][key] for p in parts]),
                                add_runs([p["sq_sums"][key] for p in parts]), est_runs).tolist()

    return {
        "pos": (pos.sum(1) / est_runs).sqrt().tolist(), "vel": (vel.sum(1) / est_runs).sqrt().tolist(),
        "count": count.tolist(), "ess": ess.tolist() if ess is not None else None,
        "members": members.tolist() if members is not None else None,
        "fallback": fallback.mean().item() if fallback is not None else None,
        "seconds_per_step": sum(p["seconds"] for p in parts) * (runs / est_runs), "runs": est_runs,
        "hists": parts[0]["hists"],
        "pos_se": armse_se(e_pos), "vel_se": armse_se(e_vel),
        "maneuver_pos_se": armse_se(e_pos[window]) if window is not None else None,
        "count_se": (run_counts.std() / est_runs**0.5).item() if est_runs > 1 else float("nan"),
        "pos_band": rmse_se_per_step(e_pos).tolist(), "vel_band": rmse_se_per_step(e_vel).tolist(),
        "count_band": band("count"), "ess_band": band("ess"),
    }


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    opts = cfg.mevsmm

    # run-indexed streams: the data in blocks of block_runs runs, each block from its own generator
    runs = int(cfg.mc_runs)
    scenario, _, _ = _data(ctx, *ctx.run_ranges(runs)[0])  # (the parent needs only the scenario)
    deterministic = scenario.random is None
    ctx.results.description = (
        f"Paper 003, scenario `{scenario.name}` (R = {scenario.R:g}^2 I, {scenario.steps} steps, D reading "
        f"`{scenario.d_reading}`), {runs} Monte Carlo runs (seed {cfg.seed}, {cfg.dtype}); "
        f"{opts.num_particles} particles per model, N = {opts.num_winners}, Thre = {opts.threshold}, "
        f"filter acceleration noise std {opts.accel_std} m/s^2, EqMA p_ii = {opts.stay_prob}, "
        f"MEVSMM p_ii = {opts.get('mevsmm_stay_prob') or 'uniform 1/21'}, "
        f"feedback = {opts.feedback}, interaction `{opts.mixing}`, process-noise normals in "
        f"{opts.get('noise_dtype') or cfg.dtype}. Timings on {ctx.device} (shared machine: contended)."
    )
    rmse = ctx.results.table(
        "rmse", ["estimator", "pos_rmse", "vel_rmse", "maneuver_pos_rmse", "pos_rmse_se", "vel_rmse_se",
                 "maneuver_pos_rmse_se"],
        note="maneuver_pos_rmse: time average over 81-120 s (deterministic scenarios). _se: delta-method "
             "standard errors of the average RMSEs over the runs (95 % interval: +- 1.96 se).")
    late = sorted(int(k) for k in opts.histogram_steps if int(k) > scenario.steps)
    if late:  # (a shortened run keeps the default steps: named, not refused and not lost silently)
        ctx.results.notes.append(f"mevsmm.histogram_steps {late}: past the scenario's last step "
                                 f"({scenario.steps}): no weight histogram there")
    if deterministic and scenario.steps < 120:  # the 81-120 s window needs all 120 steps (no partial average)
        covered = (f"covers only 81-{scenario.steps} s of the 81-120 s maneuver window (not averaged over "
                   "a part)" if scenario.steps > 80 else "ends before the 81-120 s maneuver window")
        for key in ("maneuver_pos_rmse", "maneuver_pos_rmse_se"):
            ctx.results.dropped[key] = f"the scenario's {scenario.steps} steps: the run {covered}"
    pub1 = PUBLISHED_TABLE1.get(scenario.name)
    published_counts = {} if pub1 is None else {"EqMA9+1": 10, "EqMA21+1": 22, "PF-MEVSMM": pub1}
    table1 = ctx.results.table(
        "table1", ["estimator", "avg_model_count", "avg_model_count_se", "published_inside_95"],
        note="EqMA counts include the +1 equivalent model, as the paper does. avg_model_count_se: standard "
             "error over the runs (sd of a run's time-averaged count / sqrt(runs)); published_inside_95: "
             "whether the published count lies inside our +- 1.96 se (null without a published figure).",
        published=None if pub1 is None else {
            "columns": ["estimator", "avg_model_count"],
            "rows": [[k, v] for k, v in published_counts.items()],
            "source": f"paper 003 Table 1 ({'small' if scenario.R < 100 else 'large'} error)"},
    )
    table2 = ctx.results.table(
        "table2", ["estimator", "seconds_per_step", "relative_time"],
        note="Wall time per step for all runs at once, relative to EqMA9+1 (published for scenario 2).",
        published={"columns": ["estimator", "relative_time"], "rows": PUBLISHED_TABLE2,
                   "source": "paper 003 Table 2"},
    )
    curves, count_curves, memberships, base_time, bands, fallbacks = {}, {}, {}, None, {}, {}
    count_bands = {}  # per-step standard errors of the mean model counts
    names = list(opts.estimators) if opts.get("estimator_names") is None else [str(n) for n in opts.estimator_names]
    nodes = {name: _node(opts, name) for name in names}
    # every estimator is a unit, all at once: an executor (executor=processes|slurm|ray) runs them side by side
    # (and each range of runs, unit_runs=...; an estimator's ranges are merged in run order); a node's
    # `runs` caps its runs (the exact selection: mevsmm.exact_runs), `timing_base` marks table2's base
    items = [(name, bool(node.get("timing_base")), runs if node.get("runs") is None else min(runs, int(node["runs"])))
             for name, node in nodes.items()]
    ranges = {name: ctx.run_ranges(n) for name, _, n in items}
    parts = ctx.map_units([Unit(f"{scenario.name}/{name}/runs{a}-{b}", UNIT, {"name": name, "start": a, "stop": b})
                           for name, _, _ in items for a, b in ranges[name]], desc="estimators")
    window = slice(80, 120) if deterministic and scenario.steps >= 120 else None
    values, i = [], 0
    for name, _, _ in items:
        values.append(_merge(parts[i:i + len(ranges[name])], runs, window))
        i += len(ranges[name])
    for (name, timing_base, est_runs), res in zip(items, values):
        # checkpointed lists of floats: keep float64 (torch.tensor would default to float32)
        pos, vel = torch.tensor(res["pos"], dtype=torch.float64), torch.tensor(res["vel"], dtype=torch.float64)
        maneuver = pos[80:120].mean().item() if deterministic and scenario.steps >= 120 else None
        label = name if res["runs"] == runs else f"{name} ({res['runs']} runs)"
        rmse.rows.append([label, pos.mean().item(), vel.mean().item(), maneuver, res.get("pos_se"),
                          res.get("vel_se"), res.get("maneuver_pos_se")])
        avg_count = float(torch.tensor(res["count"], dtype=torch.float64).mean())
        table1.rows.append([label, avg_count, res.get("count_se"),
                            inside(published_counts.get(label), avg_count, res.get("count_se"))])
        if base_time is None and timing_base:
            base_time = res["seconds_per_step"]
        table2.rows.append([label, res["seconds_per_step"], None])
        ctx.results.timing[name] = res["seconds_per_step"]
        for key, value in (("pos_rmse", pos.mean().item()), ("vel_rmse", vel.mean().item()),
                           ("avg_model_count", avg_count)):
            ctx.results.metric(name, key, value)
        curves[label] = pos
        if "pos_band" in res:
            bands[label] = torch.tensor(res["pos_band"], dtype=torch.float64)
        count_curves[label] = torch.tensor(res["count"], dtype=torch.float64)
        if res["members"] is not None:
            memberships[label] = torch.tensor(res["members"])
        if res.get("fallback") is not None:
            fallbacks[label] = res["fallback"]
        ctx.logger.series(f"pos_rmse/{name}", pos)
        ctx.logger.series(f"vel_rmse/{name}", vel)
        if "pos_band" in res:  # per-step standard errors of the RMSE curves
            ctx.logger.series(f"pos_rmse_se/{name}", res["pos_band"])
            ctx.logger.series(f"vel_rmse_se/{name}", res["vel_band"])
        ctx.logger.series(f"model_count/{name}", res["count"])
        if res.get("count_band") is not None:  # 0 where the count is fixed (EqMA)
            ctx.logger.series(f"model_count_se/{name}", res["count_band"])
            count_bands[label] = torch.tensor(res["count_band"], dtype=torch.float64)
        if res["ess"] is not None:
            ctx.logger.series(f"ess/{name}", res["ess"])
            if res.get("ess_band") is not None:
                ctx.logger.series(f"ess_se/{name}", res["ess_band"])
        for step, values in res["hists"].items():
            ctx.logger.histogram(f"log_weights/{name}", torch.tensor(values), int(step))
        log.info("%s: pos %.2f vel %.2f count %.2f %.3f s/step", name, pos.mean(), vel.mean(), avg_count,
                 res["seconds_per_step"])
        ctx.results.save()
    if base_time:
        for row in table2.rows:
            row[2] = row[1] / base_time
    else:
        bases = ", ".join(str(name) for name, node in opts.estimators.items() if node.get("timing_base"))
        ctx.results.dropped["relative_time"] = (f"the timing base ({bases}: timing_base true) did not run"
                                                if bases else "no estimator node has timing_base true")
    for label, frac in fallbacks.items():
        ctx.results.notes.append(
            f"{label}: the challenge match fell back at {100 * frac:.2f} % of the (run, step) pairs (no "
            "model held Thre of the N winners: the set was the model with the most winners, in table1)")
    title = f"{scenario.name}, {runs} runs"
    ctx.save_figure("position_rmse", plots.rmse_over_time({"position RMSE (m)": curves}, title,
                                                                    bands={"position RMSE (m)": bands}))
    ctx.save_figure("model_count", plots.rmse_over_time({"selected model count": count_curves}, title,
                                                                 bands={"selected model count": count_bands}))
    if memberships:
        ctx.save_figure("model_set_membership", _membership_figure(memberships, title))
    if not deterministic:
        ctx.results.notes.append("random scenario: maneuver_pos_rmse is not defined (no fixed maneuver window)")
    ctx.results.notes.append(
        "EqMA (docs/baselines.md §2.2) is a reconstruction; the filter process noise, initial particle spread and "
        "transition matrix are not given by the paper (see docs/reproduction-003.md)."
    )


def _membership_figure(memberships: dict[str, Tensor], title: str):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(memberships), figsize=(5.2 * len(memberships), 3.8), squeeze=False)
    for ax, (name, frac) in zip(axes[0], memberships.items()):
        im = ax.imshow(frac.T.numpy(), aspect="auto", origin="lower", cmap="viridis", vmin=0, vmax=1,
                       extent=[0.5, frac.shape[0] + 0.5, 0.5, frac.shape[1] + 0.5], interpolation="nearest")
        ax.set_xlabel("time step k")
        ax.set_ylabel("model m_j")
        models = frac.shape[1]  # integer model indices (1-based, as the paper's m_1 .. m_21), no blurring
        ax.set_yticks(range(1, models + 1, max(1, models // 7)))
        ax.set_title(name, fontsize=9)
    fig.colorbar(im, ax=axes[0].tolist(), label="fraction of runs with m_j selected")
    fig.suptitle(title)
    return fig


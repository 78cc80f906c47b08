"""Study ``learn_dynamics`` (docs/specification.md §4): learning an IMM's parameters and a mode's dynamics.

Scenario: a 2-D target ``[x, vx, y, vy]`` whose motion switches (Markov chain, ``stay`` on the
diagonal of the transition matrix) between constant velocity and coordinated turns at
``+turn_rate`` and ``-turn_rate`` rad/s, white-acceleration noise ``Q = q G G^T`` and position
measurements with noise ``R I``. ``mc_runs`` runs are simulated for training and ``test_runs``
(default ``mc_runs``) independent runs are held out for the RMSE comparison.

(a) The transition matrix (row-wise softmax logits) and the shared noise level ``q`` (a log-scale
    on ``G G^T``) of a 3-mode CV/CT/CT IMM are learned by maximising the IMM's marginal
    log-likelihood of the training measurements, starting from a uniform matrix and
    ``q_initial = initial_q_factor * q``.
(b) One analytic mode (``replaced_mode``, by default the left turn) is replaced by a small MLP
    motion model ``x_k = F_CV x_{k-1} + G a_theta(v_{k-1})`` (an EKF mode: Jacobians from autograd),
    its last layer initialised at zero (so it starts as a second CV mode), and trained through the
    IMM with the other modes, the transition matrix and ``q`` fixed at their true values.

Tables: ``learn`` (quantity, true, learned, initial, abs_error) and ``rmse`` (estimator,
pos_rmse, vel_rmse, part) on the held-out runs. Figures: loss curves, parameter trajectories,
RMSE before/after and RMSE over time. TensorBoard: ``learn_a/*`` and ``learn_b/*`` training
scalars (loss, gradient norm, parameters) and per-step RMSE.
"""

from __future__ import annotations

import logging
import math
import time

import torch
from torch import nn

from experiments.estimators import Estimator, evaluate, starter
from experiments.executors import Unit
from experiments.harness import StudyContext, per_run
from experiments.uncertainty import nees_consistency
from experiments.scenarios import JumpScenario, stay_matrix, turning_2d
from experiments.studies.learn_dynamics_figures import figures
from torchmm import (
    IMM,
    ConstantVelocity,
    CoordinatedTurn,
    ExtendedKalmanFilter,
    KalmanFilter,
    ModeTransition,
)
from torchmm.learn import Trainer, negative_log_likelihood
from torchmm.models import LearnedMotion, learnable_noise

log = logging.getLogger("torchmm.experiments")

ESTIMATORS = ("true-model IMM", "learned IMM", "initial IMM")


# -- scenario --------------------------------------------------------------------------------------
def turning_scenario(cfg, dtype, device) -> JumpScenario:
    """The CV / CT(+w) / CT(-w) Markov-jump scenario of the study (``cfg = learn.scenario``;
    :func:`experiments.scenarios.turning_2d`)."""
    try:
        return turning_2d(turn_rate=cfg.turn_rate, q=cfg.q, R=cfg.R, stay=cfg.stay, steps=cfg.steps, dt=cfg.dt,
                          initial_mean=cfg.initial_mean, initial_std=cfg.initial_std, dtype=dtype, device=device)
    except ValueError as err:
        raise ValueError(str(err).replace("scenario turning_2d: ", "learn.scenario.")) from None


def _imm(scenario: JumpScenario, transition, q: float) -> IMM:
    """A plain (non-learnable) IMM over the CV/CT bank with noise level ``q``."""
    cfg_motion = scenario.motion
    motion = CoordinatedTurn(cfg_motion.omega, dt=cfg_motion.dt, q=q, dtype=scenario.transition.dtype)
    like = scenario.transition
    return IMM(KalmanFilter(motion.to(like.device), scenario.measurement),
               torch.as_tensor(transition, dtype=like.dtype, device=like.device))


def _estimator(name: str, imm: IMM) -> Estimator:
    return Estimator(name, imm, starter(imm), True)


def _optimizer(params, ocfg):
    kind = str(ocfg.optimizer)
    if kind == "lbfgs":
        # one L-BFGS iteration (with a strong-Wolfe line search) per trainer iteration; its
        # curvature history carries over between iterations. max_eval must be given: torch's
        # default (max_iter * 5 // 4 = 1) leaves the line search no evaluations at all
        return torch.optim.LBFGS(params, lr=float(ocfg.lr), max_iter=1,
                                 max_eval=int(ocfg.max_line_search) + 1, history_size=20,
                                 line_search_fn="strong_wolfe")
    if kind == "adam":
        return torch.optim.Adam(params, lr=float(ocfg.lr))
    raise ValueError(f"optimizer: expected 'lbfgs' or 'adam', got {kind!r}")


class RestartStalledLBFGS:
    """Trainer callback: clear L-BFGS's memory when an iteration left the parameters unchanged,
    and stop training when it happens twice in a row (no step improves the loss: converged).

    When torch's strong-Wolfe line search fails it returns a zero step; with no new curvature
    pair L-BFGS then proposes the same direction again and never moves. Restarting from steepest
    descent is the standard remedy (a safety net: with a line-search budget it rarely triggers).
    """

    def __init__(self, params):
        self.params = list(params)
        self.last = self._flat()
        self.restarts = 0
        self.in_a_row = 0

    def _flat(self) -> torch.Tensor:
        return torch.cat([p.detach().flatten() for p in self.params]).clone()

    def __call__(self, trainer, record) -> bool:
        """Restart on a stall; stop (return True) after two stalls in a row (converged)."""
        now = self._flat()
        stalled = isinstance(trainer.optimizer, torch.optim.LBFGS) and torch.equal(now, self.last)
        self.last = now
        if not stalled:
            self.in_a_row = 0
            return False
        self.in_a_row += 1
        if self.in_a_row >= 2:
            log.info("L-BFGS made no progress twice at iteration %d: converged, stopping", record.iteration)
            return True
        trainer.optimizer.state.clear()
        self.restarts += 1
        log.info("L-BFGS made no progress at iteration %d: memory cleared", record.iteration)
        return False


# -- part (b): the MLP motion model ----------------------------------------------------------------
class AccelerationMLP(nn.Module):
    r"""``f(x) = F_CV x + G a(v)`` with ``a(v) = a_scale * MLP(v / v_scale)`` (a small tanh MLP).

    The network sees only the velocity ``v = (vx, vy)`` (the dynamics do not depend on position)
    and outputs an acceleration over the step, entered through the white-acceleration gain ``G``;
    a coordinated turn at rate ``w`` is ``a ~ (R(wT) - I) v / T``. The last layer starts at zero,
    so the untrained model is constant velocity.

    Shapes:
        x ``(*B, 4)`` -> ``(*B, 4)``
    """

    def __init__(self, hidden: int, dt: float, v_scale: float, a_scale: float, *, generator=None,
                 dtype=None, device=None):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(2, hidden), nn.Tanh(), nn.Linear(hidden, 2))
        self.mlp.to(dtype=dtype, device=device)
        with torch.no_grad():
            bound = 1.0 / math.sqrt(2)
            self.mlp[0].weight.uniform_(-bound, bound, generator=generator)
            self.mlp[0].bias.uniform_(-bound, bound, generator=generator)
            self.mlp[2].weight.zero_()
            self.mlp[2].bias.zero_()
        cv = ConstantVelocity(2, dt=dt, dtype=dtype)
        self.register_buffer("F", cv.F.to(device))
        self.register_buffer("G", cv.noise_gain.to(device))
        self.v_scale, self.a_scale = float(v_scale), float(a_scale)

    def acceleration(self, v: torch.Tensor) -> torch.Tensor:
        return self.a_scale * self.mlp(v / self.v_scale)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x @ self.F.mT + self.acceleration(x[..., [1, 3]]) @ self.G.mT


def implied_turn_rate(net: AccelerationMLP, velocities: torch.Tensor, dt: float) -> float:
    """The turn rate whose coordinated turn best matches the network on ``velocities (K, 2)``.

    A turn at rate ``w`` changes the velocity by ``(R(wT) - I) v``, whose component along
    ``J v = (-vy, vx)`` is ``sin(wT) |v|^2``; the least-squares projection of the network's
    ``T a(v)`` on ``J v`` gives ``sin(wT)``.
    """
    with torch.no_grad():
        dv = dt * net.acceleration(velocities)
        jv = torch.stack([-velocities[:, 1], velocities[:, 0]], -1)
        s = (dv * jv).sum() / jv.square().sum()
    return math.asin(max(-1.0, min(1.0, s.item()))) / dt


def complete_data_estimates(scenario: JumpScenario, sim) -> tuple[torch.Tensor, float]:
    """Estimates from the *simulated* modes and states (what a filter cannot see).

    Transition frequencies ``n_ij / n_i`` of the mode sequences (including ``r_0 -> r_1``), and
    ``q`` as the mean squared velocity increment per axis: with ``Q = q G G^T`` the process noise
    is ``G a``, ``a ~ N(0, q I)``, and ``a`` is the velocity part of ``x_k - F_{r_k} x_{k-1}``.
    Their distance to the truth is the sampling error of 400 x 100 steps alone.

    Shapes:
        sim.states ``(T, N, 4)``, sim.modes ``(T, N)`` -> ``(3, 3)``, float
    """
    modes = torch.cat([sim.initial_mode.unsqueeze(0), sim.modes], 0)
    pairs = modes[:-1] * 3 + modes[1:]
    counts = torch.bincount(pairs.flatten(), minlength=9).reshape(3, 3).to(sim.states.dtype)
    tpm = counts / counts.sum(-1, keepdim=True).clamp_min(1)
    previous = torch.cat([sim.initial_state.unsqueeze(0), sim.states[:-1]], 0)
    F = scenario.motion.F[sim.modes]  # (T, N, 4, 4)
    noise = sim.states - (F @ previous.unsqueeze(-1)).squeeze(-1)
    q = noise[..., [1, 3]].square().mean().item()
    return tpm, q


# -- the study -------------------------------------------------------------------------------------
def run(ctx: StudyContext) -> None:
    threads = ctx.cfg.learn.get("num_threads")
    previous = torch.get_num_threads()
    if threads:
        # the filters' tensors are tiny: extra intra-op threads only add synchronisation, and on a
        # shared machine spinning threads slow a step down by an order of magnitude
        torch.set_num_threads(int(threads))
    try:
        _run(ctx)
    finally:
        torch.set_num_threads(previous)


def _inputs(ctx: StudyContext) -> dict:
    """The scenario (study dtype), the training runs' data and their prior, once per process."""
    def build():
        lcfg = ctx.cfg.learn
        scenario = turning_scenario(lcfg.scenario, ctx.dtype, ctx.device)
        data_scenario = scenario if ctx.dtype == ctx.data_dtype else turning_scenario(lcfg.scenario, ctx.data_dtype,
                                                                                       ctx.device)
        runs = int(ctx.cfg.mc_runs)
        # float64 draws, cast to the study dtype: float32 and float64 runs see the same data
        sim, z = ctx.simulate_runs(data_scenario.simulate, runs, "train", scenario.name)  # run-indexed streams
        return {"scenario": scenario, "data_scenario": data_scenario, "sim": sim.to(ctx.dtype), "z": z.to(ctx.dtype),
                "prior": scenario.initial.expand(runs)}

    return ctx.memo("inputs", build)


def _initial_tpm(ctx: StudyContext) -> torch.Tensor:
    init_stay = ctx.cfg.learn.part_a.get("initial_stay")
    if init_stay is None:
        return torch.full((3, 3), 1.0 / 3, dtype=ctx.dtype, device=ctx.device)
    return stay_matrix(float(init_stay), 3, dtype=ctx.dtype, device=ctx.device)


def _history(trainer) -> list[dict]:
    return [{"iteration": r.iteration, "loss": r.loss, "grad_norm": r.grad_norm, **r.parameters}
            for r in trainer.history]


def train_a(ctx: StudyContext) -> dict:
    """Part (a): the transition matrix and ``q`` by maximum likelihood through the IMM."""
    acfg, inputs = ctx.cfg.learn.part_a, _inputs(ctx)
    scenario = inputs["scenario"]
    init_tpm, q_init = _initial_tpm(ctx), float(acfg.initial_q_factor) * float(ctx.cfg.learn.scenario.q)
    bank = CoordinatedTurn(scenario.motion.omega, dt=scenario.motion.dt, q=q_init, dtype=ctx.dtype)
    learnable_noise(bank.to(ctx.device), "Q", "scale")
    imm = IMM(KalmanFilter(bank, scenario.measurement), ModeTransition(init_tpm, learnable=True))
    theta = bank.parametrizations.Q.original

    def track() -> dict:
        tpm = imm.transition.matrix().detach()
        values = {f"tpm[{i},{j}]": tpm[i, j].item() for i in range(3) for j in range(3)}
        values["q"] = q_init * theta.detach().exp().item()
        return values

    restart = RestartStalledLBFGS(imm.parameters())
    bar, tick = _training_bar(ctx, int(acfg.iterations), "training (a)")
    trainer = Trainer(imm, _optimizer(imm.parameters(), acfg), window=acfg.get("window"),
                      track=track, logger=ctx.logger, prefix="learn_a", callbacks=[restart, tick])
    tic = time.perf_counter()
    trainer.fit(inputs["prior"], inputs["z"], int(acfg.iterations), batch_size=acfg.get("batch_size"),
                generator=ctx.generator("minibatch", "a"))
    bar.close()
    return {"seconds": time.perf_counter() - tic, "final": track(), "restarts": restart.restarts,
            "history": _history(trainer)}


def _velocities(sim) -> torch.Tensor:
    """Training velocities (at most about 4000) at which the MLP's implied turn rate is measured."""
    return sim.states[..., [1, 3]].reshape(-1, 2)[:: max(1, sim.states[..., 0].numel() // 4000)]


def build_b(ctx: StudyContext):
    """Part (b)'s ``(net, IMM)``: mode ``replaced_mode`` an MLP motion (EKF mode), freshly initialised."""
    bcfg, scenario = ctx.cfg.learn.part_b, _inputs(ctx)["scenario"]
    replaced = int(bcfg.replaced_mode)
    if not 0 <= replaced < 3:
        raise ValueError(f"learn.part_b.replaced_mode: expected 0, 1 or 2, got {replaced}")
    net = AccelerationMLP(int(bcfg.hidden), scenario.motion.dt, float(bcfg.v_scale),
                          float(bcfg.a_scale), generator=ctx.generator("mlp_init"),
                          dtype=ctx.dtype, device=ctx.device)
    learned = LearnedMotion(net, 4, Q=scenario.motion.Q, noise="fixed")
    filters = [KalmanFilter(scenario.motion.select_mode(j), scenario.measurement) for j in range(3)]
    filters[replaced] = ExtendedKalmanFilter(learned, scenario.measurement)
    return net, IMM(filters, scenario.transition)


def train_b(ctx: StudyContext) -> dict:
    """Part (b): the MLP mode trained through the IMM; its trained parameters come back as arrays."""
    bcfg, inputs = ctx.cfg.learn.part_b, _inputs(ctx)
    scenario, velocities = inputs["scenario"], _velocities(inputs["sim"])
    net, imm = build_b(ctx)

    def track() -> dict:
        return {"mlp_turn_rate": implied_turn_rate(net, velocities, scenario.motion.dt)}

    restart = RestartStalledLBFGS(net.parameters())
    bar, tick = _training_bar(ctx, int(bcfg.iterations), "training (b)")
    trainer = Trainer(imm, _optimizer(net.parameters(), bcfg), window=bcfg.get("window"), track=track,
                      logger=ctx.logger, prefix="learn_b",
                      checkpoint_path=ctx.output_dir / "checkpoints" / "mlp_mode.pt", callbacks=[restart, tick])
    tic = time.perf_counter()
    trainer.fit(inputs["prior"], inputs["z"], int(bcfg.iterations), batch_size=bcfg.get("batch_size"),
                generator=ctx.generator("minibatch", "b"))
    bar.close()
    return {"seconds": time.perf_counter() - tic, "restarts": restart.restarts, "history": _history(trainer),
            "state": {k: per_run(v) for k, v in net.state_dict().items()}}  # exact (units/*.npz)


#: the study's unit function (what an executor ships): one training part
UNIT = "experiments.studies.learn_dynamics:unit"


def unit(ctx: StudyContext, *, part: str) -> dict:
    """Training part ``"a"`` or ``"b"``; the two are independent and run side by side on an executor."""
    return {"a": train_a, "b": train_b}[part](ctx)


def _run(ctx: StudyContext) -> None:
    cfg, lcfg = ctx.cfg, ctx.cfg.learn
    inputs = _inputs(ctx)
    scenario, sim, z, prior = inputs["scenario"], inputs["sim"], inputs["z"], inputs["prior"]
    runs = int(cfg.mc_runs)
    test_runs = int(lcfg.test_runs) if lcfg.get("test_runs") else runs
    # float64 draws, cast to the study dtype: float32 and float64 runs see the same data
    test_sim, test_z = ctx.simulate_runs(inputs["data_scenario"].simulate, test_runs, "test", scenario.name)
    test_sim, test_z = test_sim.to(ctx.dtype), test_z.to(ctx.dtype)
    q_true = float(lcfg.scenario.q)
    true_tpm = scenario.transition
    ctx.results.description = (
        f"Scenario `{scenario.name}`: CV / CT(+-{lcfg.scenario.turn_rate} rad/s), q = {q_true}, "
        f"R = {lcfg.scenario.R} I, stay = {lcfg.scenario.stay}, {scenario.steps} steps; "
        f"{runs} training runs, {test_runs} held-out runs (seed {cfg.seed}, {cfg.dtype}). "
        "Parameters are learned by maximising the IMM's marginal log-likelihood of the training "
        "measurements; RMSEs are time-averaged per-step RMSEs on the held-out runs."
    )

    rmse_table = ctx.results.table("rmse", ["estimator", "pos_rmse", "vel_rmse", "part", "pos_rmse_se", "vel_rmse_se"],
                                   note="Held-out runs. part a: transition matrix + q learned; "
                                        "part b: one CT mode replaced by an MLP trained through the IMM.")
    curves: dict[str, dict[str, torch.Tensor]] = {"position RMSE": {}, "velocity RMSE": {}}
    bands: dict[str, dict[str, torch.Tensor]] = {"position RMSE": {}, "velocity RMSE": {}}  # per-step se
    scores: dict[str, tuple[float, float]] = {}

    def score(label: str, estimator: Estimator, part: str) -> tuple[float, float]:
        with torch.no_grad():
            ev = evaluate(estimator, scenario, test_sim, test_z, chunk_runs=cfg.get("chunk_runs"))
        summary = ev.summary()
        summary["nees_low"], summary["nees_high"], summary["nees_steps_inside"] = nees_consistency(
            ev.nees, ev.runs, ev.state_dim)  # the 95 % chi-square interval of a step's run-averaged NEES
        rmse_table.rows.append([estimator.name, summary["pos_rmse"], summary["vel_rmse"], part,
                                summary.get("pos_rmse_se"), summary.get("vel_rmse_se")])
        for key, value in summary.items():
            ctx.results.metric(label, key, value)
        ctx.results.timing[label] = ev.seconds_per_step
        curves["position RMSE"][label] = ev.pos_rmse
        curves["velocity RMSE"][label] = ev.vel_rmse
        bands["position RMSE"][label] = ev.pos_rmse_band
        bands["velocity RMSE"][label] = ev.vel_rmse_band
        ctx.logger.series(f"pos_rmse/{label}", ev.pos_rmse)
        ctx.logger.series(f"vel_rmse/{label}", ev.vel_rmse)
        ctx.logger.series(f"pos_rmse_se/{label}", ev.pos_rmse_band)
        ctx.logger.series(f"vel_rmse_se/{label}", ev.vel_rmse_band)
        steps = len(ev.nees)  # the run-averaged NEES and its 95 % chi-square band (torchmm-plot shades it)
        ctx.logger.series(f"nees/{label}", ev.nees)
        ctx.logger.series(f"nees_low/{label}", [summary["nees_low"]] * steps)
        ctx.logger.series(f"nees_high/{label}", [summary["nees_high"]] * steps)
        if ev.mode_accuracy is not None:  # with its standard error over the runs, sd / sqrt(N)
            ctx.logger.series(f"mode_accuracy/{label}", ev.mode_accuracy)
            ctx.logger.series(f"mode_accuracy_se/{label}", ev.mode_accuracy_se)
        scores[label] = (summary["pos_rmse"], summary["vel_rmse"])
        ctx.results.save()
        return scores[label]

    score("true-model IMM", _estimator("true-model IMM", _imm(scenario, true_tpm, q_true)), "a, b")

    columns = ["quantity", "true", "learned", "initial", "abs_error", "counted"]
    learn_table = ctx.results.table("learn", columns,
                                    note="Maximum-likelihood estimates through the IMM (part a); "
                                         "mlp_turn_rate: the turn rate implied by the trained MLP mode "
                                         "(part b). counted: the complete-data estimate from the simulated "
                                         "modes and states of the training runs (transition frequencies; "
                                         "mean squared velocity increment), i.e. the sampling error alone.")
    counted_tpm, counted_q = complete_data_estimates(scenario, sim)
    histories: dict[str, list[dict]] = {}

    # ---- the training parts: two independent units, side by side on an executor ----------------
    acfg, bcfg = lcfg.part_a, lcfg.part_b
    if bcfg.enabled and not 0 <= int(bcfg.replaced_mode) < 3:
        raise ValueError(f"learn.part_b.replaced_mode: expected 0, 1 or 2, got {int(bcfg.replaced_mode)}")
    parts = [part for part, node in (("a", acfg), ("b", bcfg)) if node.enabled]
    trained = dict(zip(parts, ctx.map_units([Unit(f"train/{part}", UNIT, {"part": part}) for part in parts],
                                            desc="training parts")))

    # ---- part (a): transition matrix and q --------------------------------------------------
    if acfg.enabled:
        init_tpm = _initial_tpm(ctx)
        q_init = float(acfg.initial_q_factor) * q_true
        result_a = trained["a"]
        histories["a"] = result_a["history"]
        _log_history(ctx, "part_a", result_a["history"])
        final = result_a["final"]
        learned_tpm = torch.tensor([[final[f"tpm[{i},{j}]"] for j in range(3)] for i in range(3)],
                                   dtype=ctx.dtype, device=ctx.device)
        learned_tpm = learned_tpm / learned_tpm.sum(-1, keepdim=True)  # JSON rounding
        for i in range(3):
            for j in range(3):
                t, got, start = true_tpm[i, j].item(), learned_tpm[i, j].item(), init_tpm[i, j].item()
                learn_table.rows.append([f"tpm[{i},{j}]", t, got, start, abs(got - t),
                                         counted_tpm[i, j].item()])
        learn_table.rows.append(["q", q_true, final["q"], q_init, abs(final["q"] - q_true), counted_q])
        # the training objective at the truth and at the learned point: the learned point must score
        # better (it is the maximiser of the IMM's approximate likelihood, not of the exact one)
        with torch.no_grad():
            for tag, tpm, q in (("nll_true", true_tpm, q_true), ("nll_learned", learned_tpm, final["q"]),
                                ("nll_initial", init_tpm, q_init)):
                value = negative_log_likelihood(_imm(scenario, tpm, q), prior, z).item()
                ctx.results.metric("training (a)", tag, value)
        ctx.results.metric("training (a)", "seconds", result_a["seconds"])
        ctx.results.metric("training (a)", "iterations", len(result_a["history"]))
        learned_imm = _imm(scenario, learned_tpm, final["q"])
        pos_learned, _ = score("learned IMM (a)", _estimator("learned IMM", learned_imm), "a")
        score("initial IMM (a)", _estimator("initial IMM", _imm(scenario, init_tpm, q_init)), "a")
        max_err = (learned_tpm - true_tpm).abs().max().item()
        ratio = pos_learned / scores["true-model IMM"][0]
        ctx.results.notes.append(
            f"part a: max |learned - true| over the transition matrix = {max_err:.4f} (target < 0.05: "
            f"{'met' if max_err < 0.05 else 'NOT met'}); learned/true-model position RMSE = {ratio:.4f} "
            f"(target within 5 %: {'met' if abs(ratio - 1) <= 0.05 else 'NOT met'}); learned q = "
            f"{final['q']:.4g} (true {q_true:g}); training {result_a['seconds']:.1f} s."
        )

    # ---- part (b): an MLP mode trained through the IMM -----------------------------------------
    if bcfg.enabled:
        replaced = int(bcfg.replaced_mode)
        velocities = _velocities(sim)
        true_rate = scenario.motion.omega[replaced].item()
        net0, imm0 = build_b(ctx)
        initial_rate = implied_turn_rate(net0, velocities, scenario.motion.dt)
        result_b = trained["b"]
        histories["b"] = result_b["history"]
        _log_history(ctx, "part_b", result_b["history"])
        net, imm = build_b(ctx)
        net.load_state_dict({k: torch.as_tensor(v, device=ctx.device) for k, v in result_b["state"].items()})
        rate = implied_turn_rate(net, velocities, scenario.motion.dt)
        learn_table.rows.append(["mlp_turn_rate", true_rate, rate, initial_rate, abs(rate - true_rate), None])
        ctx.results.metric("training (b)", "seconds", result_b["seconds"])
        ctx.results.metric("training (b)", "iterations", len(result_b["history"]))
        pos_b, _ = score("learned IMM (b)", _estimator("learned IMM", imm), "b")
        pos_b0, _ = score("initial IMM (b)", _estimator("initial IMM", imm0), "b")
        ctx.results.notes.append(
            f"part b: mode {scenario.mode_labels[replaced]} replaced by an MLP; held-out position RMSE "
            f"initial {pos_b0:.4f} -> trained {pos_b:.4f} "
            f"(true-model IMM {scores['true-model IMM'][0]:.4f}); "
            f"implied turn rate {rate:.4f} (true {true_rate:g}); training {result_b['seconds']:.1f} s."
        )

    ctx.results.save()
    figures(ctx, histories, scores, curves, true_tpm, q_true, scenario, bands=bands)


def _training_bar(ctx, iterations: int, desc: str):
    """A progress bar over training iterations and the Trainer callback that advances it."""
    bar = ctx.progress_bar(total=iterations, desc=desc, unit="it")

    def tick(trainer, record) -> bool:
        bar.update(1)
        bar.set_postfix(loss=f"{record.loss:.4g}", refresh=False)
        return False

    return bar, tick


def _log_history(ctx, part: str, history: list[dict]) -> None:
    """The training curves as data (curves.npz, over the iteration): loss, gradient norm and every
    tracked parameter - also for a resumed (checkpointed) part, whose training did not run now."""
    if not history:
        return
    iterations = [h["iteration"] for h in history]
    for key in history[0]:
        if key == "iteration":
            continue
        values = [h.get(key) for h in history]
        if all(isinstance(v, (int, float)) for v in values):
            quantity = {"loss": "training_loss", "grad_norm": "training_grad_norm"}.get(key)
            tag = f"{quantity}/{part}" if quantity else f"training_param/{part}/{key}"
            ctx.logger.sweep(tag, iterations, values, "iteration")

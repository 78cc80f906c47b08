"""Estimator builders (``conf/estimator/*.yaml``) and the Monte Carlo evaluation loop of studies.

A builder takes the scenario and returns an :class:`Estimator`: a torchmm filter plus how to start
it from the scenario's prior. Builders are instantiated by Hydra with ``_partial_: true`` so that
config values (options) and study values (scenario, transition) combine.

Every builder composes library parts from config groups (docs/architecture.md, docs/studies.md):
the combinator is a ``combinator`` config node built into a torchmm class (:func:`multiple_model`;
``conf/estimator``: imm, gpb1, gpb2, static, vsmm; ``kalman`` for one filter), the mode filter comes
from the ``mode_filter`` group (``conf/mode_filter``: ``kalman`` | ``extended`` |
``unscented`` | ``particle``, a partial of a torchmm filter class called with the scenario's motion
and sensor models), the model-set policy of ``vsmm`` from the ``policy`` group (``conf/policy``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.utils._pytree as pytree
from torch import Tensor

from torchmm import GPB1, GPB2, IMM, Filter, GaussianBelief, KalmanFilter, MultipleModelFilter, run_filter
from torchmm.metrics import mode_hits, nees, squared_error
from torchmm.run import Trajectory
from torchmm.smooth_checks import singular_process_noise, why_not_smoothable
from torchmm.two_filter_info import linear_bank

from experiments.arrays import add_runs, join_runs, per_run
from experiments.uncertainty import armse_se, mean_se_per_step, rmse_se_per_step

__all__ = ["Estimator", "Evaluation", "build_mode_filter", "custom", "evaluate", "evaluate_runs", "gpb1", "gpb2", "imm",
           "join_trajectories", "kalman", "mode_model", "multiple_model", "random_blocks", "reduce_runs",
           "starter"]


@dataclass
class Estimator:
    name: str
    filter: Filter
    #: ``(prior, generator) -> start belief`` (the generator: for filters that draw random numbers)
    init: Callable[..., Any]
    multiple_model: bool
    #: picks this estimator's input from the study's measurements (e.g. the target stream of a
    #: multi-rate pytree); None = all of it
    select: Callable[[Any], Any] | None = None
    #: the generic study (``compare``) also scores the smoothed trajectory (``torchmm.smooth``); a
    #: string is the multiple-model smoother's ``method`` (``kim``, ``two_filter``, ``two_filter_info``)
    smooth: bool | str = False
    #: a single-mode estimator's mode of the scenario (its per-step models of irregular time stamps)
    mode: int | None = None

    def __post_init__(self):
        """A smoother's ``method`` is checked when the estimator is built (the precheck's dry build), not
        after the study's folder exists: a method names a multiple-model smoother, and
        ``two_filter_info`` takes IMM, GPB1 and GPB2 over Kalman mode filters only; any ``smooth`` needs a
        filter ``torchmm.smooth`` has a backward pass for (``why_not_smoothable``: not an IMM over particle
        modes, nor a variable-structure IMM), and FFBSm a positive-definite process noise."""
        if self.smooth in (False, None, ""):
            return
        why = why_not_smoothable(self.filter)
        if why is not None:
            raise ValueError(f"smooth: {why} (smooth: false scores the filter alone)")
        if getattr(self.filter, "smoother", None) == "particles" and singular_process_noise(self.filter.motion):
            raise ValueError("smooth: FFBSm (the particle filter's smoother) needs a positive-definite process "
                             f"noise Q; {type(self.filter.motion).__name__}'s is singular")
        if not isinstance(self.smooth, str):
            return
        if not self.multiple_model:
            raise ValueError(f"smooth: {self.smooth} picks a multiple-model smoother; {type(self.filter).__name__} "
                             "is one filter (smooth: true smooths it)")
        if self.smooth == "two_filter_info":
            try:
                linear_bank(self.filter, None, None, None)
            except ValueError as err:
                why = str(err).split(": ", 2)[-1].split(". Use method=")[0]
                raise ValueError(f"smooth: two_filter_info needs IMM, GPB1 or GPB2 over Kalman mode filters, not "
                                 f"{why} (smooth: two_filter or kim smooth this one)") from None

    def run(self, prior: GaussianBelief, z: Any, generator: torch.Generator | None = None) -> Trajectory:
        """Filter every run of ``z``; ``generator`` is the random stream of particle mode filters."""
        z = z if self.select is None else self.select(z)
        if not self.filter.uses_generator:
            generator = None
        return run_filter(self.filter, self.init(prior, generator), z, generator=generator)


def starter(filt: Filter, mode_probs=None) -> Callable[..., Any]:
    """``(prior, generator) -> filt.initial_belief(prior, [mode_probs,] generator=...)``."""
    def init(prior, generator=None):
        options = {"generator": generator} if generator is not None else {}
        if mode_probs is not None:
            return filt.initial_belief(prior, mode_probs, **options)
        return filt.initial_belief(prior, **options)
    return init


def build_mode_filter(factory, motion, measurement, *, joseph: bool = False) -> Filter:
    """The mode filter a ``mode_filter`` config builds (``conf/mode_filter``) for ``motion`` and
    ``measurement`` (a mode bank for multiple-model estimators); None: a Kalman filter."""
    if isinstance(measurement, (list, tuple)):  # one sensor per mode (mode-dependent measurements)
        motions = motion if isinstance(motion, (list, tuple)) else [motion.select_mode(j) for j in range(len(measurement))]
        return [build_mode_filter(factory, m, s, joseph=joseph) for m, s in zip(motions, measurement)]
    if isinstance(motion, (list, tuple)):  # one model per mode (a heterogeneous bank: IMM takes the list)
        return [build_mode_filter(factory, m, measurement, joseph=joseph) for m in motion]
    if factory is None:
        return KalmanFilter(motion, measurement, joseph=joseph)
    return factory(motion, measurement, **({"joseph": True} if joseph else {}))


def _transition(scenario, transition) -> Tensor:
    if transition is None:
        return scenario.transition
    matrix = torch.as_tensor(transition, dtype=scenario.transition.dtype, device=scenario.transition.device)
    known = isinstance(scenario.transition, Tensor)  # (a time-varying transition model: its own check)
    M = int(scenario.transition.shape[-1]) if known else int(matrix.shape[-1])
    if tuple(matrix.shape) != (M, M):
        raise ValueError(f"transition: expected {M} x {M} (the scenario's {M} modes), got "
                         f"{' x '.join(map(str, matrix.shape))}")
    return matrix


def _multiple_model(build, scenario, name, transition, joseph, factory, smooth=False) -> Estimator:
    bank = build_mode_filter(factory, scenario.motion, scenario.measurement, joseph=joseph)
    filt = build(bank, _transition(scenario, transition))
    return Estimator(name, filt, starter(filt, scenario.initial_mode_probs), True, smooth=smooth)


def multiple_model(scenario, *, name: str = "MM", combinator=None, mode_filter=None, transition=None,
                   joseph: bool = False, smooth: bool | str = False) -> Estimator:
    """The generic builder: ``combinator(bank, transition)`` over the scenario's mode bank.

    Args:
        combinator: a partial of a torchmm multiple-model class (``conf/estimator``'s
            ``combinator`` node: ``torchmm.IMM``, ``torchmm.GPB1``, ``torchmm.GPB2``,
            ``torchmm.MultipleModelFilter`` with an ``interaction``, ``torchmm.VariableStructureIMM``
            with a ``policy``); default IMM.
        mode_filter: a partial of a torchmm filter class (``conf/mode_filter``); default Kalman.
        transition: ``(M, M)``; default the scenario's.
        smooth: the generic study (``compare``) also scores its smoothed trajectory.
    """
    return _multiple_model(combinator or IMM, scenario, name, transition, joseph, mode_filter, smooth)


def imm(scenario, *, name: str = "IMM", transition=None, joseph: bool = False, mode_filter=None) -> Estimator:
    """IMM over the scenario's mode bank (transition: the scenario's, unless given)."""
    return _multiple_model(IMM, scenario, name, transition, joseph, mode_filter)


def gpb1(scenario, *, name: str = "GPB1", transition=None, joseph: bool = False, mode_filter=None) -> Estimator:
    return _multiple_model(GPB1, scenario, name, transition, joseph, mode_filter)


def gpb2(scenario, *, name: str = "GPB2", transition=None, joseph: bool = False, mode_filter=None) -> Estimator:
    return _multiple_model(GPB2, scenario, name, transition, joseph, mode_filter)


def mode_model(motion, mode: int):
    """Mode ``mode``'s motion model of a scenario's ``motion``: a list (one model per mode), one model
    without a mode axis (a one-mode scenario: it is mode 0's), or a bank (``param_batch_shape (k,)``:
    its ``select_mode``). A mode the scenario does not have is a ``ValueError`` naming ``mode``."""
    if isinstance(motion, (list, tuple)):
        if not 0 <= mode < len(motion):
            raise ValueError(f"mode: {mode} is not one of the scenario's {len(motion)} modes")
        return motion[mode]
    if not tuple(getattr(motion, "param_batch_shape", ()) or ()):  # one mode, not a bank
        if mode != 0:
            raise ValueError(f"mode: {mode} is not a mode of a one-mode scenario")
        return motion
    count = int(motion.param_batch_shape[0])
    if not 0 <= mode < count:
        raise ValueError(f"mode: {mode} is not one of the scenario's {count} modes (0 to {count - 1})")
    return motion.select_mode(mode)


def kalman(scenario, *, name: str = "KF", mode: int = 0, joseph: bool = False, transition=None,
           mode_filter=None, smooth: bool | str = False) -> Estimator:
    """A single filter (``mode_filter``; default Kalman) on mode ``mode``'s model (e.g. the CV model)."""
    model = mode_model(scenario.motion, mode)
    sensor = scenario.measurement[mode] if isinstance(scenario.measurement, (list, tuple)) else scenario.measurement
    filt = build_mode_filter(mode_filter, model, sensor, joseph=joseph)
    return Estimator(name, filt, starter(filt), False, smooth=smooth, mode=mode)


def custom(scenario, *, name: str = "filter", filter: Any, mode_probs=None, smooth: bool | str = False) -> Estimator:
    """Any torchmm filter built from its config node (``filter: {_target_: ..., ...}``; the scenario's
    models by interpolation, e.g. ``motion: ${scenario.modes[0]}``), started from the scenario's prior
    (``mode_probs``: a multiple-model filter's initial mode probabilities, default the scenario's)."""
    if not isinstance(filter, Filter):
        raise TypeError(f"filter: expected a torchmm filter (a config node with a _target_), got {type(filter).__name__}")
    multiple = isinstance(filter, MultipleModelFilter)
    probs = mode_probs if mode_probs is not None else (scenario.initial_mode_probs if multiple else None)
    if probs is not None:
        probs = torch.as_tensor(probs, dtype=scenario.initial.dtype, device=scenario.initial.mean.device)
    return Estimator(name, filter, starter(filter, probs), multiple, smooth=smooth)


@dataclass
class Evaluation:
    """Per-step Monte Carlo statistics of one estimator (all ``(T,)``), and its timing."""

    pos_rmse: Tensor
    vel_rmse: Tensor
    nees: Tensor
    mode_accuracy: Tensor | None
    seconds_per_step: float
    trajectory: Trajectory | None = None
    #: per-step means over all runs of the ``per_step`` statistics, ``(T, ...)`` each
    means: dict[str, Tensor] = field(default_factory=dict)
    #: their standard errors, ``sd over runs / sqrt(N)`` of the per-run values at each step (the
    #: curves' bands; NaN for one run)
    means_se: dict[str, Tensor] = field(default_factory=dict)
    #: standard error of each step's mode accuracy (a mean of per-run hits), ``(T,)``
    mode_accuracy_se: Tensor | None = None
    #: standard error of the time-averaged mode accuracy: sd over runs of a run's average / sqrt(N)
    mode_accuracy_avg_se: float = float("nan")
    #: delta-method standard errors of the average RMSEs (experiments/uncertainty.py)
    pos_rmse_se: float = float("nan")
    vel_rmse_se: float = float("nan")
    #: delta-method standard errors of each step's RMSE, ``(T,)`` (the curves' bands: +- 1.96 se)
    pos_rmse_band: Tensor | None = None
    vel_rmse_band: Tensor | None = None
    #: runs and state dimension (for the NEES chi-square bounds)
    runs: int = 0
    state_dim: int = 0

    def summary(self) -> dict[str, float]:
        out = {
            "pos_rmse": self.pos_rmse.mean().item(),
            "vel_rmse": self.vel_rmse.mean().item(),
            "nees": self.nees.mean().item(),
            "pos_rmse_se": self.pos_rmse_se,
            "vel_rmse_se": self.vel_rmse_se,
        }
        if self.mode_accuracy is not None:
            out["mode_accuracy"] = self.mode_accuracy.mean().item()
        return out


def evaluate(estimator: Estimator, scenario, sim, z: Any, *, chunk_runs: int | None = None,
             keep_trajectory: bool = False,
             per_step: dict[str, Callable[[Trajectory], Tensor]] | None = None,
             generator: torch.Generator | None = None,
             block_runs: int | None = None,
             generators: Callable[[int], torch.Generator] | None = None) -> Evaluation:
    """Run ``estimator`` on every Monte Carlo run (in chunks of ``chunk_runs`` if given).

    ``z`` is ``(T, runs, m)`` or a pytree of such streams (e.g. :class:`~torchmm.multimodel.MultiRate`).

    Every statistic is a function of per-run values, reduced over all runs at once at the end, so
    the numbers do not depend on the chunking (a filter's result for a run does not depend on the
    batch it runs in). ``per_step`` functions take a chunk's trajectory and return per-run values
    ``(T, chunk, ...)``; their means over all runs are in ``Evaluation.means``.
    ``keep_trajectory`` keeps the first chunk's trajectory (run 0 is in it), for plots and diagnostics.

    Randomness of estimators that draw random numbers (particle mode filters): with
    ``block_runs`` and ``generators`` (``b -> generator``, e.g. ``ctx.block_generators(...)``),
    each block of ``block_runs`` runs is filtered with its own generator - run-indexed streams: any
    chunking (and any split over workers) gives the same numbers; ``chunk_runs`` is then unused.
    Without them, ``generator`` is one stream for each chunk (the numbers depend on the chunking).

    The same as ``reduce_runs([evaluate_runs(...)])``: a study split into units of runs
    (``unit_runs``) calls :func:`evaluate_runs` in each unit and :func:`reduce_runs` on their values.
    """
    values, kept = evaluate_runs(estimator, scenario, sim, z, chunk_runs=chunk_runs, keep_trajectory=keep_trajectory,
                                 per_step=per_step, generator=generator, block_runs=block_runs,
                                 generators=generators)
    evaluation = reduce_runs([values])
    evaluation.trajectory = kept
    return evaluation


def evaluate_runs(estimator: Estimator, scenario, sim, z: Any, *, chunk_runs: int | None = None,
                  keep_trajectory: bool = False,
                  per_step: dict[str, Callable[[Trajectory], Tensor]] | None = None,
                  generator: torch.Generator | None = None,
                  block_runs: int | None = None,
                  generators: Callable[[int], torch.Generator] | None = None,
                  first_run: int = 0) -> tuple[dict, Trajectory | None]:
    """The per-run values of ``estimator`` on the runs of ``sim`` and ``z`` (a unit's runs): what
    :func:`reduce_runs` turns into an :class:`Evaluation`, and the kept trajectory (or None).

    Arguments as :func:`evaluate` (``keep_trajectory="all"``: every chunk's trajectory, joined along
    the runs); ``first_run`` (a multiple of ``block_runs``) is the study-wide index
    of the first run here, so that block ``b`` of these runs draws from ``generators(first_run //
    block_runs + b)`` wherever the unit runs. The value is small to ship and exact to store (numpy,
    ``experiments.arrays.per_run``): ``pos``/``vel`` squared errors ``(T, runs)`` (the standard errors
    need them per run), and sums over these runs of the NEES, the mode hits and each ``per_step``
    statistic, with the sums of their squares (``hits_sq``, ``sq_sums``: each step's standard error
    over the runs, :func:`~experiments.uncertainty.mean_se_per_step`).
    """
    leaf = pytree.tree_leaves(z)[0]
    runs = leaf.shape[1]
    if estimator.filter.uses_generator and block_runs and generators is not None:
        pieces = random_blocks(runs, first_run, int(block_runs))  # each block alone, on its own stream
    else:
        chunk = runs if not chunk_runs else int(chunk_runs)
        pieces = [(slice(s, min(s + chunk, runs)), None) for s in range(0, runs, chunk)]
    values: dict[str, list[Tensor]] = {"pos": [], "vel": [], "nees": [], "hits": []}
    per_step = per_step or {}
    extra: dict[str, list[Tensor]] = {key: [] for key in per_step}
    elapsed = 0.0
    kept = []
    prior = scenario.initial
    for sl, block_index in pieces:
        size = sl.stop - sl.start
        stream = generator if block_index is None else generators(block_index)
        tic = time.perf_counter()
        traj = estimator.run(prior.expand(size), pytree.tree_map(lambda t: t[:, sl], z), stream)
        est = traj.estimate()
        elapsed += time.perf_counter() - tic
        truth = sim.states[:, sl]
        values["pos"].append(squared_error(est.mean, truth, scenario.position).detach())
        values["vel"].append(squared_error(est.mean, truth, scenario.velocity).detach())
        values["nees"].append(nees(est, truth).detach())
        if estimator.multiple_model:
            values["hits"].append(mode_hits(traj.belief.mode_log_probs, sim.modes[:, sl]).to(est.mean.dtype))
        for key, fn in per_step.items():
            extra[key].append(fn(traj).detach())
        if keep_trajectory == "all" or (keep_trajectory and not kept):
            kept.append(traj)
    joined = {key: torch.cat(v, 1) for key, v in values.items() if v}  # (T, runs)
    return {
        "pos": per_run(joined["pos"]), "vel": per_run(joined["vel"]),
        "nees_sum": per_run(joined["nees"].sum(1)),
        "hits_sum": per_run(joined["hits"].sum(1)) if estimator.multiple_model else None,
        "hits_sq": per_run(joined["hits"].square().sum(1)) if estimator.multiple_model else None,
        # each run's time-averaged mode accuracy: the standard error of the average over the runs
        "hits_runs": per_run(joined["hits"].to(torch.float64).mean(0)) if estimator.multiple_model else None,
        "sums": {key: per_run(torch.cat(v, 1).sum(1)) for key, v in extra.items()},
        "sq_sums": {key: per_run(torch.cat(v, 1).to(torch.float64).square().sum(1)) for key, v in extra.items()},
        "runs": runs, "seconds": elapsed, "state_dim": int(sim.states.shape[-1]),
    }, join_trajectories(kept) if kept else None


def _run_mean_se(per_run_values: list) -> float:
    """``sd / sqrt(N)`` of per-run values joined over the parts (NaN for one run or a part without them)."""
    if any(v is None for v in per_run_values):
        return float("nan")
    values = join_runs(per_run_values, 0).to(torch.float64)
    return float(values.std() / values.numel() ** 0.5) if values.numel() > 1 else float("nan")


def random_blocks(runs: int, first_run: int, block_runs: int) -> list[tuple[slice, int]]:
    """``(slice of the runs, block index)`` for each block of ``block_runs`` of ``runs`` runs whose first is
    the study's run ``first_run`` (a multiple of ``block_runs``): a filter that draws random numbers runs each
    block alone on the block's own stream, so that a run's draws depend on its block only (not on
    ``unit_runs``, ``chunk_runs`` or the executor: docs/scaling.md)."""
    if first_run % block_runs:
        raise ValueError(f"first_run {first_run} is not a multiple of block_runs ({block_runs})")
    return [(slice(s, min(s + block_runs, runs)), (first_run + s) // block_runs)
            for s in range(0, runs, block_runs)]


def join_trajectories(parts: list[Trajectory]) -> Trajectory:
    """Trajectories of consecutive runs as one, each field concatenated once (time-major: runs on axis 1; a
    single part is returned as it is). The parts' provenance is not joined: smooth each part before."""
    if len(parts) == 1:
        return parts[0]

    def cat(*xs):
        return None if xs[0] is None else pytree.tree_map(lambda *ts: torch.cat(ts, 1), *xs)

    fields = [f.name for f in dataclasses.fields(Trajectory) if f.name != "provenance"]
    return Trajectory(**{name: cat(*(getattr(p, name) for p in parts)) for name in fields})


def reduce_runs(parts: list[dict]) -> Evaluation:
    """One :class:`Evaluation` from the :func:`evaluate_runs` values of consecutive units of runs, in
    run order (the order of arrival never matters): per-run values joined, sums added, then reduced
    once - a single part gives exactly :func:`evaluate`'s numbers."""
    runs = sum(int(p["runs"]) for p in parts)
    pos, vel = join_runs([p["pos"] for p in parts]), join_runs([p["vel"] for p in parts])
    steps = pos.shape[0]
    sq_pos_all, sq_vel_all = pos.to(torch.float64), vel.to(torch.float64)
    multiple_model = parts[0]["hits_sum"] is not None

    def se(key, sums, squares):  # per-step SE of a mean over the runs (None: a part without the squares)
        if any(squares(p) is None for p in parts):
            return None
        return mean_se_per_step(add_runs([sums(p) for p in parts]), add_runs([squares(p) for p in parts]), runs)

    means_se = {}
    for key in parts[0]["sums"]:
        band = se(key, lambda p, k=key: p["sums"][k], lambda p, k=key: (p.get("sq_sums") or {}).get(k))
        if band is not None:
            means_se[key] = band
    return Evaluation(
        pos_rmse=(pos.sum(1) / runs).sqrt(),
        vel_rmse=(vel.sum(1) / runs).sqrt(),
        nees=add_runs([p["nees_sum"] for p in parts]) / runs,
        mode_accuracy=(add_runs([p["hits_sum"] for p in parts]) / runs) if multiple_model else None,
        seconds_per_step=sum(float(p["seconds"]) for p in parts) / steps,
        means={key: add_runs([p["sums"][key] for p in parts]) / runs for key in parts[0]["sums"]},
        means_se=means_se,
        mode_accuracy_se=se("hits", lambda p: p["hits_sum"], lambda p: p.get("hits_sq")) if multiple_model else None,
        mode_accuracy_avg_se=_run_mean_se([p.get("hits_runs") for p in parts]) if multiple_model else float("nan"),
        pos_rmse_se=armse_se(sq_pos_all),
        vel_rmse_se=armse_se(sq_vel_all),
        pos_rmse_band=rmse_se_per_step(sq_pos_all),
        vel_rmse_band=rmse_se_per_step(sq_vel_all),
        runs=runs,
        state_dim=int(parts[0]["state_dim"]),
    )

"""Estimator builders (``conf/estimator/*.yaml``) and the Monte Carlo evaluation loop of studies.

A builder takes the scenario and returns an :class:`Estimator`: a torchmm filter plus how to start
it from the scenario's prior. Builders are instantiated by Hydra with ``_partial_: true`` so that
config values (options) and study values (scenario, transition) combine.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.utils._pytree as pytree
from torch import Tensor

from torchmm import GPB1, GPB2, IMM, Filter, GaussianBelief, KalmanFilter, run_filter
from torchmm.metrics import mode_accuracy, nees, squared_error
from torchmm.run import Trajectory

__all__ = ["Estimator", "Evaluation", "evaluate", "gpb1", "gpb2", "imm", "kalman"]


@dataclass
class Estimator:
    name: str
    filter: Filter
    init: Callable[[GaussianBelief], Any]
    multiple_model: bool
    #: picks this estimator's input from the study's measurements (e.g. the target stream of a
    #: multi-rate pytree); None = all of it
    select: Callable[[Any], Any] | None = None

    def run(self, prior: GaussianBelief, z: Any) -> Trajectory:
        return run_filter(self.filter, self.init(prior), z if self.select is None else self.select(z))


def _transition(scenario, transition) -> Tensor:
    if transition is None:
        return scenario.transition
    return torch.as_tensor(transition, dtype=scenario.transition.dtype, device=scenario.transition.device)


def _multiple_model(cls, scenario, name, transition, joseph) -> Estimator:
    bank = KalmanFilter(scenario.motion, scenario.measurement, joseph=joseph)
    filt = cls(bank, _transition(scenario, transition))
    return Estimator(name, filt, lambda prior: filt.initial_belief(prior, scenario.initial_mode_probs), True)


def imm(scenario, *, name: str = "IMM", transition=None, joseph: bool = False) -> Estimator:
    """IMM over the scenario's Kalman mode bank (transition: the scenario's, unless given)."""
    return _multiple_model(IMM, scenario, name, transition, joseph)


def gpb1(scenario, *, name: str = "GPB1", transition=None, joseph: bool = False) -> Estimator:
    return _multiple_model(GPB1, scenario, name, transition, joseph)


def gpb2(scenario, *, name: str = "GPB2", transition=None, joseph: bool = False) -> Estimator:
    return _multiple_model(GPB2, scenario, name, transition, joseph)


def kalman(scenario, *, name: str = "KF", mode: int = 0, joseph: bool = False, transition=None) -> Estimator:
    """A single Kalman filter on mode ``mode``'s model (e.g. the zero-acceleration CV model)."""
    filt = KalmanFilter(scenario.motion.select_mode(mode), scenario.measurement, joseph=joseph)
    return Estimator(name, filt, lambda prior: prior, False)


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

    def summary(self) -> dict[str, float]:
        out = {
            "pos_rmse": self.pos_rmse.mean().item(),
            "vel_rmse": self.vel_rmse.mean().item(),
            "nees": self.nees.mean().item(),
        }
        if self.mode_accuracy is not None:
            out["mode_accuracy"] = self.mode_accuracy.mean().item()
        return out


def evaluate(estimator: Estimator, scenario, sim, z: Any, *, chunk_runs: int | None = None,
             keep_trajectory: bool = False,
             per_step: dict[str, Callable[[Trajectory], Tensor]] | None = None) -> Evaluation:
    """Run ``estimator`` on every Monte Carlo run (in chunks of ``chunk_runs`` if given).

    ``z`` is ``(T, runs, m)`` or a pytree of such streams (e.g. :class:`~torchmm.multimodel.MultiRate`).

    Every reported statistic combines all chunks: errors are accumulated per step over runs (memory
    is bounded by the chunk size), and so is every ``per_step`` statistic - a function of a chunk's
    trajectory returning its per-step *sum over the chunk's runs*, ``(T, ...)`` - whose mean over
    all runs is returned in ``Evaluation.means``. ``keep_trajectory`` keeps the first chunk's
    trajectory, for plots of single runs (run 0 is in it) and diagnostics only.
    """
    leaf = pytree.tree_leaves(z)[0]
    runs = leaf.shape[1]
    chunk = runs if not chunk_runs else int(chunk_runs)
    steps = leaf.shape[0]
    sums = {"pos": 0.0, "vel": 0.0, "nees": 0.0, "hits": 0.0}
    per_step = per_step or {}
    extra_sums: dict[str, Tensor] = {}
    elapsed = 0.0
    kept = None
    prior = scenario.initial
    for start in range(0, runs, chunk):
        sl = slice(start, min(start + chunk, runs))
        size = sl.stop - sl.start
        tic = time.perf_counter()
        traj = estimator.run(prior.expand(size), pytree.tree_map(lambda t: t[:, sl], z))
        est = traj.estimate()
        elapsed += time.perf_counter() - tic
        truth = sim.states[:, sl]
        sums["pos"] = sums["pos"] + squared_error(est.mean, truth, scenario.position).sum(1)
        sums["vel"] = sums["vel"] + squared_error(est.mean, truth, scenario.velocity).sum(1)
        sums["nees"] = sums["nees"] + nees(est, truth).sum(1)
        if estimator.multiple_model:
            sums["hits"] = sums["hits"] + mode_accuracy(traj.belief.mode_log_probs, sim.modes[:, sl]) * size
        for key, fn in per_step.items():
            value = fn(traj)
            extra_sums[key] = value if key not in extra_sums else extra_sums[key] + value
        if keep_trajectory and kept is None:
            kept = traj
    return Evaluation(
        pos_rmse=(sums["pos"] / runs).sqrt(),
        vel_rmse=(sums["vel"] / runs).sqrt(),
        nees=sums["nees"] / runs,
        mode_accuracy=(sums["hits"] / runs) if estimator.multiple_model else None,
        seconds_per_step=elapsed / steps,
        trajectory=kept,
        means={key: value / runs for key, value in extra_sums.items()},
    )

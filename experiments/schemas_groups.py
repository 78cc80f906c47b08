"""The config groups' nodes (conf/logger, conf/executor, conf/mode_filter, conf/policy) and the scenario
builders' schemas, split from :mod:`experiments.schemas` by concern (issue 47), which imports them: the same
rules as there (a key a YAML sets has no default here)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

import yaml
from omegaconf import MISSING

from experiments.checks import (
    each,
    non_empty,
    non_negative,
    one_of,
    positive,
    positive_int,
    probability,
    spec,
)
from experiments.checks import (
    matrix as matrix_check,
)

KINEMATIC = "experiments.scenarios.kinematic_1d"
PAPER003 = "experiments.studies.mevsmm.paper003_scenario"


def rows_stochastic(matrix) -> str | None:
    if matrix is None:
        return None
    error = matrix_check(matrix)
    if error:
        return error
    if not matrix or any(len(row) != len(matrix) for row in matrix):
        return "must be a square matrix (list of rows)"
    for row in matrix:
        if any(p < 0 for p in row) or abs(sum(row) - 1) > 1e-6:
            return "every row must be non-negative and sum to 1"
    return None


# -- the config groups' nodes (conf/logger, conf/executor, conf/mode_filter, conf/policy) ------------------
@dataclass
class Logger:
    kind: str = spec("tensorboard", one_of("tensorboard", "none"))
    subdir: str = "tb"
    flush_secs: int = spec(10, positive_int)


@dataclass
class ExecutorConfig:
    """``executor=local|processes|submitit_local|slurm|ray`` (conf/executor; experiments/executors.py)."""

    kind: str = spec("local", one_of("local", "processes", "submitit_local", "slurm", "ray"))
    workers: int = spec(2, positive_int)
    retries: int = spec(2, non_negative)
    address: Optional[str] = None
    folder: Optional[str] = None
    partition: Optional[str] = None
    timeout_min: Optional[int] = spec(60, positive_int)
    cpus_per_task: Optional[int] = spec(1, positive_int)
    mem_gb: Optional[float] = spec(None, positive)
    array_parallelism: Optional[int] = spec(64, positive_int)
    slurm_parameters: dict = field(default_factory=dict)


MODE_FILTERS = ("torchmm.KalmanFilter", "torchmm.ExtendedKalmanFilter", "torchmm.UnscentedKalmanFilter",
                "torchmm.ParticleFilter")
POLICIES = ("torchmm.multimodel.mevsmm.ExactMinimumEntropy", "torchmm.multimodel.mevsmm.ChallengeMatch",
            "torchmm.multimodel.AllModels")


@dataclass
class ModeFilter:
    """``conf/mode_filter``: the mode filters of the multiple-model estimators (a torchmm filter class)."""

    _target_: str = spec("torchmm.KalmanFilter", one_of(*MODE_FILTERS))
    _partial_: bool = True
    num_particles: Optional[int] = spec(None, positive_int)
    ess_threshold: Optional[float] = spec(None, non_negative)
    resampling: Optional[str] = spec(None, one_of("systematic", "stratified", "multinomial", "residual"))

    def config_check(self):
        particle = self._target_ == "torchmm.ParticleFilter"
        if particle and self.num_particles is None:
            return "num_particles", None, "missing: particle mode filters need num_particles"
        if not particle:
            for key in ("num_particles", "ess_threshold", "resampling"):
                if getattr(self, key) is not None:
                    return key, getattr(self, key), f"only particle mode filters take {key}"
        return None


def model_sets(value) -> str | None:
    """A list of model sets, each a non-empty list of model indices (0-based; the bank's size is checked
    when the estimator is built)."""
    if value is None:
        return None
    if not value:
        return "must not be empty (a list of model-index lists, e.g. [[0, 1], [2]])"
    for k, members in enumerate(value):
        if not isinstance(members, list) or not members or any(
                isinstance(i, bool) or not isinstance(i, int) or i < 0 for i in members):
            return f"entry {k} ({members!r}): expected a non-empty list of model indices >= 0 ([[0, 1], [2]])"
    return None


def threshold_check(threshold, num_winners, key: str = "threshold"):
    """A challenge match's ``threshold`` above its ``num_winners`` could never be reached (every step would
    fall back to the model with the most winners): ``(key, value, why)`` or None."""
    if threshold is not None and num_winners is not None and threshold > num_winners:
        return key, threshold, (f"exceeds num_winners ({num_winners}): no model could reach it (every step "
                                "would fall back to the model with the most winners)")
    return None


@dataclass
class Policy:
    """``conf/policy``: the model-set policy of the ``vsmm`` estimator."""

    _target_: str = spec("torchmm.multimodel.mevsmm.ExactMinimumEntropy", one_of(*POLICIES))
    entropy: Optional[str] = spec(None, one_of("joint", "literal"))
    num_winners: Optional[int] = spec(None, positive_int)
    threshold: Optional[int] = spec(None, non_negative)
    method: Optional[str] = spec(None, one_of("cm", "topk"))
    passes: Optional[int] = spec(None, non_negative)
    family: Optional[List[Any]] = spec(None, model_sets)  # ExactMinimumEntropy's candidate sets

    def config_check(self):
        if self.family is not None and self._target_ != POLICIES[0]:
            return "family", self.family, f"only {POLICIES[0]} takes family (candidate model sets)"
        return threshold_check(self.threshold, self.num_winners)


# -- scenarios -----------------------------------------------------------------------------------
@dataclass
class KinematicScenario:
    """``experiments.scenarios.kinematic_1d`` (paper000, maneuver2, maneuver3)."""

    _target_: str = MISSING
    name: str = MISSING
    accelerations: List[float] = spec(MISSING, check=non_empty)
    q: float = spec(MISSING, non_negative)
    noise: str = spec(MISSING, one_of("discrete", "continuous"))
    R: float = spec(MISSING, positive)
    transition: List[Any] = spec(MISSING, check=rows_stochastic)
    initial_mean: List[float] = MISSING
    initial_cov: List[Any] = spec(MISSING, check=matrix_check)
    initial_mode_probs: Optional[List[float]] = MISSING
    steps: int = spec(MISSING, positive_int)
    dt: float = spec(MISSING, positive)

    def config_check(self):
        if len(self.initial_mean) != 2 or len(self.initial_cov) != 2:  # issue 30: [] failed in the study
            bad = "initial_mean" if len(self.initial_mean) != 2 else "initial_cov"
            return bad, getattr(self, bad), "expected the 2-state [position, velocity] " + (
                "mean" if bad == "initial_mean" else "covariance (2 x 2)")
        if len(self.transition) != len(self.accelerations):
            return ("transition", self.transition,
                    f"must be {len(self.accelerations)} x {len(self.accelerations)}: one row per acceleration mode")
        if self.initial_mode_probs is not None and len(self.initial_mode_probs) != len(self.accelerations):
            return ("initial_mode_probs", self.initial_mode_probs,
                    f"expected {len(self.accelerations)} probabilities (one per mode)")
        if self.initial_mode_probs is not None and (any(p < 0 for p in self.initial_mode_probs)
                                                    or abs(sum(self.initial_mode_probs) - 1) > 1e-6):
            return "initial_mode_probs", self.initial_mode_probs, "must be non-negative and sum to 1"
        return None


@dataclass
class RandomManeuvers:
    maneuver_prob: float = spec(0.7, probability)
    accel_std: float = spec(30.0, non_negative)
    hold: str = spec("previous", one_of("previous", "zero"))


@dataclass
class Paper003Scenario:
    """``experiments.studies.mevsmm.paper003_scenario`` (det_small, det_large, random)."""

    _target_: str = PAPER003
    name: str = "scenario"
    R: float = spec(150.0, positive)
    steps: int = spec(180, positive_int)
    initial_state: List[float] = field(default_factory=list)
    initial_std: Optional[List[float]] = spec(None, each(positive))
    maneuvers: List[Any] = field(default_factory=list)
    random: Optional[RandomManeuvers] = None
    D: str = spec("kinematic", one_of("kinematic", "printed"))

    def config_check(self):  # the 4-state [x, vx, y, vy] target; maneuvers' 1-based, inclusive seconds
        if len(self.initial_state) != 4:
            return "initial_state", self.initial_state, "expected 4 numbers: [x, vx, y, vy]"
        if self.initial_std is not None and len(self.initial_std) != 2:
            return "initial_std", self.initial_std, "expected 2 numbers: [position std, velocity std]"
        for i, m in enumerate(self.maneuvers):
            ok = isinstance(m, list) and len(m) == 3 and all(isinstance(v, int) and not isinstance(v, bool)
                                                             for v in m[:2])
            if not ok or not isinstance(m[2], list) or len(m[2]) != 2:
                return f"maneuvers[{i}]", m, "expected [first second, last second, [a_x, a_y]]"
            if not 1 <= m[0] <= m[1]:  # (past steps: cut off, e.g. a shorter run)
                return f"maneuvers[{i}]", m, "needs 1 <= first <= last (1-based, inclusive seconds)"
        return None


SYSTEM = "experiments.scenarios.system"


def _models(value) -> str | None:
    """A model node (``_target_``) or a non-empty list of them."""
    nodes = value if isinstance(value, list) else [value]
    if not nodes:
        return "needs at least one model"
    for node in nodes:
        if not isinstance(node, dict) or "_target_" not in node:
            return "expected a model node with a _target_ (e.g. {_target_: torchmm.ConstantVelocity, ndim: 2}) or a list of them"
    return None


def _mode_probs(value) -> str | None:
    if value is None or value == "ergodic":
        return None
    if not isinstance(value, list) or any(not isinstance(p, (int, float)) or p < 0 for p in value) \
            or abs(sum(value) - 1) > 1e-6:
        return "expected probabilities summing to 1, or ergodic"
    return None


@dataclass
class DataSpec:
    """``scenario.data``: recorded data (experiments/datafile.py)."""

    path: str = "???"  # required
    measurements: List[str] = spec(factory=list, check=non_empty)
    truth: Optional[List[Optional[str]]] = None  # one column per state component (null: not in the file)
    time: Optional[str] = None
    series: Optional[str] = None
    inputs: Optional[List[str]] = None  # exogenous inputs (regressors): the motion models' controls


@dataclass
class SystemScenario:
    """``experiments.scenarios.system``: the generic study's scenario (conf/experiment/compare.yaml)."""

    _target_: str = SYSTEM
    _recursive_: bool = False
    name: str = "system"
    modes: Any = spec(None, _models)
    sensors: Any = spec(None, _models)
    transition: Optional[List[Any]] = spec(None, rows_stochastic)
    initial_mean: List[float] = spec(factory=list, check=non_empty)
    initial_cov: List[Any] = spec(factory=list, check=matrix_check)
    initial_mode_probs: Any = spec(None, _mode_probs)
    labels: Optional[List[str]] = None
    groups: Optional[Dict[str, List[int]]] = None
    steps: int = spec(100, positive_int)
    missing: Any = 0.0
    every: Any = 1
    data: Optional[DataSpec] = None
    mode_sensors: bool = False
    dt_key: str = "dt"

MARKOV_SWITCHING = "experiments.scenarios.markov_switching"


@dataclass
class MarkovSwitchingScenario:
    """``experiments.scenarios.markov_switching``: a Markov-switching regression from one's own data
    (conf/experiment/markov_switching.yaml)."""

    _target_: str = MARKOV_SWITCHING
    _recursive_: bool = False
    name: str = "markov_switching"
    data: Optional[DataSpec] = None
    k_regimes: int = spec(2, lambda v: None if v >= 2 else "needs at least 2 regimes")
    trend: str = spec("c", one_of("c", "n"))
    switching_trend: bool = True
    switching_exog: bool = True
    switching_variance: bool = True
    transition: Optional[List[Any]] = spec(None, rows_stochastic)
    start: Optional[Dict[str, Any]] = None
    labels: Optional[List[str]] = None
    tvtp: Optional[List[str]] = None  # columns driving time-varying transition probabilities (exog_tvtp)
    tvtp_constant: bool = True


SCENARIOS = {KINEMATIC: KinematicScenario, PAPER003: Paper003Scenario, SYSTEM: SystemScenario,
             MARKOV_SWITCHING: MarkovSwitchingScenario}


def scenario_names(targets) -> list[str]:
    """The ``conf/scenario/*.yaml`` names whose builder is one of ``targets``."""
    folder = Path(__file__).resolve().parent.parent / "conf" / "scenario"
    names = []
    for path in sorted(folder.glob("*.yaml")):
        if (yaml.safe_load(path.read_text()) or {}).get("_target_") in targets:
            names.append(path.stem)
    return names



"""The typed schema of every study's own keys, of the scenario builders and of the estimators.

One dataclass per study section (checked by :func:`experiments.config.validate`); a field's type
is enforced by OmegaConf, its range by ``spec(..., check)``. ``STUDIES`` maps a study function to
its schema and the scenario builders it accepts (``None``: it takes no ``scenario``).

**One source of truth per key.** A key that the study's YAML sets has its value there only: its
field here has no default (``MISSING``: the YAML must set it) and only types and ranges it. A field
the YAML does not set (an optional block such as compare's ``learn``, a builder's option) has its
default here only (tests/experiments/test_keys_once.py). A study that is not listed here declares
its keys in its YAML alone: their defaults type them and its module's ``CHECKS`` range them
(:func:`experiments.config.infer_types`; tests/experiments/test_new_study.py).

Matrices and vectors are typed ``List[...]`` of numbers; their sizes are checked by the library
constructors the study calls (with errors naming the library argument).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

import yaml
from omegaconf import MISSING

from experiments.checks import (
    ConfigError,
    both,
    each,
    merge,
    non_empty,
    non_negative,
    one_of,
    open_probability,
    positive,
    positive_int,
    probability,
    spec,
)
from experiments.checks import (
    matrix as matrix_check,
)
from experiments.schemas_tracking import Tracking  # (the tracking study's keys, by study)

KINEMATIC = "experiments.scenarios.kinematic_1d"
PAPER003 = "experiments.studies.mevsmm.paper003_scenario"


def _rows_stochastic(matrix) -> str | None:
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


@dataclass
class Policy:
    """``conf/policy``: the model-set policy of the ``vsmm`` estimator."""

    _target_: str = spec("torchmm.multimodel.mevsmm.ExactMinimumEntropy", one_of(*POLICIES))
    entropy: Optional[str] = spec(None, one_of("joint", "literal"))
    num_winners: Optional[int] = spec(None, positive_int)
    threshold: Optional[int] = spec(None, non_negative)
    method: Optional[str] = spec(None, one_of("cm", "topk"))
    passes: Optional[int] = spec(None, non_negative)



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
    transition: List[Any] = spec(MISSING, check=_rows_stochastic)
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
    transition: Optional[List[Any]] = spec(None, _rows_stochastic)
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


#: the studies whose config is also built dry before anything runs (experiments.config.dry_build), beyond
#: the scenario every study's precheck builds: study -> its check_build(cfg, scenario)
BUILD_CHECKS = {"experiments.studies.compare.run": "experiments.studies.compare.check_build",
                "experiments.studies.tracking.run": "experiments.studies.tracking.check_build"}

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
    transition: Optional[List[Any]] = spec(None, _rows_stochastic)
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


# -- estimators (conf/estimator/*.yaml) ------------------------------------------------------------
COMBINATORS = ("torchmm.IMM", "torchmm.GPB1", "torchmm.GPB2", "torchmm.MultipleModelFilter",
               "torchmm.VariableStructureIMM", "torchmm.StaticMM")


def _combinator(node) -> str | None:
    if node is None:
        return None
    target = node.get("_target_") if isinstance(node, dict) else None
    if target not in COMBINATORS:
        return f"_target_ must be one of {', '.join(COMBINATORS)} (got {target!r})"
    return None


@dataclass
class Estimator:
    _target_: str = spec("experiments.estimators.multiple_model", one_of(
        "experiments.estimators.multiple_model", "experiments.estimators.imm", "experiments.estimators.gpb1",
        "experiments.estimators.gpb2", "experiments.estimators.kalman"))
    combinator: Optional[Any] = spec(None, _combinator)  # a torchmm multiple-model class (partial)
    _partial_: bool = True
    transition: Optional[List[Any]] = spec(None, _rows_stochastic)
    joseph: bool = False
    mode: int = spec(0, non_negative)
    feedback: bool = True
    mode_filter: Optional[Any] = None  # the conf/mode_filter node (checked as the common key mode_filter)
    policy: Optional[Any] = None  # the conf/policy node


BUILDERS = ("experiments.estimators.multiple_model", "experiments.estimators.imm", "experiments.estimators.gpb1",
            "experiments.estimators.gpb2", "experiments.estimators.kalman", "experiments.estimators.custom")


def _smooth(value) -> str | None:
    return None if value in (True, False, "kim", "two_filter") else "expected true, false, kim or two_filter"


@dataclass
class CompareEstimator:
    """An estimator of the generic study: any builder of experiments/estimators.py, ``smooth`` included."""

    _target_: str = spec("experiments.estimators.multiple_model", one_of(*BUILDERS))
    _partial_: bool = True
    combinator: Optional[Any] = spec(None, _combinator)
    filter: Optional[Any] = None  # custom: any torchmm filter node
    mode_probs: Optional[List[float]] = None
    transition: Optional[List[Any]] = spec(None, _rows_stochastic)
    joseph: bool = False
    mode: int = spec(0, non_negative)
    mode_filter: Optional[Any] = None
    smooth: Any = spec(False, _smooth)


# -- studies ---------------------------------------------------------------------------------------
METRICS = ("rmse", "nees", "nis", "mode_accuracy", "loglik", "whiteness", "time")


def _learn_model(value) -> str | None:
    if value is None:
        return None
    return None if re.fullmatch(r"(modes|sensors)(\[\d+\])?", str(value)) else \
        "expected modes, modes[i], sensors or sensors[i]"


@dataclass
class LearnParameter:
    model: Optional[str] = spec(None, _learn_model)  # None: the transition matrix
    name: str = "Q"  # the tensor: Q, R, F, H, offset, input_matrix, ..., or transition
    kind: Optional[str] = spec(None, lambda v: None if v is None else one_of(
        "free", "variance", "covariance", "stochastic", "probabilities", "log_diagonal", "cholesky", "scale")(v))
    shared: Any = False  # one value for every mode (a bank's tensor): true, or a mask of one mode's entries
    fixed: Optional[Any] = None  # a boolean mask of one model's tensor: entries held at their values
    lower: Optional[float] = None  # bounds of a free tensor's entries
    upper: Optional[float] = None
    names: Optional[Any] = None  # one model's tensor entries named (e.g. [[const, ogap]]): const[regime]


@dataclass
class Learn:
    parameters: Any = spec(factory=list, check=lambda v: None if v == "auto" else non_empty(v))  # or auto
    method: str = spec("mle", one_of("mle", "em", "em_then_mle", "em_then_lbfgs", "gradient"))  # em_then_lbfgs = em_then_mle
    estimator: Optional[str] = None  # this one estimator learns (its own copy of the models)
    estimators: Optional[List[str]] = None  # these learn, each its own copy (default: every estimator)
    hessian: str = spec("differences", one_of("differences", "autograd"))  # mle: the information's computation
    maxiter: Optional[int] = spec(None, lambda v: None if v is None else positive_int(v))  # mle: optimiser's limit
    optimizer: str = spec("lbfgs", one_of("lbfgs", "adam"))  # gradient: the torch optimiser
    lr: float = spec(1.0, positive)  # gradient
    iterations: int = spec(30, positive_int)  # gradient, em: at most this many iterations
    tolerance: float = spec(1e-12, non_negative)  # gradient, em: stop once the loss's relative change is below it


@dataclass
class Paired:
    reference: Optional[str] = MISSING


@dataclass
class Compare:
    estimators: Dict[str, Any] = spec(MISSING, check=non_empty)
    metrics: List[str] = spec(MISSING, check=both(non_empty, each(one_of(*METRICS))))
    paired: Paired = field(default_factory=Paired)
    learn: Optional[Learn] = MISSING
    update_first: bool = MISSING
    burn: int = spec(MISSING, non_negative)
    estimator_schema = CompareEstimator

    @staticmethod
    def check(data: dict) -> None:
        names = list(data.get("estimators") or {})
        ref = (data.get("paired") or {}).get("reference")
        if ref is not None and ref not in names and not ref.endswith(" smoothed"):
            raise ConfigError("paired.reference", ref, f"must be one of the estimators ({', '.join(names)})")
        # (a malformed data file, models, estimators and learn entries: built by the study's check_build,
        # experiments.studies.compare, before anything runs)
        learn = data.get("learn")
        if learn and learn.get("estimator") is not None and learn["estimator"] not in names:
            raise ConfigError("learn.estimator", learn["estimator"], f"must be one of the estimators ({', '.join(names)})")
        if learn and isinstance(learn.get("parameters"), list):  # (typed Any, for `auto`): each entry's schema
            for i, entry in enumerate(learn["parameters"]):
                if not isinstance(entry, dict):
                    raise ConfigError(f"learn.parameters[{i}]", entry, "expected a mapping {model, name, kind, ...}")
                merge(LearnParameter, entry, f"learn.parameters[{i}]")
        if learn and learn.get("estimators") is not None:
            if learn.get("estimator") is not None:
                raise ConfigError("learn.estimators", learn["estimators"], "give learn.estimator or learn.estimators, "
                                  "not both")
            unknown = [n for n in learn["estimators"] if n not in names]
            if unknown:
                raise ConfigError("learn.estimators", learn["estimators"], f"{', '.join(unknown)}: not estimators "
                                  f"({', '.join(names)})")


@dataclass
class ImmBaseline:
    estimators: Dict[str, Any] = MISSING


@dataclass
class Influence:
    threshold: float = MISSING
    mode: int = spec(MISSING, non_negative)
    weight: str = spec(MISSING, one_of("prior", "process"))


@dataclass
class Transfer:
    smoothing_reference: str = spec(MISSING, one_of("combined", "mixed"))
    mode_likelihood: str = spec(MISSING, one_of("prior", "corrected"))
    influence: Influence = field(default_factory=Influence)


@dataclass
class Source:
    R: float = spec(MISSING, positive)
    ratio: float = spec(MISSING, probability)
    availability: str = spec(MISSING, one_of("bernoulli", "periodic"))
    period: int = spec(MISSING, positive_int)


@dataclass
class Vsimm:
    extra_model: int = spec(MISSING, non_negative)
    p_new: Optional[float] = spec(MISSING, open_probability)
    p_ee: float = spec(MISSING, lambda v: None if 0 <= v < 1 else "must lie in [0, 1)")
    eps: float = spec(MISSING, lambda v: None if 0 <= v < 1 else "must lie in [0, 1)")
    drop_below: float = spec(MISSING, lambda v: None if 0 <= v < 1 else "must lie in [0, 1)")


_VSIMM_KEYS = ("extra_model", "p_new", "p_ee", "eps", "drop_below")
TF_ESTIMATORS = ("IMM", "IMM-TF", "IF-TF", "IMM-FU", "VSIMM", "IMM-SU")
TF_CLASSES = ("torchmm.IMM", "torchmm.GPB1", "torchmm.GPB2", "torchmm.TransferIMM", "torchmm.SourceUpdateIMM",
              "torchmm.FusionIMM", "torchmm.SourceModeVSIMM", "torchmm.VariableStructureIMM")


def _tf_estimators(nodes) -> str | None:
    for name, node in (nodes or {}).items():
        target = node.get("_target_") if isinstance(node, dict) else None
        if target not in TF_CLASSES:
            return f"entry {name}: _target_ must be one of {', '.join(TF_CLASSES)} (got {target!r})"
    return None


@dataclass
class ImmTf:
    estimator_names: List[str] = spec(MISSING, check=non_empty)
    tf_estimators: Dict[str, Any] = spec(MISSING, check=_tf_estimators)
    source: Source = field(default_factory=Source)
    table1_ratios: List[float] = spec(MISSING, check=each(probability))
    rs_sweep: List[float] = spec(MISSING, check=each(positive))
    transfer: Transfer = field(default_factory=Transfer)
    vsimm: Vsimm = field(default_factory=Vsimm)


    @staticmethod
    def check(data: dict) -> None:
        known = list(data.get("tf_estimators") or {})
        for name in data["estimator_names"]:
            if name not in known:
                raise ConfigError("estimator_names", data["estimator_names"],
                                  f"entry {name}: expected one of {', '.join(known)} (the keys of tf_estimators)")
        # an entry's own options, typed and ranged as the keys they normally come from (vsimm.*,
        # transfer.influence.*); issue 30: tf_estimators.VSIMM.p_ee=abc failed with a traceback

        for name, node in (data.get("tf_estimators") or {}).items():
            prefix = f"tf_estimators.{name}"
            if node.get("_target_") == "torchmm.SourceModeVSIMM":
                merge(Vsimm, {k: v for k, v in node.items() if k in _VSIMM_KEYS}, prefix)
            gate = node.get("gate")
            if isinstance(gate, dict) and gate.get("_target_") == "torchmm.InfluenceGate":
                merge(Influence, {k: v for k, v in gate.items() if not k.startswith("_")}, f"{prefix}.gate")


@dataclass
class Alphas:
    two_model: List[float] = spec(MISSING, check=each(non_negative))
    three_model: List[float] = spec(MISSING, check=each(non_negative))


@dataclass
class AnalysisScenarios:
    two_model: KinematicScenario = field(default_factory=KinematicScenario)
    three_model: KinematicScenario = field(default_factory=KinematicScenario)


@dataclass
class Analysis:
    scenarios: AnalysisScenarios = field(default_factory=AnalysisScenarios)
    alphas: Alphas = field(default_factory=Alphas)
    matched: str = spec(MISSING, one_of("closest", "true_mode"))
    interaction_estimator: str = MISSING
    tol: float = spec(MISSING, non_negative)


@dataclass
class ImmAnalysis:
    analysis: Analysis = field(default_factory=Analysis)
    estimators: Dict[str, Any] = MISSING

    @staticmethod
    def check(data: dict) -> None:
        name = data["analysis"]["interaction_estimator"]
        if name not in (data.get("estimators") or {}):
            raise ConfigError("analysis.interaction_estimator", name,
                              f"must name one of the estimators: {', '.join(data.get('estimators') or {})}")
        # paper 001's (2.2) with M equal alphas has diagonal 1 - (M - 1) alpha: a transition only for
        # alpha <= 1 / (M - 1) (before: one unit ran, then alpha_transition's error was a traceback)
        for key, models in (("two_model", 2), ("three_model", 3)):
            alphas = data["analysis"]["alphas"].get(key) or []
            too_large = [a for a in alphas if a > 1.0 / (models - 1)]
            if too_large:
                raise ConfigError(f"analysis.alphas.{key}", alphas,
                                  f"entries {too_large} exceed 1/(M-1) = {1.0 / (models - 1):g} for M = {models} "
                                  "modes: (M-1) alpha <= 1 keeps the transition matrix's diagonal non-negative")


@dataclass
class GimmafNoise:
    kind: str = spec(MISSING, one_of("skew_t", "student_t", "gaussian"))
    R: float = spec(MISSING, positive)
    delta: float = MISSING
    nu: float = spec(MISSING, positive)


@dataclass
class Table4Noise:
    R: float = spec(MISSING, positive)
    delta: float = MISSING
    nu: float = spec(MISSING, positive)


@dataclass
class Table4:
    noises: List[str] = spec(MISSING, check=each(one_of("skew_t", "student_t", "gaussian")))
    noise: Table4Noise = field(default_factory=Table4Noise)


@dataclass
class Vbakf:
    rho: float = spec(MISSING, lambda v: None if 0 < v <= 1 else "must lie in (0, 1]")
    tau_r: float = spec(MISSING, positive)


#: what a node of ``gimmaf.estimators`` may build: IMMs over the model_rates bank (they take a
#: ``transition``) and single VB filters on the CV model
GIMMAF_TARGETS = ("torchmm.multimodel.variational.imm_vbt", "torchmm.multimodel.variational.gimmaf",
                  "torchmm.filters.variational.SkewTVBFilter", "torchmm.filters.variational.StudentTVBFilter",
                  "torchmm.filters.variational.SkewTIWVBFilter", "torchmm.filters.variational.VBAKFPR")


@dataclass
class GimmafEstimator:
    """A node of ``gimmaf.estimators``: a torchmm function or class and its options (the noise's
    ``skewness`` and ``df`` come from the setting: not options)."""

    _target_: str = spec(GIMMAF_TARGETS[1], one_of(*GIMMAF_TARGETS))
    _partial_: bool = True
    iterations: Optional[int] = spec(None, positive_int)
    tau: Optional[float] = spec(None, positive)
    rho: Optional[float] = spec(None, lambda v: None if v is None or 0 < v <= 1 else "must lie in (0, 1]")
    tau_r: Optional[float] = spec(None, positive)
    gamma_shape: Optional[str] = spec(None, one_of("derived", "printed"))
    elbo_history: Optional[bool] = None
    joseph: Optional[bool] = None


@dataclass
class GimmafSection:
    steps: int = spec(MISSING, positive_int)
    dt: float = spec(MISSING, positive)
    x0: List[float] = MISSING
    P0: List[float] = spec(MISSING, check=each(positive))
    segments: List[Any] = spec(MISSING, check=matrix_check)
    noise: GimmafNoise = field(default_factory=GimmafNoise)
    model_rates: List[float] = spec(MISSING, check=non_empty)
    transition: List[Any] = spec(MISSING, check=_rows_stochastic)
    nominal_q: float = spec(MISSING, positive)
    tau: float = spec(MISSING, positive)
    iterations: int = spec(MISSING, positive_int)
    elbo_history: bool = MISSING
    gamma_shape: str = spec(MISSING, one_of("derived", "printed"))
    vbakf: Vbakf = field(default_factory=Vbakf)
    oracle: bool = MISSING
    table4: Table4 = field(default_factory=Table4)
    estimators: Dict[str, Any] = spec(MISSING, check=non_empty)  # name: node (checked by Gimmaf.check)

    def config_check(self):
        if len(self.transition) != len(self.model_rates):
            return ("transition", self.transition,
                    f"must be {len(self.model_rates)} x {len(self.model_rates)}: one row per model rate")
        return None


@dataclass
class Gimmaf:
    noise: str = spec(MISSING, one_of("skew_t", "student_t", "gaussian"))
    gimmaf: GimmafSection = field(default_factory=GimmafSection)

    @staticmethod
    def check(data: dict) -> None:

        for name, node in data["gimmaf"]["estimators"].items():  # each node's target and options, one line
            prefix = f"gimmaf.estimators.{name}"
            if not isinstance(node, dict):
                raise ConfigError(prefix, node, f"expected an estimator node with a _target_ (one of {', '.join(GIMMAF_TARGETS)})")
            merge(GimmafEstimator, node, prefix)


def _nominal_q(value) -> str | None:
    if value == "true":
        return None
    try:
        return None if float(value) > 0 else 'must be "true" or a positive number'
    except (TypeError, ValueError):
        return 'must be "true" or a positive number'


@dataclass
class Huang:
    steps: int = spec(MISSING, positive_int)
    nominal_q: Any = spec(MISSING, _nominal_q)
    beta: float = spec(MISSING, positive)
    tau: float = spec(MISSING, positive)
    rho: float = spec(MISSING, lambda v: None if 0 < v <= 1 else "must lie in (0, 1]")
    iterations: int = spec(MISSING, positive_int)


@dataclass
class VbakfHuang:
    huang: Huang = field(default_factory=Huang)


@dataclass
class LearnScenario:
    steps: int = spec(MISSING, positive_int)
    dt: float = spec(MISSING, positive)
    turn_rate: float = MISSING
    q: float = spec(MISSING, positive)
    R: float = spec(MISSING, positive)
    stay: float = spec(MISSING, open_probability)
    initial_mean: List[float] = MISSING
    initial_std: List[float] = spec(MISSING, check=each(non_negative))


@dataclass
class LearnPart:
    enabled: bool = MISSING
    optimizer: str = spec(MISSING, one_of("lbfgs", "adam"))
    lr: float = spec(MISSING, positive)
    max_line_search: int = spec(MISSING, positive_int)
    iterations: int = spec(MISSING, non_negative)
    window: Optional[int] = spec(MISSING, positive_int)
    batch_size: Optional[int] = spec(MISSING, positive_int)


@dataclass
class LearnPartA(LearnPart):
    initial_stay: Optional[float] = spec(MISSING, open_probability)
    initial_q_factor: float = spec(MISSING, positive)


@dataclass
class LearnPartB(LearnPart):
    replaced_mode: int = spec(MISSING, lambda v: None if v in (0, 1, 2) else "expected 0 (CV), 1 or 2 (CT)")
    hidden: int = spec(MISSING, positive_int)
    v_scale: float = spec(MISSING, positive)
    a_scale: float = spec(MISSING, positive)


@dataclass
class LearnSection:
    test_runs: Optional[int] = spec(MISSING, positive_int)
    num_threads: Optional[int] = spec(MISSING, positive_int)
    scenario: LearnScenario = field(default_factory=LearnScenario)
    part_a: LearnPartA = field(default_factory=LearnPartA)
    part_b: LearnPartB = field(default_factory=LearnPartB)


@dataclass
class LearnDynamics:
    learn: LearnSection = field(default_factory=LearnSection)


#: the builders of ``mevsmm.estimators`` nodes (conf/mevsmm_estimator/*.yaml)
MEVSMM_BUILDERS = ("experiments.studies.mevsmm.eqma", "experiments.studies.mevsmm.pf_mevsmm",
                   "experiments.studies.mevsmm.vsmm")
MEVSMM_SELECTIONS = ("torchmm.multimodel.mevsmm.ChallengeMatch", "torchmm.multimodel.mevsmm.ExactMinimumEntropy")
_MEVSMM_HINT = "a conf/mevsmm_estimator entry, e.g. +mevsmm_estimator@mevsmm.estimators.NAME=topk"


def _mevsmm_model(value) -> str | None:
    return None if 1 <= value <= 21 else "must be a model m_j of section 4 (1..21)"


@dataclass
class MevsmmSelection:
    """A PF-MEVSMM node's ``selection``: the challenge match / top-k or the exact minimum-entropy set."""

    _target_: str = spec(MEVSMM_SELECTIONS[0], one_of(*MEVSMM_SELECTIONS))
    num_winners: Optional[int] = spec(None, positive_int)
    threshold: Optional[int] = spec(None, non_negative)
    method: Optional[str] = spec(None, one_of("cm", "topk"))
    passes: Optional[int] = spec(None, positive_int)
    chunk_size: Optional[int] = spec(None, positive_int)
    entropy: Optional[str] = spec(None, one_of("joint", "literal"))


@dataclass
class MevsmmEstimator:
    """A node of ``mevsmm.estimators``: a builder of experiments/studies/mevsmm.py, its options, and
    the study's own ``runs`` (cap on the runs) and ``timing_base`` (table2's base)."""

    _target_: str = spec(MEVSMM_BUILDERS[1], one_of(*MEVSMM_BUILDERS))
    _partial_: bool = True
    runs: Optional[int] = spec(None, positive_int)
    timing_base: bool = False
    models: Optional[List[int]] = spec(None, each(_mevsmm_model))  # eqma: the m_j (1-based); null: all 21
    num_particles: Optional[int] = spec(None, positive_int)
    stay_prob: Optional[float] = spec(None, probability)
    accel_std: float = spec(5.0, positive)
    mixing: str = spec("two_stage", one_of("two_stage", "systematic", "stratified", "multinomial"))
    noise_dtype: Optional[str] = spec(None, one_of("float32", "float64"))
    feedback: bool = True
    selection: Optional[Any] = None  # pf_mevsmm: a MevsmmSelection node
    entropy: str = spec("joint", one_of("joint", "literal"))
    mode_filter: Optional[Any] = None  # vsmm: the conf/mode_filter node
    policy: Optional[Any] = None  # vsmm: the conf/policy node

    def config_check(self):
        import dataclasses

        builder = self._target_.rsplit(".", 1)[-1]
        options = {"eqma": ("models", "num_particles", "stay_prob", "accel_std", "mixing", "noise_dtype"),
                   "pf_mevsmm": ("selection", "num_particles", "feedback", "stay_prob", "accel_std", "mixing",
                                 "noise_dtype"),
                   "vsmm": ("mode_filter", "policy", "entropy", "feedback", "stay_prob", "accel_std")}[builder]
        defaults = {f.name: f.default for f in dataclasses.fields(self) if f.default is not dataclasses.MISSING}
        for key, default in defaults.items():
            if key not in options and not key.startswith("_") and key not in ("runs", "timing_base") \
                    and getattr(self, key) != default:
                return key, getattr(self, key), f"not an option of {self._target_} (its options: {', '.join(options)})"
        if builder != "vsmm" and self.num_particles is None:
            return "num_particles", None, f"missing: {self._target_} needs num_particles"
        if builder == "eqma" and self.stay_prob is None:
            return "stay_prob", None, "missing: EqMA needs its p_ii"
        if builder == "pf_mevsmm" and self.selection is None:
            return "selection", None, f"missing: {self._target_} needs a selection node ({', '.join(MEVSMM_SELECTIONS)})"
        return None


@dataclass
class MevsmmSection:
    estimators: Dict[str, Any] = spec(MISSING, check=non_empty)  # name: node (checked by Mevsmm.check)
    estimator_names: Optional[List[str]] = spec(MISSING, non_empty)  # which estimators run, in order (null: all)
    num_particles: int = spec(MISSING, positive_int)
    num_winners: int = spec(MISSING, positive_int)
    threshold: int = spec(MISSING, non_negative)
    cm_passes: int = spec(MISSING, positive_int)  # 0: the CM kernel refused it after the run started (issue 30)
    stay_prob: float = spec(MISSING, probability)
    mevsmm_stay_prob: Optional[float] = spec(MISSING, probability)
    accel_std: float = spec(MISSING, positive)
    mixing: str = spec(MISSING, one_of("two_stage", "systematic", "stratified", "multinomial"))
    noise_dtype: Optional[str] = spec(MISSING, one_of("float32", "float64"))
    feedback: bool = MISSING
    entropy: str = spec(MISSING, one_of("joint", "literal"))
    exact_runs: int = spec(MISSING, positive_int)
    exact_chunk: int = spec(MISSING, positive_int)
    histogram_steps: List[int] = spec(MISSING, check=each(positive_int))


@dataclass
class Mevsmm:
    mevsmm: MevsmmSection = field(default_factory=MevsmmSection)

    @staticmethod
    def check(data: dict) -> None:

        opts = data["mevsmm"]
        if opts["num_winners"] > 21 * opts["num_particles"]:
            raise ConfigError("mevsmm.num_winners", opts["num_winners"],
                              f"must not exceed the 21 x {opts['num_particles']} particles")
        names = list(opts["estimators"])
        for name in opts.get("estimator_names") or ():
            if name not in names:
                raise ConfigError("mevsmm.estimator_names", opts["estimator_names"],
                                  f"entry {name}: expected one of {', '.join(names)} (the keys of mevsmm.estimators)")
        # every node's builder (one_of) and options (types, ranges), as one line naming the key
        for name, node in opts["estimators"].items():
            prefix = f"mevsmm.estimators.{name}"
            if not isinstance(node, dict):  # the kind strings of before (issue 30) are config-group entries now
                raise ConfigError(prefix, node, f"expected an estimator node with a _target_ ({_MEVSMM_HINT})")
            est = merge(MevsmmEstimator, node, prefix)
            if est.selection is not None:
                if not isinstance(est.selection, dict):
                    raise ConfigError(f"{prefix}.selection", est.selection,
                                      f"expected a node with a _target_ ({', '.join(MEVSMM_SELECTIONS)})")
                selection = merge(MevsmmSelection, est.selection, f"{prefix}.selection")
                winners = selection.num_winners
                if winners is not None and est.num_particles is not None and winners > 21 * est.num_particles:
                    raise ConfigError(f"{prefix}.selection.num_winners", winners,
                                      f"must not exceed the 21 x {est.num_particles} particles")
            if isinstance(est.mode_filter, dict):
                merge(ModeFilter, est.mode_filter, f"{prefix}.mode_filter")
            if isinstance(est.policy, dict):
                merge(Policy, est.policy, f"{prefix}.policy")


@dataclass
class Radar:
    steps: int = spec(MISSING, positive_int)
    T: float = spec(MISSING, positive)
    rho: List[float] = spec(MISSING, check=lambda v: None if len(v) == 2 else
                            "expected 2 numbers (the x and y acceleration correlations)")
    tau: float = spec(MISSING, positive)
    h_sign: int = spec(MISSING, lambda v: None if v in (-1, 1) else "expected -1 or 1")
    h_factor: List[float] = MISSING
    sigma_r: List[float] = spec(MISSING, check=each(non_negative))
    Qr0: Optional[List[float]] = MISSING
    eta_std: List[Any] = spec(MISSING, check=matrix_check)
    Qw_diag: List[float] = spec(MISSING, check=each(non_negative))
    x0: List[float] = MISSING
    P0_diag: List[float] = spec(MISSING, check=each(non_negative))
    position_index: int = spec(MISSING, non_negative)
    C: List[Any] = MISSING
    Ct: List[Any] = MISSING
    d: List[Any] = MISSING

    def config_check(self):  # the 6-state model's vectors (issue 30: a short one failed in the study)
        for key in ("x0", "P0_diag", "Qw_diag"):
            if len(getattr(self, key)) != 6:
                return key, getattr(self, key), "expected 6 numbers (one per state)"
        if len(self.h_factor) != len(self.sigma_r):
            sensors = len(self.sigma_r)
            return "h_factor", self.h_factor, f"expected {sensors} numbers (one per sensor, as sigma_r)"
        return None


@dataclass
class FusionRadar:
    radar: Radar = field(default_factory=Radar)


@dataclass
class Ups:
    steps: int = spec(MISSING, positive_int)
    burn_in: int = spec(MISSING, non_negative)
    horizons: List[int] = spec(MISSING, check=lambda v: None if 0 in v else
                               "must include 0 (the filter; negative: smoothing lags, positive: predictions)")
    ss_tol: float = spec(MISSING, positive)
    cf_ss_steps: int = spec(MISSING, positive_int)
    A: List[Any] = spec(MISSING, check=matrix_check)
    Gamma: List[Any] = spec(MISSING, check=matrix_check)
    Qw: float = spec(MISSING, non_negative)
    C: List[float] = MISSING
    Ct: List[Any] = spec(MISSING, check=matrix_check)
    h: List[float] = MISSING
    Qp: List[float] = spec(MISSING, check=each(non_negative))
    d: List[float] = MISSING
    Q_eta: List[float] = spec(MISSING, check=each(positive))
    mu0: List[float] = MISSING
    P0_scale: float = spec(MISSING, non_negative)
    Qr0: Optional[List[float]] = MISSING

    def config_check(self):  # sizes (issue 30: a short vector failed in the study, with a traceback)
        n, sensors = len(self.A), len(self.Ct)
        for key, size in (("C", n), ("mu0", n), ("h", sensors), ("Qp", sensors), ("d", sensors),
                          ("Q_eta", sensors)):
            if len(getattr(self, key)) != size:
                unit = "state" if key in ("C", "mu0") else "sensor"
                return key, getattr(self, key), f"expected {size} numbers (one per {unit})"
        return None


@dataclass
class FusionUps:
    ups: Ups = field(default_factory=Ups)

    @staticmethod
    def check(data: dict) -> None:
        ups = data["ups"]
        if ups["burn_in"] >= ups["steps"]:
            raise ConfigError("ups.burn_in", ups["burn_in"], f"must be below ups.steps = {ups['steps']}")


TURNING = "experiments.scenarios.turning_2d"


@dataclass
class SmoothingStudy:
    scenarios: Dict[str, Any] = spec(MISSING, check=non_empty)
    cv_mode: Dict[str, int] = MISSING
    speed: bool = MISSING  # the parallel_speed table (speed_steps x speed_runs); false in debug=smoothing
    speed_steps: List[int] = spec(MISSING, check=each(positive))
    speed_runs: int = spec(MISSING, positive_int)


@dataclass
class Smoothing:
    smoothing: SmoothingStudy = field(default_factory=SmoothingStudy)
    estimators: Dict[str, Any] = MISSING

    @staticmethod
    def check(data: dict) -> None:

        sm = data["smoothing"]
        missing = [k for k in sm["scenarios"] if k not in (sm.get("cv_mode") or {})]
        if missing:
            raise ConfigError("smoothing.cv_mode", sm.get("cv_mode"),
                              f"needs the constant-velocity mode of every scenario; missing {', '.join(missing)}")
        # every scenario's keys, as its builder's schema types and ranges them (issue 30: steps=-3 or
        # q=abc ran the filters, then failed with a traceback); the CV mode within its modes
        for key, scenario in sm["scenarios"].items():
            prefix = f"smoothing.scenarios.{key}"
            target = (scenario or {}).get("_target_")
            if target in SCENARIOS:
                merge(SCENARIOS[target], scenario, prefix)
                modes = len(scenario.get("accelerations") or ()) if target == KINEMATIC else None
            elif target == TURNING:
                own = {k: v for k, v in scenario.items() if k not in ("_target_", "name")}
                merge(LearnScenario, own, prefix)
                modes = 3  # constant velocity, left turn, right turn
            else:
                raise ConfigError(f"{prefix}._target_", target, f"expected one of {KINEMATIC}, {TURNING}")
            mode = sm["cv_mode"][key]
            if modes is not None and not 0 <= mode < modes:
                raise ConfigError(f"smoothing.cv_mode.{key}", mode, f"must be a mode index in [0, {modes})")


STUDIES: dict[str, tuple[type, tuple[str, ...] | None]] = {
    "experiments.studies.imm_baseline.run": (ImmBaseline, (KINEMATIC,)),
    "experiments.studies.imm_tf.run": (ImmTf, (KINEMATIC,)),
    "experiments.studies.imm_analysis.run": (ImmAnalysis, None),
    "experiments.studies.gimmaf.run": (Gimmaf, None),
    "experiments.studies.vbakf_huang.run": (VbakfHuang, None),
    "experiments.studies.learn_dynamics.run": (LearnDynamics, None),
    "experiments.studies.mevsmm.run": (Mevsmm, (PAPER003,)),
    "experiments.studies.fusion_radar.run": (FusionRadar, None),
    "experiments.studies.fusion_ups.run": (FusionUps, None),
    "experiments.studies.smoothing.run": (Smoothing, None),
    "experiments.studies.compare.run": (Compare, (SYSTEM, MARKOV_SWITCHING)),
    "experiments.studies.tracking.run": (Tracking, None),
}

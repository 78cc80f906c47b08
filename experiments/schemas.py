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

Split by concern (issue 47): here the estimators, the compare, learn-dynamics and smoothing studies and
``STUDIES``; the config groups' nodes and the scenario builders in :mod:`experiments.schemas_groups`; the
published papers' studies in :mod:`experiments.schemas_papers` (the fusion studies in
:mod:`experiments.schemas_fusion`); the tracking study in :mod:`experiments.schemas_tracking`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

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
    spec,
)
from experiments.schemas_groups import (  # (the scenario builders' names and schemas)
    KINEMATIC,
    MARKOV_SWITCHING,
    PAPER003,
    SCENARIOS,
    SYSTEM,
    rows_stochastic,
)
from experiments.schemas_fusion import FusionRadar, FusionUps  # (the fusion studies)
from experiments.schemas_papers import (  # (the published papers' studies, by study)
    Gimmaf,
    ImmAnalysis,
    ImmBaseline,
    ImmTf,
    Mevsmm,
    VbakfHuang,
)
from experiments.schemas_tracking import Tracking  # (the tracking study's keys, by study)


#: what each study builds from its config, built dry before anything runs (experiments.config.dry_build),
#: beyond the scenario every study's precheck builds: study -> its check_build(cfg, scenario) (the published
#: studies': experiments/study_builds.py; every study of STUDIES has one:
#: tests/experiments/test_config_dry_build.py)
BUILD_CHECKS = {"experiments.studies.compare.run": "experiments.studies.compare.check_build",
                "experiments.studies.tracking.run": "experiments.studies.tracking.check_build",
                **{f"experiments.studies.{study}.run": f"experiments.study_builds.{study}" for study in (
                    "imm_baseline", "imm_tf", "imm_analysis", "gimmaf", "learn_dynamics", "mevsmm",
                    "fusion_radar", "fusion_ups", "smoothing")},
                "experiments.studies.vbakf_huang.run": None}  # (its config: numbers the schema ranges)


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
    transition: Optional[List[Any]] = spec(None, rows_stochastic)
    joseph: bool = False
    mode: int = spec(0, non_negative)
    feedback: bool = True
    mode_filter: Optional[Any] = None  # the conf/mode_filter node (checked as the common key mode_filter)
    policy: Optional[Any] = None  # the conf/policy node


BUILDERS = ("experiments.estimators.multiple_model", "experiments.estimators.imm", "experiments.estimators.gpb1",
            "experiments.estimators.gpb2", "experiments.estimators.kalman", "experiments.estimators.custom")


def _smooth(value) -> str | None:
    return (None if value in (True, False, "kim", "two_filter", "two_filter_info")
            else "expected true, false, kim, two_filter or two_filter_info")


@dataclass
class CompareEstimator:
    """An estimator of the generic study: any builder of experiments/estimators.py, ``smooth`` included."""

    _target_: str = spec("experiments.estimators.multiple_model", one_of(*BUILDERS))
    _partial_: bool = True
    combinator: Optional[Any] = spec(None, _combinator)
    filter: Optional[Any] = None  # custom: any torchmm filter node
    mode_probs: Optional[List[float]] = None
    transition: Optional[List[Any]] = spec(None, rows_stochastic)
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
        # "<name> smoothed" only for an estimator that smooths (``smooth:`` set: compare scores it under that label)
        smoothed = [f"{n} smoothed" for n in names if isinstance(data["estimators"][n], dict)
                    and data["estimators"][n].get("smooth") not in (None, False, "")]
        if ref is not None and ref not in names and ref not in smoothed:
            raise ConfigError("paired.reference", ref, f"must be one of the estimators ({', '.join(names + smoothed)})"
                              + (" (an estimator's smoothed trajectory needs its smooth: true)"
                                 if ref.endswith(" smoothed") else ""))
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
class LearnScenario:
    steps: int = spec(MISSING, positive_int)
    dt: float = spec(MISSING, positive)
    turn_rate: float = MISSING
    q: float = spec(MISSING, positive)
    R: float = spec(MISSING, positive)
    stay: float = spec(MISSING, open_probability)
    initial_mean: List[float] = MISSING
    initial_std: List[float] = spec(MISSING, check=each(non_negative))

    def config_check(self):  # the 4-state [x, vx, y, vy] target of experiments.scenarios.turning_2d
        for key in ("initial_mean", "initial_std"):
            if len(getattr(self, key)) != 4:
                return key, getattr(self, key), "expected 4 numbers (one per state: x, vx, y, vy)"
        return None


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

TURNING = "experiments.scenarios.turning_2d"
#: the single-filter builder (the smoothing study sets its ``mode``)
SINGLE = "experiments.estimators.kalman"


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
        for name, est in (data.get("estimators") or {}).items():  # (before: accepted, then replaced)
            if isinstance(est, dict) and est.get("_target_") == SINGLE and est.get("mode") not in (None, 0):
                raise ConfigError(f"estimators.{name}.mode", est["mode"],
                                  "not used: the smoothing study runs each single filter on its scenario's "
                                  "smoothing.cv_mode (set smoothing.cv_mode.<scenario>)")
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


_SCENARIO_KEYS = ("tracking.targets", "tracking.steps", "tracking.radius", "tracking.maneuver_start",
                  "tracking.maneuver_stop")

#: study -> (the key that, when set, makes others unused; the keys it makes unused; why): an override of
#: an unused key is refused (compare: nile, fedfunds, markov_switching and one's own CSV; tracking_detections;
#: tracking from waypoints)
UNUSED_WHEN = {
    "experiments.studies.compare.run": [
        ("scenario.data", ("mc_runs",), "the runs are the series of scenario.data, one run a series")],
    "experiments.studies.tracking.run": [
        ("tracking.detections", ("mc_runs",), "the runs are the series of tracking.detections, one run a series"),
        ("tracking.detections", _SCENARIO_KEYS, "the targets and scans are those of tracking.detections"),
        ("tracking.waypoints", _SCENARIO_KEYS[:1] + _SCENARIO_KEYS[2:], "the targets fly tracking.waypoints")],
}


def check_overrides(data: dict, overrides: list[str]) -> None:
    """Refuse an override whose value the study would ignore (it would be recorded in results.json and
    listed under results.md's changes with no effect): ``mc_runs`` given while the runs are a data file's
    series, the simulated scenario's keys while the targets come from a file or from waypoints
    (:data:`UNUSED_WHEN`). ``overrides``: the command line's ``key=value`` strings."""
    given = {}
    for item in overrides:
        name, _, value = str(item).lstrip("+~").partition("=")
        given.setdefault(name.strip(), value)
    for when, unused, why in UNUSED_WHEN.get(str(data.get("study")), ()):
        node: Any = data
        for part in when.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        if node is None:
            continue
        for key in unused:
            if key in given:
                raise ConfigError(key, given[key], f"not used: {why} (leave {key} out)")


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

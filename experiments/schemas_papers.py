"""The published papers' studies' keys (IMM-TF and its baseline, the IMM analysis, GIMMAF and the VBAKF
comparison, MEVSMM), split from :mod:`experiments.schemas` by study (issue 47), which lists them in
``STUDIES``: the same rules as there (a key the YAML sets has no default here, ``MISSING``). The two fusion
studies' keys: :mod:`experiments.schemas_fusion`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from omegaconf import MISSING

from experiments.checks import (
    ConfigError,
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
from experiments.schemas_groups import KinematicScenario, ModeFilter, Policy, rows_stochastic, threshold_check


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
        twice = sorted({n for n in data["estimator_names"] if list(data["estimator_names"]).count(n) > 1})
        if twice:  # (a name given twice was one row of the tables: silently fewer estimators than listed)
            raise ConfigError("estimator_names", data["estimator_names"], f"{', '.join(twice)} given twice")
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
        # mode indices within the scenario's modes, named by the key a user sets (the nodes interpolate them;
        # a node's own value after: before, the run failed after creating its folder)
        modes = len((data.get("scenario") or {}).get("accelerations") or ())
        if modes:
            for key, value in (("transfer.influence.mode", data["transfer"]["influence"]["mode"]),
                               ("vsimm.extra_model", data["vsimm"]["extra_model"])):
                if not 0 <= value < modes:
                    raise ConfigError(key, value,
                                      f"must be a mode index in [0, {modes}) (the scenario's {modes} modes)")
            for name, node in (data.get("tf_estimators") or {}).items():
                gate = node.get("gate") if isinstance(node.get("gate"), dict) else {}
                for key, value in ((f"tf_estimators.{name}.gate.mode", gate.get("mode")),
                                   (f"tf_estimators.{name}.extra_model", node.get("extra_model"))):
                    if isinstance(value, int) and not 0 <= value < modes:
                        raise ConfigError(key, value, f"must be a mode index in [0, {modes}) "
                                          f"(the scenario's {modes} modes)")


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
        for key, est in (data.get("estimators") or {}).items():  # (before: accepted, then replaced)
            if isinstance(est, dict) and est.get("transition") is not None:
                raise ConfigError(f"estimators.{key}.transition", est["transition"],
                                  "not used: the imm_analysis study sweeps the transition matrix (2.2) over "
                                  "analysis.alphas.two_model and analysis.alphas.three_model")
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
    transition: List[Any] = spec(MISSING, check=rows_stochastic)
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
        for i, row in enumerate(self.segments):  # Table 1's rows (before: a bad one failed in the study)
            if len(row) != 4:
                return (f"segments[{i}]", row,
                        "expected [first step, last step, turn rate, process-noise variance]")
            first, last, _, q = row
            if first != int(first) or last != int(last) or not 1 <= first <= last:  # (past steps: cut off)
                return f"segments[{i}]", row, "needs whole steps 1 <= first <= last (1-based, inclusive)"
            if q < 0:
                return f"segments[{i}]", row, f"the process-noise variance {q} must be non-negative"
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

    def config_check(self):
        return threshold_check(self.threshold, self.num_winners)


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
        if builder == "eqma" and self.models is not None:
            if not self.models:
                return "models", self.models, "must not be empty (null: all 21 models)"
            repeated = sorted({m for m in self.models if list(self.models).count(m) > 1})
            if repeated:
                return "models", self.models, (f"model m{repeated[0]} is listed more than once (each model "
                                               "once: a repeat would run twice and count twice in table1)")
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
        problem = threshold_check(opts["threshold"], opts["num_winners"])
        if problem:
            raise ConfigError(f"mevsmm.{problem[0]}", problem[1], problem[2])
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

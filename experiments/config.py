"""Typed study configs: every key is checked before anything runs; user errors are one line.

The schemas are dataclasses (OmegaConf structured configs, the Hydra ecosystem's typed configs):
:class:`Common` for the keys every study shares, one dataclass per study for its own keys
(:mod:`experiments.schemas`), one per scenario builder and estimator builder. :func:`validate`
merges the composed config into them - OmegaConf converts and type-checks every value and
rejects unknown keys - and then runs each field's range check (``metadata={"check": ...}``).
Any problem is a :class:`ConfigError`, a ``ValueError`` whose message is one line naming the key,
the value and what is allowed, e.g. ``mc_runs=0: must be a positive integer``.

:func:`precheck` is the command line's gate: ``torchmm-run`` composes the config of the run (or
of every job of a ``-m`` sweep) from the command-line overrides and validates it *before* Hydra
starts, so a user error prints that one line, exits with status 2, and leaves no run folder
behind. :func:`~experiments.run.run_study` validates again (for use without the command line).
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import math
import sys
from pathlib import Path
from dataclasses import dataclass, field
from typing import Any, Optional

from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import (
    ConfigAttributeError,
    ConfigKeyError,
    OmegaConfBaseException,
)

from experiments.checks import (  # noqa: F401 - re-exported: the checks studies use (experiments.config.positive, ...)
    NO_VALUE,
    Check,
    ConfigError,
    both,
    build_error,
    check_fields,
    device_name,
    each,
    join_key,
    matrix,
    merge,
    non_empty,
    non_negative,
    one_of,
    open_probability,
    positive,
    positive_int,
    probability,
    resume_value,
    seed_value,
    spec,
    type_message,
)
from experiments import schemas as schemas_mod
from experiments.schemas_groups import ExecutorConfig, Logger, ModeFilter, Policy, scenario_names

__all__ = ["Common", "ConfigError", "infer_types", "precheck", "spec", "validate"]


# -- the common keys ---------------------------------------------------------------------------
@dataclass
class Common:
    """Keys every study has (``conf/config.yaml``)."""

    mc_runs: int = spec(MISSING, positive_int)
    seed: int = spec(MISSING, seed_value)
    block_runs: int = spec(MISSING, positive_int)
    device: str = spec(MISSING, device_name)
    dtype: str = spec(MISSING, one_of("float64", "float32", "double", "float"))
    progress: bool = MISSING
    figures: bool = MISSING
    chunk_runs: Optional[int] = spec(MISSING, positive_int)
    unit_runs: Optional[int] = spec(MISSING, positive_int)
    threads: Optional[int] = spec(MISSING, positive_int)
    retain_freed_memory: bool = MISSING
    compile: bool = MISSING
    cpu_kernels: bool = MISSING  # false: the particle filters' eager path (the same numbers, no Numba compile)
    resume: Optional[str] = spec(MISSING, resume_value)
    experiment_name: str = MISSING
    study: str = MISSING
    logger: Logger = field(default_factory=Logger)
    executor: ExecutorConfig = field(default_factory=ExecutorConfig)
    mode_filter: ModeFilter = field(default_factory=ModeFilter)
    policy: Policy = field(default_factory=Policy)

    def config_check(self):
        if self.unit_runs is not None and self.unit_runs % self.block_runs:
            return ("unit_runs", self.unit_runs,
                    f"must be a multiple of block_runs ({self.block_runs}): a unit holds whole random-number blocks")
        return None


#: top-level keys that are neither common nor a study's own: checked separately
_SHARED = {"scenario", "estimators"}


# -- validation --------------------------------------------------------------------------------
def _study_module(study: str):
    module, _, name = study.rpartition(".")
    try:
        mod = importlib.import_module(module)
        getattr(mod, name)
    except (ImportError, AttributeError, ValueError):
        raise ConfigError("study", study, "not an importable study function (module.run)") from None
    return mod


def _study_entry(study: str) -> tuple[type | None, tuple[str, ...] | None]:

    entry = schemas_mod.STUDIES.get(study)
    if entry is None:
        _study_module(study)
        return None, None  # a user's own study: its module's CHECKS and the defaults' types (validate)
    return entry


def infer_types(reference: Any, value: Any, key: str = "") -> None:
    """``value`` checked against the type of ``reference``, its default (the study's YAML): the keys of a
    study without a schema are declared once, in its YAML. Numbers stay numbers, flags flags, strings
    scalars, lists lists (elementwise like their first entry) and mappings mappings with the default's
    keys - except open ones (empty, a map of config nodes, or a ``_target_`` node), which take new
    keys. ``null`` defaults take anything. Raises :class:`ConfigError` naming the key."""
    if reference is None or value is None:
        return
    if isinstance(reference, bool):
        if not isinstance(value, bool):
            raise ConfigError(key, value, "expected true or false")
    elif isinstance(reference, (int, float)):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(key, value, "expected a number")
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(key, value, "must be finite")
    elif isinstance(reference, str):
        if isinstance(value, (list, dict)):
            raise ConfigError(key, value, "expected a string")
    elif isinstance(reference, list):
        if not isinstance(value, list):
            raise ConfigError(key, value, "expected a list")
        if reference:
            for i, item in enumerate(value):
                infer_types(reference[0], item, f"{key}[{i}]")
    elif isinstance(reference, dict):
        if not isinstance(value, dict):
            raise ConfigError(key, value, "expected a mapping")
        open_map = not reference or "_target_" in reference or all(isinstance(v, dict) for v in reference.values())
        for k, v in value.items():
            if k in reference:
                infer_types(reference[k], v, join_key(key, str(k)))
            elif not open_map:
                close = difflib.get_close_matches(str(k), [str(r) for r in reference], n=1)
                hint = f"did you mean {join_key(key, close[0])}?" if close else f"known: {', '.join(map(str, reference))}"
                raise ConfigError(join_key(key, str(k)), NO_VALUE, f"unknown key ({hint})")


def _own_checks(module, data: dict) -> None:
    """A user study's ``CHECKS`` (``{dotted key: check}``, checks as in :func:`spec`) and its
    ``check_config(data)`` (relations between keys: raise :class:`ConfigError`)."""
    for key, check in (getattr(module, "CHECKS", None) or {}).items():
        value = OmegaConf.select(OmegaConf.create(data), key, default=NO_VALUE)
        if value is NO_VALUE:
            raise ConfigError(key, NO_VALUE, "missing (CHECKS names it, the config has no such key)")
        error = check(value)
        if error:
            raise ConfigError(key, value, error)
    relation = getattr(module, "check_config", None)
    if relation is not None:
        relation(data)


def validate(cfg: DictConfig | dict, *, scenario_choice: str | None = None, reference: Any = None,
             overrides: list[str] | None = None) -> None:
    """Check every key of a composed study config (no ``hydra`` node); raise :class:`ConfigError`.

    Args:
        cfg: the composed config (``hydra.compose`` or Hydra's task config).
        scenario_choice: the ``scenario=<name>`` chosen on the command line, for the message when
            the scenario does not fit the study (default: ``scenario.name``).
        reference: the same study's config with its defaults (only the config-group choices
            applied): a study without a schema in :mod:`experiments.schemas` has each of its own
            keys typed by its default (:func:`infer_types`), and ranged by its module's ``CHECKS``.
        overrides: the command line's ``key=value`` strings: one the study would ignore is refused
            (``mc_runs`` with a data file's series as the runs: experiments.schemas.check_overrides).
    """

    data = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    data.pop("hydra", None)
    common_keys = {f.name for f in dataclasses.fields(Common)}
    merge(Common, {k: v for k, v in data.items() if k in common_keys})
    study = str(data.get("study"))
    schema, scenarios = _study_entry(study)
    if schema is None:  # a user's own study: its keys are its YAML's (types) and its module's CHECKS
        own = {k: v for k, v in data.items() if k not in common_keys}
        if reference is not None:
            ref = OmegaConf.to_container(reference, resolve=True) if isinstance(reference, DictConfig) \
                else dict(reference)
            infer_types({k: v for k, v in ref.items() if k not in common_keys and k != "hydra"}, own)
        _own_checks(_study_module(study), data)
        dry_build(data, scenario=False)  # (a study of one's own: its module's check_build only)
        return
    own = {f.name for f in dataclasses.fields(schema)}
    for key in data:
        if key not in common_keys and key not in own and key not in _SHARED:
            known = sorted(own | _SHARED | common_keys)
            close = difflib.get_close_matches(key, known, n=1)
            hint = f"did you mean {close[0]}?" if close else f"the {data.get('experiment_name')} study's keys: " \
                + ", ".join(sorted(own))
            raise ConfigError(key, NO_VALUE, f"not a key of the {data.get('experiment_name')} study ({hint})")
    merge(schema, {k: v for k, v in data.items() if k in own})
    _validate_scenario(data, scenarios, scenario_choice)
    if "estimators" in own or "estimators" in data:
        for name, est in (data.get("estimators") or {}).items():
            merge(getattr(schema, "estimator_schema", schemas_mod.Estimator), est or {}, f"estimators.{name}")
    if hasattr(schema, "check"):
        schema.check(data)
    schemas_mod.check_overrides(data, overrides or [])
    dry_build(data)


def dry_build(data: dict, *, scenario: bool = True) -> None:
    """Build what the run will build from the config, before anything runs: the ``scenario`` (its
    models, sensors, prior and data file) and what the study's ``check_build(cfg, scenario)`` builds
    (``BUILD_CHECKS`` of :mod:`experiments.schemas`: every estimator on its scenario(s), ``compare``'s
    ``learn`` block, the fusion studies' systems; a study of one's own: its module's), in the
    run's dtype on the CPU. A value only a constructor can judge (a covariance that is not PSD, an
    ``R`` of the wrong shape, a sensor whose size differs from the data's, a ``learn`` entry naming no
    model or parameter) is then one :class:`ConfigError` naming the key, before any folder exists.
    Nothing is simulated or filtered (milliseconds)."""
    import torch
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    node = data.get("scenario") if scenario else None
    scenario = None
    dtype = {"float64": torch.float64, "double": torch.float64, "float32": torch.float32,
             "float": torch.float32}.get(str(data.get("dtype")), torch.float64)
    if isinstance(node, dict) and node.get("_target_"):
        try:
            scenario = instantiate(node, dtype=dtype, device="cpu")
        except InstantiationException as err:
            cause = err.__cause__ or err.__context__
            if isinstance(cause, ConfigError):
                raise cause from None
            raise ConfigError("scenario", node.get("name", node["_target_"]),
                              f"cannot be built: {_first_line(cause or err)}") from None
        except (TypeError, ValueError) as err:
            if isinstance(err, ConfigError):
                raise
            raise ConfigError("scenario", node.get("name", node["_target_"]),
                              f"cannot be built: {_first_line(err)}") from None
    study = str(data.get("study"))
    entry = schemas_mod.BUILD_CHECKS.get(study)
    if entry is not None or study not in schemas_mod.STUDIES:  # (a study of one's own: its module's, if any)
        module, _, name = (entry or f"{study.rpartition('.')[0]}.check_build").rpartition(".")
        check = getattr(importlib.import_module(module), name, None)
        if check is not None:
            check(OmegaConf.create(data), scenario)


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


def _validate_scenario(data: dict, scenarios: tuple[str, ...] | None, choice: str | None) -> None:

    scenario = data.get("scenario")
    name = choice or (scenario or {}).get("name")
    experiment = data.get("experiment_name")
    if not scenarios:
        if scenario:
            raise ConfigError("scenario", name, f"the {experiment} study takes no scenario")
        return
    if not scenario:
        raise ConfigError("scenario", NO_VALUE, f"missing: the {experiment} study needs one of "
                          f"{', '.join(scenario_names(scenarios))}")
    target = scenario.get("_target_")
    if target not in scenarios:
        raise ConfigError("scenario", name, f"does not fit the {experiment} study; choose one of "
                          f"{', '.join(scenario_names(scenarios))}")
    merge(schemas_mod.SCENARIOS[target], scenario, "scenario")


# -- the command line ------------------------------------------------------------------------------
def precheck(argv: list[str], config_dir: str, config_name: str = "config") -> None:
    """Validate the run (or every job of a ``-m`` sweep) that ``argv`` asks for; on a user error
    print one line to stderr and exit with status 2 (before Hydra creates any folder)."""
    try:
        _precheck(argv, config_dir, config_name)
    except ConfigError as err:
        print(f"torchmm-run: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


def _precheck(argv: list[str], config_dir: str, config_name: str) -> None:
    from hydra._internal.utils import get_args_parser

    try:
        args, unknown = get_args_parser().parse_known_args(argv)
    except SystemExit:
        return  # Hydra's own argument errors: Hydra reports them
    passthrough = ("help", "hydra_help", "cfg", "info", "shell_completion", "version", "config_path",
                   "config_name", "config_dir", "experimental_rerun")
    if unknown or any(getattr(args, name, None) for name in passthrough):
        return  # Hydra's own modes (help, --cfg, a config dir of the user's, ...): Hydra handles them
    overrides = list(args.overrides)
    jobs = _sweep_jobs(overrides) if args.multirun else [overrides]
    for job in jobs:
        cfg, choice = compose_config(job, config_dir, config_name)
        reference = None
        if str(cfg.get("study")) not in _registered():  # a study without a schema: typed by its defaults
            reference, _ = compose_config(_choices_only(job, config_dir), config_dir, config_name)
        validate(cfg, scenario_choice=choice, reference=reference, overrides=job)


def _registered() -> set[str]:

    return set(schemas_mod.STUDIES)


def _choices_only(overrides: list[str], config_dir: str) -> list[str]:
    """The overrides that pick configs (config groups, ``group@package``, ``hydra.*``), not values: the
    composition of the run's defaults."""
    groups = {p.name for p in Path(config_dir).iterdir() if p.is_dir()}
    for item in overrides:  # the user's own config folders (hydra.searchpath) add groups too
        if item.startswith("hydra.searchpath="):
            for entry in item.split("=", 1)[1].strip("[]").split(","):
                folder = Path(entry.strip().removeprefix("file://"))
                if folder.is_dir():
                    groups |= {p.name for p in folder.iterdir() if p.is_dir()}
    out = []
    for item in overrides:
        name = item.lstrip("+~").split("=", 1)[0]
        if name.startswith("hydra.") or "@" in name or name.split("/", 1)[0] in groups:
            out.append(item)
    return out


def _sweep_jobs(overrides: list[str]) -> list[list[str]]:
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException as err:
        raise ConfigError("overrides", " ".join(overrides), str(err).splitlines()[0]) from None
    batches = BasicSweeper.split_arguments(parsed, max_batch_size=None)
    return [job for batch in batches for job in batch]


def compose_config(overrides: list[str], config_dir: str, config_name: str) -> tuple[DictConfig, str | None]:
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException, MissingConfigException
    from omegaconf import open_dict

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=config_dir, version_base="1.3"):
            cfg = compose(config_name, overrides=overrides, return_hydra_config=True)
    except MissingConfigException as err:
        raise missing_config(err, overrides) from None
    except (HydraException, OmegaConfBaseException) as err:
        raise composition_error(err, overrides) from None
    finally:
        GlobalHydra.instance().clear()
    choice = OmegaConf.select(cfg, "hydra.runtime.choices.scenario")
    with open_dict(cfg):
        del cfg["hydra"]  # never resolve hydra.run.dir here: its resolver creates the run folder
    return cfg, choice


def _override_for(key: str, overrides: list[str]) -> str | None:
    for item in overrides:
        name = item.lstrip("+~").split("=", 1)[0]
        if name == key or name.split("@", 1)[0] == key:
            return item
    return None


def _composed(other_overrides: list[str]) -> DictConfig | None:
    """The config composed without the refused override (for hints only; None if that fails too)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from experiments.paths import CONFIG_DIR

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            return compose("config", overrides=other_overrides)
    except Exception:  # noqa: BLE001 - only a hint
        return None
    finally:
        GlobalHydra.instance().clear()


def _close_keys(key: str, cfg: DictConfig | None) -> str | None:
    """The existing key of ``cfg`` closest to a misspelt ``key``."""
    parent, _, leaf = key.rpartition(".")
    try:
        node = OmegaConf.select(cfg, parent) if parent else cfg
    except Exception:  # noqa: BLE001 - only a hint
        return None
    if not isinstance(node, DictConfig):
        return None
    close = difflib.get_close_matches(leaf, [str(k) for k in node.keys()], n=1)
    return f"{parent}.{close[0]}" if close and parent else (close[0] if close else None)


def _reference_hint(key: str, cfg: DictConfig | None) -> str | None:
    """For a ``key`` below a node that is an interpolation (``estimators.IMM.mode_filter: ${mode_filter}``),
    which no override can reach into: what to set instead - the referenced group or key, or the whole node."""
    from experiments.paths import CONFIG_DIR

    if cfg is None:
        return None
    parts, node = key.split("."), cfg
    for i, part in enumerate(parts[:-1]):
        if not isinstance(node, DictConfig) or part not in node:
            return None
        if OmegaConf.is_interpolation(node, part):
            path, rest = ".".join(parts[:i + 1]), ".".join(parts[i + 1:])
            ref = str(OmegaConf.to_container(node, resolve=False)[part])  # the ${...} text
            target = ref[2:-1] if ref.startswith("${") and ref.endswith("}") else None
            folder = Path(CONFIG_DIR) / (target or "")
            if target and folder.is_dir():
                options = "|".join(sorted(p.stem for p in folder.glob("*.yaml")))
                choice = f"choose the group, {target}=<{options}> (every node that refers to it)"
            elif target:
                choice = f"set {target}.{rest}=... (every node that refers to it)"
            else:
                choice = "set the keys it refers to"
            return (f"{path} is {ref}, which an override cannot reach into: {choice}, or replace this node, "
                    f"{path}={{_target_:...,...}}")
        node = node[part]
    return None


def missing_config(err, overrides: list[str]) -> ConfigError:
    text = str(err)
    group = None
    if "Could not find '" in text:
        group = text.split("Could not find '", 1)[1].split("'", 1)[0].rsplit("/", 1)[0]
    options = list(getattr(err, "options", None) or [])
    if group and options:
        item = _override_for(group, overrides)
        value = item.split("=", 1)[1] if item and "=" in item else NO_VALUE
        return ConfigError(group, value, f"no such config; choose one of {', '.join(sorted(options))}")
    return ConfigError("config", NO_VALUE, text.splitlines()[0])


def composition_error(err, overrides: list[str]) -> ConfigError:
    cause = err.__cause__ if isinstance(err.__cause__, OmegaConfBaseException) else err
    key = getattr(cause, "full_key", None) or getattr(cause, "key", None)
    text = str(err).splitlines()[0]
    if isinstance(cause, (ConfigKeyError, ConfigAttributeError)) and key:
        item = _override_for(str(key), overrides) or ""
        value = item.split("=", 1)[1] if "=" in item else NO_VALUE
        composed = _composed([o for o in overrides if o != item])
        reference = _reference_hint(str(key), composed)
        if reference:  # (before: "unknown key (did you mean <the same key>?)")
            return ConfigError(str(key), value, reference)
        close = _close_keys(str(key), composed)
        hint = f"did you mean {close}? " if close else ""
        return ConfigError(str(key), value, f"unknown key ({hint}to add a new key write +{key}=...)")
    if isinstance(cause, OmegaConfBaseException) and key:
        return ConfigError(str(key), cause.value if cause.value is not None else NO_VALUE,
                           type_message(cause))
    return ConfigError("overrides", " ".join(overrides), text)

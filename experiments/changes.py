"""What a run's config changes from its study's defaults (:func:`config_changes`, the top of
``results.md``), and conf/ composed as ``torchmm-run`` composes it (:func:`compose_conf`)."""

from __future__ import annotations

import contextvars
import json
import logging
from pathlib import Path
from typing import Any

from experiments.folders import DATA_FILES, NON_RESULT_KEYS
from experiments.paths import CONFIG_DIR

__all__ = ["RUN_CHOICES", "compose_conf", "config_changes"]

log = logging.getLogger("torchmm.experiments")

#: config groups whose choice never changes a study's numbers (as :data:`experiments.folders.NON_RESULT_KEYS`)
_NON_RESULT_GROUPS = ("logger", "executor")

#: the config-group choices of the run :func:`study` is starting (Hydra's own, on the command line)
RUN_CHOICES: contextvars.ContextVar[dict | None] = contextvars.ContextVar("torchmm_choices", default=None)


def compose_conf(overrides: list[str]) -> tuple[Any, dict]:
    """``(config without hydra, config-group choices)`` of conf/ with ``overrides``, as torchmm-run
    composes it; a bad override is a :class:`~experiments.config.ConfigError`. Hydra's global state
    (a running ``torchmm-run``'s) is kept."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException, MissingConfigException
    from hydra.initialize import get_gh_backup, restore_gh_from_backup
    from omegaconf import OmegaConf, open_dict
    from omegaconf.errors import OmegaConfBaseException

    from experiments.config import composition_error, missing_config

    backup = get_gh_backup()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            cfg = compose("config", overrides=overrides, return_hydra_config=True)
    except MissingConfigException as err:
        raise missing_config(err, overrides) from None
    except (HydraException, OmegaConfBaseException) as err:
        raise composition_error(err, overrides) from None
    finally:
        restore_gh_from_backup(backup)
    choices = OmegaConf.to_container(cfg.hydra.runtime.choices, resolve=False)
    with open_dict(cfg):
        del cfg["hydra"]  # never resolve hydra.run.dir: its resolver creates the run folder
    return cfg, {str(k): v for k, v in choices.items()}


def _relevant(key: str) -> bool:
    head = key.split(".", 1)[0].split("/", 1)[0]
    return head not in NON_RESULT_KEYS and head not in _NON_RESULT_GROUPS \
        and head not in ("hydra", DATA_FILES) and key not in ("experiment", "experiment_name", "study")


def _run_choices() -> dict | None:
    """The config-group choices of the run being started: :func:`study`'s, or Hydra's (torchmm-run)."""
    choices = RUN_CHOICES.get()
    if choices is not None:
        return choices
    try:
        from hydra.core.hydra_config import HydraConfig
        from omegaconf import OmegaConf

        if HydraConfig.initialized():
            return {str(k): v for k, v in OmegaConf.to_container(HydraConfig.get().runtime.choices).items()}
    except Exception as err:  # noqa: BLE001 - no Hydra run: choices are inferred
        log.debug("no Hydra choices (%s); they are inferred", err)
    return None


def config_changes(config: dict, choices: dict | None = None) -> dict | None:
    """What a run's resolved ``config`` changes from its study's defaults (the config composed with
    ``experiment=<name>`` alone): ``{"experiment", "choices": {group: [default, value]}, "keys":
    {dotted key: [default, value]}}``, result keys only (not :data:`experiments.folders.NON_RESULT_KEYS`).

    ``choices``: the run's config-group choices (Hydra's ``runtime.choices``); by default
    :func:`study`'s or the running ``torchmm-run``'s; without them a group whose subtree differs is
    matched against its options in conf/. None when the defaults cannot be composed (a study that is
    not in conf/experiment).
    """
    try:
        return _config_changes(config, choices)
    except Exception as err:  # noqa: BLE001 - results.md is written without the section, the run goes on
        log.warning("results.md: cannot compare the config with the study's defaults (%s)", err)
        return None


def _config_changes(config: dict, choices: dict | None) -> dict | None:
    if choices is None:
        choices = _run_choices()
    experiment = (choices or {}).get("experiment") or config.get("experiment_name")
    if not experiment or not (Path(CONFIG_DIR) / "experiment" / f"{experiment}.yaml").is_file():
        return None
    from omegaconf import OmegaConf

    from experiments.report import flatten

    default_cfg, default_choices = compose_conf([f"experiment={experiment}"])
    defaults = OmegaConf.to_container(default_cfg, resolve=True)
    ours = json.loads(json.dumps(config, default=str))
    defaults = json.loads(json.dumps(defaults, default=str))
    flat, flat_default = flatten(ours), flatten(defaults)
    keys = {}
    nodes = {k.rsplit(".", i)[0] for k in (*flat, *flat_default) for i in range(1, k.count(".") + 1)}
    for key in sorted(set(flat) | set(flat_default)):
        if (key in flat) != (key in flat_default) and key in nodes:
            continue  # a null node given a value (or the reverse): its keys are listed
        if _relevant(key) and not (key in flat and key in flat_default and flat[key] == flat_default[key]):
            keys[key] = [flat_default.get(key), flat.get(key)]
    if choices is None:
        choices = _infer_choices(ours, defaults, default_choices, experiment)
    changed = {g: [default_choices.get(g), c] for g, c in sorted(choices.items())
               if _relevant(g) and "@" not in g and c != default_choices.get(g)}
    return {"experiment": experiment, "choices": changed, "keys": keys}


def _infer_choices(config: dict, defaults: dict, default_choices: dict, experiment: str) -> dict:
    """The choices of the groups whose subtree differs from the defaults, found by composing each option."""
    from omegaconf import OmegaConf

    choices = dict(default_choices)
    for group, default in default_choices.items():
        if "/" in group or "@" in group or not _relevant(group) or group not in config \
                or config.get(group) == defaults.get(group):
            continue
        for option in sorted(p.stem for p in (Path(CONFIG_DIR) / group).glob("*.yaml")):
            if option == default:
                continue
            try:
                cfg, _ = compose_conf([f"experiment={experiment}", f"{group}={option}"])
                subtree = OmegaConf.to_container(cfg[group], resolve=True)
            except Exception as err:  # noqa: BLE001 - an option that does not compose with this study
                log.debug("%s=%s does not compose with %s (%s)", group, option, experiment, err)
                continue
            if json.loads(json.dumps(subtree, default=str)) == config.get(group):
                choices[group] = option
                break
    return choices

"""Every study key has one source of truth (issue 30: 229 of 278 YAML keys were declared again, with
defaults, in experiments/schemas.py, and some of those defaults already disagreed with the YAML).

A key the YAML sets has its value there only: the schema field that types and ranges it has no
default (``omegaconf.MISSING``), so a value cannot be declared twice or disagree. A schema field the
YAML does not set (an optional block such as compare's ``learn``, a constructor option) has its
default in the schema only. A study without a schema declares its keys in its YAML alone
(tests/experiments/test_new_study.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import MISSING, OmegaConf

from experiments import schemas
from experiments.config import Common
from experiments.run import CONFIG_DIR

EXPERIMENTS = sorted(p.stem for p in (Path(CONFIG_DIR) / "experiment").glob("*.yaml"))


def _default(f: dataclasses.Field):
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return MISSING


def _twice(cls, data: dict, prefix: str = "") -> list[str]:
    """The keys of ``data`` (a study's composed YAML) whose schema field in ``cls`` also has a value."""
    out = []
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        key = f"{prefix}{f.name}"
        default = _default(f)
        if dataclasses.is_dataclass(default):  # a section: its own fields
            if isinstance(data[f.name], dict):
                out += _twice(type(default), data[f.name], key + ".")
        elif default is not MISSING:
            out.append(f"{key} (schema default {default!r}, YAML {data[f.name]!r})")
    return out


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_no_key_has_a_value_in_both_the_yaml_and_the_schema(name):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("config", overrides=[f"experiment={name}"])
    data = OmegaConf.to_container(cfg, resolve=True)
    common = {f.name for f in dataclasses.fields(Common)}
    twice = _twice(Common, {k: v for k, v in data.items() if k in common and not isinstance(v, dict)})
    entry = schemas.STUDIES.get(data["study"])
    if entry is not None:
        own = {f.name for f in dataclasses.fields(entry[0])}
        twice += _twice(entry[0], {k: v for k, v in data.items() if k in own})
    assert not twice, f"{name}: declared in the YAML and again with a default in the schema: {twice}"

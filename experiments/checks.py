"""The primitives of typed study configs: :class:`ConfigError` (one line naming the key), field
specs with range checks (:func:`spec` and the checks), and :func:`merge` (a config section into its
dataclass, with OmegaConf's type conversion and every field's check).

:mod:`experiments.schemas` types the studies' keys with them and :mod:`experiments.config`
validates whole configs; this module imports neither.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import field
from pathlib import Path
from typing import Any, Callable, Optional

from omegaconf import OmegaConf
from omegaconf.errors import (
    ConfigAttributeError,
    ConfigKeyError,
    MissingMandatoryValue,
    OmegaConfBaseException,
)

__all__ = ["NO_VALUE", "Check", "ConfigError", "both", "build_error", "check_fields", "device_name", "each",
           "join_key", "matrix", "merge", "node_key", "non_empty", "non_finite_entry", "non_negative",
           "one_of",
           "open_probability", "positive", "positive_int", "probability", "resume_value", "schema_at", "seed_value",
           "show_value", "spec", "type_message"]


class ConfigError(ValueError):
    """A user error in a study config: ``key=value: what is allowed`` (one line)."""

    def __init__(self, key: str, value: Any, allowed: str):
        self.key, self.value, self.allowed = key, value, allowed
        shown = "" if value is NO_VALUE else f"={show_value(value)}"
        super().__init__(f"{key}{shown}: {allowed}")


NO_VALUE = object()


def show_value(value: Any) -> str:
    if isinstance(value, str):
        return value
    if isinstance(value, float) and value.is_integer():
        return repr(value)
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


# -- field checks ------------------------------------------------------------------------------
Check = Callable[[Any], Optional[str]]


def spec(default: Any = dataclasses.MISSING, check: Check | None = None, *, factory=None,
         finite: bool = True):
    """A schema field with an optional range check ``check(value) -> error text | None``; ``finite=False``:
    a list whose non-finite numbers its study's own check names (not :func:`check_fields`)."""
    kwargs: dict = {"metadata": {"check": check, "finite": finite}}
    if factory is not None:
        kwargs["default_factory"] = factory
    elif default is not dataclasses.MISSING:
        kwargs["default"] = default
    return field(**kwargs)


def positive(value) -> str | None:
    return None if value is None or value > 0 else "must be positive"


def positive_int(value) -> str | None:
    return None if value is None or value >= 1 else "must be a positive integer"


def non_negative(value) -> str | None:
    return None if value is None or value >= 0 else "must be non-negative"


def probability(value) -> str | None:
    return None if value is None or 0 <= value <= 1 else "must be a probability in [0, 1]"


def open_probability(value) -> str | None:
    return None if value is None or 0 < value < 1 else "must lie in (0, 1)"


def one_of(*choices: str) -> Check:
    def check(value):
        return None if value is None or value in choices else f"expected one of {', '.join(choices)}"
    return check


def each(check: Check) -> Check:
    """Apply ``check`` to every element of a list."""
    def run(values):
        for v in values or []:
            error = check(v)
            if error:
                return f"entry {show_value(v)}: {error}"
        return None
    return run


def matrix(value) -> str | None:
    """A list of rows of numbers (typed ``List[Any]``: OmegaConf rejects ints in nested float lists)."""
    if value is None:
        return None
    if not isinstance(value, list) or not all(isinstance(row, list) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in row) for row in value):
        return "expected a matrix: a list of rows of numbers"
    return None


def non_empty(values) -> str | None:
    return None if values is None or len(values) else "must not be empty"


def both(*checks: Check) -> Check:
    def run(value):
        for check in checks:
            error = check(value)
            if error:
                return error
        return None
    return run


def device_name(value) -> str | None:
    import torch

    if value == "auto":
        return None
    try:
        device = torch.device(value)
    except (RuntimeError, TypeError):
        return "expected cpu, cuda, cuda:<index> or auto"
    if device.type not in ("cpu", "cuda"):
        return "expected cpu, cuda, cuda:<index> or auto"
    if device.type == "cuda" and not torch.cuda.is_available():
        return "CUDA is not available on this machine (torch.cuda.is_available() is False); use device=cpu"
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        return f"this machine has {torch.cuda.device_count()} CUDA device(s)"
    return None


def seed_value(value) -> str | None:
    return None if 0 <= value < 2**63 else "must be an integer in [0, 2^63)"


def resume_value(value) -> str | None:
    if value is None or value == "latest" or Path(str(value)).is_dir():
        return None
    return "expected latest or an existing run folder"



def _strict(schema: type, values: Any, prefix: str) -> None:
    """No coercion of a string into a flag or a number: OmegaConf would check ``figures=no`` as False
    while the run's config keeps the string ``'no'``, which Python reads as true. A string where the
    schema has ``bool``, ``int`` or ``float`` is a ConfigError (``expected true or false``)."""
    import typing

    if not isinstance(values, dict) or not dataclasses.is_dataclass(schema):
        return
    try:
        hints = typing.get_type_hints(schema)
    except Exception:  # noqa: BLE001 - an unresolvable annotation: OmegaConf's own checks only
        return
    for f in dataclasses.fields(schema):
        if f.name not in values:
            continue
        raw, kind = values[f.name], hints.get(f.name)
        args = [a for a in typing.get_args(kind) if a is not type(None)] if typing.get_origin(kind) is typing.Union \
            else [kind]
        base = args[0] if len(args) == 1 else None
        key = join_key(prefix, f.name)
        if base in (bool, int, float) and isinstance(raw, str):
            raise ConfigError(key, raw, {bool: "expected true or false", int: "expected an integer",
                                         float: "expected a number"}[base])
        if base is bool and raw is not None and not isinstance(raw, bool):
            raise ConfigError(key, raw, "expected true or false")
        if dataclasses.is_dataclass(base):
            if raw is not None and not isinstance(raw, dict):
                raise ConfigError(key, raw, f"expected a mapping of {', '.join(x.name for x in dataclasses.fields(base))}")
            _strict(base, raw, key)
        elif typing.get_origin(base) in (list, typing.List) and isinstance(raw, list):
            inner = typing.get_args(base)[0] if typing.get_args(base) else None
            for i, item in enumerate(raw):
                if dataclasses.is_dataclass(inner):
                    _strict(inner, item, f"{key}[{i}]")


def merge(schema: type, values: dict, prefix: str = "") -> Any:
    """``values`` merged into ``schema`` and converted to the dataclass (type errors: ConfigError)."""
    _strict(schema, values, prefix)
    try:
        merged = OmegaConf.merge(OmegaConf.structured(schema), values)
        obj = OmegaConf.to_object(merged)
    except (ConfigKeyError, ConfigAttributeError) as err:
        key = join_key(prefix, str(err.full_key or err.key))
        known = [f.name for f in dataclasses.fields(schema_at(schema, str(err.full_key or "")))]
        leaf = key.rsplit(".", 1)[-1]
        close = difflib.get_close_matches(leaf, known, n=1)
        hint = f"; did you mean {close[0]}?" if close else f" (known: {', '.join(known)})"
        raise ConfigError(key, NO_VALUE, f"unknown key{hint}") from None
    except MissingMandatoryValue as err:
        raise ConfigError(join_key(prefix, str(err.full_key)), NO_VALUE, "missing (a required key)") from None
    except OmegaConfBaseException as err:
        key = join_key(prefix, str(err.full_key or err.key))
        raise ConfigError(key, err.value if err.value is not None else NO_VALUE, type_message(err)) from None
    check_fields(obj, prefix)
    return obj


def schema_at(schema: type, path: str) -> type:
    """The dataclass of the node that holds ``path``'s last key."""
    parts = [p for p in path.split(".")[:-1] if p]
    for part in parts:
        fields = {f.name: f for f in dataclasses.fields(schema)}
        if part not in fields or not dataclasses.is_dataclass(fields[part].type if isinstance(fields[part].type, type)
                                                              else None):
            break
        schema = fields[part].type
    return schema


def type_message(err: OmegaConfBaseException) -> str:
    msg = str(err.msg).splitlines()[0]
    for word, text in (("Integer", "expected an integer"), ("Float", "expected a number"),
                       ("valid bool", "expected true or false"), ("String", "expected a string"),
                       ("not a ListConfig", "expected a list"), ("not a DictConfig", "expected a mapping"),
                       ("not a subclass of", "expected a mapping of the section's keys")):
        if word in msg:
            return text
    return msg


def build_error(key: str, node: Any, err: BaseException, aliases: dict | None = None) -> ConfigError:
    """The one-line :class:`ConfigError` for ``err``, raised while building the config node at ``key``
    (a mapping of the constructor's keywords) before anything runs (:func:`experiments.config.dry_build`).

    A constructor names the argument it refuses first (``mode: 7 is not one of the scenario's 3 modes``):
    when that name is one of the node's keys, or is mapped to one by ``aliases`` (the library argument ->
    the node's key, e.g. ``{"Q_eta": "eta_std"}``), the error names that key and its value; otherwise
    the node itself "cannot be built", with the constructor's first line. A :class:`ConfigError` (and
    one that Hydra's ``InstantiationException`` wraps) is returned as it is."""
    cause = err
    if type(err).__name__ == "InstantiationException" and err.__cause__ is not None:
        cause = err.__cause__
    if isinstance(cause, ConfigError):
        return cause
    lines = str(cause).strip().splitlines()
    first = lines[0] if lines else type(cause).__name__
    head, sep, rest = first.partition(": ")
    head = head[len(key) + 1:] if head.startswith(f"{key}.") else head  # (a message naming the full key)
    name = (aliases or {}).get(head, head)
    path = node_key(node, name) if sep and rest and hasattr(node, "keys") else None
    if path is not None:
        value = OmegaConf.select(node, path) if OmegaConf.is_config(node) else _nested(node, path)
        value = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
        shown = show_value(value)
        rest = rest[len(shown) + 1:] if rest.startswith(f"{shown} ") else rest
        return ConfigError(join_key(key, path), value, rest)
    target = node.get("_target_") if hasattr(node, "get") else None
    return ConfigError(key, target if target else NO_VALUE, f"cannot be built: {first}")


def node_key(node: Any, name: str) -> str | None:
    """The dotted path in the mapping ``node`` of the key a constructor names: ``name`` itself when it is
    one of the node's keys, else the one path whose last parts are ``name``'s (``policy.members`` is
    ``combinator.policy.members`` of an estimator node); None when there is none or more than one."""
    if name in node:
        return name
    parts, found = name.split("."), []

    def walk(sub, prefix):
        for k in list(sub.keys()):
            path = [*prefix, str(k)]
            if path[-len(parts):] == parts:
                found.append(".".join(path))
            try:
                child = sub[k]
            except OmegaConfBaseException:  # (a value that does not resolve: not searched)
                continue
            if hasattr(child, "keys"):
                walk(child, path)

    walk(node, [])
    return found[0] if len(found) == 1 else None


def _nested(node: Any, path: str) -> Any:
    for part in path.split("."):
        node = node[part]
    return node


def join_key(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def non_finite_entry(values: Any, key: str) -> tuple[str, float] | None:
    """The first NaN or infinite number of a (nested) list, with its key (``key[i][j]``); None if none."""
    for i, v in enumerate(values):
        if isinstance(v, (list, tuple)):
            found = non_finite_entry(v, f"{key}[{i}]")
            if found:
                return found
        elif isinstance(v, float) and not math.isfinite(v):
            return f"{key}[{i}]", v
    return None


def check_fields(obj: Any, prefix: str) -> None:
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        key = join_key(prefix, f.name)
        if isinstance(value, (list, tuple)) and f.metadata.get("finite", True):  # every number finite, first
            found = non_finite_entry(value, key)
            if found:
                raise ConfigError(found[0], found[1], "must be finite")
        check = f.metadata.get("check")
        if check is not None:
            error = check(value)
            if error:
                raise ConfigError(key, value, error)
        if dataclasses.is_dataclass(value):
            check_fields(value, key)
        elif isinstance(value, dict):
            for k, v in value.items():
                if dataclasses.is_dataclass(v):
                    check_fields(v, f"{key}.{k}")
        elif isinstance(value, (list, tuple)):  # a list of typed entries (e.g. learn.parameters)
            for i, v in enumerate(value):
                if dataclasses.is_dataclass(v):
                    check_fields(v, f"{key}[{i}]")
        elif isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(key, value, "must be finite")
    relation = getattr(obj, "config_check", None)
    if relation is not None:
        problem = relation()  # a check across fields: (key, value, message) or None
        if problem:
            raise ConfigError(join_key(prefix, problem[0]), problem[1], problem[2])

"""A study from Python: ``study("imm_baseline", mc_runs=20)`` runs what ``torchmm-run`` runs.

::

    from experiments import study, load

    res = study("imm_baseline", mc_runs=20, mode_filter="unscented", scenario__R=25, progress=False)
    res.table("rmse")          # a pandas DataFrame (a list of dicts without pandas)
    res.figures                # [Path(".../figures/rmse_over_time.png"), ...]
    again = load(res.dir)      # a finished run folder, read back

**Overrides** are the command line's ``key=value`` as keyword arguments: ``mc_runs=20``,
config groups by their option name (``mode_filter="unscented"``, ``debug="imm_baseline"``), nested
keys with a double underscore (``scenario__R=25`` is ``scenario.R=25``). ``overrides=`` takes the
same as a dict with dotted keys (``{"scenario.R": 25}``) or a list of Hydra override strings
(``["scenario.R=25", "+new_key=1"]``); the keyword arguments come after it. Python values are
written in Hydra's syntax (``True`` -> ``true``, ``None`` -> ``null``, lists -> ``[a,b]``).

The config is composed from conf/ as ``torchmm-run`` composes it, then checked by
:func:`experiments.config.validate`: a bad key or value raises
:class:`~experiments.config.ConfigError` (a ``ValueError`` naming the key) before anything is
written. The run goes to ``out`` (default: a fresh ``outputs/<experiment>/<date>_<time>`` under the
working directory, as the command line's) through :func:`experiments.run.run_study`; its
``results.json`` records the equivalent ``torchmm-run`` command line under ``provenance.command``
(and the Python process's own under ``provenance.process_command``).

:func:`config_changes` is what ``results.md`` opens with: the result keys and config-group choices
of a run that differ from its study's defaults (the config composed with ``experiment=<name>``
alone).
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from experiments.changes import RUN_CHOICES, compose_conf, config_changes
from experiments.paths import CONFIG_DIR

__all__ = ["StudyResults", "config_changes", "load", "study"]

log = logging.getLogger("torchmm.experiments")


# --------------------------------------------------------------------------------------------- config

def _override_value(value: Any) -> str:
    """``value`` in Hydra's override syntax."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, Path):
        value = str(value)
    if isinstance(value, str):
        if re.fullmatch(r"[A-Za-z0-9_./\-+:@]+", value):
            return value
        return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_override_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{" + ",".join(f"{k}:{_override_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"expected a number, string, bool, None, list or dict, got {type(value).__name__}")


def _override(key: str, value: Any) -> str:
    """``key=value`` in Hydra's override syntax; a value that has none is a
    :class:`~experiments.config.ConfigError` naming the key (``mc_runs=<object ...>: expected ...``)."""
    try:
        return f"{key}={_override_value(value)}"
    except TypeError as err:
        from experiments.config import ConfigError

        raise ConfigError(key, value, str(err)) from None


def _override_list(overrides: Mapping[str, Any] | Sequence[str] | None, kwargs: Mapping[str, Any]) -> list[str]:
    """The Hydra override strings of ``overrides=`` and the keyword arguments (``a__b`` -> ``a.b``)."""
    items: list[str] = []
    if overrides is None:
        pass
    elif isinstance(overrides, Mapping):
        for key, value in overrides.items():
            if not isinstance(key, str) or not key:
                raise TypeError(f"overrides: keys must be non-empty strings, got {key!r}")
            items.append(_override(key, value))
    elif isinstance(overrides, (list, tuple)):
        for item in overrides:
            if not isinstance(item, str) or "=" not in item:
                raise ValueError(f"overrides: expected 'key=value' strings, got {item!r}")
            items.append(item)
    else:
        raise TypeError(f"overrides: expected a dict or a list of 'key=value' strings, got {type(overrides).__name__}")
    for key, value in kwargs.items():
        items.append(_override(key.replace("__", "."), value))
    for item in items:
        if item.lstrip("+~").split("=", 1)[0] in ("experiment", "hydra") or item.startswith("hydra."):
            raise ValueError(f"overrides: {item.split('=', 1)[0]} is not an override here: the study is the "
                             "first argument, the run folder is out=")
    return items




# --------------------------------------------------------------------------------------------- results

class StudyResults:
    """A finished run folder: its ``results.json``, tables, figures and ``results.md``.

    ``dir`` (Path), ``json`` (the results.json dict), ``tables`` (names), ``table(name)``,
    ``metrics``, ``config``, ``figures`` (image files under ``figures/``), ``markdown`` (results.md);
    shown as its results.md in a notebook.
    """

    def __init__(self, run_dir: str | Path):
        self.dir = Path(run_dir)
        self._json: dict | None = None

    @property
    def json(self) -> dict:
        if self._json is None:
            if not self.dir.exists():
                raise ValueError(f"run_dir: {self.dir} does not exist")
            if not self.dir.is_dir():
                raise ValueError(f"run_dir: {self.dir} is a file, not a run folder (give the folder holding "
                                 "results.json)")
            file = self.dir / "results.json"
            try:
                data = json.loads(file.read_text())
            except FileNotFoundError:
                raise ValueError(f"run_dir: {self.dir} holds no results.json (not a finished run)") from None
            except OSError as err:
                raise ValueError(f"run_dir: {file} cannot be read ({err.strerror or type(err).__name__})") from None
            except ValueError as err:  # JSONDecodeError, UnicodeDecodeError
                raise ValueError(f"run_dir: {file} is not a results file ({type(err).__name__}: {err})") from None
            problem = _results_problem(data)
            if problem:
                raise ValueError(f"run_dir: {file}: not a results file ({problem})")
            self._json = data
        return self._json

    @property
    def experiment(self) -> str:
        return str(self.json.get("experiment", "study"))

    @property
    def config(self) -> dict:
        return self.json.get("config") or {}

    @property
    def tables(self) -> list[str]:
        return list(self.json.get("tables") or {})

    @property
    def metrics(self) -> dict:
        return self.json.get("metrics") or {}

    def table(self, name: str):
        """The table ``name``: a pandas DataFrame if pandas is installed, else a list of row dicts."""
        tables = self.json.get("tables") or {}
        if name not in tables:
            raise KeyError(f"table {name!r}: not in {self.dir / 'results.json'}; tables: {', '.join(tables) or 'none'}")
        columns, rows = tables[name]["columns"], tables[name]["rows"]
        try:
            import pandas as pd
        except ImportError:
            return [dict(zip(columns, row)) for row in rows]
        return pd.DataFrame(rows, columns=columns)

    @property
    def figures(self) -> list[Path]:
        folder = self.dir / "figures"
        return sorted(p for p in folder.rglob("*") if p.suffix in (".png", ".pdf", ".svg")) if folder.is_dir() else []

    @property
    def markdown(self) -> str:
        file = self.dir / "results.md"
        return file.read_text() if file.exists() else ""

    def _repr_markdown_(self) -> str:
        return f"*{self.dir}*\n\n" + self.markdown

    def __repr__(self) -> str:
        return f"StudyResults({self.experiment!r}, dir={str(self.dir)!r}, tables={self.tables})"


def _results_problem(data: Any) -> str:
    """What keeps ``data`` from being a results.json (experiments.results.Results.to_json), or ''."""
    if not isinstance(data, dict):
        return f"a JSON {type(data).__name__}, not an object"
    missing = [key for key in ("experiment", "tables") if key not in data]
    if missing:
        return "no " + ", ".join(repr(key) for key in missing)
    for key in ("tables", "config", "metrics", "timing", "provenance"):
        if data.get(key) is not None and not isinstance(data[key], dict):
            return f"{key}: {type(data[key]).__name__}, not an object"
    for name, table in data["tables"].items():
        columns = table.get("columns") if isinstance(table, dict) else None
        rows = table.get("rows") if isinstance(table, dict) else None
        if not isinstance(columns, list) or not isinstance(rows, list) or not all(
                isinstance(row, list) and len(row) == len(columns) for row in rows):
            return f"table {name!r}: expected columns and rows of as many cells"
    return ""


def load(run_dir: str | Path) -> StudyResults:
    """A finished run folder (holding ``results.json``) as :class:`StudyResults`.

    Raises:
        ValueError naming ``run_dir`` and the path: it does not exist, is a file, holds no
        results.json, or one that is not a results object (``{"experiment", "tables", ...}``, with
        tables of columns and rows).
        TypeError: ``run_dir`` is not a path.
    """
    if not isinstance(run_dir, (str, Path)):
        raise TypeError(f"run_dir: expected a path, got {type(run_dir).__name__}")
    results = StudyResults(run_dir)
    results.json  # noqa: B018 - a folder without results.json is a ValueError now, not later
    return results


def study(name: str, *, out: str | Path | None = None, overrides: Mapping[str, Any] | Sequence[str] | None = None,
          **kwargs: Any) -> StudyResults:
    """Run the study ``name`` (a conf/experiment/*.yaml) with overrides; see the module docstring.

    ``out``: the run folder (default ``outputs/<experiment>/<date>_<time>``, made fresh). A folder
    holding a run of another result config is kept and the run goes to a fresh sibling (the
    returned ``.dir``), as with ``torchmm-run hydra.run.dir=...``.
    """
    from experiments.config import validate
    from experiments.folders import unique_dir
    from experiments.run import run_study

    if not isinstance(name, str) or not name:
        raise TypeError(f"name: expected a study name (conf/experiment/*.yaml), got {name!r}")
    if not (Path(CONFIG_DIR) / "experiment" / f"{name}.yaml").is_file():
        known = sorted(p.stem for p in (Path(CONFIG_DIR) / "experiment").glob("*.yaml"))
        raise ValueError(f"name: no study {name!r}; choose one of {', '.join(known)}")
    if out is not None and not isinstance(out, (str, Path)):
        raise TypeError(f"out: expected a folder path, got {type(out).__name__}")
    if out is not None and Path(out).exists() and not Path(out).is_dir():
        raise ValueError(f"out: {out} is a file, not a folder (the run's results go into a folder)")
    items = _override_list(overrides, kwargs)
    cfg, choices = compose_conf([f"experiment={name}", *items])
    validate(cfg, scenario_choice=choices.get("scenario"), overrides=items)
    if out is None:
        stamp = _dt.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
        out = unique_dir(str(Path("outputs") / str(cfg.get("experiment_name", name)) / stamp))
    token = RUN_CHOICES.set(choices)
    try:
        results = run_study(cfg, Path(out), overrides=items)
    finally:
        RUN_CHOICES.reset(token)
    command = " ".join(["torchmm-run", f"experiment={name}", *items])
    if results.provenance.get("command") != command:  # the equivalent command line, not the Python process's
        results.provenance["process_command"] = results.provenance.get("command")
        results.provenance["command"] = command
        results.save()
    return StudyResults(results.output_dir)

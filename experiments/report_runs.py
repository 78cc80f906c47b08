"""The runs of ``torchmm-report`` (:mod:`experiments.report`): every ``results.json`` under the paths
given, read and checked (:func:`collect_runs`), and the runs it cannot report, each named with why
(:class:`LeftOut`: an interrupted or failed run, a sweep's job that never started); split from the
command's module by concern."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from experiments.folders import NON_RESULT_KEYS

__all__ = ["IGNORED_KEYS", "LeftOut", "ResultsFileError", "Run", "attach_left_out", "collect_runs", "flatten",
           "sweep_jobs"]

#: keys never treated as factors (they do not change the numbers, or are bookkeeping)
IGNORED_KEYS = (*NON_RESULT_KEYS, "hydra")


@dataclass
class Run:
    """One finished study run: its folder, its results.json and its (flattened) result config."""

    path: Path
    results: dict
    overrides: list[str] = field(default_factory=list)

    @property
    def experiment(self) -> str:
        return str(self.results.get("experiment", "study"))

    @property
    def config(self) -> dict[str, Any]:
        return flatten({k: v for k, v in (self.results.get("config") or {}).items() if k not in IGNORED_KEYS})


def flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """A nested config as ``{dotted key: value}`` (lists are values)."""
    if isinstance(tree, dict):
        out: dict[str, Any] = {}
        for key, value in tree.items():
            out.update(flatten(value, f"{prefix}.{key}" if prefix else str(key)))
        return out
    if isinstance(tree, list):  # compare and display lists as one value
        return {prefix: json.dumps(tree, sort_keys=True, default=str)}
    return {prefix: tree}


class ResultsFileError(ValueError):
    """A ``results.json`` that cannot be read or is not a results file: one line naming it."""


def _check_results(data: Any, file: Path) -> dict:
    """``data`` if it has the shape :func:`combine` reads (docs/studies.md), else
    :class:`ResultsFileError`."""
    def bad(what: str):
        return ResultsFileError(f"{file}: not a results file ({what}); remove it or report the other runs")

    if not isinstance(data, dict):
        raise bad(f"a JSON {type(data).__name__}, not an object")
    if not isinstance(data.get("config") or {}, dict) or not isinstance(data.get("tables") or {}, dict):
        raise bad("config and tables must be objects")
    for name, table in (data.get("tables") or {}).items():
        columns = table.get("columns") if isinstance(table, dict) else None
        rows = table.get("rows") if isinstance(table, dict) else None
        if not isinstance(columns, list) or not isinstance(rows, list) or not all(
                isinstance(row, list) and len(row) == len(columns) for row in rows):
            raise bad(f"table {name}: expected columns and rows of as many cells")
    return data


@dataclass
class LeftOut:
    """A run the report cannot hold, and why: ``path`` (a run folder, or a sweep folder for its jobs that
    never started), ``reason`` (one phrase), the study it belongs to where its files say (else None) and
    the number of ``runs`` it stands for."""

    path: Path
    reason: str
    experiment: str | None = None
    #: how many runs it stands for (a sweep folder: its jobs that never started)
    runs: int = 1


def collect_runs(paths: list[Path], left_out: list[LeftOut] | None = None) -> list[Run]:
    """Every finished run under ``paths`` (a folder holding ``results.json``, or any folder above such
    ones). A ``results.json`` that cannot be read or is not a results file is a :class:`ResultsFileError`
    naming it. A run that did not finish is never left out silently: ``left_out`` (a list) gets a
    :class:`LeftOut` for each run folder (with ``.hydra/`` or ``checkpoint.json``) without a finished
    ``results.json`` - interrupted or failed; a ``results.json`` written before its study ended (a
    ``provenance`` without ``end``: studies that rewrite it after each unit) is such a run too - and for
    each sweep folder whose ``multirun.yaml`` names jobs without a folder (:func:`sweep_jobs`); without
    ``left_out`` each is a warning on stderr."""
    found: dict[Path, None] = {}
    searched: list[Path] = []
    for path in map(Path, paths):
        if not path.exists():
            raise FileNotFoundError(f"PATH: {path} does not exist")
        if path.is_file():
            candidates = [path] if path.name == "results.json" else []
        elif (path / "results.json").exists():
            candidates = [path / "results.json"]
        else:
            candidates = sorted(path.rglob("results.json"))
            searched.append(path)
        for candidate in candidates:
            found[candidate.resolve()] = None
    runs, missed = [], []
    for file in found:
        try:
            results = _check_results(json.loads(file.read_text()), file)
        except OSError as err:
            raise ResultsFileError(f"{file}: cannot read ({err.strerror or type(err).__name__})") from None
        except ValueError as err:  # JSONDecodeError, UnicodeDecodeError: truncated or not JSON
            if isinstance(err, ResultsFileError):
                raise
            raise ResultsFileError(f"{file}: not a results file ({type(err).__name__}: {err})") from None
        provenance = results.get("provenance")
        if isinstance(provenance, dict) and not provenance.get("end"):
            why = (f"interrupted or failed: its results.json was written before the study ended (no "
                   f"provenance end; {_units(file.parent)})")
            missed.append(LeftOut(file.parent, why, _experiment_of(file.parent)))
            continue
        overrides_file = file.parent / ".hydra" / "overrides.yaml"
        overrides = []
        if overrides_file.exists():
            overrides = [line[2:].strip() for line in overrides_file.read_text().splitlines()
                         if line.startswith("- ")]
        runs.append(Run(file.parent, results, overrides))
    missed += _unfinished_folders(searched, {f.parent for f in found})
    if left_out is None:
        for item in missed:
            print(f"torchmm-report: warning: {item.path}: left out: {item.reason}", file=sys.stderr)
    else:
        left_out.extend(missed)
    return runs


def _units(folder: Path) -> str:
    """How many finished units ``folder``'s checkpoint.json holds, as a phrase."""
    try:
        units = json.loads((folder / "checkpoint.json").read_text()).get("units")
    except FileNotFoundError:
        return "no checkpoint.json"
    except (OSError, ValueError, AttributeError) as err:
        return f"its checkpoint.json cannot be read ({type(err).__name__})"
    return f"checkpoint.json holds {len(units) if isinstance(units, dict) else 0} finished unit(s)"


def _experiment_of(folder: Path) -> str | None:
    """The study of a run folder, from its checkpoint.json's config or Hydra's .hydra/config.yaml."""
    try:
        checkpoint = json.loads((folder / "checkpoint.json").read_text())
        name = (checkpoint.get("config") or {}).get("experiment_name")
        if name is not None:
            return str(name)
    except (OSError, ValueError, AttributeError):
        pass
    try:
        name = (yaml.safe_load((folder / ".hydra" / "config.yaml").read_text()) or {}).get("experiment_name")
        return None if name is None else str(name)
    except (OSError, ValueError, AttributeError, yaml.YAMLError):
        return None


def _unfinished_folders(searched: list[Path], finished: set[Path]) -> list[LeftOut]:
    """The run folders under ``searched`` without a results.json, and the sweeps' jobs that never started."""
    out: list[LeftOut] = []
    folders: dict[Path, None] = {}
    for root in searched:
        for marker in (*root.rglob(".hydra"), *root.rglob("checkpoint.json")):
            folders[marker.parent.resolve()] = None
    for folder in sorted(folders):
        if folder not in finished and not (folder / "results.json").exists():
            out.append(LeftOut(folder, f"interrupted or failed: no results.json ({_units(folder)})",
                               _experiment_of(folder)))
    for record in sorted({r.resolve() for root in searched for r in root.rglob("multirun.yaml")}):
        jobs = sweep_jobs(record)
        if jobs is None:
            continue
        started = set()
        for job in record.parent.glob("*/.hydra/hydra.yaml"):
            num = _job_num(job)
            if num is not None:
                started.add(num)
        missing = [n for n in range(jobs) if n not in started]
        if missing:
            shown = ", ".join(map(str, missing[:10])) + (", ..." if len(missing) > 10 else "")
            names = {_experiment_of(job.parent.parent) for job in record.parent.glob("*/.hydra/hydra.yaml")}
            why = f"{len(missing)} of the {jobs} jobs of its multirun.yaml never started (no folder: job "
            experiment = next(iter(names)) if len(names) == 1 else None
            out.append(LeftOut(record.parent, why + f"{shown})", experiment, len(missing)))
    return out


def _job_num(hydra_yaml: Path) -> int | None:
    try:
        num = ((yaml.safe_load(hydra_yaml.read_text()) or {}).get("hydra") or {}).get("job", {}).get("num")
        return int(num)
    except (OSError, ValueError, TypeError, AttributeError, yaml.YAMLError):
        return None


def sweep_jobs(record: Path) -> int | None:
    """How many jobs the sweep of ``record`` (a ``multirun.yaml``) has: the product of the numbers of
    values of its sweep overrides (``seed=0,1,2``, ``range(...)``, ``choice(...)``; command line and
    ``hydra.sweeper.params``), or None where it cannot be counted (``glob(...)``, an unreadable file)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:

        hydra = (yaml.safe_load(record.read_text()) or {}).get("hydra") or {}
        task = list((hydra.get("overrides") or {}).get("task") or [])
        params = (hydra.get("sweeper") or {}).get("params") or {}
        task += [f"{key}={value}" for key, value in params.items()]
        jobs = 1
        for override in OverridesParser.create().parse_overrides(task):
            if override.is_sweep_override():
                jobs *= len(list(override.sweep_iterator()))
        return jobs
    except (OSError, ValueError, AttributeError, TypeError, yaml.YAMLError, HydraException):
        return None


def attach_left_out(report: dict[str, Any], left_out: list[LeftOut], empty: dict[str, Any]) -> None:
    """Put each :class:`LeftOut` into ``report`` (:func:`experiments.report.combine`'s) as its study's
    ``left_out`` list of ``{"path", "reason", "runs"}`` - a study with no finished run gets a body ``empty``
    (no groups, no tables) to hold it; one whose study is not known goes to the only study, else to
    ``"(unknown study)"``."""
    for item in left_out:
        name = item.experiment
        if name is None:
            name = next(iter(report)) if len(report) == 1 else "(unknown study)"
        body = report.setdefault(name, json.loads(json.dumps(empty)))
        entry = {"path": str(item.path), "reason": item.reason, "runs": item.runs}
        body.setdefault("left_out", []).append(entry)

"""The runs of ``torchmm-report`` (:mod:`experiments.report`): every ``results.json`` under the paths
given, read and checked (:func:`collect_runs`); split from the command's module by concern."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from experiments.folders import NON_RESULT_KEYS

__all__ = ["IGNORED_KEYS", "ResultsFileError", "Run", "collect_runs", "flatten"]

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


def collect_runs(paths: list[Path]) -> list[Run]:
    """Every run under ``paths`` (a folder holding ``results.json``, or any folder above such ones).
    A ``results.json`` that cannot be read or is not a results file is a :class:`ResultsFileError`
    naming it: a report never leaves out a run silently."""
    found: dict[Path, None] = {}
    for path in map(Path, paths):
        if not path.exists():
            raise FileNotFoundError(f"PATH: {path} does not exist")
        if path.is_file():
            candidates = [path] if path.name == "results.json" else []
        else:
            candidates = [path / "results.json"] if (path / "results.json").exists() else sorted(path.rglob("results.json"))
        for candidate in candidates:
            found[candidate.resolve()] = None
    runs = []
    for file in found:
        try:
            results = _check_results(json.loads(file.read_text()), file)
        except OSError as err:
            raise ResultsFileError(f"{file}: cannot read ({err.strerror or type(err).__name__})") from None
        except ValueError as err:  # JSONDecodeError, UnicodeDecodeError: truncated or not JSON
            if isinstance(err, ResultsFileError):
                raise
            raise ResultsFileError(f"{file}: not a results file ({type(err).__name__}: {err})") from None
        overrides_file = file.parent / ".hydra" / "overrides.yaml"
        overrides = []
        if overrides_file.exists():
            overrides = [line[2:].strip() for line in overrides_file.read_text().splitlines() if line.startswith("- ")]
        runs.append(Run(file.parent, results, overrides))
    return runs

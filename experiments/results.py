"""Study results: ``results.json`` and ``results.md`` (:class:`Results`, :class:`Table`), the
formatting of values in tables and the conversion of tensors and non-finite floats to JSON."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from experiments.files import write_atomic
from experiments.formatting import format_value  # noqa: F401 - re-exported (experiments.results.format_value)


def jsonable(value: Any) -> Any:
    """``value`` as JSON data: tensors as numbers or lists, non-finite floats as None, dict keys as strings."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu()
        return value.item() if value.dim() == 0 else value.tolist()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    return value




@dataclass
class Table:
    columns: list[str]
    rows: list[list[Any]] = field(default_factory=list)
    note: str = ""
    #: optional published values: ``{"columns": [...], "rows": [...], "source": "..."}``
    published: dict | None = None

    def markdown(self) -> str:
        lines = ["| " + " | ".join(self.columns) + " |", "|" + "---|" * len(self.columns)]
        lines += ["| " + " | ".join(format_value(v) for v in row) + " |" for row in self.rows]
        return "\n".join(lines)


class Results:
    """The machine- and human-readable results of one study run.

    ``results.json``: ``{"experiment", "config", "metrics": {estimator: {metric: value}},
    "tables": {name: {"columns", "rows"}}, "timing": {estimator: seconds_per_step},
    "provenance": {versions, git, host, platform, command, start, end, wall_seconds, device, dtype,
    threads, kernels: {name: run_filter calls}, kernels_note, resumes / resumed / replaced (a continued
    run: experiments.provenance.Provenance.continue_from)}, "dropped": {metric: why}}``
    (docs/studies.md). ``dropped`` names every metric that was asked for but cannot be computed from
    the data (no truth, no measurement), with the reason: such a
    metric is never reported as a number.
    """

    def __init__(self, output_dir: Path, experiment: str, config: dict, description: str = ""):
        self.output_dir = output_dir
        self.experiment = experiment
        self.config = config
        self.description = description
        self.metrics: dict[str, dict[str, Any]] = {}
        self.tables: dict[str, Table] = {}
        self.timing: dict[str, float] = {}
        self.notes: list[str] = []
        #: ``{metric (estimator): why}``: metrics asked for that the data cannot give (never a number)
        self.dropped: dict[str, str] = {}
        self.provenance: dict[str, Any] = {}
        #: what the config changes from the study's defaults (:func:`experiments.changes.config_changes`),
        #: set when the run starts; None: not known (results.md then lists no changes)
        self.changes: dict | None = None

    def table(self, name: str, columns: Sequence[str], *, note: str = "", published: dict | None = None) -> Table:
        """Create (or reset) a table; append rows to ``.rows``."""
        self.tables[name] = Table(list(columns), [], note, published)
        return self.tables[name]

    def metric(self, estimator: str, name: str, value: Any) -> None:
        self.metrics.setdefault(estimator, {})[name] = jsonable(value)

    def to_json(self) -> dict:
        return {
            "experiment": self.experiment,
            "config": self.config,
            "metrics": jsonable(self.metrics),
            "tables": {k: {"columns": t.columns, "rows": jsonable(t.rows)} for k, t in self.tables.items()},
            "timing": jsonable(self.timing),
            "provenance": jsonable(self.provenance),
            "dropped": dict(self.dropped),
        }

    @staticmethod
    def _show_value(value: Any) -> str:
        """A config value as written on the command line (``null``, ``true``, lists as JSON)."""
        if value is None:
            return "null"
        if isinstance(value, bool):
            return "true" if value else "false"
        return str(value)

    def _setup_markdown(self) -> list[str]:
        """The command line (``provenance.command``) and every result value that differs from the
        study's defaults (:attr:`changes`), for the top of results.md."""
        out = []
        command = (self.provenance or {}).get("command")
        if command:
            out += ["Command:", "", "```bash", str(command), "```", ""]
        changes = self.changes
        if changes is not None:
            choices, keys = changes.get("choices") or {}, changes.get("keys") or {}
            name = changes.get("experiment", self.experiment)
            if not choices and not keys:
                out += [f"Ran with the defaults of `{name}` (conf/experiment/{name}.yaml).", ""]
            else:
                out += [f"Differs from the defaults of `{name}` (conf/experiment/{name}.yaml) in:", ""]
                out += [f"- `{group}={self._show_value(value)}` (default: {self._show_value(default)})"
                        for group, (default, value) in choices.items()]
                out += [f"- `{key}={self._show_value(value)}` (default: {self._show_value(default)})"
                        for key, (default, value) in keys.items()]
                out += [""]
        return out

    def to_markdown(self) -> str:
        out = [f"# {self.experiment}", "", *self._setup_markdown()]
        if self.description:
            out += [self.description, ""]
        for name, table in self.tables.items():
            out += [f"## {name}", ""]
            if table.note:
                out += [table.note, ""]
            out += [table.markdown(), ""]
            if table.published:
                pub = Table(table.published["columns"], table.published["rows"])
                out += [f"Published ({table.published.get('source', 'paper')}):", "", pub.markdown(), ""]
        if self.metrics:
            names = sorted({m for v in self.metrics.values() for m in v})
            metrics = Table(["estimator", *names], [[e, *[v.get(m) for m in names]] for e, v in self.metrics.items()])
            out += ["## metrics", "", metrics.markdown(), ""]
        if self.timing:
            timing = Table(["estimator", "seconds_per_step"], [[k, v] for k, v in self.timing.items()])
            out += ["## timing", "", "Wall time per time step for all Monte Carlo runs at once.", "",
                    timing.markdown(), ""]
        if self.dropped:
            out += ["## not computed", "", "Asked for, but the data cannot give them (never reported as numbers):", ""]
            out += [f"- `{name}`: {why}" for name, why in self.dropped.items()] + [""]
        if self.notes:
            out += ["## notes", ""] + [f"- {n}" for n in self.notes] + [""]
        if self.provenance:
            p = self.provenance
            git = p.get("git") or {}
            commit = (git.get("commit") or "unknown")[:12] + (" (uncommitted changes)" if git.get("dirty") else "")
            v = p.get("versions") or {}
            out += ["## provenance", "",
                    f"torchmm {v.get('torchmm')}, torch {v.get('torch')}, numpy {v.get('numpy')}, "
                    f"Python {v.get('python')}; commit {commit}; {p.get('host')}; device {p.get('device')}, "
                    f"{p.get('dtype')}, {p.get('threads')} threads; {p.get('start')} to {p.get('end')} "
                    f"({p.get('wall_seconds')} s)."
                    + (" Runs by kernel (torchmm.kernels): " + ", ".join(f"{k} {v}" for k, v in p["kernels"].items())
                       + "." if p.get("kernels") else "")
                    + (f" ({p['kernels_note']}.)" if p.get("kernels_note") else "")
                    + (f" Continued {len(p['resumes'])} time(s) since (provenance resumes), last "
                       f"{p['resumes'][-1].get('start')} ({p['resumes'][-1].get('units_kept')} units kept)."
                       if p.get("resumes") else "")
                    + (f" Resumed from a checkpoint ({p['resumed'].get('units_kept')} units kept; the times "
                       "are this process's)." if isinstance(p.get("resumed"), dict) else ""), ""]
        return "\n".join(out)

    def to_latex(self) -> str:
        """``results.tex``: every table as a booktabs table (``\\usepackage{booktabs}``; ``\\input`` it), numbers
        as in results.md, text escaped: e.g. the ``learned`` estimates with their standard errors."""
        from experiments.formatting import latex_escape, latex_number, latex_table

        out = [f"% torchmm {latex_escape(self.experiment)}: the run's tables (booktabs; \\usepackage{{booktabs}})", ""]
        for name, table in self.tables.items():
            rows = [[latex_number(v) if isinstance(v, (int, float)) and not isinstance(v, bool)
                     else latex_escape(format_value(v)) for v in row] for row in table.rows]
            align = "".join("r" if any(isinstance(r[i], (int, float)) and not isinstance(r[i], bool)
                                       for r in table.rows) else "l" for i in range(len(table.columns)))
            out += latex_table([latex_escape(c) for c in table.columns], rows,
                                f"{latex_escape(self.experiment)}: {latex_escape(name)}", align or "l")
        return "\n".join(out)

    def save(self) -> None:
        write_atomic(self.output_dir / "results.json", json.dumps(self.to_json(), indent=2) + "\n")
        write_atomic(self.output_dir / "results.md", self.to_markdown())
        write_atomic(self.output_dir / "results.tex", self.to_latex())

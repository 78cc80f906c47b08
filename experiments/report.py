r"""``torchmm-report PATH...``: one table across runs - seed sweeps, override sweeps, separate runs.

Every ``results.json`` under the given paths (a run folder, a ``-m`` sweep folder, ``outputs/``)
is one run. Runs of the same study are grouped by their *result config* (the resolved config
without the keys that do not change numbers, :data:`experiments.folders.NON_RESULT_KEYS`):

* the **replicate key** (``seed`` by default, ``--replicate``) varies within a group: its runs are
  independent replications of one experiment;
* every other key that differs between runs is a **factor**: one row (block of rows) per value.

Within a group, the rows of each results table line up run by run. A column is a **label** (it
names the row: ``estimator``, ``alpha``, ...) if it is not numeric or if it holds the same value in
every run of each group (``nees_low`` of a given ``mc_runs``; with one run per group: in every
run); every other numeric column is a **measurement**, reported as the mean over
the group's runs with a Student-t confidence interval (``--level``, 95 % by default):
``mean +- t_{n-1} sd / sqrt(n)`` with ``sd`` the sample standard deviation over the ``n`` runs
(no interval for ``n = 1``; non-finite values are left out of ``n``).

Writes into ``--out`` (default: ``<PATH>/report`` for one PATH, else ``./report``):
``report.md`` (mean +- half-width), ``report.csv`` (tidy: one line per study, table, group, row and
measurement, with ``n, mean, sd, ci_low, ci_high``), ``report.json`` (the same, nested) and
``report.png`` / ``report.pdf`` (each study's first table's first measurement with its intervals)
and ``report.tex``.

**Paired differences.** A table with an ``estimator`` label column also gets its estimators
compared by replicate: the runs of a group share their seeds (and so their simulated data), so per
run ``d = value(estimator) - value(reference)`` at the same other labels, then the mean of ``d``
over the group's runs with its Student-t interval (:func:`mean_interval`). This interval is much
narrower than the difference of two unpaired intervals when the estimators' errors are correlated.
The reference is the first row's estimator (``--reference NAME`` for another). Written as the
``paired`` section of report.json (``{experiment: {"paired": {table: {"reference", "labels",
"measurements", "rows"}}}}``), report.md, report.tex and report.csv (the rows whose ``reference``
column is set; their ``labels`` name the estimator subtracted from).

**LaTeX.** ``report.tex`` is a fragment of one booktabs table per results table (and per paired
section): ``\toprule``/``\midrule``/``\bottomrule``, cells ``mean $\pm$ half-width``, text
escaped. It needs ``\usepackage{booktabs}`` only; ``\input{report.tex}`` it, or compile it alone
inside ``\documentclass{article}\usepackage{booktabs}\begin{document} ... \end{document}``.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from experiments.files import RunFolderError, write_atomic
from experiments.folders import NON_RESULT_KEYS
from experiments.formatting import format_value, latex_escape
from experiments.formatting import latex_number as _latex_number
from experiments.formatting import latex_table as _latex_table

__all__ = ["Run", "collect_runs", "combine", "main", "mean_interval", "paired_differences", "to_latex",
           "write_report"]

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


def mean_interval(values: list[float], level: float = 0.95) -> dict[str, float | int | None]:
    """``{"n", "mean", "sd", "ci_low", "ci_high"}`` of the finite ``values`` (Student-t interval)."""
    finite = [float(v) for v in values if _is_number(v) and math.isfinite(v)]
    n = len(finite)
    if n == 0:
        return {"n": 0, "mean": None, "sd": None, "ci_low": None, "ci_high": None}
    mean = math.fsum(finite) / n
    if n == 1:
        return {"n": 1, "mean": mean, "sd": None, "ci_low": None, "ci_high": None}
    from scipy.stats import t as student_t

    if min(finite) == max(finite):
        mean, sd = finite[0], 0.0  # exactly: no rounding noise in the interval of a constant
    else:
        sd = math.sqrt(math.fsum((v - mean) ** 2 for v in finite) / (n - 1))
    half = float(student_t.ppf(0.5 + level / 2, n - 1)) * sd / math.sqrt(n)
    return {"n": n, "mean": mean, "sd": sd, "ci_low": mean - half, "ci_high": mean + half}


def is_standard_error(column: str) -> bool:
    """A run's own standard error of another column (``se``, ``<metric>_se``): combined over the
    replicates as the standard error of their mean (:func:`pooled_se`), never averaged or differenced."""
    return column == "se" or column.endswith("_se")


def is_bound(column: str, columns: list[str]) -> bool:
    """A run's own interval bound or half-width (``ci_low``, ``ci_high``, ``separate_half_width``,
    ``<metric>_low``/``_high``/``_bound`` beside ``<metric>``): meaningful in its run only, so not
    combined (the report's own interval replaces it) - unless it is the same in every run (a label)."""
    if column in ("ci_low", "ci_high", "separate_half_width") or column.endswith("_bound"):
        return True
    for suffix in ("_low", "_high"):
        if column.endswith(suffix) and column[: -len(suffix)] in columns:
            return True
    return False


def pooled_se(values: list[float]) -> dict[str, float | int | None]:
    """The standard error of the mean of ``n`` independent estimates with standard errors ``values``,
    ``sqrt(sum se_i^2) / n``, as a :func:`mean_interval` record without an interval (its ``mean``)."""
    finite = [float(v) for v in values if _is_number(v) and math.isfinite(v)]
    n = len(finite)
    if n == 0:
        return {"n": 0, "mean": None, "sd": None, "ci_low": None, "ci_high": None}
    return {"n": n, "mean": math.sqrt(math.fsum(v * v for v in finite)) / n, "sd": None, "ci_low": None,
            "ci_high": None}


def identifying_labels(tables: list[dict], columns: list[str], labels: list[str]) -> list[str]:
    """The label columns besides ``estimator`` that tell an estimator's rows apart (``alpha`` in a sweep
    table): those that vary among the rows of one estimator in some run. Constant companions of a
    measurement (``nees_low``, ``nis_dof``: empty for an estimator without them) do not identify a row."""
    if "estimator" not in columns:
        return [c for c in labels]
    est = columns.index("estimator")
    out = []
    for c in labels:
        if c == "estimator":
            continue
        i = columns.index(c)
        for table in tables:
            seen: dict[Any, set] = defaultdict(set)
            for row in table["rows"]:
                seen[json.dumps(row[est], default=str)].add(json.dumps(row[i], default=str))
            if any(len(v) > 1 for v in seen.values()):
                out.append(c)
                break
    return out


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _label_columns(tables_by_group: list[list[dict]]) -> list[bool]:
    """Per column: is it a label? Non-numeric columns are; a numeric one is if it holds the same
    value in every run of each group (at every row), given that some group has replicates - else
    (one run per group) if it holds the same value in every run."""
    columns = tables_by_group[0][0]["columns"]
    replicated = [g for g in tables_by_group if len(g) > 1]
    pools = replicated or [[t for g in tables_by_group for t in g]]
    labels = []
    for c in range(len(columns)):
        numeric = any(_is_number(row[c]) for g in tables_by_group for t in g for row in t["rows"])
        same = all([row[c] for row in t["rows"]] == [row[c] for row in pool[0]["rows"]] for pool in pools for t in pool)
        labels.append(not numeric or same)
    return labels


def combine(runs: list[Run], replicate: str = "seed", level: float = 0.95, reference: str | None = None) -> dict[str, Any]:
    """Combine ``runs`` into ``{experiment: {"factors", "groups", "tables": {name: {...}}}}``.

    ``groups``: one entry per distinct factor setting, ``{"factors": {key: value}, "runs": [paths],
    "replicates": [replicate values]}``. Each table: ``{"labels": [columns], "measurements":
    [columns], "rows": [{"group": i, "labels": {...}, "values": {column: mean_interval}}]}``.
    ``paired``: per table with an ``estimator`` label, :func:`paired_differences` against
    ``reference`` (default: the table's first row's estimator).
    """
    by_experiment: dict[str, list[Run]] = defaultdict(list)
    for run in runs:
        by_experiment[run.experiment].append(run)
    report: dict[str, Any] = {}
    for experiment, members in sorted(by_experiment.items()):
        configs = [run.config for run in members]
        keys = sorted({k for c in configs for k in c})
        varying = [k for k in keys if len({json.dumps(c.get(k), default=str) for c in configs}) > 1]
        factors = [k for k in varying if k != replicate]
        groups: dict[str, dict] = {}
        order: list[str] = []
        for run, config in zip(members, configs):
            setting = {k: config.get(k) for k in factors}
            token = json.dumps(setting, sort_keys=True, default=str)
            if token not in groups:
                groups[token] = {"factors": setting, "runs": [], "replicates": []}
                order.append(token)
            groups[token]["runs"].append(run)
            groups[token]["replicates"].append(config.get(replicate))
        order.sort(key=lambda tok: [_sort_key(groups[tok]["factors"][k]) for k in factors])
        group_list = [groups[tok] for tok in order]
        duplicated = [g for g in group_list if len(set(map(str, g["replicates"]))) < len(g["replicates"])]
        if duplicated:
            paths = ", ".join(str(r.path) for r in duplicated[0]["runs"])
            print(f"torchmm-report: warning: {experiment}: runs with the same config and {replicate} are "
                  f"combined as if independent ({paths})", file=sys.stderr)
        for g in group_list:  # replicates that give the same numbers are not independent replications
            if len(g["runs"]) > 1 and all(run.results.get("tables") == g["runs"][0].results.get("tables")
                                          for run in g["runs"][1:]):
                paths = ", ".join(str(r.path) for r in g["runs"])
                print(f"torchmm-report: warning: {experiment}: the {len(g['runs'])} runs with different {replicate} "
                      f"give identical tables ({replicate} changes nothing here, e.g. recorded data): their "
                      f"intervals are 0, not a measure of uncertainty ({paths})", file=sys.stderr)
        tables_out: dict[str, Any] = {}
        paired_out: dict[str, Any] = {}
        table_names = list(dict.fromkeys(n for run in members for n in run.results.get("tables", {})))
        for name in table_names:
            tables = [run.results["tables"].get(name) for run in members]
            if any(t is None for t in tables):
                continue
            columns = tables[0]["columns"]
            comparable = [t for t in tables if t["columns"] == columns and len(t["rows"]) == len(tables[0]["rows"])]
            if len(comparable) < len(tables):
                print(f"torchmm-report: warning: {experiment}/{name}: runs differ in the table's columns or "
                      "rows; it is left out", file=sys.stderr)
                continue
            is_label = _label_columns([[run.results["tables"][name] for run in g["runs"]] for g in group_list])
            label_cols = [c for c, lab in zip(columns, is_label) if lab]
            errors = [c for c, lab in zip(columns, is_label) if not lab and is_standard_error(c)]
            bounds = [c for c, lab in zip(columns, is_label) if not lab and is_bound(c, columns)]
            measure_cols = [c for c, lab in zip(columns, is_label) if not lab and c not in errors and c not in bounds]
            rows = []
            for gi, group in enumerate(group_list):
                group_tables = [run.results["tables"][name] for run in group["runs"]]
                for r in range(len(tables[0]["rows"])):
                    labels = {c: group_tables[0]["rows"][r][i] for i, c in enumerate(columns) if is_label[i]}
                    values = {c: mean_interval([t["rows"][r][i] for t in group_tables], level)
                              for i, c in enumerate(columns) if c in measure_cols}
                    values.update({c: pooled_se([t["rows"][r][columns.index(c)] for t in group_tables])
                                   for c in errors})
                    rows.append({"group": gi, "labels": labels, "values": values})
            identifying = identifying_labels([t for g in group_list for t in
                                              (run.results["tables"][name] for run in g["runs"])], columns, label_cols)
            tables_out[name] = {"labels": label_cols, "identifying": identifying, "measurements": measure_cols,
                                "standard_errors": errors, "not_combined": bounds, "rows": rows}
            # a table of the study's own paired differences (a `reference` column) is not paired again
            if "estimator" in label_cols and "reference" not in columns and measure_cols:
                paired = paired_differences(
                    [[run.results["tables"][name] for run in g["runs"]] for g in group_list], columns,
                    measure_cols, label_cols, reference, level)
                if paired is not None:
                    paired_out[name] = paired
        report[experiment] = {
            "replicate": replicate,
            "level": level,
            "factors": factors,
            "groups": [{"factors": g["factors"], "runs": [str(r.path) for r in g["runs"]],
                        "replicates": g["replicates"]} for g in group_list],
            "tables": tables_out,
            "paired": paired_out,
        }
    return report


def paired_differences(tables_by_group: list[list[dict]], columns: list[str], measurements: list[str],
                       labels: list[str], reference: str | None = None, level: float = 0.95) -> dict | None:
    """Estimators minus ``reference``, paired by run: ``{"reference", "labels", "measurements",
    "rows": [{"group", "labels", "values": {column: mean_interval}}]}`` or None (no reference row).

    ``tables_by_group``: per group, the table of each of its runs (rows in the same order in every
    run). A row of estimator ``B`` is paired with the row of ``reference`` holding the same other
    identifying labels (:func:`identifying_labels`: e.g. ``alpha``; not a measurement's constant
    companion such as ``nees_low``, which may be empty for one estimator) in the same run;
    ``d_r = B_r - reference_r`` for each run ``r`` of the group, then :func:`mean_interval` over ``d``.
    Cells that are not finite numbers are left out of ``n``. ``measurements`` are values, never standard
    errors or bounds (:func:`is_standard_error`, :func:`is_bound`).
    """
    est = columns.index("estimator")
    keys = identifying_labels([t for g in tables_by_group for t in g], columns, labels)
    others = [columns.index(c) for c in keys]
    first = next((t["rows"][0] for g in tables_by_group for t in g[:1] if t["rows"]), None)
    if first is None:
        return None
    reference = first[est] if reference is None else reference
    if not any(row[est] == reference for g in tables_by_group for t in g for row in t["rows"]):
        return None
    measure = [columns.index(c) for c in measurements]
    rows = []
    for gi, group in enumerate(tables_by_group):
        base = group[0]["rows"]
        for r, row in enumerate(base):
            if row[est] == reference:
                continue
            key = [row[i] for i in others]
            ref = next((q for q, other in enumerate(base) if other[est] == reference
                        and [other[i] for i in others] == key), None)
            if ref is None:
                continue
            values = {}
            for i, column in zip(measure, measurements):
                diffs = []
                for table in group:
                    a, b = table["rows"][r][i], table["rows"][ref][i]
                    diffs.append(a - b if _is_number(a) and _is_number(b) else float("nan"))
                values[column] = mean_interval(diffs, level)
            rows.append({"group": gi, "labels": {c: row[columns.index(c)] for c in ["estimator", *keys]},
                         "values": values})
    return {"reference": reference, "labels": ["estimator", *keys], "measurements": measurements, "rows": rows}


def _sort_key(value: Any):
    return (0, value, "") if _is_number(value) else (1, 0, str(value))


def _cell(stats: dict) -> str:
    if stats["mean"] is None:
        return ""
    if stats["ci_low"] is None:
        return format_value(stats["mean"])
    return f"{format_value(stats['mean'])} ± {format_value((stats['ci_high'] - stats['ci_low']) / 2)}"


def to_markdown(report: dict[str, Any]) -> str:
    out = ["# torchmm report", ""]
    for experiment, body in report.items():
        groups = body["groups"]
        pct = f"{100 * body['level']:g} %"
        out += [f"## {experiment}", "",
                f"{sum(len(g['runs']) for g in groups)} runs in {len(groups)} group(s); factors: "
                f"{', '.join(body['factors']) or 'none'}; replicates: {body['replicate']} "
                f"(mean ± half-width of the {pct} Student-t interval over the replicates; n = replicates).", ""]
        for name, table in body["tables"].items():
            factor_cols = body["factors"]
            errors = table.get("standard_errors", [])
            columns = [*factor_cols, *table["labels"], "n", *table["measurements"], *errors]
            lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
            for row in table["rows"]:
                g = groups[row["group"]]
                n = max((v["n"] for v in row["values"].values()), default=len(g["runs"]))
                cells = [*(format_value(g["factors"][k]) for k in factor_cols), *(format_value(row["labels"][c]) for c in table["labels"]),
                         str(n), *(_cell(row["values"][c]) for c in [*table["measurements"], *errors])]
                lines.append("| " + " | ".join(cells) + " |")
            out += [f"### {name}", "", *lines, ""]
            if errors or table.get("not_combined"):
                out += [_columns_note(table), ""]
        for name, paired in (body.get("paired") or {}).items():
            columns, rows = _paired_rows(body, paired, minus=" − ")
            lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
            lines += ["| " + " | ".join(row) + " |" for row in rows]
            out += [f"### {name}: paired differences", "",
                    (f"Each estimator minus {paired['reference']}, run by run ({body['replicate']} paired: the runs "
                     f"share their data), then mean ± half-width of the {pct} Student-t interval over the replicates."),
                    "", *lines, ""]
    return "\n".join(out)


def _columns_note(table: dict) -> str:
    """What the report did with a table's own uncertainty columns."""
    parts = []
    if table.get("standard_errors"):
        parts.append(f"{', '.join(table['standard_errors'])}: each run's standard error, combined as that of the mean "
                     "over the replicates, sqrt(sum se^2) / n (no interval)")
    if table.get("not_combined"):
        parts.append(f"{', '.join(table['not_combined'])}: each run's own bounds, not combined (the intervals above "
                     "replace them)")
    return "; ".join(parts) + "."


def _paired_rows(body: dict, paired: dict, minus: str, cell=None, text=None) -> tuple[list[str], list[list[str]]]:
    """Header and cells of a paired-differences table (the estimator column reads ``B - reference``)."""
    cell = cell or _cell
    text = text or (lambda v: v)
    factors = body["factors"]
    columns = [*factors, *paired["labels"], "n", *paired["measurements"]]
    rows = []
    for row in paired["rows"]:
        g = body["groups"][row["group"]]
        n = max((v["n"] for v in row["values"].values()), default=len(g["runs"]))
        labels = [text(format_value(row["labels"][c])) if c != "estimator"
                  else text(format_value(row["labels"][c])) + minus + text(str(paired["reference"]))
                  for c in paired["labels"]]
        rows.append([*(text(format_value(g["factors"][k])) for k in factors), *labels, str(n),
                     *(cell(row["values"][c]) for c in paired["measurements"])])
    return [text(c) for c in columns], rows


def to_csv(report: dict[str, Any]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["experiment", "table", "group", "factors", "labels", "measurement", "n", "mean", "sd",
                     "ci_low", "ci_high", "reference"])
    for experiment, body in report.items():
        sections = [(name, table, "") for name, table in body["tables"].items()]
        sections += [(name, paired, paired["reference"]) for name, paired in (body.get("paired") or {}).items()]
        for name, table, reference in sections:  # reference set: the paired difference labels - reference
            for row in table["rows"]:
                factors = json.dumps(body["groups"][row["group"]]["factors"], default=str)
                labels = json.dumps(row["labels"], default=str)
                for measurement, s in row["values"].items():
                    writer.writerow([experiment, name, row["group"], factors, labels, measurement, s["n"],
                                     *("" if s[k] is None else repr(s[k]) for k in ("mean", "sd", "ci_low", "ci_high")),
                                     reference])
    return buf.getvalue()


def _latex_cell(stats: dict) -> str:
    if stats["mean"] is None:
        return ""
    if stats["ci_low"] is None:
        return _latex_number(stats["mean"])
    return f"{_latex_number(stats['mean'])} $\\pm$ {_latex_number((stats['ci_high'] - stats['ci_low']) / 2)}"


def to_latex(report: dict[str, Any]) -> str:
    """``report.tex``: one booktabs table per results table and per paired section (needs
    ``\\usepackage{booktabs}``; see the module docstring)."""
    esc = latex_escape
    out = ["% torchmm-report: booktabs tables (\\usepackage{booktabs}); \\input{report.tex} in a document,",
           "% e.g. \\documentclass{article}\\usepackage{booktabs}\\begin{document}\\input{report.tex}\\end{document}",
           "% cells: mean $\\pm$ half-width of the Student-t interval over the replicates; n = replicates", ""]
    for experiment, body in report.items():
        groups, factors = body["groups"], body["factors"]
        pct = f"{100 * body['level']:g}\\,\\%"
        for name, table in body["tables"].items():
            values = [*table["measurements"], *table.get("standard_errors", [])]
            columns = [*factors, *table["labels"], "n", *values]
            rows = []
            for row in table["rows"]:
                g = groups[row["group"]]
                n = max((v["n"] for v in row["values"].values()), default=len(g["runs"]))
                rows.append([*(esc(format_value(g["factors"][k])) for k in factors),
                             *(esc(format_value(row["labels"][c])) for c in table["labels"]), str(n),
                             *(_latex_cell(row["values"][c]) for c in values)])
            align = "l" * (len(factors) + len(table["labels"])) + "r" * (1 + len(values))
            caption = (f"{esc(experiment)}: {esc(name)} (mean $\\pm$ half-width of the {pct} Student-t interval "
                       f"over {esc(body['replicate'])}; n replicates)")
            out += _latex_table([esc(c) for c in columns], rows, caption, align)
        for name, paired in (body.get("paired") or {}).items():
            columns, rows = _paired_rows(body, paired, minus=" $-$ ", cell=_latex_cell, text=esc)
            align = "l" * (len(factors) + len(paired["labels"])) + "r" * (1 + len(paired["measurements"]))
            caption = (f"{esc(experiment)}: {esc(name)}, paired differences: each estimator minus "
                       f"{esc(paired['reference'])} per {esc(body['replicate'])} (mean $\\pm$ half-width of the "
                       f"{pct} Student-t interval)")
            out += _latex_table(columns, rows, caption, align)
    return "\n".join(out)


def figure(report: dict[str, Any]):
    """Each study's first table's first measurement: means with their intervals, per group and row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(exp, name, table) for exp, body in report.items()
              for name, table in list(body["tables"].items())[:1] if table["measurements"]]
    if not panels:
        return None
    fig, axes = plt.subplots(len(panels), 1, figsize=(6.5, 2.2 + 0.18 * max(len(t["rows"]) for *_, t in panels)),
                             squeeze=False)
    for ax, (exp, name, table) in zip(axes[:, 0], panels):
        measure = table["measurements"][0]
        body = report[exp]
        keys = table.get("identifying")
        if keys is None:
            keys = [c for c in table["labels"] if c != "estimator"]
        labels, means, lows, highs = [], [], [], []
        for row in table["rows"]:
            s = row["values"][measure]
            if s["mean"] is None:
                continue
            factors = body["groups"][row["group"]]["factors"]
            names = ["estimator", *keys] if "estimator" in table["labels"] else keys
            text = ", ".join([*(f"{k}={format_value(v)}" for k, v in factors.items()),
                              *(f"{c}={format_value(row['labels'][c])}" if c != "estimator" and _is_number(row["labels"][c])
                                else format_value(row["labels"][c])
                                for c in names if row["labels"].get(c) not in (None, ""))])
            labels.append(text or exp)
            means.append(s["mean"])
            lows.append(s["mean"] - (s["ci_low"] if s["ci_low"] is not None else s["mean"]))
            highs.append((s["ci_high"] if s["ci_high"] is not None else s["mean"]) - s["mean"])
        y = list(range(len(means)))[::-1]
        ax.errorbar(means, y, xerr=[lows, highs], fmt="o", ms=3, capsize=2, lw=1)
        ax.set_yticks(y, labels, fontsize=7)
        ax.set_xlabel(f"{measure} (mean, {100 * body['level']:g} % interval over {body['replicate']})", fontsize=8)
        ax.set_title(f"{exp}: {name}", fontsize=9)
        ax.grid(True, axis="x", linewidth=0.3, alpha=0.5)
    fig.tight_layout()
    return fig


def write_report(report: dict[str, Any], out_dir: Path) -> list[Path]:
    written = []
    for name, text in (("report.md", to_markdown(report)), ("report.csv", to_csv(report)),
                       ("report.json", json.dumps(report, indent=2, default=str) + "\n"),
                       ("report.tex", to_latex(report))):
        write_atomic(out_dir / name, text)
        written.append(out_dir / name)
    fig = figure(report)
    if fig is not None:
        import matplotlib.pyplot as plt

        from experiments.plot import save_tight

        paths = [out_dir / f"report.{fmt}" for fmt in ("png", "pdf")]
        save_tight(fig, [(path, 200) for path in paths])
        written.extend(paths)
        plt.close(fig)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="torchmm-report", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", metavar="PATH", help="run folders, sweep folders or outputs/")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default PATH/report or ./report)")
    parser.add_argument("--replicate", default="seed", help="the config key whose runs are replications (seed)")
    parser.add_argument("--level", default="0.95", help="confidence level of the intervals (0.95)")
    parser.add_argument("--reference", default=None, metavar="NAME",
                        help="the estimator the paired differences subtract (default: each table's first row's)")
    args = parser.parse_args(argv)
    try:
        level = float(args.level)
    except ValueError:
        level = math.nan
    if not 0 < level < 1:
        print(f"torchmm-report: error: --level: expected a number in (0, 1), got {args.level}", file=sys.stderr)
        return 2
    args.level = level
    try:
        runs = collect_runs([Path(p) for p in args.paths])
    except (FileNotFoundError, ResultsFileError) as err:
        print(f"torchmm-report: error: {err}", file=sys.stderr)
        return 2
    if not runs:
        print(f"torchmm-report: error: PATH: no results.json under {' '.join(args.paths)}", file=sys.stderr)
        return 2
    if not any(args.replicate in run.config for run in runs):
        keys = sorted({k for run in runs for k in run.config if k in ("seed", "block_runs") or "seed" in k})
        print(f"torchmm-report: error: --replicate: no run's config has a key {args.replicate!r}"
              + (f" (e.g. {', '.join(keys)})" if keys else ""), file=sys.stderr)
        return 2
    report = combine(runs, args.replicate, args.level, args.reference)
    if args.reference is not None and not any(body["paired"] for body in report.values()):
        names = sorted({str(row["labels"]["estimator"]) for body in report.values() for table in body["tables"].values()
                        for row in table["rows"] if "estimator" in row["labels"]})
        print(f"torchmm-report: error: --reference: no table has an estimator {args.reference!r} "
              f"(estimators: {', '.join(names) or 'none'})", file=sys.stderr)
        return 2
    out = args.out or (Path(args.paths[0]) / "report" if len(args.paths) == 1 else Path("report"))
    try:
        write_report(report, out)
    except RunFolderError as err:  # --out cannot be written: one line naming the file
        print(f"torchmm-report: error: {err}", file=sys.stderr)
        return 2
    for experiment, body in report.items():
        groups = body["groups"]
        print(f"torchmm-report: {experiment}: {sum(len(g['runs']) for g in groups)} runs, {len(groups)} group(s) "
              f"(factors: {', '.join(body['factors']) or 'none'})")
    print(f"torchmm-report: report.md, report.csv, report.json, report.tex, report.png in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

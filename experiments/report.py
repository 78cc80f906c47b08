r"""``torchmm-report PATH...``: one table across runs - seed sweeps, override sweeps, separate runs.

Every ``results.json`` under the given paths (a run folder, a ``-m`` sweep folder, ``outputs/``)
is one run. Runs of the same study are grouped by their *result config* (the resolved config
without the keys that do not change numbers, :data:`experiments.folders.NON_RESULT_KEYS`):

* the **replicate key** (``seed`` by default, ``--replicate``) varies within a group: its runs are
  independent replications of one experiment;
* every other key that differs between runs is a **factor**: one row (block of rows) per value.

Within a group, the rows of each results table are matched run by run by their text labels (``estimator``,
``metric``, ...: a run whose config lists the estimators in another order is matched by name, never by
position; :func:`aligned_rows`). Runs need not hold the same columns or rows (a metric a run could not
compute is not in its table): a table is combined on the union of its runs' columns and rows, a cell over the
runs that have a value there (its ``n``), and the runs lacking a column, a row or the table are named
(a warning; the table's ``absent``; :mod:`experiments.report_tables`). A column is a **label** (it
names the row: ``estimator``, ``alpha``, ...) if it is text (not a number, not true/false) or if it holds
the same value in every run of each group (``nees_low`` of a given ``mc_runs``; with one run per group: in
every run); every other numeric column is a **measurement**, reported as the mean over
the group's runs with a Student-t confidence interval (``--level``, 95 % by default):
``mean +- t_{n-1} sd / sqrt(n)`` with ``sd`` the sample standard deviation over the ``n`` runs
(no interval for ``n = 1``; non-finite values are left out of ``n``). A true/false column
(``pos_armse_inside_95``) is always a measurement, never a label: the fraction of the group's runs where
it is True, with ``n`` (:func:`fraction_true`; no interval; not in the paired differences).

Writes into ``--out`` (default: ``<PATH>/report`` for one PATH, else ``./report``):
``report.md`` (mean +- half-width, ``(n=k)`` in a cell whose ``n`` is not its row's; under the tables, what
runs lack and the runs' own ``dropped`` entries), ``report.csv`` (tidy: one line per study, table, group, row
and
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

The runs are found and read by :mod:`experiments.report_runs`, the formats written by
:mod:`experiments.report_formats`; here the runs' grouping and statistics.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

from experiments.files import RunFolderError
from experiments.formatting import is_number
from experiments.report_formats import figure, to_csv, to_latex, to_markdown, write_report  # (the formats)
from experiments.report_runs import (  # (the runs)
    IGNORED_KEYS,
    LeftOut,
    ResultsFileError,
    Run,
    attach_left_out,
    collect_runs,
    flatten,
)
from experiments.report_tables import (  # (a table of several runs lined up; a cell's statistics)
    absences,
    aligned_rows,
    flag_columns,
    fraction_true,
    identifying_labels,
    is_bound,
    is_standard_error,
    label_columns,
    mean_interval,
    pooled_se,
    se_base,
    template_rows,
    union_columns,
    union_table,
)

__all__ = ["IGNORED_KEYS", "LeftOut", "ResultsFileError", "Run", "aligned_rows", "collect_runs", "combine",
           "combine_table", "figure", "flag_columns", "flatten", "fraction_true", "identifying_labels",
           "is_bound", "is_standard_error", "main", "mean_interval", "paired_differences", "pooled_se",
           "runs_dropped", "to_csv", "to_latex", "to_markdown", "write_report"]


def _sort_key(value: Any):
    return (0, value, "") if is_number(value) else (1, 0, str(value))


def combine(runs: list[Run], replicate: str = "seed", level: float = 0.95, reference: str | None = None) -> dict[str, Any]:
    """Combine ``runs`` into ``{experiment: {"factors", "groups", "tables": {name: {...}}}}``.

    ``groups``: one entry per distinct factor setting, ``{"factors": {key: value}, "runs": [paths],
    "replicates": [replicate values]}``. Each table (:func:`combine_table`): ``{"labels": [columns],
    "measurements": [columns], "rows": [{"group": i, "labels": {...}, "values": {column: mean_interval},
    "held_by": runs holding the row}], "absent": {...}}`` (``absent`` only where some runs lack a column,
    a row or the table). ``paired``: per table with an ``estimator`` label, :func:`paired_differences`
    against ``reference`` (default: the table's first row's estimator). ``dropped``: the runs' own
    (:func:`runs_dropped`).
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
            table, paired = combine_table(experiment, name, group_list, level, reference)
            tables_out[name] = table
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
            "dropped": runs_dropped(group_list),
        }
    return report


def runs_dropped(group_list: list[dict]) -> list[dict]:
    """The runs' own ``dropped`` entries (results.json: ``{metric: why}``, what a run could not compute):
    ``[{"metric", "reason", "runs": [paths]}]``, one per metric and reason, in the runs' order."""
    out: dict[tuple[str, str], list[str]] = {}
    for g in group_list:
        for run in g["runs"]:
            dropped = run.results.get("dropped")
            for metric, reason in (dropped.items() if isinstance(dropped, dict) else ()):
                out.setdefault((str(metric), str(reason)), []).append(str(run.path))
    return [{"metric": m, "reason": r, "runs": paths} for (m, r), paths in out.items()]


def _names(labels: dict) -> str:
    return ", ".join(str(v) for v in labels.values() if v not in (None, "")) or "(no label)"


def combine_table(experiment: str, name: str, group_list: list[dict], level: float,
                  reference: str | None) -> tuple[dict, dict | None]:
    """One results table ``name`` of every run of ``group_list`` (one study's groups) combined:
    ``(table, paired differences or None)`` (see :func:`combine`).

    On the union of the runs' columns, and per group on the union of its runs' rows matched by their text
    labels (:mod:`experiments.report_tables`): what a run lacks is no value there, so each cell's ``n``
    counts the runs with a value; ``absent`` names the runs that lack a column, a row or the whole table
    (and a warning says so), never dropping the table."""
    with_table = [[run for run in g["runs"] if name in run.results.get("tables", {})] for g in group_list]
    own = [run.results["tables"][name] for runs in with_table for run in runs]
    columns = union_columns(own)
    lined = [[union_table(run.results["tables"][name], columns) for run in runs] for runs in with_table]
    flags = flag_columns([t for g in lined for t in g])
    # rows are matched by their text labels (estimator, metric, ...) present in every run, never by
    # position (nor by a true/false column: a measurement that may differ between seeds)
    text = [i for i, c in enumerate(columns) if i not in flags and all(c in t["columns"] for t in own)
            and not any(is_number(row[i]) for g in lined for t in g for row in t["rows"])]
    by_group = [aligned_rows(g, text) for g in lined]
    is_label = label_columns([g for g in by_group if g], flags)
    fractions = [columns[i] for i in flags]
    label_cols = [c for c, lab in zip(columns, is_label) if lab]
    errors = [c for c, lab in zip(columns, is_label) if not lab and is_standard_error(c)]
    bounds = [c for c, lab in zip(columns, is_label) if not lab and is_bound(c, columns)]
    measure_cols = [c for c, lab in zip(columns, is_label) if not lab and c not in errors and c not in bounds]
    bases = {c: se_base(c, columns) for c in errors}
    rows = []
    for gi, group in enumerate(by_group):
        for r, template in enumerate(template_rows(group) if group else []):
            held = [t["rows"][r] for t in group if t["rows"][r] is not None]
            labels = {c: template[i] for i, c in enumerate(columns) if is_label[i]}
            values = {c: fraction_true([row[i] for row in held]) if c in fractions
                      else mean_interval([row[i] for row in held], level)
                      for i, c in enumerate(columns) if c in measure_cols}
            for c in errors:
                base = columns.index(bases[c]) if bases[c] is not None else None
                values[c] = pooled_se([row[columns.index(c)] for row in held],
                                      None if base is None else [row[base] for row in held])
            rows.append({"group": gi, "labels": labels, "values": values, "held_by": len(held)})
    identifying = identifying_labels([t for g in by_group for t in g], columns, label_cols)
    table = {"labels": label_cols, "identifying": identifying, "measurements": measure_cols,
             "standard_errors": errors, "not_combined": bounds, "fractions": fractions, "rows": rows}
    paths = [[str(run.path) for run in runs] for runs in with_table]
    absent = absences([p for group in paths for p in group], [t["columns"] for t in own], columns, by_group,
                      paths, label_cols)
    without = [str(run.path) for g in group_list for run in g["runs"]
               if name not in run.results.get("tables", {})]
    if without:
        absent["table"] = without
    if absent:
        table["absent"] = absent
        total = sum(len(g["runs"]) for g in group_list)
        parts = [f"not in {len(without)} of the {total} runs"] if without else []
        parts += [f"{c} not in {len(p)} run(s)" for c, p in absent.get("columns", {}).items()]
        held_rows = absent.get("rows", [])
        parts += [f"row {_names(item['labels'])} not in {len(item['runs'])} run(s)" for item in held_rows[:3]]
        parts += [f"{len(held_rows) - 3} more rows not in every run"] if len(held_rows) > 3 else []
        print(f"torchmm-report: warning: {experiment}/{name}: {'; '.join(parts)}: no value there, so each "
              "cell's n counts the runs with one (report.md names the runs)", file=sys.stderr)
    dropped = [f"{c} ({_names({k: v for k, v in row['labels'].items() if not is_number(v)})})"
               for row in rows for c, v in row["values"].items() if v.get("dropped")]
    if dropped:
        more = ", ..." if len(dropped) > 3 else ""
        print(f"torchmm-report: warning: {experiment}/{name}: {len(dropped)} pooled standard error(s) not "
              f"computed, some replicates in the mean having none ({', '.join(dropped[:3])}{more}): "
              "report.md names them", file=sys.stderr)
    # a table of the study's own paired differences (a `reference` column) is not paired again;
    # true/false columns are not differenced
    numbers = [c for c in measure_cols if c not in fractions]
    paired = None
    if "estimator" in label_cols and "reference" not in columns and numbers:
        paired = paired_differences([g for g in by_group if g], columns, numbers, label_cols, reference,
                                    level, groups=[gi for gi, g in enumerate(by_group) if g])
    return table, paired


def paired_differences(tables_by_group: list[list[dict]], columns: list[str], measurements: list[str],
                       labels: list[str], reference: str | None = None, level: float = 0.95,
                       groups: list[int] | None = None) -> dict | None:
    """Estimators minus ``reference``, paired by run: ``{"reference", "labels", "measurements",
    "rows": [{"group", "labels", "values": {column: mean_interval}}]}`` or None (no reference row).

    ``tables_by_group``: per group, the table of each of its runs on the same rows
    (:func:`experiments.report_tables.aligned_rows`; a row a run lacks is None there); ``groups``: their
    indices in the report (default 0, 1, ...). A row of estimator ``B`` is paired with the row of
    ``reference`` holding the same other identifying labels (:func:`identifying_labels`: e.g. ``alpha``;
    not a measurement's constant companion such as ``nees_low``, which may be empty for one estimator) in
    the same run; ``d_r = B_r - reference_r`` for each run ``r`` of the group, then :func:`mean_interval`
    over ``d``. Cells that are not finite numbers (or a row the run lacks) are left out of ``n``.
    ``measurements`` are values, never standard errors or bounds (:func:`is_standard_error`,
    :func:`is_bound`).
    """
    est = columns.index("estimator")
    keys = identifying_labels([t for g in tables_by_group for t in g], columns, labels)
    others = [columns.index(c) for c in keys]
    first = next((template_rows(g)[0] for g in tables_by_group if g and g[0]["rows"]), None)
    if first is None:
        return None
    reference = first[est] if reference is None else reference
    if not any(row is not None and row[est] == reference
               for g in tables_by_group for t in g for row in t["rows"]):
        return None
    measure = [columns.index(c) for c in measurements]
    rows = []
    for gi, group in zip(groups if groups is not None else range(len(tables_by_group)), tables_by_group):
        base = template_rows(group)
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
                    a, b = table["rows"][r], table["rows"][ref]
                    a, b = (None, None) if a is None or b is None else (a[i], b[i])
                    diffs.append(a - b if is_number(a) and is_number(b) else float("nan"))
                values[column] = mean_interval(diffs, level)
            rows.append({"group": gi, "labels": {c: row[columns.index(c)] for c in ["estimator", *keys]},
                         "values": values})
    return {"reference": reference, "labels": ["estimator", *keys], "measurements": measurements, "rows": rows}


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
    left_out: list[LeftOut] = []
    try:
        runs = collect_runs([Path(p) for p in args.paths], left_out)
    except (FileNotFoundError, ResultsFileError) as err:
        print(f"torchmm-report: error: {err}", file=sys.stderr)
        return 2
    for item in left_out:  # interrupted or failed runs, jobs never started: each named, never silently
        print(f"torchmm-report: warning: {item.path}: left out: {item.reason}", file=sys.stderr)
    if not runs:
        print(f"torchmm-report: error: PATH: no finished run (results.json) under {' '.join(args.paths)}"
              + (f" ({sum(i.runs for i in left_out)} not finished: see the warnings)" if left_out else ""),
              file=sys.stderr)
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
    empty = {"replicate": args.replicate, "level": args.level, "factors": [], "groups": [], "tables": {},
             "paired": {}, "dropped": []}
    attach_left_out(report, left_out, empty)
    out = args.out or (Path(args.paths[0]) / "report" if len(args.paths) == 1 else Path("report"))
    try:
        write_report(report, out)
    except RunFolderError as err:  # --out cannot be written: one line naming the file
        print(f"torchmm-report: error: {err}", file=sys.stderr)
        return 2
    for experiment, body in report.items():
        groups = body["groups"]
        print(f"torchmm-report: {experiment}: {sum(len(g['runs']) for g in groups)} runs, {len(groups)} group(s) "
              f"(factors: {', '.join(body['factors']) or 'none'})"
              + (f"; {sum(i['runs'] for i in body['left_out'])} left out (not finished: see the warnings)"
                 if body.get("left_out") else ""))
    print(f"torchmm-report: report.md, report.csv, report.json, report.tex, report.png in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

r"""``torchmm-report PATH...``: one table across runs - seed sweeps, override sweeps, separate runs.

Every ``results.json`` under the given paths (a run folder, a ``-m`` sweep folder, ``outputs/``)
is one run. Runs of the same study are grouped by their *result config* (the resolved config
without the keys that do not change numbers, :data:`experiments.folders.NON_RESULT_KEYS`):

* the **replicate key** (``seed`` by default, ``--replicate``) varies within a group: its runs are
  independent replications of one experiment;
* every other key that differs between runs is a **factor**: one row (block of rows) per value.

Within a group, the rows of each results table are matched run by run by their text labels (``estimator``,
``metric``, ...: a run whose config lists the estimators in another order is matched by name, never by
position; :func:`aligned_rows`); a table whose runs of one config hold different labels is left out with a
warning naming them. A column is a **label** (it
names the row: ``estimator``, ``alpha``, ...) if it is text (not a number, not true/false) or if it holds
the same value in every run of each group (``nees_low`` of a given ``mc_runs``; with one run per group: in
every run); every other numeric column is a **measurement**, reported as the mean over
the group's runs with a Student-t confidence interval (``--level``, 95 % by default):
``mean +- t_{n-1} sd / sqrt(n)`` with ``sd`` the sample standard deviation over the ``n`` runs
(no interval for ``n = 1``; non-finite values are left out of ``n``). A true/false column
(``pos_armse_inside_95``) is always a measurement, never a label: the fraction of the group's runs where
it is True, with ``n`` (:func:`fraction_true`; no interval; not in the paired differences).

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

__all__ = ["IGNORED_KEYS", "LeftOut", "ResultsFileError", "Run", "aligned_rows", "collect_runs", "combine",
           "figure", "flag_columns", "flatten", "fraction_true", "main", "mean_interval",
           "paired_differences", "to_csv", "to_latex", "to_markdown", "write_report"]


def mean_interval(values: list[float], level: float = 0.95) -> dict[str, float | int | None]:
    """``{"n", "mean", "sd", "ci_low", "ci_high"}`` of the finite ``values`` (Student-t interval)."""
    finite = [float(v) for v in values if is_number(v) and math.isfinite(v)]
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
    finite = [float(v) for v in values if is_number(v) and math.isfinite(v)]
    n = len(finite)
    if n == 0:
        return {"n": 0, "mean": None, "sd": None, "ci_low": None, "ci_high": None}
    return {"n": n, "mean": math.sqrt(math.fsum(v * v for v in finite)) / n, "sd": None, "ci_low": None,
            "ci_high": None}


def _sort_key(value: Any):
    return (0, value, "") if is_number(value) else (1, 0, str(value))


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


def flag_columns(tables: list[dict]) -> list[int]:
    """The columns of ``tables`` (one results table of several runs) that hold true/false values: some
    cell is a ``bool`` and every other one is a ``bool`` or empty (None). They are measurements, never
    labels (``pos_armse_inside_95`` is True in one seed and False in another): see :func:`fraction_true`."""
    columns = tables[0]["columns"]
    cells = [[row[i] for t in tables for row in t["rows"]] for i in range(len(columns))]
    return [i for i, col in enumerate(cells)
            if any(isinstance(v, bool) for v in col) and all(isinstance(v, bool) or v is None for v in col)]


def fraction_true(values: list[Any]) -> dict[str, float | int | None]:
    """A true/false column over a group's runs: ``{"n", "true", "mean", "sd", "ci_low", "ci_high"}`` with
    ``n`` the runs holding a ``bool``, ``true`` how many of them are True and ``mean = true / n`` (None for
    ``n = 0``); no interval (``sd``, ``ci_low``, ``ci_high`` None)."""
    flags = [v for v in values if isinstance(v, bool)]
    n, true = len(flags), sum(flags)
    return {"n": n, "true": true, "mean": true / n if n else None, "sd": None, "ci_low": None,
            "ci_high": None}


def _label_columns(tables_by_group: list[list[dict]], flags: list[int] = ()) -> list[bool]:
    """Per column: is it a label? Non-numeric columns are (not the true/false ``flags``, which are
    measurements); a numeric one is if it holds the same value in every run of each group (at every
    row), given that some group has replicates - else (one run per group) if it holds the same value in
    every run."""
    columns = tables_by_group[0][0]["columns"]
    replicated = [g for g in tables_by_group if len(g) > 1]
    pools = replicated or [[t for g in tables_by_group for t in g]]
    labels = []
    for c in range(len(columns)):
        if c in flags:
            labels.append(False)
            continue
        numeric = any(is_number(row[c]) for g in tables_by_group for t in g for row in t["rows"])
        same = all([row[c] for row in t["rows"]] == [row[c] for row in pool[0]["rows"]] for pool in pools for t in pool)
        labels.append(not numeric or same)
    return labels


def aligned_rows(tables: list[dict], key_columns: list[int]) -> list[dict] | str:
    """The tables of one group's runs with each run's rows put in the first run's order by their labels
    (the cells of ``key_columns``: e.g. ``estimator``; two rows with the same labels keep their order
    among themselves), so that a row means the same estimator in every run whatever order a run's config
    listed them in; a string saying which labels differ if the runs do not hold the same rows."""
    def keys(table):
        seen: dict[str, int] = defaultdict(int)
        out = []
        for row in table["rows"]:
            k = json.dumps([row[i] for i in key_columns], default=str)
            out.append((k, seen[k]))  # (labels, occurrence)
            seen[k] += 1
        return out

    first = keys(tables[0])
    out = [tables[0]]
    for table in tables[1:]:
        mine = keys(table)
        if set(mine) != set(first):
            def name(ks):
                return ", ".join(sorted({k for k, _ in ks})) or "none"
            return (f"labels {name(set(mine) - set(first))} in one run, {name(set(first) - set(mine))} in another"
                    if set(mine) ^ set(first) else "the same labels, another count")
        where = {k: r for r, k in enumerate(mine)}
        out.append({**table, "rows": [table["rows"][where[k]] for k in first]})
    return out


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
            # each run's rows matched to its group's first run's by their text labels (estimator, ...), never
            # by position: a config listing the same estimators in another order is the same experiment
            # (not by a true/false column: a measurement that may differ between seeds)
            flags = flag_columns(tables)
            text = [i for i in range(len(columns))
                    if i not in flags and not any(is_number(row[i]) for t in tables for row in t["rows"])]
            by_group = [aligned_rows([run.results["tables"][name] for run in g["runs"]], text) for g in group_list]
            bad = next((gi for gi, a in enumerate(by_group) if isinstance(a, str)), None)
            if bad is not None:
                paths = ", ".join(str(r.path) for r in group_list[bad]["runs"])
                print(f"torchmm-report: warning: {experiment}/{name}: the runs of one config hold different rows "
                      f"({by_group[bad]}: {', '.join(columns[i] for i in text) or 'no label column'}); the table is "
                      f"left out ({paths})", file=sys.stderr)
                continue
            is_label = _label_columns(by_group, flags)
            fractions = [columns[i] for i in flags]
            label_cols = [c for c, lab in zip(columns, is_label) if lab]
            errors = [c for c, lab in zip(columns, is_label) if not lab and is_standard_error(c)]
            bounds = [c for c, lab in zip(columns, is_label) if not lab and is_bound(c, columns)]
            measure_cols = [c for c, lab in zip(columns, is_label) if not lab and c not in errors and c not in bounds]
            rows = []
            for gi, group_tables in enumerate(by_group):
                for r in range(len(tables[0]["rows"])):
                    labels = {c: group_tables[0]["rows"][r][i] for i, c in enumerate(columns) if is_label[i]}
                    values = {c: fraction_true([t["rows"][r][i] for t in group_tables]) if c in fractions
                              else mean_interval([t["rows"][r][i] for t in group_tables], level)
                              for i, c in enumerate(columns) if c in measure_cols}
                    values.update({c: pooled_se([t["rows"][r][columns.index(c)] for t in group_tables])
                                   for c in errors})
                    rows.append({"group": gi, "labels": labels, "values": values})
            identifying = identifying_labels([t for g in by_group for t in g], columns, label_cols)
            tables_out[name] = {"labels": label_cols, "identifying": identifying, "measurements": measure_cols,
                                "standard_errors": errors, "not_combined": bounds, "fractions": fractions,
                                "rows": rows}
            # a table of the study's own paired differences (a `reference` column) is not paired again;
            # true/false columns are not differenced
            numbers = [c for c in measure_cols if c not in fractions]
            if "estimator" in label_cols and "reference" not in columns and numbers:
                paired = paired_differences(by_group, columns, numbers, label_cols, reference, level)
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
    run: :func:`aligned_rows`). A row of estimator ``B`` is paired with the row of ``reference`` holding the same other
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
             "paired": {}}
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

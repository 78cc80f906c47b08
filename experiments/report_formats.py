"""The formats of ``torchmm-report`` (:mod:`experiments.report`): report.md, report.csv, report.json,
report.tex (booktabs) and the figure, written from :func:`experiments.report.combine`'s report; split from the
command's module by concern (issue 47)."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

from experiments.files import write_atomic
from experiments.formatting import format_value, is_number, latex_escape
from experiments.formatting import latex_number as _latex_number
from experiments.formatting import latex_table as _latex_table

__all__ = ["dropped_lines", "figure", "row_n", "table_notes", "to_csv", "to_latex", "to_markdown",
           "write_report"]


def _cell(stats: dict, number=format_value, plus_minus: str = " ± ", row_n: int | None = None) -> str:
    """A table cell: the mean, ``± half the interval`` where there is one, and ``(n=k)`` where the cell
    has fewer (or more) replicates than its row's ``row_n``; empty without a mean, ``dropped`` where the
    report could not compute it (a pooled standard error some replicates lack: the notes say why); a
    true/false column's fraction of runs where it is True with its count, ``0.2500 (1/4)``."""
    if stats.get("dropped"):
        return "dropped"
    if stats["mean"] is None:
        return ""
    if "true" in stats:
        return f"{number(stats['mean'])} ({stats['true']}/{stats['n']})"
    text = number(stats["mean"])
    if stats["ci_low"] is not None:
        text += f"{plus_minus}{number((stats['ci_high'] - stats['ci_low']) / 2)}"
    if row_n is not None and stats.get("n") is not None and stats["n"] != row_n:
        text += f" (n={stats['n']})"
    return text


def _latex_cell(stats: dict, row_n: int | None = None) -> str:
    return _cell(stats, _latex_number, " $\\pm$ ", row_n)


def row_n(row: dict, default: int) -> int:
    """A row's ``n``: the most replicates any of its cells has (the runs holding the row without any)."""
    return max((v["n"] for v in row["values"].values() if v["mean"] is not None),
               default=row.get("held_by", default))


def _which(body: dict, paths: list[str]) -> str:
    """Which runs ``paths`` are, by their group's factors and replicates: ``2 of 4 runs:
    scenario.missing=0.7 (seed 0, 1)``."""
    total = sum(len(g["runs"]) for g in body["groups"])
    if len(paths) == total:
        return f"all {total} runs"
    parts = []
    for g in body["groups"]:
        reps = [format_value(rep) for run, rep in zip(g["runs"], g["replicates"]) if run in paths]
        if reps:
            factors = ", ".join(f"{k}={format_value(v)}" for k, v in g["factors"].items())
            parts.append(f"{factors} ({body['replicate']} {', '.join(reps)})" if factors
                         else f"{body['replicate']} {', '.join(reps)}")
    return f"{len(paths)} of {total} runs: " + "; ".join(parts)


def _labels_text(labels: dict) -> str:
    return ", ".join(format_value(v) for v in labels.values() if v not in (None, "")) or "(no label)"


def table_notes(body: dict, table: dict) -> list[str]:
    """What a table's cells lack, one line each: the columns, rows (or the whole table) some runs do not
    hold, naming those runs, and the standard errors the report did not pool (dropped, with why)."""
    absent = table.get("absent", {})
    lines = []
    if absent.get("table"):
        lines.append(f"the table: not in {_which(body, absent['table'])}")
    lines += [f"column {c}: not in {_which(body, paths)}" for c, paths in absent.get("columns", {}).items()]
    lines += [f"row {_labels_text(item['labels'])}: not in {_which(body, item['runs'])}"
              for item in absent.get("rows", [])]
    for row in table["rows"]:
        factors = body["groups"][row["group"]]["factors"]
        names = _labels_text({c: v for c, v in row["labels"].items() if not is_number(v)})
        setting = ", ".join(f"{k}={format_value(v)}" for k, v in factors.items())
        where = ", ".join(x for x in (names, setting) if x)
        lines += [f"{c} of {where}: dropped: {v['dropped']}" for c, v in row["values"].items()
                  if v.get("dropped")]
    return lines


def dropped_lines(body: dict) -> list[str]:
    """The runs' own ``dropped`` entries (what a run could not compute, results.json), with the runs."""
    return [f"{item['metric']}: {item['reason']} ({_which(body, item['runs'])})"
            for item in body.get("dropped", [])]


def to_markdown(report: dict[str, Any]) -> str:
    out = ["# torchmm report", ""]
    for experiment, body in report.items():
        groups = body["groups"]
        pct = f"{100 * body['level']:g} %"
        out += [f"## {experiment}", "",
                f"{sum(len(g['runs']) for g in groups)} runs in {len(groups)} group(s); factors: "
                f"{', '.join(body['factors']) or 'none'}; replicates: {body['replicate']} "
                f"(mean ± half-width of the {pct} Student-t interval over the replicates; n = the replicates "
                "with a value, and (n=k) in a cell with another number).", ""]
        if body.get("left_out"):
            left = sum(item["runs"] for item in body["left_out"])
            out += [f"**Left out: {left} run(s)** (not finished, so not in the tables below):", "",
                    *(f"- `{item['path']}`: {item['reason']}" for item in body["left_out"]), ""]
        for name, table in body["tables"].items():
            factor_cols = body["factors"]
            errors = table.get("standard_errors", [])
            columns = [*factor_cols, *table["labels"], "n", *table["measurements"], *errors]
            lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
            for row in table["rows"]:
                g = groups[row["group"]]
                n = row_n(row, len(g["runs"]))
                cells = [*(format_value(g["factors"][k]) for k in factor_cols), *(format_value(row["labels"][c]) for c in table["labels"]),
                         str(n), *(_cell(row["values"][c], row_n=n)
                                   for c in [*table["measurements"], *errors])]
                lines.append("| " + " | ".join(cells) + " |")
            out += [f"### {name}", "", *lines, ""]
            if errors or table.get("not_combined") or table.get("fractions"):
                out += [_columns_note(table), ""]
            notes = table_notes(body, table)
            if notes:
                out += ["Not in every run, or not computed (no value there; each cell's n counts the runs "
                        "with one):", "", *(f"- {line}" for line in notes), ""]
        for name, paired in (body.get("paired") or {}).items():
            columns, rows = _paired_rows(body, paired, minus=" − ")
            lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
            lines += ["| " + " | ".join(row) + " |" for row in rows]
            out += [f"### {name}: paired differences", "",
                    (f"Each estimator minus {paired['reference']}, run by run ({body['replicate']} paired: the runs "
                     f"share their data), then mean ± half-width of the {pct} Student-t interval over the replicates."),
                    "", *lines, ""]
        if body.get("dropped"):
            out += ["**Dropped in the runs** (each run's results.json `dropped`: what it could not compute, "
                    "so its cells hold no value from those runs):", "",
                    *(f"- {line}" for line in dropped_lines(body)), ""]
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
    if table.get("fractions"):
        parts.append(f"{', '.join(table['fractions'])}: true or false in each run; the fraction of the runs "
                     "where it is true (true/n), no interval")
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
        n = row_n(row, len(g["runs"]))
        labels = [text(format_value(row["labels"][c])) if c != "estimator"
                  else text(format_value(row["labels"][c])) + minus + text(str(paired["reference"]))
                  for c in paired["labels"]]
        rows.append([*(text(format_value(g["factors"][k])) for k in factors), *labels, str(n),
                     *(cell(row["values"][c], row_n=n) for c in paired["measurements"])])
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


def to_latex(report: dict[str, Any]) -> str:
    """``report.tex``: one booktabs table per results table and per paired section (needs
    ``\\usepackage{booktabs}``; see the module docstring)."""
    esc = latex_escape
    out = ["% torchmm-report: booktabs tables (\\usepackage{booktabs}); \\input{report.tex} in a document,",
           "% e.g. \\documentclass{article}\\usepackage{booktabs}\\begin{document}\\input{report.tex}\\end{document}",
           "% cells: mean $\\pm$ half-width of the Student-t interval over the replicates; n = replicates",
           "% with a value (a cell with another number: (n=k)); what runs lack or could not compute:",
           "% comments after each table", ""]
    for experiment, body in report.items():
        groups, factors = body["groups"], body["factors"]
        pct = f"{100 * body['level']:g}\\,\\%"
        out += [f"% {experiment}: left out (not finished): {item['path']}: {item['reason']}"
                for item in body.get("left_out", [])]
        for name, table in body["tables"].items():
            values = [*table["measurements"], *table.get("standard_errors", [])]
            columns = [*factors, *table["labels"], "n", *values]
            rows = []
            for row in table["rows"]:
                g = groups[row["group"]]
                n = row_n(row, len(g["runs"]))
                rows.append([*(esc(format_value(g["factors"][k])) for k in factors),
                             *(esc(format_value(row["labels"][c])) for c in table["labels"]), str(n),
                             *(_latex_cell(row["values"][c], row_n=n) for c in values)])
            align = "l" * (len(factors) + len(table["labels"])) + "r" * (1 + len(values))
            caption = (f"{esc(experiment)}: {esc(name)} (mean $\\pm$ half-width of the {pct} Student-t interval "
                       f"over {esc(body['replicate'])}; n replicates, (n=k) in a cell with another number)")
            out += _latex_table([esc(c) for c in columns], rows, caption, align)
            out += [f"% {experiment}/{name}: {line}" for line in table_notes(body, table)]
        for name, paired in (body.get("paired") or {}).items():
            columns, rows = _paired_rows(body, paired, minus=" $-$ ", cell=_latex_cell, text=esc)
            align = "l" * (len(factors) + len(paired["labels"])) + "r" * (1 + len(paired["measurements"]))
            caption = (f"{esc(experiment)}: {esc(name)}, paired differences: each estimator minus "
                       f"{esc(paired['reference'])} per {esc(body['replicate'])} (mean $\\pm$ half-width of the "
                       f"{pct} Student-t interval)")
            out += _latex_table(columns, rows, caption, align)
        out += [f"% {experiment}: dropped in the runs: {line}" for line in dropped_lines(body)]
    return "\n".join(out)


def figure(report: dict[str, Any]):
    """Each study's first table's first measurement (not a true/false fraction): means with their
    intervals, per group and row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def numbers(table):  # the measurements with a mean and an interval (not a true/false fraction)
        return [c for c in table["measurements"] if c not in table.get("fractions", ())]

    panels = [(exp, name, table) for exp, body in report.items()
              for name, table in list(body["tables"].items())[:1] if numbers(table)]
    if not panels:
        return None
    fig, axes = plt.subplots(len(panels), 1, figsize=(6.5, 2.2 + 0.18 * max(len(t["rows"]) for *_, t in panels)),
                             squeeze=False)
    for ax, (exp, name, table) in zip(axes[:, 0], panels):
        measure = numbers(table)[0]
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
                              *(f"{c}={format_value(row['labels'][c])}" if c != "estimator" and is_number(row["labels"][c])
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

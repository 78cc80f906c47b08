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

__all__ = ["figure", "to_csv", "to_latex", "to_markdown", "write_report"]


def _cell(stats: dict, number=format_value, plus_minus: str = " ± ") -> str:
    """A table cell: the mean, ``± half the interval`` where there is one (empty without a mean); a
    true/false column's fraction of runs where it is True with its count, ``0.2500 (1/4)``."""
    if stats["mean"] is None:
        return ""
    if "true" in stats:
        return f"{number(stats['mean'])} ({stats['true']}/{stats['n']})"
    if stats["ci_low"] is None:
        return number(stats["mean"])
    return f"{number(stats['mean'])}{plus_minus}{number((stats['ci_high'] - stats['ci_low']) / 2)}"


def _latex_cell(stats: dict) -> str:
    return _cell(stats, _latex_number, " $\\pm$ ")


def to_markdown(report: dict[str, Any]) -> str:
    out = ["# torchmm report", ""]
    for experiment, body in report.items():
        groups = body["groups"]
        pct = f"{100 * body['level']:g} %"
        out += [f"## {experiment}", "",
                f"{sum(len(g['runs']) for g in groups)} runs in {len(groups)} group(s); factors: "
                f"{', '.join(body['factors']) or 'none'}; replicates: {body['replicate']} "
                f"(mean ± half-width of the {pct} Student-t interval over the replicates; n = replicates).", ""]
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
                n = max((v["n"] for v in row["values"].values()), default=len(g["runs"]))
                cells = [*(format_value(g["factors"][k]) for k in factor_cols), *(format_value(row["labels"][c]) for c in table["labels"]),
                         str(n), *(_cell(row["values"][c]) for c in [*table["measurements"], *errors])]
                lines.append("| " + " | ".join(cells) + " |")
            out += [f"### {name}", "", *lines, ""]
            if errors or table.get("not_combined") or table.get("fractions"):
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
        out += [f"% {experiment}: left out (not finished): {item['path']}: {item['reason']}"
                for item in body.get("left_out", [])]
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

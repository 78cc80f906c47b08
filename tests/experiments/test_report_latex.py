"""torchmm-report's report.tex (booktabs tables that hold report.json's numbers) and its paired
differences between estimators (estimator minus reference, run by run, over the shared seeds)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from experiments import report as rep
from experiments import report_formats as formats
from tests.experiments.test_report import _synthetic_sweep, _write_run

#: t_{0.975} with 2 degrees of freedom (scipy.stats.t.ppf(0.975, 2))
T975_2 = 4.302652729911275


def _strip_escapes(text: str) -> str:
    return re.sub(r"\\[{}&%$#_]", "", text)


def parse_latex_tables(tex: str) -> list[dict]:
    """A small structural parser: braces balance, environments nest, and each tabular is
    ``\\toprule header \\midrule rows \\bottomrule`` with as many cells per line as its column spec.
    Returns ``[{"caption", "align", "header": [...], "rows": [[...], ...]}]``; AssertionError otherwise."""
    body = "\n".join(line for line in tex.splitlines() if not line.lstrip().startswith("%"))
    plain = _strip_escapes(body)
    depth = 0
    for ch in plain:
        depth += {"{": 1, "}": -1}.get(ch, 0)
        assert depth >= 0, "a } closes nothing"
    assert depth == 0, "unbalanced braces"
    assert plain.count("$") % 2 == 0, "unbalanced math shifts"
    stack: list[str] = []
    for kind, env in re.findall(r"\\(begin|end)\{(\w+)\}", body):
        if kind == "begin":
            stack.append(env)
        else:
            assert stack and stack.pop() == env, f"\\end{{{env}}} does not close the open environment"
    assert not stack, f"unclosed environments {stack}"
    tables = []
    for block in re.findall(r"\\begin\{table\}.*?\\end\{table\}", body, re.DOTALL):
        caption = re.search(r"\\caption\{(.*)\}\n", block).group(1)
        align, inner = re.search(r"\\begin\{tabular\}\{([lcr]+)\}\n(.*?)\\end\{tabular\}", block, re.DOTALL).groups()
        lines = [line.strip() for line in inner.strip().splitlines()]
        assert lines[0] == r"\toprule" and lines[2] == r"\midrule" and lines[-1] == r"\bottomrule", lines
        assert all(rule not in line for line in lines[3:-1] for rule in ("rule",))

        tables.append({"caption": caption, "align": align, "header": _cells(lines[1], align),
                       "rows": [_cells(line, align) for line in lines[3:-1]]})
    return tables


def _cells(line: str, align: str) -> list[str]:
    """The cells of one tabular line: ``a & b \\\\``, as many as the column spec has columns."""
    assert line.endswith(r"\\"), line
    parts = re.split(r"(?<!\\)&", line[:-2])
    assert len(parts) == len(align), (line, align)
    return [p.strip() for p in parts]


def _number(text: str) -> float:
    """A cell's number back: ``1.2345``, ``$-$1.2345``, ``$-1.234\\times10^{-5}$``."""
    text = text.replace("$-$", "-")
    power = re.fullmatch(r"\$(-?[0-9.]+)\\times10\^\{(-?\d+)\}\$", text)
    return float(f"{power.group(1)}e{power.group(2)}") if power else float(text)


def _mean_half(cell: str) -> tuple[float, float | None]:
    mean, sep, half = cell.partition(r"$\pm$")
    return _number(mean.strip()), (_number(half.strip()) if sep else None)


def _close(parsed: float, exact: float) -> bool:
    return parsed == pytest.approx(exact, rel=1e-3, abs=6e-5)  # the cells are rounded to 4 decimals


def test_report_tex_parses_and_holds_the_json_numbers(tmp_path):
    _synthetic_sweep(tmp_path / "sweep", np.random.default_rng(3))
    assert rep.main([str(tmp_path / "sweep")]) == 0
    out = tmp_path / "sweep" / "report"
    tex = (out / "report.tex").read_text()
    body = json.loads((out / "report.json").read_text())["toy"]
    assert "\\usepackage{booktabs}" in tex  # named in its header comment
    assert not any(line.startswith("\\documentclass") for line in tex.splitlines())  # a fragment
    tables = parse_latex_tables(tex)
    assert len(tables) == 2  # rmse, and its paired differences
    main, paired = tables
    assert main["header"] == ["a", "model.b", "estimator", "alpha", "n", "rmse", "nees"]
    assert "rmse" in main["caption"] and "95" in main["caption"]
    rows = body["tables"]["rmse"]["rows"]
    assert len(main["rows"]) == len(rows) == 8
    for cells, row in zip(main["rows"], rows):
        factors = body["groups"][row["group"]]["factors"]
        assert cells[:3] == [str(factors["a"]), factors["model.b"], row["labels"]["estimator"]]
        assert cells[4] == "3"
        for cell, column in zip(cells[5:], ("rmse", "nees")):
            stats = row["values"][column]
            mean, half = _mean_half(cell)
            assert _close(mean, stats["mean"]) and _close(half, (stats["ci_high"] - stats["ci_low"]) / 2), cell
    assert len(paired["rows"]) == len(body["paired"]["rmse"]["rows"]) == 4
    # alpha is the same for every row of an estimator: it does not identify a row, so pairs match on the
    # estimator alone (identifying_labels)
    assert paired["header"] == ["a", "model.b", "estimator", "n", "rmse", "nees"]
    for cells, row in zip(paired["rows"], body["paired"]["rmse"]["rows"]):
        assert cells[2] == "KF $-$ IMM"
        mean, half = _mean_half(cells[4])
        stats = row["values"]["rmse"]
        assert _close(mean, stats["mean"]) and _close(half, (stats["ci_high"] - stats["ci_low"]) / 2)


def test_latex_numbers():
    assert formats._latex_number(-0.5) == "$-$0.5000" and _number("$-$0.5000") == -0.5
    assert formats._latex_number(1.5e-6) == "$1.500\\times10^{-6}$" and _number("$1.500\\times10^{-6}$") == 1.5e-6
    assert _number(formats._latex_number(-2.5e7)) == -2.5e7
    assert formats._latex_cell({"mean": 1.0, "ci_low": 0.5, "ci_high": 1.5}) == "1.0000 $\\pm$ 0.5000"


def test_latex_escapes_and_structure_checks_fail_on_bad_input():
    assert formats.latex_escape("pos_rmse & 5% #1 {x} $") == r"pos\_rmse \& 5\% \#1 \{x\} \$"
    assert formats.latex_escape("a\\b") == r"a\textbackslash{}b"
    good = formats._latex_table(["a\\_b", "n"], [["x", "1"]], "cap", "lr")
    assert parse_latex_tables("\n".join(good))[0]["header"] == ["a\\_b", "n"]
    with pytest.raises(AssertionError):
        parse_latex_tables("\n".join(good).replace("\\bottomrule", ""))
    with pytest.raises(AssertionError):
        parse_latex_tables("\n".join(good).replace("x & 1", "x & 1 & 2"))
    with pytest.raises(AssertionError):
        parse_latex_tables("\n".join(good).replace("\\caption{cap}", "\\caption{cap"))


def _paired_runs(root: Path) -> dict:
    """3 seeds x 3 estimators, two factor settings (R); returns the values written."""
    values = {
        (1, "IMM"): [1.0, 2.0, 3.0], (1, "KF"): [2.0, 4.0, 3.0], (1, "GPB1"): [1.5, 2.5, 3.5],
        (2, "IMM"): [4.0, 4.0, 7.0], (2, "KF"): [5.0, 8.0, 6.0], (2, "GPB1"): [4.0, 4.5, 7.0],
    }
    for R in (1, 2):
        for seed in range(3):
            rows = [[est, values[(R, est)][seed], 10.0 * values[(R, est)][seed]] for est in ("IMM", "KF", "GPB1")]
            config = {"experiment_name": "toy", "seed": seed, "scenario": {"R": R}}
            _write_run(root / f"R={R},seed={seed}", config,
                       {"rmse": {"columns": ["estimator", "pos_rmse", "vel_rmse"], "rows": rows}})
    return values


def _expected(a: list[float], b: list[float]) -> tuple[float, float, float]:
    d = [x - y for x, y in zip(a, b)]
    mean = sum(d) / 3
    sd = math.sqrt(sum((x - mean) ** 2 for x in d) / 2)
    return mean, sd, T975_2 * sd / math.sqrt(3)


def test_paired_differences_equal_a_hand_computation(tmp_path):
    values = _paired_runs(tmp_path / "runs")
    assert rep.main([str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 0
    body = json.loads((tmp_path / "out" / "report.json").read_text())["toy"]
    paired = body["paired"]["rmse"]
    assert paired["reference"] == "IMM" and paired["measurements"] == ["pos_rmse", "vel_rmse"]
    assert len(paired["rows"]) == 4  # (KF, GPB1) x 2 settings of R
    for row in paired["rows"]:
        R = body["groups"][row["group"]]["factors"]["scenario.R"]
        est = row["labels"]["estimator"]
        mean, sd, half = _expected(values[(R, est)], values[(R, "IMM")])
        got = row["values"]["pos_rmse"]
        assert got["n"] == 3
        assert got["mean"] == pytest.approx(mean, rel=1e-12, abs=1e-12)
        assert got["sd"] == pytest.approx(sd, rel=1e-12)
        assert (got["ci_low"], got["ci_high"]) == pytest.approx((mean - half, mean + half), rel=1e-9)
        assert row["values"]["vel_rmse"]["mean"] == pytest.approx(10 * mean, rel=1e-12, abs=1e-12)
    # R=1, KF - IMM: d = (1, 2, 0): mean 1, sd 1
    first = next(r for r in paired["rows"] if r["labels"]["estimator"] == "KF"
                 and body["groups"][r["group"]]["factors"]["scenario.R"] == 1)
    assert first["values"]["pos_rmse"]["mean"] == 1.0 and first["values"]["pos_rmse"]["sd"] == 1.0
    # the paired interval is narrower than the unpaired ones here (the estimators share the seed's luck)
    assert first["values"]["pos_rmse"]["ci_high"] - 1.0 == pytest.approx(T975_2 / math.sqrt(3))

    md = (tmp_path / "out" / "report.md").read_text()
    assert "### rmse: paired differences" in md and "| 1 | KF − IMM | 3 | 1.0000 ± " in md
    lines = (tmp_path / "out" / "report.csv").read_text().splitlines()
    assert lines[0].endswith(",reference")
    paired_lines = [line for line in lines[1:] if line.endswith(",IMM")]
    assert len(paired_lines) == 4 * 2 and len(lines) == 1 + 6 * 2 + 4 * 2
    tex = parse_latex_tables((tmp_path / "out" / "report.tex").read_text())
    assert [t["header"] for t in tex] == [["scenario.R", "estimator", "n", "pos\\_rmse", "vel\\_rmse"]] * 2
    assert "minus IMM" in tex[1]["caption"] and tex[1]["rows"][0][1] == "KF $-$ IMM"


def test_reference_option(tmp_path, capsys):
    values = _paired_runs(tmp_path / "runs")
    assert rep.main([str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--reference", "KF"]) == 0
    body = json.loads((tmp_path / "out" / "report.json").read_text())["toy"]
    paired = body["paired"]["rmse"]
    assert paired["reference"] == "KF"
    assert sorted({r["labels"]["estimator"] for r in paired["rows"]}) == ["GPB1", "IMM"]
    row = next(r for r in paired["rows"] if r["labels"]["estimator"] == "IMM"
               and body["groups"][r["group"]]["factors"]["scenario.R"] == 2)
    assert row["values"]["pos_rmse"]["mean"] == pytest.approx(_expected(values[(2, "IMM")], values[(2, "KF")])[0])
    capsys.readouterr()
    assert rep.main([str(tmp_path / "runs"), "--out", str(tmp_path / "out2"), "--reference", "UKF"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--reference" in err[0] and "GPB1, IMM, KF" in err[0]
    assert not (tmp_path / "out2").exists()


def test_tables_without_an_estimator_column_have_no_paired_section(tmp_path):
    for seed in range(2):
        _write_run(tmp_path / f"s{seed}", {"seed": seed},
                   {"sweep": {"columns": ["alpha", "pos_rmse"], "rows": [["a", 1.0 + seed], ["b", 2.0]]}})
    report = rep.combine(rep.collect_runs([tmp_path]))
    assert report["toy"]["paired"] == {}
    assert len(parse_latex_tables(rep.to_latex(report))) == 1

"""How values and tables are written: a table cell (results.md, report.md) and LaTeX (booktabs: escaped
text, typeset numbers, one table) for torchmm-report's report.tex and a run's results.tex."""

from __future__ import annotations

from typing import Any

__all__ = ["format_value", "is_number", "latex_escape", "latex_number", "latex_table"]


def is_number(value: Any) -> bool:
    """A table cell that is a number (``int`` or ``float``, not ``bool``)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def format_value(value: Any) -> str:
    """A table cell: floats to 4 decimals (or 4 significant digits in e-notation); None and NaN (a value
    that could not be computed: results.json's null, named in "not computed", docs/studies.md) as empty,
    never as a number."""
    if isinstance(value, float):
        if value != value:
            return ""
        if value == 0 or 1e-3 <= abs(value) < 1e5:
            return f"{value:.4f}"
        return f"{value:.3e}"
    return "" if value is None else str(value)


#: LaTeX's special characters in text mode
_LATEX_ESCAPES = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                  "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}",
                  "±": r"$\pm$", "−": "$-$"}


def latex_escape(text: Any) -> str:
    """``text`` safe in LaTeX's text mode (``_`` -> ``\\_``, ...)."""
    return "".join(_LATEX_ESCAPES.get(ch, ch) for ch in str(text))


def latex_number(value: Any) -> str:
    """``format_value(value)`` typeset: a minus sign, not a hyphen; ``1.2e-04`` as ``$1.2\\times10^{-4}$``."""
    text = format_value(value)
    mantissa, e, exponent = text.partition("e")
    if e and exponent.lstrip("+-").isdigit():
        return f"${mantissa}\\times10^{{{int(exponent)}}}$"
    return "$-$" + text[1:] if text.startswith("-") else text


def latex_table(columns: list[str], rows: list[list[str]], caption: str, align: str) -> list[str]:
    """One booktabs table (``\\toprule``/``\\midrule``/``\\bottomrule``) as lines; cells already escaped."""
    return [r"\begin{table}[htbp]", r"\centering", rf"\caption{{{caption}}}", rf"\begin{{tabular}}{{{align}}}",
            r"\toprule", " & ".join(columns) + r" \\", r"\midrule",
            *(" & ".join(row) + r" \\" for row in rows), r"\bottomrule", r"\end{tabular}", r"\end{table}", ""]

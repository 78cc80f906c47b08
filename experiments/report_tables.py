"""How ``torchmm-report`` (:mod:`experiments.report`) lines up one results table of several runs and what a
cell over the replicates is: the runs' columns and rows matched by name, never by position, and the
statistics of a cell (a mean with its Student-t interval, a pooled standard error, a fraction of True).

Runs of one study need not hold the same columns or rows: a metric that cannot be computed in a run (too
few innovations for ``whiteness_lag1``, fewer than two Monte Carlo runs with a value for ``nis_se``) is left
out of that run's table, and the study's own ``paired`` table holds a row only where its difference could
be computed. A table is combined on the **union** of its runs' columns (:func:`union_columns`) and, within
each group of runs, on the union of their rows matched by their text labels (:func:`aligned_rows`): a
column or a row that a run lacks is no value there, so each cell's ``n`` counts the runs that have one, and
the report names the runs that lack it (:func:`absences`). Split from :mod:`experiments.report` by concern.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from typing import Any

from experiments.formatting import is_number

__all__ = ["aligned_rows", "absences", "flag_columns", "fraction_true", "identifying_labels", "is_bound",
           "is_standard_error", "label_columns", "mean_interval", "pooled_se", "se_base", "template_rows",
           "union_columns", "union_table"]


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


def se_base(column: str, columns: list[str]) -> str | None:
    """The column whose standard error ``column`` is: ``<metric>`` for ``<metric>_se``, the column just
    before it for a bare ``se`` (the study tables' ``difference, se`` and ``estimate, se``); None if
    there is none."""
    if column.endswith("_se") and column[:-3] in columns:
        return column[:-3]
    if column == "se" and columns.index(column) > 0:
        before = columns[columns.index(column) - 1]
        return None if is_standard_error(before) else before
    return None


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


def pooled_se(values: list[Any], means: list[Any] | None = None) -> dict[str, Any]:
    """The standard error of the mean of ``n`` independent estimates with standard errors ``values``,
    ``sqrt(sum se_i^2) / n``, as a :func:`mean_interval` record without an interval (its ``mean``).

    ``means``: the estimates themselves, one per replicate as ``values``; the replicates that enter
    their mean are those where it is a finite number (without ``means``: every replicate given). The
    pooled value needs a finite standard error in **each** of them: where only some have one it is not
    computed (``mean`` None, ``dropped`` saying how many lack one; ``n`` the replicates that have one) -
    never the standard error of fewer replicates presented as that of the mean. Where none has one: no
    value (``n`` 0), as for any cell without values (the runs' own ``dropped`` say why)."""
    def finite(v):
        return is_number(v) and math.isfinite(v)

    entering = [i for i in range(len(values)) if means is None or finite(means[i])]
    have = [float(values[i]) for i in entering if finite(values[i])]
    record: dict[str, Any] = {"n": len(have), "mean": None, "sd": None, "ci_low": None, "ci_high": None}
    if not entering:
        if any(finite(v) for v in values):
            record["dropped"] = "no replicate has a value of the quantity it is the standard error of"
        return record
    if 0 < len(have) < len(entering):
        lacking = len(entering) - len(have)
        record["dropped"] = f"{lacking} of the {len(entering)} replicates in the mean have no standard error"
        return record
    if have:
        record["mean"] = math.sqrt(math.fsum(v * v for v in have)) / len(have)
    return record


def flag_columns(tables: list[dict]) -> list[int]:
    """The columns of ``tables`` (one results table of several runs, on the same columns: :func:`union_table`)
    that hold true/false values: some cell is a ``bool`` and every other one is a ``bool`` or empty (None).
    They are measurements, never labels (``pos_armse_inside_95`` is True in one seed and False in another):
    see :func:`fraction_true`."""
    columns = tables[0]["columns"]
    cells = [[row[i] for t in tables for row in t["rows"] if row is not None] for i in range(len(columns))]
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


def _merge_order(sequences: list[list]) -> list:
    """The items of ``sequences`` once each, in the first's order; an item the first lacks goes right after
    the item before it in its own sequence (at the start if none)."""
    out: list = []
    for seq in sequences:
        previous = None
        for item in seq:
            if item not in out:
                out.insert(out.index(previous) + 1 if previous is not None else 0, item)
            previous = item
    return out


def union_columns(tables: list[dict]) -> list[str]:
    """Every column of ``tables`` (one results table of several runs), each once, in the runs' order."""
    return _merge_order([list(t["columns"]) for t in tables])


def union_table(table: dict, columns: list[str]) -> dict:
    """``table`` on ``columns`` (:func:`union_columns`): a column it lacks is empty (None) in each row."""
    where = [table["columns"].index(c) if c in table["columns"] else None for c in columns]
    return {"columns": list(columns),
            "rows": [[None if i is None else row[i] for i in where] for row in table["rows"]]}


def _row_keys(table: dict, key_columns: list[int]) -> list[tuple[str, int]]:
    """Each row's ``(labels, occurrence)``: two rows with the same labels keep their order."""
    seen: dict[str, int] = defaultdict(int)
    out = []
    for row in table["rows"]:
        k = json.dumps([row[i] for i in key_columns], default=str)
        out.append((k, seen[k]))
        seen[k] += 1
    return out


def aligned_rows(tables: list[dict], key_columns: list[int]) -> list[dict]:
    """The tables of one group's runs (on the same columns) on the union of their rows, matched by their
    labels (the cells of ``key_columns``: e.g. ``estimator``), so that a row means the same estimator in
    every run whatever order a run's config listed them in. Each table gets ``"keys"`` (the union's
    ``(labels, occurrence)``, the same in every table) and ``"rows"`` in that order, None where the run does
    not hold the row (no value there: e.g. the study's paired difference of a metric it could not compute)."""
    mine = [_row_keys(t, key_columns) for t in tables]
    keys = _merge_order(mine)
    out = []
    for table, own in zip(tables, mine):
        where = dict(zip(own, table["rows"]))
        out.append({**table, "keys": keys, "rows": [where.get(k) for k in keys]})
    return out


def template_rows(group: list[dict]) -> list[list]:
    """Per row of a group's aligned tables (:func:`aligned_rows`): the first run's row that holds it."""
    return [next(t["rows"][r] for t in group if t["rows"][r] is not None)
            for r in range(len(group[0]["rows"]))]


def label_columns(tables_by_group: list[list[dict]], flags: list[int] = ()) -> list[bool]:
    """Per column: is it a label? Non-numeric columns are (not the true/false ``flags``, which are
    measurements); a numeric one is if it holds the same value (None included: a run without the column
    has None there) in every run of each group that holds the row, given that some group has replicates -
    else (one run per group) in every run holding the row."""
    columns = tables_by_group[0][0]["columns"]
    replicated = [g for g in tables_by_group if len(g) > 1]
    pools = replicated or [[t for g in tables_by_group for t in g]]
    labels = []
    for c in range(len(columns)):
        if c in flags:
            labels.append(False)
            continue
        numeric = any(is_number(row[c]) for g in tables_by_group for t in g for row in t["rows"]
                      if row is not None)
        same = True
        for pool in pools:
            seen: dict[Any, set] = defaultdict(set)
            for t in pool:
                for key, row in zip(t["keys"], t["rows"]):
                    if row is not None:
                        seen[key].add(json.dumps(row[c], default=str))
            same = same and all(len(v) == 1 for v in seen.values())
        labels.append(not numeric or same)
    return labels


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
                if row is not None:
                    seen[json.dumps(row[est], default=str)].add(json.dumps(row[i], default=str))
            if any(len(v) > 1 for v in seen.values()):
                out.append(c)
                break
    return out


def absences(paths: list[str], own_columns: list[list[str]], columns: list[str],
             by_group: list[list[dict]], group_paths: list[list[str]], label_cols: list[str]) -> dict:
    """What some runs of a table lack: ``{"columns": {column: [run paths]}, "rows": [{"group", "labels",
    "runs": [run paths]}]}`` (empty parts left out). ``paths``/``own_columns``: each run holding the table
    and its own columns; ``by_group``/``group_paths``: each group's aligned tables (:func:`aligned_rows`) and
    their runs' paths."""
    out: dict[str, Any] = {}
    missing = {c: [p for p, own in zip(paths, own_columns) if c not in own] for c in columns}
    if any(missing.values()):
        out["columns"] = {c: runs for c, runs in missing.items() if runs}
    rows = []
    for gi, (group, runs) in enumerate(zip(by_group, group_paths)):
        for r, row in enumerate(template_rows(group) if group else []):
            lacking = [p for p, t in zip(runs, group) if t["rows"][r] is None]
            if lacking:
                rows.append({"group": gi, "labels": {c: row[columns.index(c)] for c in label_cols
                                                     if not is_number(row[columns.index(c)])},
                             "runs": lacking})
    if rows:
        out["rows"] = rows
    return out

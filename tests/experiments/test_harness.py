"""Harness pieces later studies rely on: results files, published tables, generators, units."""

from __future__ import annotations

import json
import math

import torch
from omegaconf import OmegaConf

from experiments.harness import Results, open_context


def test_results_files_schema_and_published_table(tmp_path):
    results = Results(tmp_path, "demo", {"mc_runs": 3}, "A demo.")
    table = results.table("table1", ["ratio", "pos_rmse"],
                          published={"columns": ["ratio", "pos_rmse"], "rows": [[0.1, 5.8755]], "source": "paper 000"})
    table.rows.append([0.1, torch.tensor(5.9)])
    results.metric("IMM", "nees", math.nan)
    results.timing["IMM"] = 0.001
    results.save()
    data = json.loads((tmp_path / "results.json").read_text())
    assert set(data) == {"experiment", "config", "metrics", "tables", "timing", "provenance", "dropped"}
    assert data["tables"]["table1"] == {"columns": ["ratio", "pos_rmse"], "rows": [[0.1, 5.9]]}
    assert data["metrics"]["IMM"]["nees"] is None  # NaN is not valid JSON
    md = (tmp_path / "results.md").read_text()
    assert "Published (paper 000)" in md and "5.8755" in md and "5.9000" in md


def _ctx(tmp_path, seed=0):
    cfg = OmegaConf.create({"dtype": "float64", "device": "cpu", "seed": seed, "progress": False,
                            "logger": {"kind": "none"}})
    return open_context(cfg, tmp_path, OmegaConf.to_container(cfg), "demo")


def test_generators_depend_on_seed_and_key_not_on_order(tmp_path):
    ctx = _ctx(tmp_path)
    a1 = torch.rand(3, generator=ctx.generator("data", "x"))
    b = torch.rand(3, generator=ctx.generator("data", "y"))
    a2 = torch.rand(3, generator=ctx.generator("data", "x"))
    assert torch.equal(a1, a2) and not torch.equal(a1, b)
    other = torch.rand(3, generator=_ctx(tmp_path / "s1", seed=1).generator("data", "x"))
    assert not torch.equal(a1, other)


def test_units_are_cached_in_the_checkpoint(tmp_path):
    ctx = _ctx(tmp_path)
    calls = []
    value = ctx.unit("u1", lambda: calls.append(1) or {"x": torch.tensor(2.0)})
    assert value == {"x": 2.0}
    again = _ctx(tmp_path).unit("u1", lambda: calls.append(1) or {"x": 3.0})
    assert again == {"x": 2.0} and len(calls) == 1


def test_read_only_per_run_arrays_join_without_a_warning():
    """A Ray worker's arrays arrive read-only (shared zero-copy): joined and summed with the same
    values, without torch's warning about non-writable arrays."""
    import warnings

    import numpy as np

    from experiments.harness import add_runs, join_runs

    parts = [np.arange(6.0).reshape(2, 3), np.arange(6.0, 10.0).reshape(2, 2)]
    for part in parts:
        part.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        joined = join_runs(parts, dim=1)
        total = add_runs([parts[0], parts[0]])
    assert torch.equal(joined, torch.tensor([[0.0, 1, 2, 6, 7], [3, 4, 5, 8, 9]], dtype=torch.float64))
    assert torch.equal(total, 2 * torch.arange(6.0, dtype=torch.float64).reshape(2, 3))
    assert not parts[0].flags.writeable  # the caller's array is left as it was

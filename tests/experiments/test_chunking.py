"""Defect 8: every reported figure combines all chunks, so ``chunk_runs`` changes no result.

``transfer_fraction`` of imm_tf and the mode-probability and influence curves used to be read from
the first chunk only (IMM-TF 0.586 -> 0.565 with ``chunk_runs=2``). For every study that chunks -
imm_tf, imm_baseline and learn_dynamics (held-out evaluation) - the chunked and unchunked results are
compared. (mevsmm filters its runs in blocks of ``block_runs`` with one random stream each, whatever
``chunk_runs``: tests/experiments/test_run_streams.py; so do the particle mode filters elsewhere.)
"""

from __future__ import annotations

import json
import math

import pytest
from hydra import compose, initialize_config_dir

from experiments.run import CONFIG_DIR, run_study

FAST = {
    "imm_tf": ["table1_ratios=[0.3]", "rs_sweep=[1.0]"],
    "imm_baseline": [],
    "learn_dynamics": ["learn.scenario.steps=20", "learn.part_a.iterations=1", "learn.part_b.iterations=1"],
}


def _compose(name: str, *overrides: str):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose("config", overrides=[f"experiment={name}", "progress=false", "logger=none", "figures=false",
                                                    *overrides])


def _assert_same(a, b, path="results", rel_tol=1e-11):
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for key in a:
            if key in ("timing", "config", "relative_time", "provenance", "sha256") or "seconds" in key:
                # wall times, the run's provenance (its times), unit files' checksums (bytes of
                # floats that agree to rounding; the files' arrays are compared through the results)
                continue
            _assert_same(a[key], b[key], f"{path}.{key}", rel_tol)
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{path}[{i}]", rel_tol)
    elif isinstance(a, float) and isinstance(b, float):
        assert math.isclose(a, b, rel_tol=rel_tol, abs_tol=1e-13), (path, a, b)
    else:
        assert a == b, (path, a, b)


def _drop_timing_rows(data: dict) -> dict:
    tables = data.get("tables", {})
    for name in ("table2", "parallel_speed"):  # wall-time tables (mevsmm, smoothing)
        if name in tables and any("second" in str(c) for c in tables[name]["columns"]):
            tables.pop(name)
    return data


@pytest.mark.parametrize("name", sorted(FAST))
def test_chunked_and_unchunked_results_agree(name, tmp_path):
    runs = "mc_runs=7"  # chunks of 3, 3 and 1
    run_study(_compose(name, runs, *FAST[name]), tmp_path / "whole")
    run_study(_compose(name, runs, "chunk_runs=3", *FAST[name]), tmp_path / "chunked")
    for file in ("results.json", "checkpoint.json"):
        whole, chunked = tmp_path / "whole" / file, tmp_path / "chunked" / file
        if not whole.exists():
            continue
        a, b = json.loads(whole.read_text()), json.loads(chunked.read_text())
        a.pop("config_hash", None), b.pop("config_hash", None)
        _assert_same(_drop_timing_rows(a), _drop_timing_rows(b), file)


def test_imm_tf_transfer_fraction_and_curves_cover_every_chunk(tmp_path):
    """The figures of the issue: transfer fraction, mode-probability and influence curves."""
    import numpy as np

    run_study(_compose("imm_tf", "mc_runs=6", *FAST["imm_tf"]), tmp_path / "a")
    run_study(_compose("imm_tf", "mc_runs=6", "chunk_runs=2", *FAST["imm_tf"]), tmp_path / "b")
    a, b = (json.loads((tmp_path / d / "results.json").read_text())["metrics"] for d in ("a", "b"))
    curves_a, curves_b = (np.load(tmp_path / d / "curves.npz") for d in ("a", "b"))
    for name in ("IMM-TF", "IF-TF"):
        assert b[name]["transfer_fraction"] == pytest.approx(a[name]["transfer_fraction"], rel=1e-12)
        tags = [t for t in curves_a.files if "#" not in t and t.endswith(f"/{name}")
                and t.split("/")[0] in ("influence", "influence_abs")]
        tags += [t for t in curves_a.files if t.startswith(f"mode_probability/{name}/") and "#" not in t]
        assert len(tags) >= 3, curves_a.files
        for tag in tags:
            np.testing.assert_allclose(curves_b[tag], curves_a[tag], rtol=1e-11, atol=1e-13)


def test_compile_key_gives_the_same_numbers_and_is_restored(tmp_path):
    """``compile=true``: imm_baseline's IMMs over linear Kalman modes run their fast path under
    torch.compile, with the eager numbers to rounding; the process default is restored afterwards."""
    from torchmm.runtime import fast_paths_compiled

    run_study(_compose("imm_baseline", "mc_runs=4"), tmp_path / "eager")
    run_study(_compose("imm_baseline", "mc_runs=4", "compile=true"), tmp_path / "compiled")
    assert not fast_paths_compiled()
    a, b = (json.loads((tmp_path / d / "results.json").read_text()) for d in ("eager", "compiled"))
    assert a["config"]["compile"] is False and b["config"]["compile"] is True
    a.pop("config"), b.pop("config")
    _assert_same(_drop_timing_rows(a), _drop_timing_rows(b), "results.json", rel_tol=1e-9)

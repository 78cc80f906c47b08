"""Benchmarks stay runnable: tiny sizes, and their own three-way equality check must pass."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_imm_benchmark_runs_and_agrees():
    pytest.importorskip("filterpy")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "imm_vs_filterpy.py"),
         "--runs", "12", "--steps", "15", "--repeats", "1", "--filterpy-runs", "3"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert re.fullmatch(r"speedup_vs_filterpy=[0-9.]+ speedup_vs_numpy=[0-9.]+ speedup_vs_numpy_soa=[0-9.]+",
                        lines[-1]), lines[-1]
    diffs = [float(x) for x in re.findall(r"([0-9.]+e[-+][0-9]+)", next(line for line in lines if "difference" in line))]
    assert diffs and max(diffs) < 1e-9


def test_imm_tf_benchmark_runs_and_agrees():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "imm_tf_throughput.py"),
         "--runs", "8", "--steps", "15", "--repeats", "1", "--numpy-runs", "3"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert re.fullmatch(r"speedup_vs_numpy_loop=[0-9.]+ transfer_overhead_vs_imm=[0-9.]+", lines[-1]), lines[-1]
    diff = float(re.search(r"reference: ([0-9.e+-]+)", proc.stdout).group(1))
    assert diff < 1e-8


def test_gimmaf_benchmark_runs_and_agrees():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "gimmaf_vs_numpy.py"),
         "--runs", "4", "--steps", "10", "--numpy-runs", "1", "--repeats", "1"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    assert re.match(r"speedup_vs_numpy_loop=[0-9.]+", proc.stdout.strip().splitlines()[-1])
    assert float(re.search(r"reference: ([0-9.e+-]+)", proc.stdout).group(1)) < 1e-8

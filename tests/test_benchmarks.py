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
         "--runs", "12", "--steps", "15", "--repeats", "1", "--filterpy-runs", "3", "--no-compile"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert re.fullmatch(r"speedup_vs_filterpy=[0-9.]+ speedup_vs_numpy=[0-9.]+ speedup_vs_numpy_soa=[0-9.]+ "
                        r"compiled_vs_numpy_soa=nan compiled_vs_filterpy=nan compile_s=nan", lines[-1]), lines[-1]
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


def test_gpu_benchmark_runs_on_the_cpu_and_agrees():
    """benchmarks/gpu.py needs only torch and numpy; on the CPU at tiny sizes (no compile) it prints
    its figures and the agreement with the CPU (trivially the same device here, but the same code)."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "gpu.py"), "--device", "cpu", "--runs", "100", "300",
         "--steps", "5", "--check-runs", "20", "--repeats", "1", "--no-compile", "--tracking-runs", "20",
         "--nonlinear-runs", "20"],
        capture_output=True, text=True, timeout=300, env={"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": ""},
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert re.fullmatch(r"imm_run_steps_per_s=[0-9.e+]+ pf_particle_steps_per_s=[0-9.e+]+ "
                        r"pda_track_scans_per_s=[0-9.e+]+ agree=True", lines[-1]), lines
    assert sum(line.startswith("IMM runs=") for line in lines) == 2
    assert sum(line.startswith("PF  runs=") for line in lines) == 2
    assert sum(line.startswith("PDA runs=") for line in lines) == 1
    assert sum(line.startswith(("IMM-EKF runs=", "IMM-UKF runs=")) for line in lines) == 2


def test_imm_layout_benchmark_runs_and_agrees():
    """benchmarks/imm_layout.py (the batch-last route of issue 17) at tiny size, without compiling: its
    SoA step must equal the NumPy SoA reference and torchmm (the script exits non-zero otherwise)."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "imm_layout.py"), "--runs", "20", "--steps", "10",
         "--repeats", "1", "--no-compile"], capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    last = proc.stdout.strip().splitlines()[-1]
    assert re.fullmatch(r"soa_eager_vs_numpy_soa=[0-9.]+ soa_compiled_vs_numpy_soa=nan "
                        r"torchmm_batch_first_vs_numpy_soa=[0-9.]+ torchmm_vs_numpy_soa=[0-9.]+ "
                        r"torchmm_compiled_vs_numpy_soa=nan torchmm_callable_record_vs_numpy_soa=[0-9.]+", last), last


def test_startup_benchmark_runs():
    """benchmarks/startup.py (issue 30) with one repeat: its figures and its last line (no timing asserted)."""
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "startup.py"), "--repeats", "1"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert re.fullmatch(r"help_s=[0-9.]+ import_torchmm_extra_s=-?[0-9.]+", lines[-1]), lines[-1]
    assert sum("best" in line and "median" in line for line in lines) == 3


def test_single_series_benchmark_runs_and_agrees():
    """benchmarks/single_series.py (torchmm against statsmodels on the Nile and Fed funds data, and a
    one-run IMM) at tiny sizes: its equality checks hold and it prints its ratios."""
    pytest.importorskip("statsmodels")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "single_series.py"), "--repeats", "1", "--imm-steps", "20"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": ""},
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    last = proc.stdout.strip().splitlines()[-1]
    assert re.fullmatch(r"nile_ratio=[0-9.]+ fedfunds_ratio=[0-9.]+ imm_us_per_step=[0-9.]+", last), last
    diffs = [float(x) for x in re.findall(r"= ([0-9.]+e[-+][0-9]+)", proc.stdout)]
    assert len(diffs) == 2 and max(diffs) < 1e-8, proc.stdout


def test_threads_benchmark_runs():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "threads.py"), "--runs", "1", "20", "--steps", "3",
         "--particles", "10"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "2", "PATH": ""},
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    assert re.fullmatch(r"worst_auto_vs_one_thread=[0-9.]+", proc.stdout.strip().splitlines()[-1])


def test_ct_imm_benchmark_runs_and_agrees():
    """benchmarks/ct_imm.py (issue 31, goal 3: IMM over EKF and UKF coordinated-turn banks against a
    NumPy batch-last reference) at tiny size: its equality checks (8 runs x 20 steps, 1e-9; torchmm's
    kernel and its eager steps) pass (the script exits non-zero otherwise) and it prints its ratios."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "ct_imm.py"), "--runs", "8", "--steps", "5",
         "--repeats", "1"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": ""},
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert re.fullmatch(r"ekf_ratio_8=[0-9.]+ ukf_ratio_8=[0-9.]+", lines[-1]), lines[-1]
    checks = "\n".join(line for line in lines if line.startswith("equality check"))
    diffs = [float(x) for x in re.findall(r"([0-9.]+e[-+][0-9]+)", checks)]
    assert len(diffs) == 12 and max(diffs) < 1e-9, proc.stdout


def test_small_kernel_benchmark_runs_and_agrees():
    """benchmarks/small_kernel.py (issue 31: the Numba kernel against the batch-last kernel, the
    crossover behind MAX_RUNS) at tiny sizes: its equality asserts hold and it prints the crossover."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "small_kernel.py"), "--runs", "1", "4", "--steps", "5",
         "--repeats", "1"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": ""},
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    assert re.fullmatch(r"crossover_runs=[0-9]+ \(MAX_RUNS = [0-9]+\)", proc.stdout.strip().splitlines()[-1])


def test_engine_throughput_benchmark_runs():
    """benchmarks/engine_throughput.py at tiny sizes (without --against: no worktree in the suite)."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "engine_throughput.py"), "--runs", "6", "--steps", "5",
         "--repeats", "1"], capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert re.fullmatch(r"gpb2_speedup_6=nan vsimm_speedup_6=nan imm_tf_speedup_6=nan "
                        r"two_filter_vs_full_filter_6=[0-9.]+", lines[-1]), lines[-1]
    assert sum(line.split()[0] == "6" for line in lines if line.strip()) == 5  # one row per contender


def test_set_metrics_benchmark_runs_and_agrees_with_stone_soup():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "set_metrics.py"), "--runs", "4", "--steps", "5",
         "--targets", "3", "--stone-soup-sets", "20", "--repeats", "1"], capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    assert re.fullmatch(r"speedup_vs_stone_soup=[0-9.]+", proc.stdout.strip().splitlines()[-1])
    assert float(re.search(r"difference over those 20 pairs \(4 figures each\): ([0-9.e+-]+)", proc.stdout).group(1)) < 1e-9


def test_pda_benchmark_runs_and_agrees_with_stone_soup():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "pda_throughput.py"), "--runs", "3", "--targets", "2",
         "--steps", "4", "--stone-soup-runs", "1", "--repeats", "1"], capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    assert re.fullmatch(r"speedup_vs_stone_soup=[0-9.]+", proc.stdout.strip().splitlines()[-1])
    assert float(re.search(r"final means on those runs: ([0-9.e+-]+)", proc.stdout).group(1)) < 1e-8


def test_tracking_benchmark_runs_and_agrees_with_stone_soup():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "tracking.py"), "--runs", "2", "--targets", "3",
         "--steps", "4", "--stone-soup-runs", "1", "--repeats", "1"], capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    assert re.fullmatch(r"speedup_exact=[0-9.]+ speedup_lbp=[0-9.]+", proc.stdout.strip().splitlines()[-1])
    diff = float(re.search(r"exact Stone Soup .* final means: ([0-9.e+-]+)", proc.stdout).group(1))
    assert diff < 1e-8


def test_estimation_benchmark_runs_and_agrees():
    pytest.importorskip("pykalman")
    pytest.importorskip("statsmodels")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "estimation.py"), "--repeats", "1", "--series", "6",
         "--steps", "30", "--iterations", "3", "--pykalman-series", "2", "--threads", "1"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert re.fullmatch(r"em_robot_speedup=[0-9.]+ em_batch_speedup=[0-9.]+ fedfunds_speedup=[0-9.]+ "
                        r"fedfunds_exog_speedup=[0-9.]+ fedfunds_tvtp_speedup=[0-9.]+", lines[-1])
    # the time-varying transition's fit reaches statsmodels' optimum, through the kernel
    tv_ours, tv_theirs = re.search(r"fedfunds_tvtp: .*llf (-[0-9.]+), kernel linear_gaussian\), statsmodels .*llf "
                                   r"(-[0-9.]+)\)", proc.stdout).groups()
    assert abs(float(tv_ours) - float(tv_theirs)) < 1e-3
    # the regressors' fit reaches statsmodels' optimum, through the kernel (its controls)
    ours, theirs = re.search(r"fedfunds_exog: .*llf (-[0-9.]+), kernel linear_gaussian\), statsmodels .*llf "
                             r"(-[0-9.]+)\)", proc.stdout).groups()
    assert abs(float(ours) - float(theirs)) < 1e-3
    for diff in re.findall(r"difference(?: after \d+)? ([0-9.]+e[-+][0-9]+)", proc.stdout):
        assert float(diff) < 1e-7


def test_murty_benchmark_runs_and_agrees():
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "murty.py"), "--runs", "20", "--reference-runs", "5",
                           "--n", "6", "--d", "8", "--k", "5", "--threads", "1"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert re.fullmatch(r"murty_speedup=[0-9.]+ murty_runs_per_s=[0-9.]+", proc.stdout.strip().splitlines()[-1])
    diff = float(re.search(r"largest cost difference ([0-9.e+-]+)", proc.stdout).group(1))
    assert diff < 1e-9


def test_mht_benchmark_runs():
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "mht.py"), "--targets", "3", "--runs", "4",
                           "--steps", "4", "--hypotheses", "3", "--threads", "1"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert re.fullmatch(r"mht_scans_per_s=[0-9.]+ mht_run_scans_per_s=[0-9.]+ mfa_run_scans_per_s=[0-9.]+ "
                        r"mht_vs_mfa=[0-9.]+", proc.stdout.strip().splitlines()[-1])  # (Stone Soup's MFA timed too)
    # both track: each final median error below 10 m (the measurement noise is 2 m a coordinate)
    errors = [float(v) for v in re.findall(r"final median error ([0-9.]+)", proc.stdout)]
    assert len(errors) == 4 and max(errors) < 10.0, proc.stdout


def test_tracking_scale_benchmark_runs():
    """benchmarks/tracking_scale.py on a tiny grid: every method's cell, the exact JPDA refused beyond 12."""
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "tracking_scale.py"), "--targets", "3", "13",
                           "--clutter", "2", "--runs", "2", "--steps", "6", "--k", "20", "--hypotheses", "2",
                           "--threads", "1"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = [line for line in proc.stdout.splitlines() if line.startswith("| 3 |") or line.startswith("| 13 |")]
    assert len(rows) == 2 and rows[1].split("|")[3].strip() == "-"  # (13 targets: no exact JPDA)
    few, many = ([float(cell.split("/")[0]) for cell in row.split("|")[3:-1] if "/" in cell] for row in rows)
    assert len(few) == 6 and len(many) == 5
    assert all(0 < g < 20.0 for g in few), few  # 3 targets, little clutter: every method tracks (~10 m)
    assert all(0 < g <= 30.0 * 13**0.5 for g in many), many  # (GOSPA's bound with 13 targets and 13 tracks)
    assert re.fullmatch(r"cells=2 best=[A-Za-z_-]+", proc.stdout.strip().splitlines()[-1])


def test_smoother_accuracy_benchmark_runs():
    """benchmarks/smoother_accuracy.py (docs/smoothing.md's table) on two tiny cases: a row per case with the
    three smoothers' errors against the exact smoother, and its last line."""
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "smoother_accuracy.py"), "--cases", "q 6 3 0 0.9",
                           "ct 5 2 1"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = re.findall(r"^\| (q 6 3 0 0.9|ct 5 2 1) \| ([0-9.]+) \| ([0-9.]+) \| ([0-9.]+) \|$", proc.stdout, re.M)
    assert len(rows) == 2, proc.stdout
    assert re.fullmatch(r"worst_ratio_info_vs_kim=[0-9.]+", proc.stdout.strip().splitlines()[-1])

"""Parallel-in-time (associative scan) against sequential Kalman filtering and RTS smoothing.

    PYTHONPATH=. python benchmarks/parallel_kalman.py [--steps 100 1000 10000 100000] [--runs 1 100]
                                                      [--device cpu|cuda] [--dtype float64|float32]

A 2-D constant-velocity target (n = 4) with position measurements (m = 2). For each length T and
batch of runs: the wall time of ``run_filter`` + ``torchmm.smooth`` (sequential: T steps, one after
another) and of ``parallel.filter`` + ``parallel.smooth`` (about 2 log2 T levels of batched ops),
best of ``--repeat``, their ratio, and the largest difference of the smoothed means (equal to
rounding). The scan does O(T) more arithmetic than the sequential filter (a few times as much), so
it pays where many small steps waste the hardware: on a GPU, and on a CPU once the per-step dispatch
of the sequential loop dominates.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402

from torchmm import GaussianBelief, KalmanFilter, parallel, run_filter, smooth  # noqa: E402
from torchmm.models import ConstantVelocity, PositionMeasurement  # noqa: E402


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def _time(fn, repeat, device):
    best = float("inf")
    out = None
    for _ in range(repeat):
        _sync(device)
        tic = time.perf_counter()
        out = fn()
        _sync(device)
        best = min(best, time.perf_counter() - tic)
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[100, 1000, 10000, 100000])
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 100])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    kf = KalmanFilter(ConstantVelocity(2, q=0.1, dtype=dtype), PositionMeasurement(4, [0, 2], 4.0, dtype=dtype)).to(device)
    print(f"device {device}, {args.dtype}, {torch.get_num_threads()} thread(s); n = 4, m = 2")
    print(f"{'T':>8}{'runs':>6}{'sequential s':>14}{'parallel s':>12}{'speed-up':>10}{'max |diff|':>12}")
    for runs in args.runs:
        for steps in args.steps:
            g = torch.Generator().manual_seed(steps)
            z = torch.cumsum(torch.randn(steps, runs, 2, generator=g, dtype=torch.float64), 0).to(device, dtype)
            b0 = GaussianBelief(torch.zeros(runs, 4, dtype=dtype, device=device),
                                10 * torch.eye(4, dtype=dtype, device=device).expand(runs, 4, 4))
            repeat = args.repeat if steps <= 10000 else 1
            with torch.no_grad():
                t_seq, seq = _time(lambda: smooth(kf, run_filter(kf, b0, z)).belief.mean, repeat, device)
                t_par, par = _time(lambda: parallel.smooth(kf, b0, z).belief.mean, repeat, device)
            diff = (seq - par).abs().max().item()
            print(f"{steps:>8}{runs:>6}{t_seq:>14.4f}{t_par:>12.4f}{t_seq / t_par:>10.2f}{diff:>12.2e}", flush=True)


if __name__ == "__main__":
    main()

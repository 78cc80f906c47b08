"""Threads by problem size: the IMM, its two-filter smoother and a particle filter at 1, 400 and 40,000 runs,
on one thread, at torch's setting (``thread_policy("torch")``) and under the default rule
(``thread_policy("auto")``: one thread below ``torchmm.runtime.SMALL_PROBLEM`` state entries).

    python benchmarks/threads.py [--threads 2] [--steps 50] [--load]

``--load`` keeps one other core busy while timing (a shared machine), where spinning threads hurt most.
Prints microseconds a step (best of 3) for each setting; the last line is
``worst_auto_vs_one_thread=<max over the cases of auto / one thread>`` (at most about 1: the rule never
makes a small problem slower than one thread).
"""

from __future__ import annotations

import argparse
import multiprocessing
import time

import torch

from torchmm import (IMM, ConstantVelocity, GaussianBelief, KalmanFilter, ParticleFilter, PositionMeasurement,
                     run_filter, smooth)
from torchmm.runtime import thread_policy


def _busy(seconds: float) -> None:
    end = time.time() + seconds
    while time.time() < end:
        pass


def _best(fn, repeats: int = 3) -> float:
    fn()
    out = []
    for _ in range(repeats):
        tic = time.perf_counter()
        fn()
        out.append(time.perf_counter() - tic)
    return min(out)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 400, 40000])
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--load", action="store_true")
    args = parser.parse_args(argv)
    torch.set_default_dtype(torch.float64)
    motion = ConstantVelocity(1, q=1.0, acceleration=[[0.25], [0.0], [-0.25]])
    sensor = PositionMeasurement(2, [0], 100.0)
    transition = torch.tensor([[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.25, 0.25, 0.5]])
    imm = IMM(KalmanFilter(motion, sensor), transition)
    pf = ParticleFilter(motion.select_mode(1), sensor, num_particles=args.particles)
    load = None
    if args.load:
        load = multiprocessing.Process(target=_busy, args=(3600,), daemon=True)
        load.start()
    worst = 0.0
    print(f"us a step, T = {args.steps}; torch threads {args.threads}{' (one core kept busy)' if args.load else ''}")
    print(f"{'work':<22}{'runs':>7}{'1 thread':>12}{'torch':>12}{'auto':>12}")
    try:
        for runs in args.runs:
            z = torch.randn(args.steps, runs, 1, generator=torch.Generator().manual_seed(0)) * 10
            prior = GaussianBelief.create([0.0, 1.0], torch.eye(2) * 100).expand(runs)
            b0 = imm.initial_belief(prior)
            traj = run_filter(imm, b0, z)
            cases = {
                "IMM filter": lambda: run_filter(imm, b0, z, record="estimate"),
                "IMM two-filter smoother": lambda: smooth(traj),
                "particle filter": lambda: run_filter(pf, pf.initial_belief(prior, generator=torch.Generator().manual_seed(1)),
                                                      z, generator=torch.Generator().manual_seed(2), record="estimate"),
            }
            for name, fn in cases.items():
                row = []
                for threads, policy in ((1, "torch"), (args.threads, "torch"), (args.threads, "auto")):
                    torch.set_num_threads(threads)
                    thread_policy(policy)
                    row.append(_best(fn) / args.steps * 1e6)
                worst = max(worst, row[2] / row[0])
                print(f"{name:<22}{runs:>7}{row[0]:>12.1f}{row[1]:>12.1f}{row[2]:>12.1f}")
    finally:
        thread_policy("auto")
        if load is not None:
            load.terminate()
    print(f"worst_auto_vs_one_thread={worst:.2f}")


if __name__ == "__main__":
    main()

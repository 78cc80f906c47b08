"""Where the small Numba kernel beats the batched tensor kernels: the crossover behind ``MAX_RUNS``.

    python benchmarks/small_kernel.py [--runs 1 16 64 256 1024 4096] [--steps 200] [--repeats 5]

A 3-mode IMM over linear Kalman modes (paper 000's modes, n = 2, m = 1, float64, one thread), the
same data, three routes through ``run_filter`` (results checked equal to 1e-9):

* ``numba``: the linear-Gaussian kernel (``torchmm.kernels.linear``, forced with ``fast_path=True``);
* ``batch_last``: the batch-last IMM kernel (``torchmm.kernels.batch_last.imm.BATCH_LAST``, the
  Numba kernel switched off);
* ``steps``: the eager batch-first steps (``fast_path=False``),

each for the likelihood with ``record="estimate"`` and for the likelihood's gradient with respect to
a log-parametrised ``R`` (``negative_log_likelihood`` + ``backward``). Prints microseconds per step
(best of ``--repeats``) and the ratio ``batch_last / numba`` (above 1: the Numba kernel is faster);
the last line is ``crossover_runs=...``, the largest run count at which the Numba kernel is still
faster for both the likelihood and its gradient.
"""

from __future__ import annotations

import argparse
import time

import torch

torch.set_num_threads(1)


def _best(fn, repeats: int) -> float:
    fn()
    out = []
    for _ in range(repeats):
        tic = time.perf_counter()
        fn()
        out.append(time.perf_counter() - tic)
    return min(out)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 16, 64, 256, 1024, 4096])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)

    import torchmm.kernels.linear as linear
    from torchmm import IMM, ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, run_filter
    from torchmm.learn import negative_log_likelihood
    from torchmm.models import learnable_noise

    linear.load()
    dtype = torch.float64
    motion = ConstantVelocity(1, q=1.0, acceleration=[[0.25], [0.0], [-0.25]], dtype=dtype)
    sensor = PositionMeasurement(2, [0], 100.0, dtype=dtype)
    learnable_noise(sensor, "R", "log_diagonal")
    transition = torch.tensor([[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.25, 0.25, 0.5]], dtype=dtype)
    imm = IMM(KalmanFilter(motion, sensor), transition)
    limit = linear.MAX_RUNS
    print(f"3-mode IMM (n = 2, m = 1), {args.steps} steps, float64, one thread; us a step, best of {args.repeats}")
    print(f"{'runs':>6} | {'numba':>9} {'batch_last':>10} {'steps':>9} {'ratio':>6} | "
          f"{'numba grad':>10} {'b_l grad':>9} {'ratio':>6}")
    crossover = 0
    for runs in args.runs:
        g = torch.Generator().manual_seed(runs)
        prior = imm.initial_belief(GaussianBelief(torch.zeros(runs, 2, dtype=dtype),
                                                  100 * torch.eye(2, dtype=dtype).expand(runs, 2, 2)))
        z = torch.randn(args.steps, runs, 1, generator=g, dtype=dtype) * 10
        per_step = 1e6 / args.steps

        def estimate(**kw):
            with torch.no_grad():
                return run_filter(imm, prior, z, record="estimate", **kw).belief.mean

        def gradient():
            loss = negative_log_likelihood(imm, prior, z, reduction="sum")
            imm.zero_grad()
            loss.backward()

        try:
            linear.MAX_RUNS = 10**9
            reference = estimate(fast_path=False)
            got = estimate(fast_path=True)
            assert torch.allclose(got, reference, rtol=1e-9, atol=1e-9)
            t_numba = _best(lambda: estimate(fast_path=True), args.repeats)
            g_numba = _best(gradient, args.repeats)
            linear.MAX_RUNS = 0
            assert torch.allclose(estimate(), reference, rtol=1e-9, atol=1e-9)
            t_bl = _best(estimate, args.repeats)
            g_bl = _best(gradient, args.repeats)
            t_steps = _best(lambda: estimate(fast_path=False), max(1, args.repeats // 2))
        finally:
            linear.MAX_RUNS = limit
        if t_bl > t_numba and g_bl > g_numba:
            crossover = runs
        print(f"{runs:>6} | {t_numba * per_step:9.1f} {t_bl * per_step:10.1f} {t_steps * per_step:9.1f} "
              f"{t_bl / t_numba:6.2f} | {g_numba * per_step:10.1f} {g_bl * per_step:9.1f} {g_bl / g_numba:6.2f}")
    print(f"crossover_runs={crossover} (MAX_RUNS = {limit})")


if __name__ == "__main__":
    main()

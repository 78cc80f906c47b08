"""Murty's k best assignments, side by side in one run (issue 46): torchmm's batched
:func:`torchmm.assignment.k_best_assignments` against a Python loop over the runs of a Murty built on
scipy's ``linear_sum_assignment`` (the usual way in Python: a heap of subproblems, each child solved from
scratch by scipy, forbidden pairs a large cost), on random ``N x D`` cost matrices.

Prints each one's runs per second, the ratio, and the largest difference between their k costs (ties
may order different assignments; the costs must agree). The last line:
``murty_speedup=... murty_runs_per_s=...``.

    .venv/bin/python benchmarks/murty.py                      # k = 10, N = D = 20, 1000 runs
    .venv/bin/python benchmarks/murty.py --runs 100 --reference-runs 20
"""

from __future__ import annotations

import argparse
import heapq
import time

import numpy as np
import torch


def scipy_murty(cost: np.ndarray, k: int) -> list[float]:
    """The k best assignment costs of one ``(n, m)`` matrix (n <= m) by Murty's partition, each
    subproblem solved from scratch by ``scipy.optimize.linear_sum_assignment``."""
    from scipy.optimize import linear_sum_assignment

    n, m = cost.shape
    big = (np.abs(cost).max() + 1) * (2 * n + 1)

    def solve(forced: dict, forbidden: set):
        c = cost.copy()
        for (i, j) in forbidden:
            c[i, j] = big
        for i, j in forced.items():
            c[i, :] = big
            c[:, j] = big
            c[i, j] = cost[i, j]
        rows, cols = linear_sum_assignment(c)
        total = c[rows, cols].sum()
        if total >= big:
            return None
        return total, cols

    first = solve({}, set())
    heap = [(first[0], 0, {}, frozenset(), tuple(first[1]))]
    out, counter = [], 1
    while heap and len(out) < k:
        total, _, forced, forbidden, cols = heapq.heappop(heap)
        out.append(total)
        forced_now = dict(forced)
        for i in range(n):
            if i in forced:
                continue
            child_forbidden = set(forbidden) | {(i, cols[i])}
            found = solve(forced_now, child_forbidden)
            if found is not None:
                heapq.heappush(heap, (found[0], counter, dict(forced_now), frozenset(child_forbidden), tuple(found[1])))
                counter += 1
            forced_now[i] = cols[i]
    return out + [np.inf] * (k - len(out))


def main() -> None:
    from torchmm.assignment import k_best_assignments

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1000)
    parser.add_argument("--reference-runs", type=int, default=50, help="runs timed for scipy (scaled to --runs)")
    parser.add_argument("--n", type=int, default=20)
    parser.add_argument("--d", type=int, default=20)
    parser.add_argument("--k", type=int, default=10)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(0)
    cost = torch.rand(args.runs, args.n, args.d, dtype=torch.float64, generator=g)
    k_best_assignments(cost[:2], args.k)  # (warm-up)
    tic = time.perf_counter()
    _, ours = k_best_assignments(cost, args.k)
    mine = time.perf_counter() - tic
    sample = min(args.reference_runs, args.runs)
    tic = time.perf_counter()
    theirs = [scipy_murty(c, args.k) for c in cost[:sample].numpy()]
    ref = (time.perf_counter() - tic) * args.runs / sample
    diff = float(np.abs(ours[:sample].numpy() - np.array(theirs)).max())
    print(f"murty: k = {args.k}, {args.n} x {args.d}, {args.runs} runs: torchmm {mine:.2f} s "
          f"({args.runs / mine:.0f} runs/s, {args.threads} threads), scipy loop {ref:.2f} s ({sample} runs timed, "
          f"scaled; {args.runs / ref:.0f} runs/s) ({ref / mine:.1f}x); largest cost difference {diff:.1e}")
    print(f"murty_speedup={ref / mine:.2f} murty_runs_per_s={args.runs / mine:.1f}")


if __name__ == "__main__":
    main()

"""GOSPA over a Monte Carlo study: torchmm's batched ``gospa`` against Stone Soup's ``GOSPAMetric``, same sets.

    python benchmarks/set_metrics.py [--runs 400] [--steps 100] [--targets 10] [--stone-soup-sets 300]

Every run and step has ``--targets`` true points (2-D positions, uniform over 1 km^2) and an estimated
set: each target detected with probability 0.9 (position error 10 m standard deviation) plus Poisson(1)
false points; cut-off ``c = 50`` m, ``p = 2``. torchmm scores all ``runs x steps`` set pairs at once
(padded sets with presence masks, one thread); Stone Soup's ``GOSPAMetric.compute_gospa_metric`` is
called on ``--stone-soup-sets`` of them (its loop over time steps, as a study would call it), timed
and scaled to all; the four figures (distance, localisation, missed, false) of those pairs must agree
to 1e-9 (the script exits non-zero otherwise). The last line is ``speedup_vs_stone_soup=<x>``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import datetime
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchmm.metrics import gospa  # noqa: E402


def sets(runs: int, steps: int, targets: int, seed: int = 0):
    """``truth (T, R, N, 2)``, ``estimates (T, R, K, 2)`` and their presence ``(T, R, K)``."""
    gen = torch.Generator().manual_seed(seed)
    truth = torch.rand(steps, runs, targets, 2, generator=gen, dtype=torch.float64) * 1000
    detected = torch.rand(steps, runs, targets, generator=gen) < 0.9
    hits = truth + 10 * torch.randn(steps, runs, targets, 2, generator=gen, dtype=torch.float64)
    clutter_count = torch.poisson(torch.ones(steps, runs), generator=gen).long().clamp(max=6)
    clutter = torch.rand(steps, runs, 6, 2, generator=gen, dtype=torch.float64) * 1000
    estimates = torch.cat([hits, clutter], dim=-2)
    present = torch.cat([detected, torch.arange(6) < clutter_count.unsqueeze(-1)], dim=-1)
    return truth, estimates, present


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=400)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--targets", type=int, default=10)
    parser.add_argument("--stone-soup-sets", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    from stonesoup.measures import Euclidean
    from stonesoup.metricgenerator.ospametric import GOSPAMetric
    from stonesoup.types.state import State

    c, p = 50.0, 2.0
    truth, estimates, present = sets(args.runs, args.steps, args.targets)
    gospa(estimates[:1], truth[:1], c=c, p=p, estimate_present=present[:1])  # warm-up
    best, out = float("inf"), None
    for _ in range(args.repeats):
        tic = time.perf_counter()
        out = gospa(estimates, truth, c=c, p=p, estimate_present=present)
        best = min(best, time.perf_counter() - tic)
    pairs = args.runs * args.steps
    metric = GOSPAMetric(c=c, p=p, measure=Euclidean())
    when = datetime.datetime(2026, 12, 4)
    flat_truth, flat_est, flat_present = (t.reshape(pairs, *t.shape[2:]).numpy() for t in (truth, estimates, present))
    count = min(args.stone_soup_sets, pairs)
    worst = 0.0
    tic = time.perf_counter()
    results = []
    for k in range(count):
        X = [State(x.reshape(-1, 1), timestamp=when) for x in flat_truth[k]]
        Y = [State(y.reshape(-1, 1), timestamp=when) for y in flat_est[k][flat_present[k]]]
        results.append(metric.compute_gospa_metric(Y, X)[0].value)
    ss_time = (time.perf_counter() - tic) * pairs / count
    for k, value in enumerate(results):
        for key in ("distance", "localisation", "missed", "false"):
            ours = float(out[key].reshape(-1)[k])
            worst = max(worst, abs(ours - value[key]) / max(abs(value[key]), 1.0))
    print(f"GOSPA (c = {c:g}, p = {p:g}) of {args.runs} runs x {args.steps} steps, {args.targets} targets, "
          f"P_D = 0.9, Poisson(1) false points; float64, one thread")
    print(f"torchmm gospa     {best:8.3f} s for {pairs} set pairs ({best / pairs * 1e6:.1f} us a pair, best of "
          f"{args.repeats})")
    print(f"Stone Soup        {ss_time:8.3f} s (GOSPAMetric.compute_gospa_metric on {count} pairs, scaled)")
    print(f"largest relative difference over those {count} pairs (4 figures each): {worst:.1e}")
    if not worst <= 1e-9:
        raise SystemExit(f"torchmm and Stone Soup disagree ({worst:.1e}): the comparison is void")
    print(f"mean GOSPA {float(out['distance'].mean()):.3f} m; localisation {float(out['localisation'].mean()):.1f}, "
          f"missed {float(out['missed'].mean()):.1f}, false {float(out['false'].mean()):.1f} (m^2)")
    print(f"speedup_vs_stone_soup={ss_time / best:.2f}")


if __name__ == "__main__":
    main()

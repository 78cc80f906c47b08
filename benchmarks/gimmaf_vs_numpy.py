"""GIMMAF throughput: torchmm (runs x models batched) vs a per-run, per-model NumPy/SciPy loop.

The paper-004 scenario (3 models, n = 4, m = 2, skew-t noise), ``--runs`` Monte Carlo runs x
``--steps`` steps in float64, same simulated data. torchmm filters all runs in one
``run_filter`` call; the NumPy reference (``tests/reference/vb_numpy.py``) loops over runs, models
and components, timed on ``--numpy-runs`` runs and scaled by ``runs / numpy_runs``. The estimates
must agree (max abs difference printed). Last line: ``speedup_vs_numpy_loop=<x>``.

Usage: ``python benchmarks/gimmaf_vs_numpy.py [--runs 100] [--steps 250] [--numpy-runs 2]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from omegaconf import OmegaConf

from experiments.studies import gimmaf as study
from tests.reference.vb_numpy import gimmaf as gimmaf_numpy
from torchmm import GaussianBelief, run_filter


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--steps", type=int, default=250)
    parser.add_argument("--numpy-runs", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(1)
    g = OmegaConf.load(ROOT / "conf" / "experiment" / "gimmaf.yaml")["gimmaf"]
    g.steps = args.steps
    kw = {"dtype": torch.float64, "device": torch.device("cpu")}
    noise = g.noise
    data = study.simulate(g, args.runs, torch.Generator().manual_seed(0), "skew_t", noise.R, noise.delta,
                          noise.nu, **kw)
    imm = study.build_estimators(g, noise.R, noise.delta, noise.nu, **kw)["GIMMAF"]
    start = GaussianBelief(data["xhat0"], data["P0"].expand(args.runs, 4, 4))
    best = float("inf")
    for _ in range(args.repeats):
        tic = time.perf_counter()
        traj = run_filter(imm, imm.initial_belief(start), data["z"], record=lambda o: o._replace(prior=None))
        best = min(best, time.perf_counter() - tic)
    est = traj.estimate().mean
    bank = imm.bank.filter
    F, Q, H = bank.motion.F.numpy(), bank.motion.Q.numpy(), bank.measurement.H.numpy()
    P = imm.transition.matrix().detach().numpy()
    tic = time.perf_counter()
    diffs = []
    for run in range(args.numpy_runs):
        x_ref, _ = gimmaf_numpy(list(F), Q, H, bank.r.numpy(), bank.delta.numpy(), bank.nu.numpy(), bank.tau,
                                bank.iterations, P, data["xhat0"][run].numpy(), data["P0"].numpy(),
                                data["z"][:, run].numpy())
        diffs.append(np.abs(est[:, run].numpy() - x_ref).max())
    numpy_time = (time.perf_counter() - tic) * args.runs / args.numpy_runs
    print(f"torchmm: {best:.3f} s for {args.runs} runs x {args.steps} steps "
          f"({best / args.steps * 1e3:.2f} ms/step)")
    print(f"numpy loop (scaled from {args.numpy_runs} runs): {numpy_time:.3f} s")
    print(f"max abs difference of the estimates vs the reference: {max(diffs):.3e}")
    print(f"speedup_vs_numpy_loop={numpy_time / best:.2f}")


if __name__ == "__main__":
    main()

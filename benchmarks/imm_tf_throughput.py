"""IMM-TF throughput: torchmm's batched TransferIMM vs a per-run NumPy loop, and its cost over the IMM.

The paper-000 scenario (3 acceleration modes, n = 2, m = 1, R = 100, R_S = 10, source ratio 0.6),
``--runs`` Monte Carlo runs x ``--steps`` steps in float64, the same data for every estimator:

* torchmm IMM-TF: ``TransferIMM`` over all runs and modes at once (``run_filter``);
* torchmm IMM: the plain IMM on the target stream (the cost baseline of the transfer);
* NumPy: the naive float64 reference of the paper's equations (``tests/reference/transfer_numpy.py``),
  one run at a time (the straightforward way to code the paper), timed on ``--numpy-runs`` runs and
  scaled to ``--runs``.

torchmm and the reference must agree (checked to 1e-8 on the runs the reference processed). The
last line is ``speedup_vs_numpy_loop=<x> transfer_overhead_vs_imm=<y>`` (wall-time ratios).

Usage: ``python benchmarks/imm_tf_throughput.py [--runs 400] [--steps 100] [--numpy-runs 20]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.reference.transfer_numpy import imm_tf as imm_tf_numpy  # noqa: E402
from torchmm import IMM, ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, run_filter  # noqa: E402
from torchmm.multimodel import MultiRate, TransferIMM  # noqa: E402
from torchmm.simulate import bernoulli_mask, simulate_jump_system, simulate_measurements  # noqa: E402

TRANSITION = [[0.50, 0.25, 0.25], [0.25, 0.50, 0.25], [0.25, 0.25, 0.50]]


def best_of(repeats: int, fn):
    best, out = float("inf"), None
    for _ in range(repeats):
        tic = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - tic)
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=400)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--numpy-runs", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    dtype = torch.float64
    motion = ConstantVelocity(1, q=1.0, acceleration=torch.tensor([[0.25], [0.0], [-0.25]], dtype=dtype), dtype=dtype)
    sensor = PositionMeasurement(2, [0], torch.tensor(100.0, dtype=dtype))
    source = PositionMeasurement(2, [0], torch.tensor(10.0, dtype=dtype))
    P = torch.tensor(TRANSITION, dtype=dtype)
    prior = GaussianBelief(torch.tensor([10.0, 10.0], dtype=dtype), torch.tensor([[100.0, 1.0], [1.0, 100.0]], dtype=dtype))
    g = torch.Generator().manual_seed(0)
    sim = simulate_jump_system(motion, P, prior, args.steps, (args.runs,), generator=g)
    y = simulate_measurements(sensor, sim.states, generator=g)
    ys = simulate_measurements(source, sim.states, available=bernoulli_mask(args.steps, (args.runs,), 0.6, generator=g),
                               generator=g)
    kf = KalmanFilter(motion, sensor)
    tf, imm = TransferIMM(kf, P, source), IMM(kf, P)
    keep = lambda out: out._replace(prior=None, innovation=None, innovation_cov=None, extras=None)  # noqa: E731
    with torch.no_grad():
        t_tf, traj = best_of(args.repeats, lambda: run_filter(tf, tf.initial_belief(prior.expand(args.runs)),
                                                              MultiRate(y, ys), record=keep))
        t_imm, _ = best_of(args.repeats, lambda: run_filter(imm, imm.initial_belief(prior.expand(args.runs)), y,
                                                            record=keep))
    est = traj.estimate().mean.numpy()
    models = [(motion.F.numpy(), motion.offset[j].numpy(), motion.Q.numpy()) for j in range(3)]
    nr = min(args.numpy_runs, args.runs)
    tic = time.perf_counter()
    diffs = []
    for b in range(nr):
        ref_x, _, _ = imm_tf_numpy(models, sensor.H.numpy(), sensor.R.numpy(), source.H.numpy(), source.R.numpy(),
                                   np.array(TRANSITION), prior.mean.numpy(), prior.cov.numpy(), np.full(3, 1 / 3),
                                   y[:, b].numpy(), ys[:, b].numpy())
        diffs.append(np.abs(ref_x - est[:, b]).max())
    t_np = (time.perf_counter() - tic) * args.runs / nr
    diff = max(diffs)
    print(f"scenario: paper 000, {args.runs} runs x {args.steps} steps, float64, torch threads {torch.get_num_threads()}")
    print(f"torchmm IMM-TF   {t_tf:8.3f} s  ({1e3 * t_tf / args.steps:.3f} ms/step for all runs)")
    print(f"torchmm IMM      {t_imm:8.3f} s")
    print(f"NumPy loop       {t_np:8.3f} s  (measured on {nr} runs, scaled)")
    print(f"max abs difference vs the NumPy reference: {diff:.3e}")
    if diff > 1e-8:
        raise SystemExit(f"torchmm and the NumPy reference disagree: {diff:.3e}")
    print(f"speedup_vs_numpy_loop={t_np / t_tf:.2f} transfer_overhead_vs_imm={t_tf / t_imm:.2f}")


if __name__ == "__main__":
    main()

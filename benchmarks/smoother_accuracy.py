"""Accuracy of the multiple-model smoothers against the exact smoother (docs/smoothing.md's table).

    python benchmarks/smoother_accuracy.py [--cases "ct 9 10 1" "q 8 20 0 0.9" ...]

Each case ``name T runs seed [stay]`` simulates ``runs`` runs of ``T`` steps from a jump-Markov linear system,
runs the IMM, and smooths it three ways: the two-filter smoother's default reading (``method="two_filter"``), the
information-form reading (``"two_filter_info"``) and Kim's (``"kim"``). The reference is the exact smoother:
every mode sequence enumerated (``M^T`` of them), each sequence's Kalman smoother weighted by its prior and
marginal likelihood. A row gives the mean over runs and steps ``0 .. T - 2`` of ``|smoothed mean - exact| /
exact posterior sd``, for each smoother. Cases (the modes and sensor of each):

- ``ct``: constant velocity and coordinated turns of +-0.15 rad/step (``q = 0.01``), positions measured with
  ``R = 25``: the compare study's default modes - modes that differ in ``F``;
- ``ctq``: a CV mode and a turn of 0.3 rad/step that also differ in noise (``q`` 0.01 and 0.5);
- ``q``: two CV modes of ``q`` 0.05 and 2.0 (the same ``F``), ``R = 4``;
- ``acc``: paper 001's target (tests/smoothing/test_two_filter.py): accelerations 0 and 2, ``R = 100``.

The last line is ``worst_ratio_info_vs_kim=<x>`` (the largest two_filter_info / kim error over the cases).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import sys
from pathlib import Path

import torch

from torchmm import IMM, GaussianBelief, KalmanFilter, LinearMotion, run_filter, smooth
from torchmm.models import ConstantVelocity, CoordinatedTurn, PositionMeasurement
from torchmm.simulate import simulate_jump_system, simulate_measurements

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (the enumeration of tests/reference)
from tests.reference.jump_enumeration import exact_moments  # noqa: E402

CASES = ("ct 9 10 1", "ct 9 10 2", "ct 8 10 3", "ctq 10 10 0 0.9", "q 8 20 0 0.9", "q 10 20 0 0.95",
         "acc 11 12 0")
METHODS = ("two_filter", "two_filter_info", "kim")


def setup(case: str, steps: int, runs: int, seed: int, stay: float = 0.9):
    """The case's mode bank, sensor, transition ``(M, M)``, start mode probabilities ``(M,)``, start belief
    ``(runs, n)`` and simulated measurements ``(steps, runs, m)``."""
    t = torch.tensor
    if case == "ct":
        bank = LinearMotion.stack([ConstantVelocity(2, dt=1.0, q=0.01), CoordinatedTurn(omega=0.15, dt=1.0, q=0.01),
                                   CoordinatedTurn(omega=-0.15, dt=1.0, q=0.01)])
        sensor = PositionMeasurement(4, [0, 2], 25.0)
        transition = t([[0.90, 0.05, 0.05], [0.10, 0.90, 0.00], [0.10, 0.00, 0.90]])
        mean, var, mu0 = [0.0, 10.0, 0.0, 0.0], [25.0, 4.0, 25.0, 4.0], torch.full((3,), 1 / 3)
    elif case == "ctq":
        bank = LinearMotion.stack([ConstantVelocity(2, dt=1.0, q=0.01), CoordinatedTurn(omega=0.3, dt=1.0, q=0.5)])
        sensor = PositionMeasurement(4, [0, 2], 25.0)
        transition = t([[stay, 1 - stay], [1 - stay, stay]])
        mean, var, mu0 = [0.0, 10.0, 0.0, 0.0], [25.0, 4.0, 25.0, 4.0], t([0.5, 0.5])
    elif case == "q":
        a, b = ConstantVelocity(1, q=0.05), ConstantVelocity(1, q=2.0)
        bank = LinearMotion(a.F, torch.stack([a.Q, b.Q]))
        sensor = PositionMeasurement(2, [0], 4.0)
        transition = t([[stay, 1 - stay], [1 - stay, stay]])
        mean, var, mu0 = [0.0, 1.0], [4.0, 1.0], t([0.5, 0.5])
    elif case == "acc":
        bank = ConstantVelocity(1, q=0.1, acceleration=[[0.0], [2.0]])
        sensor = PositionMeasurement(2, [0], 100.0)
        transition = t([[0.95, 0.05], [0.1, 0.9]])
        mean, var, mu0 = [0.0, 10.0], [100.0, 10.0], t([0.7, 0.3])
    else:
        raise ValueError(f"case: expected one of ct, ctq, q, acc, got {case!r}")
    prior = GaussianBelief(t(mean), torch.diag(t(var)))
    g = torch.Generator().manual_seed(seed)
    truth = simulate_jump_system(bank, transition, prior, steps=steps, batch_shape=(runs,), generator=g)
    z = simulate_measurements(sensor, truth.states, generator=g)
    start = GaussianBelief(prior.mean.expand(runs, -1), prior.cov.expand(runs, -1, -1))
    return bank, sensor, transition, mu0, start, z


def errors(case: str) -> dict[str, float]:
    """``{method: mean |error| / exact sd}`` of one case (``name T runs seed [stay]``)."""
    parts = case.split()
    bank, sensor, transition, mu0, start, z = setup(parts[0], *map(int, parts[1:4]), *map(float, parts[4:]))
    imm = IMM(KalmanFilter(bank, sensor), transition)
    traj = run_filter(imm, imm.initial_belief(start, mu0), z)
    mean, cov, _ = exact_moments(bank, sensor, transition, mu0, start, z)
    sd = cov.diagonal(dim1=-2, dim2=-1).sqrt()
    return {m: float(((smooth(traj, method=m).belief.estimate().mean - mean).abs() / sd)[:-1].mean())
            for m in METHODS}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES))
    args = parser.parse_args()
    torch.set_default_dtype(torch.float64)
    print(f"| case | {' | '.join(METHODS)} |\n|---|{'---|' * len(METHODS)}")
    worst = 0.0
    for case in args.cases:
        r = errors(case)
        worst = max(worst, r["two_filter_info"] / r["kim"])
        print(f"| {case} | {' | '.join(f'{r[m]:.3f}' for m in METHODS)} |", flush=True)
    print(f"worst_ratio_info_vs_kim={worst:.3f}")


if __name__ == "__main__":
    main()

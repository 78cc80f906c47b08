"""PDA over many targets and runs: torchmm's batched PDA against Stone Soup's per-track loop, same data.

    python benchmarks/pda_throughput.py [--runs 400] [--targets 10] [--steps 30] [--stone-soup-runs 2]

Each run has ``--targets`` targets moving with nearly constant velocity (2-D, ``q = 0.5``, T = 1 s), a
position sensor (R = 25 I m^2), P_D = 0.9 and Poisson clutter (mean 10 a scan over a 2 km square); every
target's track is a PDA filter (Kalman, gate 0.99) fed the whole scan, the tracks of a run independent
(PDA per target, no joint association). torchmm filters every track of every run at once
(``run_filter(PDA(KalmanFilter(...)), ...)``, the scan broadcast over a run's targets, float64, one
thread). Stone Soup 1.9 runs its ``KalmanPredictor``, ``PDAHypothesiser`` and ``PDAUpdater`` track by
track, step by step, as its tutorials do, on ``--stone-soup-runs`` runs (timed and scaled to all); the
tracks' final means on those runs must agree to 1e-8 relative (exit non-zero otherwise). The last line
is ``speedup_vs_stone_soup=<x>``.
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

from torchmm import GaussianBelief, KalmanFilter, run_filter  # noqa: E402
from torchmm.association import PDA  # noqa: E402
from torchmm.models import ConstantVelocity, PositionMeasurement  # noqa: E402
from torchmm.simulate import simulate_detections  # noqa: E402

P_D, CLUTTER, SIDE, R_VAR, Q, GATE = 0.9, 10.0, 2000.0, 25.0, 0.5, 0.99


def scenario(runs: int, targets: int, steps: int, seed: int = 0):
    """Truth ``(T, R, N, 4)``, the scans ``(T, R, D, 2)`` and the tracks' start ``(R, N)``."""
    gen = torch.Generator().manual_seed(seed)
    start = torch.cat([torch.rand(runs, targets, 1, generator=gen) * SIDE / 2 + SIDE / 4,
                       torch.randn(runs, targets, 1, generator=gen) * 5,
                       torch.rand(runs, targets, 1, generator=gen) * SIDE / 2 + SIDE / 4,
                       torch.randn(runs, targets, 1, generator=gen) * 5], dim=-1).double()
    motion = ConstantVelocity(2, dt=1.0, q=Q, noise="continuous", dtype=torch.float64)
    x, states = start, []
    for _ in range(steps):
        x = x @ motion.F.mT + torch.randn(x.shape, generator=gen, dtype=torch.float64) @ torch.linalg.cholesky(motion.Q).mT
        states.append(x)
    truth = torch.stack(states)
    sensor = PositionMeasurement(4, [0, 2], R_VAR, dtype=torch.float64)
    det = simulate_detections(sensor, truth, detection_probability=P_D, clutter_rate=CLUTTER,
                              region=torch.tensor([[0.0, SIDE], [0.0, SIDE]], dtype=torch.float64), generator=gen)
    prior = GaussianBelief(start, torch.diag(torch.tensor([100.0, 25.0, 100.0, 25.0], dtype=torch.float64)))
    return motion, sensor, det.z, prior


def stone_soup(motion, sensor, z: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Final means ``(N, 4)`` of one run's tracks, Stone Soup's PDA track by track."""
    from stonesoup.hypothesiser.probability import PDAHypothesiser
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel
    from stonesoup.models.transition.linear import ConstantVelocity as SSConstantVelocity
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.types.detection import Detection
    from stonesoup.types.state import GaussianState
    from stonesoup.types.track import Track
    from stonesoup.updater.kalman import KalmanUpdater
    from stonesoup.updater.probability import PDAUpdater

    start = datetime.datetime(2026, 12, 4)
    model = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.eye(2) * R_VAR)
    transition = CombinedLinearGaussianTransitionModel([SSConstantVelocity(Q), SSConstantVelocity(Q)])
    hypothesiser = PDAHypothesiser(predictor=KalmanPredictor(transition), updater=KalmanUpdater(model),
                                   clutter_spatial_density=CLUTTER / SIDE**2, prob_detect=P_D, prob_gate=GATE)
    updater = PDAUpdater(model)
    out = []
    for n in range(mean.shape[0]):
        track = Track([GaussianState(mean[n].reshape(-1, 1), cov, timestamp=start)])
        for k in range(z.shape[0]):
            when = start + datetime.timedelta(seconds=k + 1)
            scan = {Detection(d.reshape(-1, 1), timestamp=when, measurement_model=model)
                    for d in z[k] if np.isfinite(d).all()}
            track.append(updater.update(hypothesiser.hypothesise(track, scan, when)))
        out.append(np.asarray(track.state_vector, dtype=float).ravel())
    return np.stack(out)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=400)
    parser.add_argument("--targets", type=int, default=10)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--stone-soup-runs", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    motion, sensor, z, prior = scenario(args.runs, args.targets, args.steps)
    pda = PDA(KalmanFilter(motion, sensor), detection_probability=P_D, clutter_density=CLUTTER / SIDE**2,
              gate_probability=GATE)
    scans = z.unsqueeze(2)  # (T, R, 1, D, 2): every target of a run sees the run's scan
    best, traj = float("inf"), None
    with torch.no_grad():
        run_filter(pda, prior, scans[:2], record="estimate")  # warm-up
        for _ in range(args.repeats):
            tic = time.perf_counter()
            traj = run_filter(pda, prior, scans, record="estimate")
            best = min(best, time.perf_counter() - tic)
    count = min(args.stone_soup_runs, args.runs)
    tic = time.perf_counter()
    theirs = [stone_soup(motion, sensor, z[:, r].numpy(), prior.mean[r].numpy(), prior.cov.numpy())
              for r in range(count)]
    ss_time = (time.perf_counter() - tic) * args.runs / count
    ours = traj.belief.mean[-1, :count].numpy()
    diff = max(float(np.abs(o - t).max() / np.abs(t).max()) for o, t in zip(ours, theirs))
    tracks = args.runs * args.targets
    print(f"PDA, {args.runs} runs x {args.targets} targets ({tracks} tracks) x {args.steps} scans, P_D = {P_D}, "
          f"clutter {CLUTTER:g} a scan (D = {z.shape[-2]} rows), float64, one thread")
    print(f"torchmm           {best:8.3f} s ({best / (tracks * args.steps) * 1e6:.2f} us a track-scan, best of "
          f"{args.repeats})")
    print(f"Stone Soup        {ss_time:8.3f} s (track by track on {count} runs, scaled)")
    print(f"largest relative difference of the final means on those runs: {diff:.1e}")
    if not diff <= 1e-8:
        raise SystemExit(f"torchmm and Stone Soup disagree ({diff:.1e}): the comparison is void")
    print(f"speedup_vs_stone_soup={ss_time / best:.1f}")


if __name__ == "__main__":
    main()

"""JPDA over many targets and runs: torchmm's batched JPDA against Stone Soup's loop, same data.

    python benchmarks/tracking.py [--runs 400] [--targets 10] [--steps 30] [--stone-soup-runs 2]

The scenario of benchmarks/pda_throughput.py: per run, ``--targets`` targets moving with nearly
constant velocity over a 2 km square (2-D, ``q = 0.5``, T = 1 s), a position sensor (R = 25 I m^2),
P_D = 0.9 and Poisson clutter (mean 10 a scan). A run's tracks share each scan and are associated
jointly: JPDA with a Kalman filter, gate 0.99, float64, one thread.

* ``exact``: torchmm's ``JPDA(method="exact")`` (every joint event) against Stone Soup 1.9's ``JPDA``
  associator with ``PDAHypothesiser`` and ``PDAUpdater`` (every joint event of the gated hypotheses).
* ``lbp``: ``JPDA(method="lbp")`` against Stone Soup's ``JPDAwithLBP`` (loopy belief propagation,
  Williams & Lau 2014; Stone Soup's own stopping rule, delta 1e-3, against torchmm's tolerance 1e-13).

Stone Soup runs track by track and scan by scan as its tutorials do, on ``--stone-soup-runs`` runs
(timed, scaled to all). The exact final means must agree to 1e-8 relative (exit non-zero otherwise);
the belief-propagation ones are printed (their stopping rules differ). The last line is
``speedup_exact=<x> speedup_lbp=<x>``.
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

from benchmarks.pda_throughput import CLUTTER, GATE, P_D, R_VAR, SIDE, Q, scenario  # noqa: E402
from torchmm import KalmanFilter, run_filter  # noqa: E402
from torchmm.association import JPDA  # noqa: E402


def stone_soup(z: np.ndarray, mean: np.ndarray, cov: np.ndarray, lbp: bool) -> np.ndarray:
    """Final means ``(N, 4)`` of one run's tracks, Stone Soup's JPDA scan by scan."""
    from stonesoup.dataassociator.probability import JPDA as SSJPDA
    from stonesoup.dataassociator.probability import JPDAwithLBP
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
    associator = JPDAwithLBP(hypothesiser=hypothesiser) if lbp else SSJPDA(hypothesiser=hypothesiser)
    updater = PDAUpdater(model)
    tracks = [Track([GaussianState(m.reshape(-1, 1), cov, timestamp=start)]) for m in mean]
    for k in range(z.shape[0]):
        when = start + datetime.timedelta(seconds=k + 1)
        scan = {Detection(d.reshape(-1, 1), timestamp=when, measurement_model=model)
                for d in z[k] if np.isfinite(d).all()}
        hypotheses = associator.associate(set(tracks), scan, when)
        for track in tracks:
            track.append(updater.update(hypotheses[track]))
    return np.stack([np.asarray(t.state_vector, dtype=float).ravel() for t in tracks])


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
    count = min(args.stone_soup_runs, args.runs)
    tracks = args.runs * args.targets
    print(f"JPDA, {args.runs} runs x {args.targets} targets ({tracks} tracks) x {args.steps} scans, P_D = {P_D}, "
          f"clutter {CLUTTER:g} a scan (D = {z.shape[-2]} rows), float64, one thread")
    speedups = {}
    for method in ("exact", "lbp"):
        jpda = JPDA(KalmanFilter(motion, sensor), detection_probability=P_D, clutter_density=CLUTTER / SIDE**2,
                    gate_probability=GATE, method=method)
        best, traj = float("inf"), None
        with torch.no_grad():
            run_filter(jpda, prior, z[:2], record="estimate")  # warm-up
            for _ in range(args.repeats):
                tic = time.perf_counter()
                traj = run_filter(jpda, prior, z, record="estimate")
                best = min(best, time.perf_counter() - tic)
        tic = time.perf_counter()
        theirs = [stone_soup(z[:, r].numpy(), prior.mean[r].numpy(), prior.cov.numpy(), lbp=method == "lbp")
                  for r in range(count)]
        ss_time = (time.perf_counter() - tic) * args.runs / count
        ours = traj.belief.mean[-1, :count].numpy()
        diff = max(float(np.abs(o - t).max() / np.abs(t).max()) for o, t in zip(ours, theirs))
        print(f"{method:5s} torchmm    {best:8.3f} s ({best / (tracks * args.steps) * 1e6:.2f} us a track-scan, best "
              f"of {args.repeats})")
        print(f"{method:5s} Stone Soup {ss_time:8.3f} s (on {count} runs, scaled); largest relative difference of "
              f"the final means: {diff:.1e}")
        if method == "exact" and not diff <= 1e-8:
            raise SystemExit(f"torchmm and Stone Soup disagree ({diff:.1e}): the comparison is void")
        speedups[method] = ss_time / best
    print(f"speedup_exact={speedups['exact']:.1f} speedup_lbp={speedups['lbp']:.1f}")


if __name__ == "__main__":
    main()

"""MHT throughput (issue 46): torchmm's batched MHT (``torchmm.association.MHT``, Murty per hypothesis,
N-scan pruning) over ``--targets`` targets in ``--clutter`` clutter points a scan, ``--runs`` runs, beside
the exact JPDA and the k-best JPDA on the same scans (one run). No external MHT is timed yet: Stone Soup's
multi-frame assignment (``stonesoup.dataassociator.mfa``) is the reference the issue names, left for later.

Prints scans per second (a scan: every run's update) and run-scans per second for each. The last line:
``mht_scans_per_s=... mht_run_scans_per_s=...``.

    .venv/bin/python benchmarks/mht.py                                  # 10 targets, clutter 20, 100 runs
    .venv/bin/python benchmarks/mht.py --targets 4 --runs 10 --steps 5 --hypotheses 4
"""

from __future__ import annotations

import argparse
import time

import torch


def main() -> None:
    from torchmm import GaussianBelief, KalmanFilter, run_filter
    from torchmm.association import JPDA, MHT
    from torchmm.models import ConstantVelocity, PositionMeasurement
    from torchmm.simulate import simulate_detections

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--targets", type=int, default=10)
    parser.add_argument("--clutter", type=float, default=20.0)
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--hypotheses", type=int, default=10)
    parser.add_argument("--n-scan", type=int, default=3)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    N, runs, T = args.targets, args.runs, args.steps
    dt = torch.float64
    motion = ConstantVelocity(2, dt=1.0, q=0.5, dtype=dt)
    sensor = PositionMeasurement(4, [0, 2], torch.eye(2, dtype=dt) * 4.0)
    g = torch.Generator().manual_seed(0)
    start = torch.zeros(runs, N, 4, dtype=dt)
    start[..., 0] = torch.linspace(-400, 400, N, dtype=dt)
    start[..., 1] = 2.0
    start[..., 3] = torch.linspace(10, -10, N, dtype=dt)  # converging paths
    truth = start.unsqueeze(0) + torch.cumsum(torch.randn(T, runs, N, 4, generator=g, dtype=dt) * 0.3, 0)
    truth[..., 0] += torch.arange(T, dtype=dt).view(-1, 1, 1) * start[..., 1]
    truth[..., 2] += torch.arange(T, dtype=dt).view(-1, 1, 1) * start[..., 3]
    region = torch.tensor([[-600.0, 600.0], [-600.0, 600.0]])
    det = simulate_detections(sensor, truth, detection_probability=0.9, clutter_rate=args.clutter, region=region,
                              generator=g)
    options = {"detection_probability": 0.9, "clutter_density": args.clutter / 1200.0**2, "gate_probability": 0.99}
    prior = GaussianBelief(truth[0], torch.eye(4, dtype=dt) * 4.0)
    kf = KalmanFilter(motion, sensor)
    trackers = {"MHT": MHT(kf, hypotheses=args.hypotheses, n_scan=args.n_scan, **options),
                "JPDA (k-best, 100)": JPDA(kf, method="kbest", k=100, **options)}
    if N <= 12:
        trackers["JPDA (exact)"] = JPDA(kf, **options)
    rates = {}
    for name, tracker in trackers.items():
        b0 = tracker.initial_belief(prior) if isinstance(tracker, MHT) else prior
        run_filter(tracker, b0, det.z[:2], record="estimate")  # (warm-up: Numba's first load)
        tic = time.perf_counter()
        with torch.no_grad():
            traj = run_filter(tracker, b0, det.z, record="estimate")
        seconds = time.perf_counter() - tic
        err = (traj.belief.mean[-1][..., [0, 2]] - truth[-1][..., [0, 2]]).norm(dim=-1).median()
        rates[name] = T / seconds
        print(f"{name}: {T} scans x {runs} runs x {N} targets, {det.z.shape[-2]} detection slots: {seconds:.2f} s, "
              f"{T / seconds:.1f} scans/s, {T * runs / seconds:.0f} run-scans/s; final median error {float(err):.2f}")
    print(f"mht_scans_per_s={rates['MHT']:.2f} mht_run_scans_per_s={rates['MHT'] * runs:.1f}")


if __name__ == "__main__":
    main()

"""MHT throughput (issue 46): torchmm's batched MHT (``torchmm.association.MHT``, Murty per hypothesis,
N-scan pruning) over ``--targets`` targets in ``--clutter`` clutter points a scan, ``--runs`` runs, beside
the exact JPDA and the k-best JPDA on the same scans, and Stone Soup's multi-frame assignment
(``MFADataAssociator(MFAHypothesiser(PDAHypothesiser(...)), slide_window=n_scan)``, Xia et al. 2019, the
MHT-like associator Stone Soup ships; needs ``ortools``) on ``--reference-runs`` of the same runs, one run
at a time as Stone Soup tracks, with the same F, Q, R, P_D, clutter density and gate.

Prints scans per second (a scan: every run's update) and run-scans per second for each, the final
median position error of each (MFA: the mean of each track's mixture). The last line:
``mht_scans_per_s=... mht_run_scans_per_s=... mfa_run_scans_per_s=... mht_vs_mfa=...`` (the two
run-scan rates' ratio; ``nan`` without ortools).

    .venv/bin/python benchmarks/mht.py                                  # 10 targets, clutter 20, 100 runs
    .venv/bin/python benchmarks/mht.py --targets 4 --runs 10 --steps 5 --hypotheses 4
"""

from __future__ import annotations

import argparse
import math
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
    parser.add_argument("--reference-runs", type=int, default=1, help="runs Stone Soup's MFA tracks (0: none)")
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
    mfa = stone_soup_mfa(motion, sensor, truth, det.z, prior, options, args) if args.reference_runs else math.nan
    print(f"mht_scans_per_s={rates['MHT']:.2f} mht_run_scans_per_s={rates['MHT'] * runs:.1f} "
          f"mfa_run_scans_per_s={mfa:.2f} mht_vs_mfa={rates['MHT'] * runs / mfa:.1f}")


def stone_soup_mfa(motion, sensor, truth, z, prior, options: dict, args) -> float:
    """Stone Soup's MFA on the first ``--reference-runs`` runs: run-scans per second (nan without ortools)."""
    import datetime

    import numpy as np
    try:
        from stonesoup.dataassociator.mfa import MFADataAssociator
    except ImportError as err:  # (ortools: an optional dependency of Stone Soup's MFA)
        print(f"Stone Soup MFA: not timed ({err})")
        return math.nan
    from stonesoup.hypothesiser.mfa import MFAHypothesiser
    from stonesoup.hypothesiser.probability import PDAHypothesiser
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import LinearGaussianTimeInvariantTransitionModel
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.types.detection import Detection
    from stonesoup.types.mixture import GaussianMixture
    from stonesoup.types.numeric import Probability
    from stonesoup.types.state import TaggedWeightedGaussianState
    from stonesoup.types.track import Track
    from stonesoup.types.update import GaussianMixtureUpdate
    from stonesoup.updater.kalman import KalmanUpdater

    transition = LinearGaussianTimeInvariantTransitionModel(transition_matrix=motion.F.numpy(),
                                                            covariance_matrix=motion.Q.numpy())
    measurement = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=sensor.R.numpy())
    predictor, updater = KalmanPredictor(transition), KalmanUpdater(measurement)
    hypothesiser = MFAHypothesiser(PDAHypothesiser(predictor, updater, options["clutter_density"],
                                                   prob_gate=options["gate_probability"],
                                                   prob_detect=options["detection_probability"]))
    associator = MFADataAssociator(hypothesiser, slide_window=max(1, args.n_scan))
    start = datetime.datetime(2026, 12, 7)
    T, errors, seconds = z.shape[0], [], 0.0
    for r in range(args.reference_runs):
        tracks = [Track([GaussianMixture([TaggedWeightedGaussianState(
            prior.mean[r, i].numpy().reshape(-1, 1), prior.cov.expand(*prior.mean.shape, 4)[r, i].numpy(), timestamp=start,
            weight=Probability(1), tag=[])])]) for i in range(prior.mean.shape[1])]
        tic = time.perf_counter()
        for k in range(T):
            when = start + datetime.timedelta(seconds=k + 1)
            rows = z[k, r][torch.isfinite(z[k, r]).all(-1)].numpy()
            detections = {Detection(row.reshape(-1, 1), timestamp=when, measurement_model=measurement) for row in rows}
            for track, hypotheses in associator.associate(set(tracks), detections, when).items():
                parts = [updater.update(h) if h else h.prediction for h in hypotheses]
                track.append(GaussianMixtureUpdate(components=parts, hypothesis=hypotheses))
        seconds += time.perf_counter() - tic
        for i, track in enumerate(tracks):
            parts = track.state.components
            w = np.array([float(c.weight) for c in parts])
            mean = sum(wi * np.asarray(c.state_vector, float).ravel() for wi, c in zip(w / w.sum(), parts))
            errors.append(float(np.hypot(*(mean[[0, 2]] - truth[-1, r, i, [0, 2]].numpy()))))
    rate = T * args.reference_runs / seconds
    print(f"Stone Soup MFA (slide window {max(1, args.n_scan)}): {T} scans x {args.reference_runs} run(s): "
          f"{seconds:.2f} s, {rate:.2f} run-scans/s; final median error {float(np.median(errors)):.2f}")
    return rate


if __name__ == "__main__":
    main()

"""Paper 002, Example 2: batched torch fusion vs a hand-written NumPy loop, in one process.

torchmm: all sensors and runs batched (non-augmented local filters, Theorem 4/6 cross-covariances,
matrix-weighted fusion), and the augmented formulation for comparison (the paper's claim: the
non-augmented method is cheaper). Reference: float64 NumPy, gains and weights computed once
(they are data-independent), then a Python loop over runs, sensors and steps for the estimates.
Prints the timings, the largest difference of the fused estimates, and the ratios on the last line.

    python benchmarks/fusion_throughput.py [--runs 1000] [--steps 100] [--numpy-runs 50]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torchmm.fusion import (
    MultiSensorSystem,
    augmented_local_estimates,
    cross_covariances,
    cross_predictor_stats,
    fuse,
    local_estimates,
    local_predictor_stats,
    simulate_fusion,
)


def ups() -> MultiSensorSystem:
    return MultiSensorSystem.from_correlation(
        A=[[0.9226, -0.6330, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], Gamma=[[0.5], [0.0], [0.2]], Qw=[[5.0]],
        C=[[[23.738, 20.287, 0.0]]] * 3, Ct=[[[8.0, 12.0, 3.0]], [[10.0, 8.0, 5.0]], [[8.0, 6.0, 10.0]]],
        h=[0.6, -0.7, 0.8], Qp=[2.0, 3.0, 0.5], d=[[[-0.5]], [[0.4]], [[-1.0]]],
        Q_eta=[[[5.0]], [[15.0]], [[10.0]]], mu0=[0.0, 0.0, 0.0], P0=0.1 * torch.eye(3, dtype=torch.float64),
        dtype=torch.float64)


def numpy_fused_filter(sys: MultiSensorSystem, y: np.ndarray) -> np.ndarray:
    """Thm 1 + filter update + matrix fusion; loops over runs, sensors and steps. ``y (T, R, L, m)``."""
    f = lambda t: t.numpy()  # noqa: E731
    A, G, Qw, C, Ct, h, Qv = f(sys.A), f(sys.Gamma), f(sys.Qw), f(sys.C), f(sys.Ct), f(sys.h), f(sys.Qv)
    R_, Qp, Qr0, mu0, P0 = f(sys.R), f(sys.Qp), f(sys.Qr0), f(sys.mu0), f(sys.P0)
    T, R, L, m = y.shape
    n = A.shape[0]
    GQG = G @ Qw @ G.T
    # offline: gains per sensor and step (Theorem 1), filter gains K = (Px C^T + Pxr Ct^T) Qe^-1
    Xi = P0 + np.outer(mu0, mu0)
    Qr = Qr0.copy()
    Px = [P0.copy() for _ in range(L)]
    Pr = [Qr0[i] * Xi for i in range(L)]
    Pxr = [np.zeros((n, n)) for _ in range(L)]
    Lx, Lr, K = np.zeros((T, L, n, m)), np.zeros((T, L, n, m)), np.zeros((T, L, n, m))
    for t in range(T):
        for i in range(L):
            Phi = h[i] * A
            Qxi = h[i] ** 2 * Qr[i] * GQG + Qp[i] * A @ Xi @ A.T + Qp[i] * GQG
            Qe = C[i] @ Px[i] @ C[i].T + Ct[i] @ Pr[i] @ Ct[i].T + C[i] @ Pxr[i] @ Ct[i].T \
                + Ct[i] @ Pxr[i].T @ C[i].T + Qv[i, i]
            Qi = np.linalg.inv(Qe)
            Lx[t, i] = (A @ (Px[i] @ C[i].T + Pxr[i] @ Ct[i].T) + G @ R_[i]) @ Qi
            Lr[t, i] = Phi @ (Pxr[i].T @ C[i].T + Pr[i] @ Ct[i].T) @ Qi
            K[t, i] = (Px[i] @ C[i].T + Pxr[i] @ Ct[i].T) @ Qi
            Px[i], Pr[i], Pxr[i] = (A @ Px[i] @ A.T - Lx[t, i] @ Qe @ Lx[t, i].T + GQG,
                                    Phi @ Pr[i] @ Phi.T - Lr[t, i] @ Qe @ Lr[t, i].T + Qxi,
                                    A @ Pxr[i] @ Phi.T - Lx[t, i] @ Qe @ Lr[t, i].T)
        Xi = A @ Xi @ A.T + GQG
        Qr = h**2 * Qr + Qp
    # offline weights from torchmm's cross-covariances (Theorem 6) — the reference checks the estimates
    stats = local_predictor_stats(sys, T)
    W = fuse(torch.zeros(T, 1, L, n, dtype=torch.float64),
             cross_covariances(sys, stats, cross_predictor_stats(sys, stats), 0)).weights.numpy()
    out = np.zeros((T, R, n))
    for r in range(R):
        for i in range(L):
            x, xr = mu0.copy(), np.zeros(n)
            Phi = h[i] * A
            for t in range(T):
                eps = y[t, r, i] - C[i] @ x - Ct[i] @ xr
                out[t, r] += W[t, i] @ (x + K[t, i] @ eps)
                x, xr = A @ x + Lx[t, i] @ eps, Phi @ xr + Lr[t, i] @ eps
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--numpy-runs", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    sys = ups()
    sim = simulate_fusion(sys, args.steps, (args.runs,), torch.Generator().manual_seed(0))

    def torch_pipeline():
        stats = local_predictor_stats(sys, args.steps)
        mean, _ = local_estimates(sys, sim.y, 0, stats)
        Pij = cross_covariances(sys, stats, cross_predictor_stats(sys, stats), 0)
        return fuse(mean, Pij, "matrix").mean

    def best(fn):
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            out = fn()
            times.append(time.perf_counter() - t0)
        return min(times), out

    t_torch, fused = best(torch_pipeline)
    t_local, _ = best(lambda: local_estimates(sys, sim.y, 0))
    t_aug, _ = best(lambda: augmented_local_estimates(sys, sim.y, 0))
    y_np = sim.y[:, : args.numpy_runs].numpy()
    t0 = time.perf_counter()
    ref = numpy_fused_filter(sys, y_np)
    t_np = (time.perf_counter() - t0) * args.runs / args.numpy_runs
    diff = float(np.abs(ref - fused[:, : args.numpy_runs].numpy()).max())
    print(f"runs={args.runs} steps={args.steps} sensors={sys.num_sensors}")
    print(f"torchmm local filters + cross-covariances + MF: {t_torch:.4f} s")
    print(f"torchmm local filters only (non-augmented): {t_local:.4f} s; augmented (12)-(15): {t_aug:.4f} s")
    print(f"numpy loop (scaled from {args.numpy_runs} runs): {t_np:.4f} s")
    print(f"max difference of the fused filter vs the numpy reference: {diff:.3e}")
    print(f"speedup_vs_numpy_loop={t_np / t_torch:.2f} augmented_over_nonaugmented={t_aug / t_local:.2f}")


if __name__ == "__main__":
    main()

"""IMM throughput: torchmm vs FilterPy's IMMEstimator vs a hand-vectorised NumPy IMM.

The paper-000 IMM (3 acceleration modes, n = 2, m = 1, transition (38)), ``--runs`` Monte Carlo
runs x ``--steps`` steps in float64, on the same simulated data in this one process:

* torchmm: ``IMM(KalmanFilter(bank))`` over all runs at once (``run_filter``);
* FilterPy: one ``IMMEstimator`` per run, looping over runs (its intended use);
* NumPy: the same IMM vectorised by hand over runs and modes (batch axis first, generic
  matmul / ``np.linalg.solve``, like torchmm's public layout).

All three must give the same estimates (checked to 1e-9). torchmm and NumPy are timed as the best
of ``--repeats`` runs, FilterPy once. The last line is
``speedup_vs_filterpy=<x> speedup_vs_numpy=<y>`` (wall-time ratios, > 1 means torchmm is faster).

Usage: ``python benchmarks/imm_vs_filterpy.py [--runs 400] [--steps 100] [--filterpy-runs N]``
(``--filterpy-runs`` times FilterPy on the first N runs only and scales its time by runs / N).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torchmm import IMM, ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, run_filter
from torchmm.simulate import simulate_jump_system, simulate_measurements

ACCELERATIONS = [0.25, 0.0, -0.25]
TRANSITION = [[0.50, 0.25, 0.25], [0.25, 0.50, 0.25], [0.25, 0.25, 0.50]]
X0, P0, R, Q_ACC = [10.0, 10.0], [[100.0, 1.0], [1.0, 100.0]], 100.0, 1.0


def scenario(runs: int, steps: int, seed: int):
    dtype = torch.float64
    motion = ConstantVelocity(1, q=Q_ACC, acceleration=torch.tensor(ACCELERATIONS, dtype=dtype)[:, None], dtype=dtype)
    sensor = PositionMeasurement(2, [0], torch.tensor(R, dtype=dtype), dtype=dtype)
    prior = GaussianBelief(torch.tensor(X0, dtype=dtype), torch.tensor(P0, dtype=dtype))
    transition = torch.tensor(TRANSITION, dtype=dtype)
    gen = torch.Generator().manual_seed(seed)
    sim = simulate_jump_system(motion, transition, prior, steps, (runs,), generator=gen)
    z = simulate_measurements(sensor, sim.states, generator=gen)
    return motion, sensor, prior, transition, z


def run_torchmm(motion, sensor, prior, transition, z):
    imm = IMM(KalmanFilter(motion, sensor), transition)
    belief0 = imm.initial_belief(prior.expand(z.shape[1]))
    record = lambda out: out._replace(prior=None, innovation=None, innovation_cov=None, extras=None)  # noqa: E731
    with torch.no_grad():
        traj = run_filter(imm, belief0, z, record=record)
        return traj.estimate().mean


def run_numpy(F, b, Q, H, Rm, Pi, x0, P0, mu0, zs):
    """Hand-vectorised IMM: arrays (runs, modes, ...), loops over time only."""
    T, N, m = zs.shape
    M, n = b.shape
    x = np.broadcast_to(x0, (N, M, n)).copy()
    P = np.broadcast_to(P0, (N, M, n, n)).copy()
    mu = np.broadcast_to(mu0, (N, M)).copy()
    Ft, Ht = np.swapaxes(F, -1, -2), H.T
    out = np.empty((T, N, n))
    log2pi = m * np.log(2 * np.pi)
    for k in range(T):
        # mixing: cbar_j = sum_i pi_ij mu_i; w_ij = pi_ij mu_i / cbar_j
        cbar = mu @ Pi
        w = mu[:, :, None] * Pi / cbar[:, None, :]
        wt = np.swapaxes(w, 1, 2)  # (N, j, i)
        xm = wt @ x  # (N, j, n)
        d = x[:, None, :, :] - xm[:, :, None, :]  # (N, j, i, n)
        Pm = np.einsum("nji,nide->njde", wt, P) + np.einsum("nji,njid,njie->njde", wt, d, d)
        # mode-matched Kalman filters
        xp = (F @ xm[..., None])[..., 0] + b
        Pp = F @ Pm @ Ft + Q
        PHt = Pp @ Ht  # (N, M, n, m)
        S = H @ PHt + Rm  # (N, M, m, m)
        nu = zs[k][:, None, :] - xp @ Ht
        Sinv_nu = np.linalg.solve(S, nu[..., None])[..., 0]
        K = np.swapaxes(np.linalg.solve(S, np.swapaxes(PHt, -1, -2)), -1, -2)
        x = xp + (K @ nu[..., None])[..., 0]
        P = Pp - K @ S @ np.swapaxes(K, -1, -2)
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
        ll = -0.5 * (np.einsum("nmi,nmi->nm", nu, Sinv_nu) + np.linalg.slogdet(S)[1] + log2pi)
        # mode probabilities (log-sum-exp) and output combination
        a = ll + np.log(cbar)
        a -= a.max(-1, keepdims=True)
        mu = np.exp(a)
        mu /= mu.sum(-1, keepdims=True)
        out[k] = np.einsum("nm,nmd->nd", mu, x)
    return out


def run_filterpy(F, b, Q, H, Rm, Pi, x0, P0, mu0, zs, runs: int):
    from filterpy.kalman import IMMEstimator
    from filterpy.kalman import KalmanFilter as FPKalmanFilter

    T, _, m = zs.shape
    n = x0.shape[0]
    out = np.empty((T, runs, n))
    u = np.ones((1, 1))
    for r in range(runs):
        filters = []
        for j in range(len(b)):
            kf = FPKalmanFilter(dim_x=n, dim_z=m, dim_u=1)
            kf.F, kf.Q, kf.H, kf.R, kf.B = F[j], Q[j], H, Rm, b[j].reshape(n, 1)
            kf.x, kf.P = x0.reshape(n, 1).copy(), P0.copy()
            filters.append(kf)
        imm = IMMEstimator(filters, mu0, Pi)
        for k in range(T):
            imm.predict(u)
            imm.update(zs[k, r].reshape(m, 1))
            out[k, r] = imm.x.ravel()
    return out


def best_of(fn, repeats: int):
    times, result = [], None
    for _ in range(repeats):
        tic = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - tic)
    return min(times), result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=400)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--filterpy-runs", type=int, default=None, help="time FilterPy on this many runs only")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    motion, sensor, prior, transition, z = scenario(args.runs, args.steps, args.seed)
    F = motion.F.numpy()
    F = np.broadcast_to(F, (len(ACCELERATIONS), *F.shape)).copy()
    b, Q = motion.offset.numpy(), np.broadcast_to(motion.Q.numpy(), F.shape).copy()
    H, Rm, Pi = sensor.H.numpy(), sensor.R.numpy(), transition.numpy()
    x0, P0, mu0 = prior.mean.numpy(), prior.cov.numpy(), np.full(3, 1 / 3)
    zs = z.numpy()
    print(f"IMM, 3 modes, n=2, m=1, {args.runs} runs x {args.steps} steps, float64, "
          f"torch {torch.__version__} ({torch.get_num_threads()} threads)")

    run_torchmm(motion, sensor, prior, transition, z[:2])  # warm-up (lazy inits)
    t_torch, est_torch = best_of(lambda: run_torchmm(motion, sensor, prior, transition, z), args.repeats)
    t_numpy, est_numpy = best_of(lambda: run_numpy(F, b, Q, H, Rm, Pi, x0, P0, mu0, zs), args.repeats)
    fp_runs = min(args.filterpy_runs or args.runs, args.runs)
    tic = time.perf_counter()
    est_fp = run_filterpy(F, b, Q, H, Rm, Pi, x0, P0, mu0, zs, fp_runs)
    t_fp = (time.perf_counter() - tic) * args.runs / fp_runs

    scale = 1 + np.abs(est_fp).max()
    err_fp = np.abs(est_torch.numpy()[:, :fp_runs] - est_fp).max() / scale
    err_np = np.abs(est_torch.numpy() - est_numpy).max() / scale
    print(f"max relative difference: torchmm vs FilterPy {err_fp:.2e}, torchmm vs NumPy {err_np:.2e}")
    if err_fp > 1e-9 or err_np > 1e-9:
        raise SystemExit("estimates disagree: the comparison is void")
    note = "" if fp_runs == args.runs else f" (measured on {fp_runs} runs, scaled)"
    print(f"torchmm  {t_torch:8.4f} s")
    print(f"NumPy    {t_numpy:8.4f} s")
    print(f"FilterPy {t_fp:8.4f} s{note}")
    print(f"speedup_vs_filterpy={t_fp / t_torch:.1f} speedup_vs_numpy={t_numpy / t_torch:.2f}")


if __name__ == "__main__":
    main()

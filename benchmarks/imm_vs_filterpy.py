"""IMM throughput: torchmm vs FilterPy's IMMEstimator vs a hand-vectorised NumPy IMM.

The paper-000 IMM (3 acceleration modes, n = 2, m = 1, transition (38)), ``--runs`` Monte Carlo
runs x ``--steps`` steps in float64, on the same simulated data in this one process:

* torchmm: ``IMM(KalmanFilter(bank))`` over all runs at once (``run_filter(..., record="estimate")``,
  which takes the engine's batch-last fast path), eager (the default) and with ``compile=True``;
* FilterPy: one ``IMMEstimator`` per run, looping over runs (its intended use);
* NumPy: the same IMM vectorised by hand over runs and modes (batch axis first, generic
  matmul / ``np.linalg.solve``, like torchmm's public layout);
* NumPy SoA: the strong reference - the IMM written by hand for this problem's sizes (n = 2,
  m = 1) with the batch axis last ("structure of arrays": one contiguous array per matrix entry,
  shape ``(M, runs)``) and the 2 x 2 Kalman algebra in closed form, so that every operation is one
  elementwise pass over all runs and modes.

All four must give the same estimates (checked to 1e-9). torchmm and the NumPy versions are timed as
the best of ``--repeats`` rounds in which they take turns (a contended machine's slow spells then
hit every contender alike), FilterPy once; one thread each (``--threads``). The last line is
``speedup_vs_filterpy=<x> speedup_vs_numpy=<y> speedup_vs_numpy_soa=<z> compiled_vs_numpy_soa=<c>
compiled_vs_filterpy=<f> compile_s=<s>`` (wall-time ratios, > 1 means torchmm is faster; the first
three for eager torchmm; ``compile_s`` is the first compiled call, compile included).

Usage: ``python benchmarks/imm_vs_filterpy.py [--runs 400] [--steps 100] [--filterpy-runs N] [--no-compile]``
(``--filterpy-runs`` times FilterPy on the first N runs only and scales its time by runs / N).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one thread each (before numpy)
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchmm import IMM, ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, run_filter  # noqa: E402
from torchmm.simulate import simulate_jump_system, simulate_measurements  # noqa: E402

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


def run_torchmm(motion, sensor, prior, transition, z, compile: bool = False):
    imm = IMM(KalmanFilter(motion, sensor), transition)
    belief0 = imm.initial_belief(prior.expand(z.shape[1]))
    with torch.no_grad():
        traj = run_filter(imm, belief0, z, record="estimate", compile=compile)
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


def run_numpy_soa(F, b, Q, H, Rm, Pi, x0, P0, mu0, zs):
    """The IMM for n = 2, m = 1 with the batch axis last: every quantity is an ``(M, N)`` array per
    matrix entry, the Kalman algebra in closed form (no matmul, no solve). Loops over time only."""
    T, N, _ = zs.shape
    M = b.shape[0]
    f00, f01, f10, f11 = (F[:, i, j][:, None] for i, j in ((0, 0), (0, 1), (1, 0), (1, 1)))
    b0, b1 = b[:, 0:1], b[:, 1:2]
    q00, q01, q11 = Q[:, 0, 0][:, None], Q[:, 0, 1][:, None], Q[:, 1, 1][:, None]
    h0, h1, r = H[0, 0], H[0, 1], Rm[0, 0]
    x0_, x1_ = np.full((M, N), x0[0]), np.full((M, N), x0[1])
    p00, p01, p11 = np.full((M, N), P0[0, 0]), np.full((M, N), P0[0, 1]), np.full((M, N), P0[1, 1])
    mu = np.repeat(mu0[:, None], N, axis=1)
    PiT = np.ascontiguousarray(Pi.T)
    out = np.empty((T, N, 2))
    half_log2pi = 0.5 * np.log(2 * np.pi)
    for k in range(T):
        cbar = PiT @ mu  # (j, N)
        w = Pi[:, :, None] * mu[:, None, :] / cbar[None, :, :]  # (i, j, N)
        m0 = np.einsum("ijn,in->jn", w, x0_)
        m1 = np.einsum("ijn,in->jn", w, x1_)
        d0 = x0_[:, None, :] - m0[None]  # (i, j, N)
        d1 = x1_[:, None, :] - m1[None]
        c00 = np.einsum("ijn,in->jn", w, p00) + np.einsum("ijn,ijn->jn", w, d0 * d0)
        c01 = np.einsum("ijn,in->jn", w, p01) + np.einsum("ijn,ijn->jn", w, d0 * d1)
        c11 = np.einsum("ijn,in->jn", w, p11) + np.einsum("ijn,ijn->jn", w, d1 * d1)
        # prediction: x- = F m + b, P- = F C F^T + Q (closed form)
        xp0, xp1 = f00 * m0 + f01 * m1 + b0, f10 * m0 + f11 * m1 + b1
        a00, a01 = f00 * c00 + f01 * c01, f00 * c01 + f01 * c11
        a10, a11 = f10 * c00 + f11 * c01, f10 * c01 + f11 * c11
        pp00, pp01, pp11 = a00 * f00 + a01 * f01 + q00, a00 * f10 + a01 * f11 + q01, a10 * f10 + a11 * f11 + q11
        # update with the scalar measurement z = h x + v
        g0, g1 = pp00 * h0 + pp01 * h1, pp01 * h0 + pp11 * h1  # P- H^T
        s = h0 * g0 + h1 * g1 + r
        nu = zs[k, :, 0][None, :] - (h0 * xp0 + h1 * xp1)
        k0, k1 = g0 / s, g1 / s
        x0_, x1_ = xp0 + k0 * nu, xp1 + k1 * nu
        p00, p01, p11 = pp00 - k0 * g0, pp01 - k0 * g1, pp11 - k1 * g1
        ll = -0.5 * nu * nu / s - 0.5 * np.log(s) - half_log2pi
        a = ll + np.log(cbar)
        a -= a.max(0, keepdims=True)
        mu = np.exp(a)
        mu /= mu.sum(0, keepdims=True)
        out[k, :, 0] = (mu * x0_).sum(0)
        out[k, :, 1] = (mu * x1_).sum(0)
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
    """The best wall time of ``fn()`` over ``repeats`` calls, and its last result."""
    times, result = [], None
    for _ in range(repeats):
        tic = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - tic)
    return min(times), result


def interleaved_best(fns: dict, repeats: int) -> tuple[dict, dict]:
    """The best wall time of each of ``fns`` over ``repeats`` rounds, the contenders taking turns in
    every round (on a contended machine, a slow spell then hits all of them, not one), and each one's
    last result."""
    best = dict.fromkeys(fns, float("inf"))
    results = {}
    for _ in range(repeats):
        for name, fn in fns.items():
            tic = time.perf_counter()
            results[name] = fn()
            best[name] = min(best[name], time.perf_counter() - tic)
    return best, results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=400)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--filterpy-runs", type=int, default=None, help="time FilterPy on this many runs only")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (NumPy: one, set before import)")
    parser.add_argument("--no-compile", action="store_true", help="skip torchmm with compile=True")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

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
    t_compiled = compile_s = float("nan")
    contenders = {
        "torch": lambda: run_torchmm(motion, sensor, prior, transition, z),
        "numpy": lambda: run_numpy(F, b, Q, H, Rm, Pi, x0, P0, mu0, zs),
        "soa": lambda: run_numpy_soa(F, b, Q, H, Rm, Pi, x0, P0, mu0, zs),
    }
    if not args.no_compile:
        tic = time.perf_counter()
        run_torchmm(motion, sensor, prior, transition, z, compile=True)  # compiles (cached on disk)
        compile_s = time.perf_counter() - tic
        contenders["compiled"] = lambda: run_torchmm(motion, sensor, prior, transition, z, compile=True)
    best, results = interleaved_best(contenders, args.repeats)
    t_torch, est_torch = best["torch"], results["torch"]
    t_numpy, est_numpy = best["numpy"], results["numpy"]
    t_soa, est_soa = best["soa"], results["soa"]
    if not args.no_compile:
        t_compiled, est_compiled = best["compiled"], results["compiled"]
    fp_runs = min(args.filterpy_runs or args.runs, args.runs)
    tic = time.perf_counter()
    est_fp = run_filterpy(F, b, Q, H, Rm, Pi, x0, P0, mu0, zs, fp_runs)
    t_fp = (time.perf_counter() - tic) * args.runs / fp_runs

    scale = 1 + np.abs(est_fp).max()
    err_fp = np.abs(est_torch.numpy()[:, :fp_runs] - est_fp).max() / scale
    err_np = np.abs(est_torch.numpy() - est_numpy).max() / scale
    err_soa = np.abs(est_torch.numpy() - est_soa).max() / scale
    print(f"max relative difference: torchmm vs FilterPy {err_fp:.2e}, torchmm vs NumPy {err_np:.2e}, "
          f"torchmm vs NumPy SoA {err_soa:.2e}")
    err_compiled = 0.0 if args.no_compile else np.abs(est_compiled.numpy() - est_soa).max() / scale
    if err_fp > 1e-9 or err_np > 1e-9 or err_soa > 1e-9 or err_compiled > 1e-9:
        raise SystemExit("estimates disagree: the comparison is void")
    note = "" if fp_runs == args.runs else f" (measured on {fp_runs} runs, scaled)"
    from torchmm.kernels.batch_last import traced as batch_last  # noqa: PLC0415

    traced = "traced" if batch_last._TRACED else "not traced"
    print(f"torchmm  {t_torch:8.4f} s (eager, the default; its steps {traced}: a structure's steps run as a cached "
          f"torch.fx graph once it has run {batch_last._TRACE_AFTER} steps in the process)")
    print(f"torchmm compiled {t_compiled:8.4f} s (compile=True; the first call took {compile_s:.1f} s)")
    print(f"NumPy    {t_numpy:8.4f} s")
    print(f"NumPy SoA {t_soa:7.4f} s")
    print(f"FilterPy {t_fp:8.4f} s{note}")
    steps = args.runs * args.steps
    print(f"run-steps/s: torchmm {steps / t_torch:.3g}, NumPy {steps / t_numpy:.3g}, NumPy SoA {steps / t_soa:.3g}, "
          f"FilterPy {steps / t_fp:.3g}")
    print(f"speedup_vs_filterpy={t_fp / t_torch:.1f} speedup_vs_numpy={t_numpy / t_torch:.2f} "
          f"speedup_vs_numpy_soa={t_soa / t_torch:.2f} compiled_vs_numpy_soa={t_soa / t_compiled:.2f} "
          f"compiled_vs_filterpy={t_fp / t_compiled:.1f} compile_s={compile_s:.1f}")


if __name__ == "__main__":
    main()

"""IMM over nonlinear banks (issue 31, goal 3): torchmm's IMM over an *extended* and over an *unscented*
Kalman bank for the coordinated turn, against a hand-written NumPy **batch-last** reference.

    python benchmarks/ct_imm.py [--runs 400 4000 40000] [--steps 50] [--repeats 5] [--dense-jacobian] [--vsimm]

The problem: state ``[x, vx, y, vy, omega]`` (n = 5, torchmm's ``NonlinearCoordinatedTurn``, turn
rate in the state), three nearly-coordinated-turn modes that differ in their process noise (white
acceleration ``q`` and turn-rate random walk ``q_omega``: nearly constant turn, slow turn changes,
manoeuvre; one mode-bank model, ``Q (3, 5, 5)``), a range-bearing sensor (m = 2, torchmm's
``RangeBearing``), transition matrix 0.95 on the diagonal; data simulated by torchmm's
``simulate_jump_system`` and ``simulate_measurements``. torchmm runs ``IMM(ExtendedKalmanFilter(bank,
sensor), Pi)`` and ``IMM(UnscentedKalmanFilter(bank, sensor), Pi)`` (its default Van der Merwe
points, alpha = 1, beta = 2, kappa = 0; weights taken from the filter) with ``run_filter(...,
record="estimate")`` in float64, twice: as a user gets it (the batch-last kernel of the nonlinear
banks, ``torchmm/kernels/batch_last/nonlinear.py``, from 300 runs x modes) and with
``fast_path=False`` (the eager batch-first steps). ``--dense-jacobian`` gives the kernel the turn
model's Jacobian without its 13 declared exact zeros and ones (the default entry hook), as the
reference multiplies them. ``--vsimm`` also times ``VariableStructureIMM`` (paper 003's
minimum-entropy set) over the same banks, the kernel against the eager steps.

The NumPy reference implements the same equations in the same order, written for this model: every
array has the Monte Carlo run axis *last* (mean ``(M, n, R)``, covariance ``(M, n, n, R)``, sigma
points ``(S, M, n, R)``), so that every operation is one elementwise pass over all runs and modes;
Python loops only over time and the small matrix indices (a batch-last matrix product is a sum over
its inner index). Moment mixing, the CT model and its analytic Jacobian (the same series below
``|omega T| = 0.1`` as torchmm's ``_turn_terms``), the range-bearing model and its Jacobian, the
EKF predict / update, the UKF's sigma points (Cholesky by hand), moments and update, the
conditioning on the innovation as in ``torchmm.linalg.condition`` (2 x 2 Cholesky, ``P - V^T V``,
log-likelihood from the factor), the mode posterior in log space and the combined estimate (mean and
covariance). Dense algebra throughout (the Jacobian's zeros are multiplied like any other entry).

First, at 8 runs x 20 steps, the reference's combined estimate (mean and covariance) and
log-likelihood must equal torchmm's to 1e-9 relative (the script exits non-zero otherwise; it prints
the maximum differences); at every timed size the differences are printed again (checked to 1e-6).
Then, one thread each (``torch.set_num_threads(1)``, NumPy's BLAS limited to one thread), each
contender's best and median of ``--repeats`` runs of ``--steps`` steps (after a two-step warm-up), in
milliseconds per step, and the ratios ``numpy_time / torchmm_time`` of the best times (above 1: torchmm
is faster), the kernel's and the eager steps'. The last line is ``ekf_ratio_<R>=... ukf_ratio_<R>=...``
(the kernel's) for the largest run count ``R`` given (``ekf_ratio_40000=... ukf_ratio_40000=...`` by
default).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one thread each (before numpy)
    os.environ.setdefault(_var, "1")

import argparse
import math
import statistics
import time

import numpy as np
import torch

from torchmm import (
    IMM,
    ExtendedKalmanFilter,
    GaussianBelief,
    NonlinearCoordinatedTurn,
    RangeBearing,
    UnscentedKalmanFilter,
    run_filter,
)
from torchmm.simulate import simulate_jump_system, simulate_measurements

DT = 1.0
#: (q, q_omega) per mode: nearly constant turn, slow turn-rate changes, manoeuvre
MODES = ((0.01, 1e-8), (0.1, 1e-5), (1.0, 1e-3))
TRANSITION = [[0.95, 0.025, 0.025], [0.025, 0.95, 0.025], [0.025, 0.025, 0.95]]
X0 = [1000.0, 10.0, 500.0, 5.0, 0.02]
P0_DIAG = [100.0, 4.0, 100.0, 4.0, 1e-3]
R_DIAG = [100.0, 1e-6]  # range (m^2), bearing (rad^2)
ORIGIN = (-2000.0, 0.0)  # the sensor, well away from the bearing's +-pi cut
CHECK_RUNS, CHECK_STEPS = 8, 20


def scenario(runs: int, steps: int, seed: int = 0, dtype=torch.float64, dense_jacobian: bool = False):
    """The mode-bank motion, the sensor, the prior, the transition matrix and measurements ``(T, R, 2)``."""
    modes = [NonlinearCoordinatedTurn(DT, q, q_omega, dtype=dtype) for q, q_omega in MODES]
    bank = (DenseJacobianTurn if dense_jacobian else NonlinearCoordinatedTurn)(DT, *MODES[0], dtype=dtype)
    bank.Q = torch.stack([m.Q for m in modes])  # (M, n, n): one model, every mode's noise
    sensor = RangeBearing(5, torch.diag(torch.tensor(R_DIAG, dtype=dtype)), origin=ORIGIN, dtype=dtype)
    prior = GaussianBelief(torch.tensor(X0, dtype=dtype), torch.diag(torch.tensor(P0_DIAG, dtype=dtype)))
    transition = torch.tensor(TRANSITION, dtype=dtype)
    gen = torch.Generator().manual_seed(seed)
    sim = simulate_jump_system(modes, transition, prior, steps, (runs,), generator=gen)
    z = simulate_measurements(sensor, sim.states, generator=gen)
    return bank, sensor, prior, transition, z


def make_imm(kind: str, bank, sensor, transition) -> IMM:
    filt = ExtendedKalmanFilter(bank, sensor) if kind == "ekf" else UnscentedKalmanFilter(bank, sensor)
    return IMM(filt, transition)


class DenseJacobianTurn(NonlinearCoordinatedTurn):
    """The turn model with every Jacobian entry a tensor, its exact zeros and ones too (``--dense-jacobian``)."""

    def jacobian_entries(self, x, *, u=None):
        rows = super().jacobian_entries(x, u=u)
        like = rows[0][1]
        return [[e if isinstance(e, torch.Tensor) else torch.full_like(like, e) for e in row] for row in rows]


def run_torchmm(imm: IMM, prior: GaussianBelief, z: torch.Tensor, fast_path: bool | None = None):
    """``(mean (T, R, n), cov (T, R, n, n), log-likelihood (T, R))`` of the combined estimate."""
    with torch.no_grad():
        traj = run_filter(imm, imm.initial_belief(prior.expand(z.shape[1])), z, record="estimate",
                          fast_path=fast_path)
        est = traj.estimate()
        return est.mean, est.cov, traj.log_likelihood


# --------------------------------------------------------------------------------------------------
# The NumPy batch-last reference: run axis last everywhere
# --------------------------------------------------------------------------------------------------

_LOG_2PI = math.log(2 * math.pi)
_SERIES_BELOW = 0.1  # torchmm.models.motion._TURN_SERIES_BELOW


def bl_matmul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` per mode and run: ``A (M, i, l, R)``, ``B (M, l, j, R)`` -> ``(M, i, j, R)``."""
    out = A[:, :, 0, None] * B[:, None, 0]
    for k in range(1, A.shape[2]):
        out += A[:, :, k, None] * B[:, None, k]
    return out


def bl_matmul_t(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B^T`` per mode and run: ``A (M, i, l, R)``, ``B (M, j, l, R)`` -> ``(M, i, j, R)``."""
    out = A[:, :, None, 0] * B[:, None, :, 0]
    for k in range(1, A.shape[2]):
        out += A[:, :, None, k] * B[:, None, :, k]
    return out


def bl_cholesky(P: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of ``P (M, n, n, R)`` (its lower triangle; a column at a time)."""
    n = P.shape[1]
    L = np.zeros_like(P)
    for j in range(n):
        d = P[:, j, j] - (L[:, j, :j] ** 2).sum(1)
        L[:, j, j] = np.sqrt(d)
        if j + 1 < n:
            below = P[:, j + 1:, j] - (L[:, j + 1:, :j] * L[:, j, None, :j]).sum(2)
            L[:, j + 1:, j] = below / L[:, j, None, j]
    return L


def symmetrize(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + P.swapaxes(-2, -3))


class NumpyCTIMM:
    """The IMM over the CT bank, batch-last (see the module docstring); ``kind`` ``"ekf"`` or ``"ukf"``."""

    def __init__(self, kind: str, imm: IMM):
        filt = imm.bank.filter
        motion, sensor = filt.motion, filt.measurement
        self.kind, self.dt = kind, motion.dt
        self.Q = motion.Q.detach().numpy()[..., None]  # (M, n, n, 1)
        self.R = sensor.R.detach().numpy()[None, :, :, None]  # (1, 2, 2, 1)
        self.origin = sensor.origin.detach().numpy()
        self.Pi = imm.transition.matrix().detach().numpy()
        self.M, self.n = self.Pi.shape[0], motion.state_dim
        if kind == "ukf":
            sp = filt.sigma_points
            wm, wc = sp.weights(self.n, torch.float64, "cpu")
            self.wm, self.wc = wm.numpy(), wc.numpy()
            self.spread, self.center = math.sqrt(sp.spread(self.n)), sp.include_center
            self.joseph = filt.joseph if filt.joseph is not None else False  # float64: P - K S K^T
            if self.joseph:
                raise ValueError("the reference implements the UKF's P - K S K^T update (float64's) only")

    # -- models ------------------------------------------------------------------------------------
    def _turn(self, omega):
        """``s, c`` and their derivatives in ``omega`` (torchmm's series below |omega T| = 0.1)."""
        T = self.dt
        theta = omega * T
        small = np.abs(theta) < _SERIES_BELOW
        safe = np.where(small, 1.0, omega)
        st = safe * T
        sin_st, cos_st = np.sin(st), np.cos(st)
        s_closed = sin_st / safe
        c_closed = 2 * np.sin(0.5 * st) ** 2 / safe
        ds_closed = (T * cos_st - s_closed) / safe
        dc_closed = (T * sin_st - c_closed) / safe
        t = np.where(small, theta, 0.0)
        t2 = t * t
        s_series = T * (1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42 * (1 - t2 / 72))))
        c_series = T * t * (0.5 - t2 / 24 * (1 - t2 / 30 * (1 - t2 / 56 * (1 - t2 / 90))))
        ds_series = T * T * t * (-1 / 3 + t2 / 30 * (1 - t2 / 28 * (1 - t2 / 54)))
        dc_series = T * T * (0.5 - t2 / 8 * (1 - t2 / 18 * (1 - t2 / 40 * (1 - t2 / 70))))
        return (np.where(small, s_series, s_closed), np.where(small, c_series, c_closed),
                np.where(small, ds_series, ds_closed), np.where(small, dc_series, dc_closed))

    def _f(self, X):
        """The CT transition on ``X (..., n, R)`` (component axis -2)."""
        s, c, _, _ = self._turn(X[..., 4, :])
        wt = X[..., 4, :] * self.dt
        cos, sin = np.cos(wt), np.sin(wt)
        x, vx, y, vy = X[..., 0, :], X[..., 1, :], X[..., 2, :], X[..., 3, :]
        return np.stack([x + s * vx - c * vy, cos * vx - sin * vy, c * vx + y + s * vy, sin * vx + cos * vy,
                         X[..., 4, :]], -2)

    def _f_jacobian(self, X):
        """``f(X)`` and its Jacobian ``(M, n, n, R)`` at ``X (M, n, R)``."""
        T = self.dt
        vx, vy, omega = X[:, 1], X[:, 3], X[:, 4]
        s, c, ds, dc = self._turn(omega)
        wt = omega * T
        cos, sin = np.cos(wt), np.sin(wt)
        dcos, dsin = -T * sin, T * cos
        fx = np.stack([X[:, 0] + s * vx - c * vy, cos * vx - sin * vy, c * vx + X[:, 2] + s * vy,
                       sin * vx + cos * vy, omega], 1)
        one, zero = np.ones_like(omega), np.zeros_like(omega)
        F = np.stack([
            np.stack([one, s, zero, -c, vx * ds - vy * dc], 1),
            np.stack([zero, cos, zero, -sin, vx * dcos - vy * dsin], 1),
            np.stack([zero, c, one, s, vx * dc + vy * ds], 1),
            np.stack([zero, sin, zero, cos, vx * dsin + vy * dcos], 1),
            np.stack([zero, zero, zero, zero, one], 1),
        ], 1)
        return fx, F

    def _h(self, X):
        """Range and bearing of ``X (..., n, R)`` -> ``(..., 2, R)``."""
        dx, dy = X[..., 0, :] - self.origin[0], X[..., 2, :] - self.origin[1]
        return np.stack([np.sqrt(dx * dx + dy * dy), np.arctan2(dy, dx)], -2)

    def _h_jacobian(self, X):
        dx, dy = X[:, 0] - self.origin[0], X[:, 2] - self.origin[1]
        r2 = dx * dx + dy * dy
        r = np.sqrt(r2)
        zero = np.zeros_like(dx)
        H = np.stack([np.stack([dx / r, zero, dy / r, zero, zero], 1),
                      np.stack([-dy / r2, zero, dx / r2, zero, zero], 1)], 1)
        return np.stack([r, np.arctan2(dy, dx)], 1), H

    # -- filter steps ------------------------------------------------------------------------------
    def _condition(self, X, P, nu, S, C):
        """``torchmm.linalg.condition`` for m = 2: posterior mean, covariance and log-likelihood."""
        a, b, c = S[:, 0, 0], S[:, 1, 0], S[:, 1, 1]
        l11 = np.sqrt(a)
        l21 = b / l11
        l22 = np.sqrt(c - l21 * l21)
        v0 = C[:, :, 0] / l11[:, None]  # rows of V = L^{-1} C^T, (M, n, R)
        v1 = (C[:, :, 1] - l21[:, None] * v0) / l22[:, None]
        w0 = nu[:, 0] / l11
        w1 = (nu[:, 1] - l21 * w0) / l22
        X = X + v0 * w0[:, None] + v1 * w1[:, None]
        P = P - (v0[:, :, None] * v0[:, None] + v1[:, :, None] * v1[:, None])
        ll = -0.5 * (w0 * w0 + w1 * w1 + 2 * _LOG_2PI) - (np.log(l11) + np.log(l22))
        return X, symmetrize(P), ll

    def _ekf(self, X, P, z):
        X, F = self._f_jacobian(X)
        P = bl_matmul_t(bl_matmul(F, P), F) + self.Q
        zp, H = self._h_jacobian(X)
        C = bl_matmul_t(P, H)  # P H^T (M, n, 2, R)
        S = bl_matmul(H, C) + self.R
        return self._condition(X, P, z[None] - zp, S, C)

    def _sigma_points(self, X, P):
        """``(S, M, n, R)``: the centre (if the rule has one), then ``X + c L e_i``, then ``X - c L e_i``."""
        offsets = self.spread * np.moveaxis(bl_cholesky(symmetrize(P)), 2, 0)  # (n, M, n, R): the columns
        parts = [X[None] + offsets, X[None] - offsets]
        if self.center:
            parts.insert(0, X[None])
        return np.concatenate(parts, 0)

    def _moments(self, points):
        mean = np.tensordot(self.wm, points, (0, 0))
        return mean, points - mean[None]

    def _wsum_outer(self, A, B):
        """``sum_s wc_s A_s B_s^T``: ``A (S, M, i, R)``, ``B (S, M, j, R)`` -> ``(M, i, j, R)``."""
        wA = self.wc[:, None, None, None] * A
        return np.stack([(wA[:, :, i, None] * B).sum(0) for i in range(A.shape[2])], 1)

    def _ukf(self, X, P, z):
        points = self._sigma_points(X, P)
        X, dev = self._moments(self._f(points))
        P = symmetrize(self._wsum_outer(dev, dev) + self.Q)
        points = self._sigma_points(X, P)
        zp, z_dev = self._moments(self._h(points))
        S = symmetrize(self._wsum_outer(z_dev, z_dev) + self.R)
        C = self._wsum_outer(points - X[None], z_dev)
        return self._condition(X, P, z[None] - zp, S, C)

    def run(self, x0: np.ndarray, P0: np.ndarray, zs: np.ndarray):
        """``zs (T, 2, R)`` -> the combined mean ``(T, n, R)``, covariance ``(T, n, n, R)`` and the
        log-likelihood ``(T, R)``."""
        steps, _, runs = zs.shape
        M, n = self.M, self.n
        X = np.broadcast_to(x0[None, :, None], (M, n, runs)).copy()
        P = np.broadcast_to(P0[None, :, :, None], (M, n, n, runs)).copy()
        log_mu = np.full((M, runs), -math.log(M))
        PiT, Pi3 = self.Pi.T.copy(), self.Pi[:, :, None]
        step = self._ekf if self.kind == "ekf" else self._ukf
        means, covs, lls = np.empty((steps, n, runs)), np.empty((steps, n, n, runs)), np.empty((steps, runs))
        for k in range(steps):
            # mixing: c_j = sum_i pi_ij mu_i, w_ij = pi_ij mu_i / c_j, moment-matched start beliefs
            mu = np.exp(log_mu)
            cbar = PiT @ mu  # (j, R)
            w = Pi3 * mu[:, None] / cbar[None]  # (i, j, R)
            Xm = (w[:, :, None] * X[:, None]).sum(0)  # (j, n, R)
            d = X[:, None] - Xm[None]  # (i, j, n, R)
            Pm = (w[:, :, None, None] * (P[:, None] + d[:, :, :, None] * d[:, :, None])).sum(0)
            # mode-matched filters, then the mode posterior in log space
            X, P, ell = step(Xm, Pm, zs[k])
            joint = ell + np.log(cbar)
            top = joint.max(0)
            lls[k] = top + np.log(np.exp(joint - top).sum(0))
            log_mu = joint - lls[k]
            # the combined estimate
            mu = np.exp(log_mu)
            means[k] = (mu[:, None] * X).sum(0)
            d = X - means[k][None]
            covs[k] = (mu[:, None, None] * (P + d[:, :, None] * d[:, None])).sum(0)
        return means, covs, lls


def run_numpy(ref: NumpyCTIMM, prior: GaussianBelief, zs_batch_last: np.ndarray):
    return ref.run(prior.mean.numpy(), prior.cov.numpy(), zs_batch_last)


def differences(torch_out, numpy_out) -> tuple[float, float, float]:
    """Relative max differences of the mean (per state component, against that component's largest
    magnitude), the covariance (per entry, likewise) and the log-likelihood (against its largest)."""
    mean_t, cov_t, ll_t = (t.numpy() for t in torch_out)
    mean_n = np.moveaxis(numpy_out[0], -1, 1)  # (T, R, n)
    cov_n = np.moveaxis(numpy_out[1], -1, 1)  # (T, R, n, n)
    ll_n = numpy_out[2]
    mean_d = (np.abs(mean_t - mean_n) / np.abs(mean_n).max((0, 1))).max()
    cov_d = (np.abs(cov_t - cov_n) / np.abs(cov_n).max((0, 1))).max()
    ll_d = np.abs(ll_t - ll_n).max() / np.abs(ll_n).max()
    return float(mean_d), float(cov_d), float(ll_d)


def timings(fn, repeats: int) -> tuple[float, float, object]:
    """Best and median wall time of ``fn()`` over ``repeats`` calls, and the last result."""
    times, result = [], None
    for _ in range(repeats):
        tic = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - tic)
    return min(times), statistics.median(times), result


def check_equal(kind: str) -> tuple[float, float, float]:
    """The reference against torchmm's kernel (``fast_path=True``: taken at any size) and eager steps."""
    bank, sensor, prior, transition, z = scenario(CHECK_RUNS, CHECK_STEPS, seed=1)
    imm = make_imm(kind, bank, sensor, transition)
    reference = run_numpy(NumpyCTIMM(kind, imm), prior, z.permute(0, 2, 1).numpy())
    worst = (0.0, 0.0, 0.0)
    for path, fast_path in (("kernel", True), ("eager", False)):
        diffs = differences(run_torchmm(imm, prior, z, fast_path), reference)
        print(f"equality check ({kind.upper()} {path}, {CHECK_RUNS} runs x {CHECK_STEPS} steps, float64): max "
              f"relative difference mean {diffs[0]:.1e}, cov {diffs[1]:.1e}, log-likelihood {diffs[2]:.1e}")
        if not max(diffs) <= 1e-9:
            raise SystemExit(f"{kind.upper()} {path}: the NumPy reference disagrees with torchmm "
                             f"({max(diffs):.1e} > 1e-9): the comparison is void")
        worst = tuple(map(max, worst, diffs))
    return worst


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, nargs="+", default=[400, 4000, 40000])
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dense-jacobian", action="store_true",
                        help="the kernel multiplies the turn model's exact Jacobian zeros too, as the reference")
    parser.add_argument("--vsimm", action="store_true",
                        help="also the variable-structure IMM over the same banks, kernel against eager steps")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print(f"IMM over CT banks (n=5, m=2 range-bearing, M=3), float64, torch {torch.__version__}, "
          f"numpy {np.__version__}, one thread" + (", dense Jacobian" if args.dense_jacobian else ""))
    for kind in ("ekf", "ukf"):
        check_equal(kind)
    print(f"{args.steps} steps, best / median of {args.repeats} (ms per step); "
          "ratio = NumPy best / torchmm best (> 1: torchmm faster); kernel: as run_filter takes it "
          "(the eager steps below 300 runs x modes), eager: fast_path=False")
    header = (f"{'runs':>7} {'bank':>4} | {'NumPy best':>11} {'median':>9} | "
              f"{'kernel best':>12} {'median':>9} {'ratio':>6} | {'eager best':>11} {'median':>9} {'ratio':>6} | "
              "max rel. diff")
    print(header)
    print("-" * len(header))
    ratios = {}
    for runs in args.runs:
        bank, sensor, prior, transition, z = scenario(runs, args.steps, seed=0, dense_jacobian=args.dense_jacobian)
        zs = z.permute(0, 2, 1).contiguous().numpy()  # (T, 2, R): the reference's batch-last data
        for kind in ("ekf", "ukf"):
            imm = make_imm(kind, bank, sensor, transition)
            ref = NumpyCTIMM(kind, imm)
            run_numpy(ref, prior, zs[:2])  # warm-up
            run_torchmm(imm, prior, z[:2])
            np_best, np_med, np_out = timings(lambda ref=ref, prior=prior, zs=zs: run_numpy(ref, prior, zs),
                                              args.repeats)
            tm_best, tm_med, tm_out = timings(lambda imm=imm, prior=prior, z=z: run_torchmm(imm, prior, z),
                                              args.repeats)
            eg_best, eg_med, eg_out = timings(lambda imm=imm, prior=prior, z=z: run_torchmm(imm, prior, z, False),
                                              args.repeats)
            diff = max(max(differences(tm_out, np_out)), max(differences(eg_out, np_out)))
            if not diff <= 1e-6:
                raise SystemExit(f"{kind.upper()} at {runs} runs: the reference disagrees with torchmm "
                                 f"({diff:.1e})")
            ratios[kind] = np_best / tm_best
            per = 1e3 / args.steps
            print(f"{runs:>7} {kind.upper():>4} | {np_best * per:>11.3f} {np_med * per:>9.3f} | "
                  f"{tm_best * per:>12.3f} {tm_med * per:>9.3f} {ratios[kind]:>6.2f} | "
                  f"{eg_best * per:>11.3f} {eg_med * per:>9.3f} {np_best / eg_best:>6.2f} | {diff:.1e}")
    if args.vsimm:
        vsimm_rows(args)
    runs = args.runs[-1]
    print(f"ekf_ratio_{runs}={ratios['ekf']:.2f} ukf_ratio_{runs}={ratios['ukf']:.2f}")


def vsimm_rows(args) -> None:
    """``--vsimm``: ``VariableStructureIMM(filter, Pi, ExactMinimumEntropy())`` (paper 003's minimum-entropy
    set after every update) over the same banks and data, as ``run_filter`` takes it (the same kernel,
    with the policy as its post-update) and with ``fast_path=False``; no NumPy reference (the two
    torchmm paths' largest relative difference, as :func:`differences`, is printed: the modes' noises
    differ, so no two candidate sets tie)."""
    from torchmm.multimodel import VariableStructureIMM
    from torchmm.multimodel.mevsmm import ExactMinimumEntropy

    print("VSIMM over the same banks (ms per step, best / median; speed-up = eager best / kernel best)")
    header = f"{'runs':>7} {'bank':>4} | {'kernel best':>12} {'median':>9} | {'eager best':>11} {'median':>9} | speed-up | diff"
    print(header)
    print("-" * len(header))
    for runs in args.runs:
        bank, sensor, prior, transition, z = scenario(runs, args.steps, seed=0, dense_jacobian=args.dense_jacobian)
        for kind in ("ekf", "ukf"):
            vs = VariableStructureIMM(make_imm(kind, bank, sensor, transition).bank.filter, transition,
                                      ExactMinimumEntropy())
            run_torchmm(vs, prior, z[:2])
            best, med, out = timings(lambda vs=vs, z=z: run_torchmm(vs, prior, z), args.repeats)
            eg_best, eg_med, eg_out = timings(lambda vs=vs, z=z: run_torchmm(vs, prior, z, False), args.repeats)
            diff = max(differences(out, (eg_out[0].movedim(1, -1).numpy(), eg_out[1].movedim(1, -1).numpy(),
                                         eg_out[2].numpy())))
            per = 1e3 / args.steps
            print(f"{runs:>7} {kind.upper():>4} | {best * per:>12.3f} {med * per:>9.3f} | {eg_best * per:>11.3f} "
                  f"{eg_med * per:>9.3f} | {eg_best / best:>8.2f} | {diff:.1e}")


if __name__ == "__main__":
    main()

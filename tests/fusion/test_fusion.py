"""Paper 002: local estimators, augmented cross-check, cross-covariances, fusion, steady state."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmm.fusion import (
    augmented_cross_predictor,
    augmented_local_estimates,
    centralized_estimates,
    cross_covariances,
    cross_predictor_stats,
    fuse,
    fusion_weights,
    local_covariances,
    local_estimates,
    local_one_step,
    local_predictor_stats,
    simulate_fusion,
    steady_fused_estimates,
    steady_moments,
    steady_state,
)
from torchmm.fusion.system import MultiSensorSystem

from .systems import oracle, radar_system, random_system, ups_system

HORIZONS = [-3, -2, -1, 0, 1, 2]
DIAG = dict(dim1=-2, dim2=-1)


def _rel(a, b):
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))


# ---------------------------------------------------------------------------------------------
# system and simulator
# ---------------------------------------------------------------------------------------------


def test_simulator_shapes_and_second_moments():
    sys = random_system(1)
    T, R = 12, 20000
    sim = simulate_fusion(sys, T, (R,), torch.Generator().manual_seed(0))
    assert sim.x.shape == (T, R, 2) and sim.r.shape == (T, R, 3) and sim.y.shape == (T, R, 3, 2)
    Xi, Qr, _ = sys.second_moments(T)
    emp_xi = torch.einsum("tra,trb->tab", sim.x, sim.x) / R
    emp_r = (sim.r**2).mean(1)
    # sample second moments within 5 standard errors (Gaussian x: var of x_a x_b <= 2 Xi_aa Xi_bb)
    se = (2 * Xi.diagonal(**DIAG)[..., :, None] * Xi.diagonal(**DIAG)[..., None, :] / R).sqrt()
    assert bool(((emp_xi - Xi).abs() <= 5 * se).all())
    assert bool(((emp_r - Qr).abs() <= 5 * (2 * Qr**2 / R).sqrt()).all())
    # the w/v correlation R_i = E[w v_i^T] is realised: v = y - (C + Ct r) x
    v = sim.y - ((sys.C + sys.Ct * sim.r[..., None, None]) @ sim.x[:, :, None, :, None]).squeeze(-1)
    x_next = sim.x[1:] - sim.x[:-1] @ sys.A.T  # = Gamma w
    emp = torch.einsum("tra,trib->iab", x_next, v[:-1]) / (R * (T - 1))
    assert torch.allclose(emp, sys.Gamma @ sys.R, atol=0.05 * float(sys.R.abs().max()) + 0.02)


def test_system_validation_errors():
    good = dict(A=[[0.5]], Gamma=[[1.0]], Qw=[[1.0]], C=[[[1.0]]], Ct=[[[0.5]]], h=[0.6], Qp=[0.1],
                d=[[[0.0]]], Q_eta=[[[1.0]]], mu0=[0.0], P0=[[1.0]])
    MultiSensorSystem.from_correlation(**good)
    with pytest.raises(ValueError, match="h:"):
        MultiSensorSystem.from_correlation(**{**good, "h": [1.2214]})  # the printed e^{T/5}
    with pytest.raises(ValueError, match="Qp"):
        MultiSensorSystem.from_correlation(**{**good, "Qp": [-1.0]})
    with pytest.raises(ValueError, match="Ct"):
        MultiSensorSystem.from_correlation(**{**good, "Ct": [[[0.5, 1.0]]]})
    with pytest.raises(ValueError, match="P0"):
        MultiSensorSystem.from_correlation(**{**good, "P0": [[-1.0]]})
    with pytest.raises(ValueError, match="Q_eta"):
        MultiSensorSystem.from_correlation(**{**good, "Q_eta": [[[-1.0]]]})
    sys = MultiSensorSystem.from_correlation(**good)
    y = torch.zeros(3, 2, 1, 1)
    y[1, 0] = float("nan")  # missing in run 0 only: the shared gains cannot represent it
    with pytest.raises(ValueError, match="pattern"):
        local_estimates(sys, y)
    with pytest.raises(ValueError, match="y:"):
        local_estimates(sys, torch.zeros(3, 2, 2, 1))
    with pytest.raises(ValueError, match="method"):
        fusion_weights(torch.eye(1).expand(2, 2, 1, 1), "median")
    y_all = torch.zeros(3, 2, 1, 1)
    y_all[1] = float("nan")  # same pattern in both runs: fine for the time-varying estimators
    assert bool(torch.isfinite(local_estimates(sys, y_all, 1)[0]).all())
    with pytest.raises(ValueError, match="steady-state"):
        steady_fused_estimates(sys, steady_state(sys), y_all, 0)
    unstable = MultiSensorSystem.from_correlation(**{**good, "A": [[1.0]]})
    with pytest.raises(ValueError, match="A:"):
        steady_state(unstable)


@pytest.mark.parametrize("stats_steps", [10, 30])
def test_statistics_for_another_number_of_steps_raise_value_errors(stats_steps):
    """Time-varying statistics computed for T' != T steps (an IndexError, a broadcast RuntimeError or,
    for a predictor N < -1, covariances silently of T' steps beside means of T steps before)."""
    sys = MultiSensorSystem.from_correlation(
        A=[[0.5]], Gamma=[[1.0]], Qw=[[1.0]], C=[[[1.0]], [[1.0]]], Ct=[[[0.5]], [[0.2]]], h=[0.6, 0.7],
        Qp=[0.1, 0.1], d=[[[0.0]], [[0.3]]], Q_eta=[[[1.0]], [[2.0]]], mu0=[0.0], P0=[[1.0]])
    y = simulate_fusion(sys, 20, (4,), torch.Generator().manual_seed(0)).y
    stats = local_predictor_stats(sys, stats_steps)
    for N in (-2, 0, 2):
        with pytest.raises(ValueError, match=f"stats: computed for {stats_steps} steps, but y has 20"):
            local_estimates(sys, y, N, stats)
    with pytest.raises(ValueError, match="stats:"):
        local_one_step(sys, stats, y)
    with pytest.raises(ValueError, match="stats:"):
        local_covariances(sys, stats, 0, steps=20)
    stats20 = local_predictor_stats(sys, 20)
    cross = cross_predictor_stats(sys, stats)
    for N in (-2, 0, 1):
        with pytest.raises(ValueError, match="stats: computed for 20 steps"):
            cross_covariances(sys, stats20, cross, N)
        with pytest.raises(ValueError, match="cross:"):
            cross_covariances(sys, stats, cross, N, steps=20)
    with pytest.raises(ValueError, match="cross:"):
        cross_covariances(sys, steady_state(sys).stats, cross, 0)
    if stats_steps < 20:
        with pytest.raises(ValueError, match="steps:"):
            cross_predictor_stats(sys, stats, steps=20)
    # matching lengths still run, and a stationary pair fits any number of steps
    torch.testing.assert_close(local_estimates(sys, y, 1, stats20)[0], local_estimates(sys, y, 1)[0])
    ss = steady_state(sys)
    assert cross_covariances(sys, ss.stats, ss.cross, 1, steps=7).shape[0] == 7


# ---------------------------------------------------------------------------------------------
# local estimators: oracle, augmented cross-check
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("N", HORIZONS)
def test_local_and_cross_covariances_match_batch_lmmse_oracle(N):
    sys = random_system(2)
    T = 7
    orc = oracle(sys, T)
    stats = local_predictor_stats(sys, T)
    cross = cross_predictor_stats(sys, stats)
    Pij = cross_covariances(sys, stats, cross, N).numpy()
    Pl = local_covariances(sys, stats, N).numpy()
    sim = simulate_fusion(sys, T, (2,), torch.Generator().manual_seed(5))
    mean, _ = local_estimates(sys, sim.y, N, stats)
    cmean, ccov = centralized_estimates(sys, sim.y, N)
    y0 = sim.y[:, 0].numpy()
    for t in range(T):
        for i in range(3):
            np.testing.assert_allclose(Pl[t, i], orc.error_cov(t, N, [i], [i]), rtol=1e-8, atol=1e-10)
            np.testing.assert_allclose(mean[t, 0, i].numpy(), orc.estimate(y0, t, N, [i]),
                                       rtol=1e-8, atol=1e-9)
            for j in range(3):
                np.testing.assert_allclose(Pij[t, i, j], orc.error_cov(t, N, [i], [j]), rtol=1e-8, atol=1e-10)
        allS = [0, 1, 2]
        np.testing.assert_allclose(ccov[t].numpy(), orc.error_cov(t, N, allS, allS), rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(cmean[t, 0].numpy(), orc.estimate(y0, t, N, allS), rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("make", [ups_system, radar_system, random_system])
def test_augmented_agrees_with_non_augmented(make):
    sys = make()
    T = 40
    sim = simulate_fusion(sys, T, (5,), torch.Generator().manual_seed(0))
    stats = local_predictor_stats(sys, T)
    for N in HORIZONS:
        m, P = local_estimates(sys, sim.y, N, stats)
        ma, Pa = augmented_local_estimates(sys, sim.y, N)
        # 1e-8 relative to the largest entry at every step (Example 1: |x| ~ 4e4, P ~ 1e9)
        step_scale = m.abs().flatten(1).amax(1).clamp_min(1.0)
        assert float(((m - ma).abs().flatten(1).amax(1) / step_scale).max()) < 1e-8, N
        assert float(((P - Pa).abs().amax((-1, -2)) / Pa.abs().amax((-1, -2)).clamp_min(1e-300)).max()) < 1e-8
    cross = cross_predictor_stats(sys, stats)
    Pb = augmented_cross_predictor(sys, T)
    assert _rel(cross.joint(), Pb) < 1e-8
    idx = torch.arange(sys.num_sensors)
    assert _rel(cross.state_cov[:, idx, idx], stats.state_cov) < 1e-12
    for N in HORIZONS:
        diag = cross_covariances(sys, stats, cross, N)[:, idx, idx]
        assert _rel(diag, local_covariances(sys, stats, N)) < 1e-10


def test_float32_runs_and_stays_finite():
    sys = ups_system(torch.float32)
    sim = simulate_fusion(sys, 30, (16,), torch.Generator().manual_seed(0))
    stats = local_predictor_stats(sys, 30)
    cross = cross_predictor_stats(sys, stats)
    for N in (-2, 0, 2):
        m, P = local_estimates(sys, sim.y, N, stats)
        f = fuse(m, cross_covariances(sys, stats, cross, N), "matrix")
        assert m.dtype == torch.float32 and f.mean.dtype == torch.float32
        assert bool(torch.isfinite(f.mean).all() & torch.isfinite(f.cov).all() & torch.isfinite(P).all())
    cm, _ = centralized_estimates(sys, sim.y, 0)
    assert bool(torch.isfinite(cm).all())
    ss = steady_state(sys)  # stops at float32 rounding level instead of running to max_iter
    assert ss.iterations < 1000 and ss.cross_iterations < 1000
    xo, Po, _ = steady_fused_estimates(sys, ss, sim.y, 1)
    assert xo.dtype == torch.float32 and bool(torch.isfinite(xo).all() & torch.isfinite(Po).all())


# ---------------------------------------------------------------------------------------------
# Monte Carlo consistency
# ---------------------------------------------------------------------------------------------


def _z(err2: torch.Tensor, computed: torch.Tensor) -> torch.Tensor:
    """z-score of the per-run time average of squared errors (runs iid) against the computed value."""
    per_run = err2.mean(0)  # (R, ...)
    se = per_run.std(0) / per_run.shape[0] ** 0.5
    return (per_run.mean(0) - computed) / se


def test_monte_carlo_variances_match_computed_ones():
    """Tolerance: |z| < 4.5, z = (MC - computed) / SE, SE from the spread of the runs' time-averaged
    squared errors (runs are independent, time steps within a run are not). The z-scores of all
    estimators share one realisation, so they move together; 4.5 keeps the test reliable."""
    sys = ups_system()
    T, R, w = 40, 3000, slice(15, 40)
    sim = simulate_fusion(sys, T, (R,), torch.Generator().manual_seed(11))
    stats = local_predictor_stats(sys, T)
    cross = cross_predictor_stats(sys, stats)
    for N in (-2, 0, 2):
        wN = slice(15, 38) if N > 0 else w  # the smoother's last N steps lack future data
        m, P = local_estimates(sys, sim.y, N, stats)
        err = sim.x[:, :, None] - m
        assert bool((_z(err[wN] ** 2, P[wN].diagonal(**DIAG).mean(0)).abs() < 4.5).all())
        Pij = cross_covariances(sys, stats, cross, N)
        cross_err = err[wN, :, 0, 0] * err[wN, :, 1, 0]
        assert float(_z(cross_err[..., None], Pij[wN, 0, 1, 0, 0].mean(0)[None]).abs()) < 4.5
        for method in ("matrix", "diagonal", "scalar"):
            f = fuse(m, Pij, method)
            assert bool((_z((sim.x - f.mean)[wN] ** 2, f.cov[wN].diagonal(**DIAG).mean(0)).abs() < 4.5).all())
        cm, cP = centralized_estimates(sys, sim.y, N)
        assert bool((_z((sim.x - cm)[wN] ** 2, cP[wN].diagonal(**DIAG).mean(0)).abs() < 4.5).all())


# ---------------------------------------------------------------------------------------------
# fusion weights
# ---------------------------------------------------------------------------------------------


def _random_joint(L, n, seed):
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(L * n, L * n + 3, generator=g)
    S = X @ X.T / (L * n) + 0.1 * torch.eye(L * n)
    return S.reshape(L, n, L, n).transpose(1, 2)


@pytest.mark.parametrize("method", ["matrix", "diagonal", "scalar"])
def test_fusion_weights_sum_to_identity_and_beat_local(method):
    L, n = 4, 3
    P = torch.stack([_random_joint(L, n, s) for s in range(5)])  # batch of 5
    A, Po = fusion_weights(P, method)
    eye = torch.eye(n).expand(5, n, n)
    assert torch.allclose(A.sum(-3), eye, atol=1e-10)
    if method == "scalar":
        assert torch.allclose(A[..., 0, 0], A.diagonal(**DIAG)[..., 0].expand_as(A[..., 0, 0]))
        assert torch.allclose(A.diagonal(**DIAG).mean(-1), A[..., 0, 0])
    if method == "diagonal":
        assert torch.allclose(A, torch.diag_embed(A.diagonal(**DIAG)))
    idx = torch.arange(L)
    Pl = P[:, idx, idx]
    if method == "matrix":  # Po <= P_i in the matrix sense, and Po = (F^T P^-1 F)^-1 (45)
        assert bool((torch.linalg.eigvalsh(Pl - Po[:, None]) > -1e-10).all())
        Sigma = P.transpose(-3, -2).reshape(5, L * n, L * n)
        F = torch.eye(n).repeat(L, 1)
        assert torch.allclose(Po, torch.linalg.inv(F.T @ torch.linalg.solve(Sigma, F)), atol=1e-10)
    elif method == "diagonal":
        assert bool((Po.diagonal(**DIAG)[:, None] <= Pl.diagonal(**DIAG) + 1e-10).all())
    else:
        assert bool((Po.diagonal(**DIAG).sum(-1)[:, None] <= Pl.diagonal(**DIAG).sum(-1) + 1e-10).all())


def test_matrix_weights_are_optimal_among_unbiased_weights():
    L, n = 3, 2
    P = _random_joint(L, n, 7)
    A, Po = fusion_weights(P, "matrix")
    g = torch.Generator().manual_seed(1)
    for _ in range(20):
        B = A + 0.3 * torch.randn(L, n, n, generator=g)
        B[-1] = torch.eye(n) - B[:-1].sum(0)  # still sums to I
        Pb = torch.einsum("iab,ijbc,jdc->ad", B, P, B)
        assert bool((torch.linalg.eigvalsh(Pb - Po) > -1e-10).all())


@pytest.mark.parametrize("method", ["matrix", "diagonal", "scalar"])
def test_identical_uncorrelated_sensors_fuse_to_P_over_L(method):
    L, n = 5, 3
    X = torch.randn(n, n, generator=torch.Generator().manual_seed(2))
    Pi = X @ X.T + 0.5 * torch.eye(n)
    P = torch.zeros(L, L, n, n)
    P[torch.arange(L), torch.arange(L)] = Pi
    A, Po = fusion_weights(P, method)
    assert torch.allclose(Po, Pi / L, atol=1e-12)
    assert torch.allclose(A, torch.eye(n).expand(L, n, n) / L, atol=1e-12)


def test_singular_joint_covariance_gives_admissible_weights():
    """Before any data all local errors are identical (P_ij = P0): every unbiased weight is optimal."""
    P = torch.eye(2).expand(3, 3, 2, 2)
    for method in ("matrix", "diagonal", "scalar"):
        A, Po = fusion_weights(P, method)
        assert torch.allclose(A.sum(0), torch.eye(2), atol=1e-10)
        assert torch.allclose(Po, torch.eye(2), atol=1e-10)


# ---------------------------------------------------------------------------------------------
# orderings (Example 2)
# ---------------------------------------------------------------------------------------------


def test_variance_orderings_example2():
    sys = ups_system()
    T = 60
    stats = local_predictor_stats(sys, T)
    cross = cross_predictor_stats(sys, stats)
    dummy = torch.zeros(T, 1, 3, 1)
    fused = {}
    for N in (-2, -1, 0, 1, 2):
        Pij = cross_covariances(sys, stats, cross, N)
        var = {meth: fuse(torch.zeros(T, 1, 3, 3), Pij, meth).cov.diagonal(**DIAG) for meth in
               ("matrix", "diagonal", "scalar")}
        var["CF"] = centralized_estimates(sys, dummy, N)[1].diagonal(**DIAG)
        LF = local_covariances(sys, stats, N).diagonal(**DIAG)  # (T, L, n)
        tol = 1e-10
        assert bool((var["CF"] <= var["matrix"] + tol).all()), N
        assert bool((var["matrix"] <= var["diagonal"] + tol).all()), N
        assert bool((var["diagonal"] <= var["scalar"] + tol).all()), N
        # SF <= each LF per component is not a theorem (SF minimises the trace): for this example
        # it fails by ~5e-3 at t = 1, 2 (prediction horizons) and holds from t = 3 on
        assert bool((var["scalar"][3:, None] <= LF[3:] + tol).all()), N
        assert bool((var["scalar"].sum(-1)[:, None] <= LF.sum(-1) + tol).all()), N
        fused[N] = var["matrix"][: T - 2]  # exclude the end where the smoother has no future data
    # predictor >= filter >= smoother per component; not a theorem for fused estimates: the second
    # component of N = 2 exceeds N = 1 by <= 1.2e-4 at t = 1..4, from t = 5 on it holds
    for a, b in ((-2, -1), (-1, 0), (0, 1), (1, 2)):
        assert bool((fused[b][5:] <= fused[a][5:] + 1e-10).all()), (a, b)
        assert bool((fused[b].sum(-1) <= fused[a].sum(-1) + 1e-10).all()), (a, b)


# ---------------------------------------------------------------------------------------------
# steady state
# ---------------------------------------------------------------------------------------------


def test_steady_moments_solve_the_lyapunov_equations():
    scipy_linalg = pytest.importorskip("scipy.linalg")
    sys = ups_system()
    Xi, Qr, Qxi = steady_moments(sys)
    ref = scipy_linalg.solve_discrete_lyapunov(sys.A.numpy(), sys.GQG.numpy())
    np.testing.assert_allclose(Xi.numpy(), ref, rtol=1e-10, atol=1e-12)
    assert torch.allclose(Qr, sys.h**2 * Qr + sys.Qp)
    assert torch.allclose(Qxi, sys.virtual_noise_cov(Xi, Qr))


def test_steady_state_is_the_limit_of_the_time_varying_recursions():
    sys = ups_system()
    ss = steady_state(sys)
    T = 150
    stats = local_predictor_stats(sys, T)
    cross = cross_predictor_stats(sys, stats)
    assert _rel(stats.state_gain[-1], ss.stats.state_gain[0]) < 1e-9
    assert _rel(stats.aux_gain[-1], ss.stats.aux_gain[0]) < 1e-9
    assert _rel(stats.state_cov[-1], ss.stats.state_cov[0]) < 1e-9
    for N in (-2, -1, 0, 1, 2):
        t = T - 10
        assert _rel(cross_covariances(sys, stats, cross, N)[t], ss.cross_covariances(sys, N)) < 1e-9, N
        assert _rel(local_covariances(sys, stats, N)[t], ss.local_covariances(sys, N)) < 1e-9, N
    A_tv, _ = fusion_weights(cross_covariances(sys, stats, cross, 0)[T - 10], "matrix")
    A_ss, _ = fusion_weights(ss.cross_covariances(sys, 0), "matrix")
    assert _rel(A_tv, A_ss) < 1e-8


def test_steady_state_fused_estimator_monte_carlo():
    """Steady-state (offline-gain) MF predictor/filter/smoother: MC variance vs computed, |z| < 4.5."""
    sys = ups_system()
    ss = steady_state(sys)
    T, R = 60, 3000
    sim = simulate_fusion(sys, T, (R,), torch.Generator().manual_seed(4))
    for N in (-2, 0, 2):
        xo, Po, W = steady_fused_estimates(sys, ss, sim.y, N)
        assert torch.allclose(W.sum(0), torch.eye(3), atol=1e-10)
        err2 = (sim.x - xo)[25:55] ** 2
        assert bool((_z(err2, Po.diagonal()).abs() < 4.5).all()), N


@pytest.mark.parametrize("make", [ups_system, random_system])
def test_theorem6_closed_sums_match_the_recursion(make):
    from torchmm.fusion.cross import theorem6_cross_covariances

    sys = make()
    T = 25
    stats = local_predictor_stats(sys, T)
    cross = cross_predictor_stats(sys, stats)
    idx = torch.arange(sys.num_sensors)
    for N in range(4):
        rec = cross_covariances(sys, stats, cross, N)
        assert _rel(theorem6_cross_covariances(sys, stats, cross, N), rec) < 1e-10, N
        printed = theorem6_cross_covariances(sys, stats, cross, N, xi_term=False)
        off = torch.ones(sys.num_sensors, sys.num_sensors, dtype=torch.bool)
        off[idx, idx] = False
        assert _rel(printed[:, off], rec[:, off]) < 1e-10, N  # i != j: (42) as printed is exact
        if N <= 1:
            assert _rel(printed, rec) < 1e-10
        else:  # i = j, N >= 2: the printed (42) misses E[eps_i xi_i^T]; (39) then differs from (31)
            assert _rel(printed[:, idx, idx], local_covariances(sys, stats, N)) > 1e-4


@pytest.mark.parametrize("N", [-2, 0, 2])
def test_missing_measurements_match_the_oracle_without_them(N):
    """NaN = missing: the same pattern in every run; estimates equal the projection on the data left."""
    sys = random_system(3)
    T = 7
    sim = simulate_fusion(sys, T, (3,), torch.Generator().manual_seed(8))
    y = sim.y.clone()
    present = torch.ones(T, 3, 2, dtype=torch.bool)
    present[0, 0] = False  # sensor 1 silent at t = 0
    present[1::2, 1] = False  # sensor 2 at half rate
    present[2:4, 2, 0] = False  # one component of sensor 3 missing at t = 2, 3
    y[~present[:, None].expand(T, 3, 3, 2)] = float("nan")
    orc = oracle(sys, T)
    orc.present = present.numpy()
    stats = local_predictor_stats(sys, T, present)
    cross = cross_predictor_stats(sys, stats)
    mean, P = local_estimates(sys, y, N, stats)
    amean, aP = augmented_local_estimates(sys, y, N)
    Pij = cross_covariances(sys, stats, cross, N)
    cmean, ccov = centralized_estimates(sys, y, N)
    assert bool(torch.isfinite(mean).all() & torch.isfinite(cmean).all() & torch.isfinite(Pij).all())
    assert _rel(mean, amean) < 1e-8 and _rel(P, aP) < 1e-8
    y0 = torch.nan_to_num(y[:, 0]).numpy()
    for t in range(T):
        for i in range(3):
            np.testing.assert_allclose(mean[t, 0, i].numpy(), orc.estimate(y0, t, N, [i]),
                                       rtol=1e-8, atol=1e-9)
            for j in range(3):
                np.testing.assert_allclose(Pij[t, i, j], orc.error_cov(t, N, [i], [j]),
                                           rtol=1e-8, atol=1e-10)
        everyone = [0, 1, 2]
        np.testing.assert_allclose(ccov[t].numpy(), orc.error_cov(t, N, everyone, everyone),
                                   rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(cmean[t, 0].numpy(), orc.estimate(y0, t, N, everyone),
                                   rtol=1e-8, atol=1e-9)
    f = fuse(mean, Pij, "matrix")
    assert bool(torch.isfinite(f.mean).all())
    with pytest.raises(ValueError, match="pattern"):
        local_estimates(sys, sim.y, N, stats)  # complete data against stats for the masked pattern


def test_gradients_flow_through_local_estimators_and_fusion():
    """Differentiable in the noise parameters (e.g. to learn h_i, Q^p_i by gradient)."""

    def fused(h, qp):
        sys = MultiSensorSystem.from_correlation(
            A=[[0.5, 0.1], [0.0, 0.7]], Gamma=[[1.0], [0.5]], Qw=[[1.0]], C=[[[1.0, 0.0]], [[1.0, 1.0]]],
            Ct=[[[0.5, 0.1]], [[0.2, 0.3]]], h=h, Qp=qp, d=[[[0.0]], [[0.3]]], Q_eta=[[[1.0]], [[2.0]]],
            mu0=[0.1, 0.0], P0=torch.eye(2))
        y = torch.linspace(-1, 1, 12).reshape(6, 1, 2, 1)
        stats = local_predictor_stats(sys, 6)
        mean, _ = local_estimates(sys, y, 1, stats)
        f = fuse(mean, cross_covariances(sys, stats, cross_predictor_stats(sys, stats), 1), "matrix")
        return f.mean.sum() + f.cov.diagonal(**DIAG).sum()

    h = torch.tensor([0.6, 0.7], requires_grad=True)
    qp = torch.tensor([0.1, 0.2], requires_grad=True)
    assert torch.autograd.gradcheck(fused, (h, qp))


def test_fuse_tracks_on_beliefs_matches_information_fusion_and_fuses_imm_tracks():
    """Independent tracks: the matrix weights give information fusion; any estimator's belief is a track."""
    import torch

    from torchmm import IMM, ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, run_filter
    from torchmm.fusion import fuse_tracks

    g = torch.Generator().manual_seed(0)
    A = torch.randn(5, 2, 2, generator=g, dtype=torch.float64)
    P1 = A @ A.mT + 0.5 * torch.eye(2, dtype=torch.float64)
    B = torch.randn(5, 2, 2, generator=g, dtype=torch.float64)
    P2 = B @ B.mT + 0.5 * torch.eye(2, dtype=torch.float64)
    x1, x2 = torch.randn(5, 2, generator=g, dtype=torch.float64), torch.randn(5, 2, generator=g, dtype=torch.float64)
    fused = fuse_tracks([GaussianBelief(x1, P1), GaussianBelief(x2, P2)])
    info = torch.linalg.inv(P1) + torch.linalg.inv(P2)
    want_cov = torch.linalg.inv(info)
    want_mean = (want_cov @ (torch.linalg.solve(P1, x1.unsqueeze(-1)) + torch.linalg.solve(P2, x2.unsqueeze(-1)))
                 ).squeeze(-1)
    torch.testing.assert_close(fused.cov, want_cov, rtol=0, atol=1e-10)
    torch.testing.assert_close(fused.mean, want_mean, rtol=0, atol=1e-10)
    # two IMM tracks of one target from two sensors: the fused track is tighter than either
    motion = ConstantVelocity(1, q=0.5, acceleration=torch.tensor([[0.5], [0.0], [-0.5]], dtype=torch.float64),
                              dtype=torch.float64)
    P = torch.full((3, 3), 0.05, dtype=torch.float64) + 0.85 * torch.eye(3, dtype=torch.float64)
    z = torch.cumsum(torch.randn(20, 4, 1, generator=g, dtype=torch.float64), 0)
    prior = GaussianBelief(torch.zeros(4, 2, dtype=torch.float64), 10 * torch.eye(2, dtype=torch.float64))
    tracks = []
    for r in (1.0, 4.0):
        imm = IMM(KalmanFilter(motion, PositionMeasurement(2, [0], torch.tensor(r, dtype=torch.float64),
                                                         dtype=torch.float64)), P)
        tracks.append(run_filter(imm, imm.initial_belief(prior), z + r * torch.randn(20, 4, 1, generator=g,
                                                                                  dtype=torch.float64)).belief)
    out = fuse_tracks(tracks)
    for t in tracks:
        assert (out.cov.diagonal(dim1=-2, dim2=-1) <= t.estimate().cov.diagonal(dim1=-2, dim2=-1) + 1e-12).all()
    with pytest.raises(ValueError, match="cross_covs"):
        fuse_tracks(tracks, torch.zeros(2, 2, 3, 3, dtype=torch.float64))


def test_local_unscented_filters_fused_by_covariance_intersection():
    """Any filter as a local estimator: two UKF tracks of one target from two range-bearing radars,
    fused by covariance intersection (unknown cross-covariance): consistent and tighter than the worse."""
    import math

    import torch

    from torchmm import ConstantVelocity, GaussianBelief, PositionMeasurement, UnscentedKalmanFilter, run_filter
    from torchmm.fusion import fuse_tracks
    from torchmm.simulate import simulate_jump_system, simulate_measurements

    kw = dict(dtype=torch.float64)
    cv = ConstantVelocity(2, q=0.05, dtype=torch.float64)
    sensors = [PositionMeasurement(4, [0, 2], torch.tensor(r, **kw), dtype=torch.float64) for r in (1.0, 9.0)]
    prior = GaussianBelief(torch.zeros(4, **kw), 4 * torch.eye(4, **kw))
    g = torch.Generator().manual_seed(3)
    truth = simulate_jump_system(cv, torch.ones(1, 1, **kw), prior, 30, (200,), generator=g).states
    tracks = []
    for s in sensors:
        z = simulate_measurements(s, truth, generator=g)
        tracks.append(run_filter(UnscentedKalmanFilter(cv, s), prior.expand(200), z).belief)
    fused = fuse_tracks(tracks, method="covariance_intersection")
    w = torch.tensor([1 / t.cov.diagonal(dim1=-2, dim2=-1).sum(-1).mean() for t in tracks])
    assert w[0] > w[1]  # the accurate radar dominates
    # consistency: the NEES of the fused estimate does not exceed its dimension (CI is conservative)
    err = (fused.mean - truth).unsqueeze(-1)
    nees = (err.mT @ torch.linalg.solve(fused.cov, err)).squeeze().mean()
    assert nees < 4.0 * 1.1, nees
    worse = tracks[1].cov.diagonal(dim1=-2, dim2=-1).sum(-1)
    assert (fused.cov.diagonal(dim1=-2, dim2=-1).sum(-1) < worse).all()
    assert math.isfinite(float(nees))
    with pytest.raises(ValueError, match="cross_covs"):
        fuse_tracks(tracks, torch.zeros(30, 200, 2, 2, 4, 4, **kw), method="covariance_intersection")


# ---------------------------------------------------------------------------------------------
# matrix weights on badly scaled state components (docs/reproduction-002.md, "fusion with singular P")
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("small", [1e-8, 1e-14, 1e-16])
def test_matrix_weights_match_45_when_components_differ_in_scale(small):
    """Two uncorrelated sensors, ``P_11 = diag(1, s)``, ``P_22 = diag(1, 2 s)``: (45) in float64 NumPy
    gives component 2 the weights ``(2/3, 1/3)`` whatever ``s``; a cutoff relative to the largest
    entry only used to truncate the small component (0.5 / 0.5 at ``s = 1e-16``)."""
    P11, P22 = np.diag([1.0, small]), np.diag([1.0, 2 * small])
    Sigma = np.block([[P11, np.zeros((2, 2))], [np.zeros((2, 2)), P22]])
    F = np.vstack([np.eye(2), np.eye(2)])
    Po_ref = np.linalg.inv(F.T @ np.linalg.solve(Sigma, F))  # (45)
    A_ref = Po_ref @ F.T @ np.linalg.inv(Sigma)  # (2, 4) = [A_1, A_2]
    P = torch.zeros(2, 2, 2, 2, dtype=torch.float64)
    P[0, 0], P[1, 1] = torch.from_numpy(P11), torch.from_numpy(P22)
    A, Po = fusion_weights(P, "matrix")
    np.testing.assert_allclose(torch.cat([A[0], A[1]], -1).numpy(), A_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(Po.diagonal().numpy(), np.diag(Po_ref), rtol=1e-12)


def test_matrix_fusion_beats_diagonal_per_component_on_a_badly_scaled_state():
    """Correlated sensors whose state components have variances ``1``, ``1e-8``, ``1e-16``: the
    matrix-weighted variance (45) is at most the diagonal-weighted one (46) in every component, and
    ``P_o <= P_i`` in the matrix sense, both relative to each component's scale. Reference: the
    constraint-exact optimum ``x^_L + sum_{i<L} A_i (x^_i - x^_L)`` in float64 NumPy."""
    L, n = 3, 3
    scale = torch.tensor([1.0, 1e-4, 1e-8], dtype=torch.float64)
    P0 = _random_joint(L, n, 11).double()
    P = P0 * scale[:, None] * scale  # D P_ij D, D = diag(scale)
    A, Po = fusion_weights(P, "matrix")
    _, Pd = fusion_weights(P, "diagonal")
    Sigma = P.transpose(-3, -2).reshape(L * n, L * n).numpy()
    Tm = np.hstack([np.eye((L - 1) * n), -np.tile(np.eye(n), (L - 1, 1))])  # x^_i - x^_L, i < L
    eL = np.hstack([np.zeros((n, (L - 1) * n)), np.eye(n)])
    CD, CLD = Tm @ Sigma @ Tm.T, eL @ Sigma @ Tm.T
    d = np.sqrt(np.diag(CD))
    W = eL - np.linalg.solve(CD / np.outer(d, d), (CLD / d).T).T / d @ Tm
    Po_ref = W @ Sigma @ W.T
    var, var_d, var_ref = Po.diagonal().numpy(), Pd.diagonal().numpy(), np.diag(Po_ref)
    np.testing.assert_allclose(var, var_ref, rtol=1e-9)
    assert (var <= var_d * (1 + 1e-9)).all(), (var / var_d)
    assert (var_d / var > 1 + 1e-3).any()  # the case separates the two methods
    unit = 1 / scale[:, None] / scale
    idx = torch.arange(L)
    assert bool((torch.linalg.eigvalsh((P[idx, idx] - Po) * unit) > -1e-10).all())

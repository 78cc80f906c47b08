"""Modes with different state dimensions (CV 4-state + CA 6-state) and the static MM estimator."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmm import (
    GPB1,
    IMM,
    ConstantAcceleration,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    PositionMeasurement,
    run_filter,
)
from torchmm.multimodel import Embedded, StaticMM, kinematic_index

PI = [[0.9, 0.1], [0.2, 0.8]]


def _cv_ca(q_cv=0.5, q_ca=0.2, r=4.0):
    cv = KalmanFilter(ConstantVelocity(2, q=q_cv), PositionMeasurement(4, [0, 2], r))
    ca = KalmanFilter(ConstantAcceleration(2, q=q_ca), PositionMeasurement(6, [0, 3], r))
    return cv, ca


def _numpy_imm(cv, ca, pi, x0, P0, zs):
    """A hand-written float64 IMM over a CV(4) and a CA(6) mode, one run at a time: the CV mode's
    belief lives in the CA space with zero acceleration and zero acceleration variance."""
    idx = np.array([0, 1, 3, 4])
    F = [cv.motion.F.numpy(), ca.motion.F.numpy()]
    Q = [cv.motion.Q.numpy(), ca.motion.Q.numpy()]
    H = [cv.measurement.H.numpy(), ca.measurement.H.numpy()]
    R = ca.measurement.R.numpy()
    pi = np.asarray(pi)
    runs, steps = zs.shape[1], zs.shape[0]
    means = np.zeros((steps, runs, 6))
    probs = np.zeros((steps, runs, 2))
    for r in range(runs):
        x = [x0[r].copy(), x0[r].copy()]
        P = [P0[r].copy(), P0[r].copy()]
        # the CV mode starts from the prior's CV components (accelerations zero, variance zero)
        x[0][[2, 5]] = 0.0
        P[0][[2, 5], :] = 0.0
        P[0][:, [2, 5]] = 0.0
        mu = np.array([0.5, 0.5])
        for k in range(steps):
            cbar = mu @ pi
            xs, Ps, lik = [], [], []
            for j in range(2):
                w = pi[:, j] * mu / cbar[j]
                xm = sum(w[i] * x[i] for i in range(2))
                Pm = sum(w[i] * (P[i] + np.outer(x[i] - xm, x[i] - xm)) for i in range(2))
                if j == 0:
                    xo, Po = xm[idx], Pm[np.ix_(idx, idx)]
                else:
                    xo, Po = xm, Pm
                xp = F[j] @ xo
                Pp = F[j] @ Po @ F[j].T + Q[j]
                S = H[j] @ Pp @ H[j].T + R
                K = Pp @ H[j].T @ np.linalg.inv(S)
                nu = zs[k, r] - H[j] @ xp
                xu = xp + K @ nu
                Pu = Pp - K @ S @ K.T
                lik.append(np.exp(-0.5 * nu @ np.linalg.solve(S, nu)) / np.sqrt(np.linalg.det(2 * np.pi * S)))
                if j == 0:
                    full_x, full_P = np.zeros(6), np.zeros((6, 6))
                    full_x[idx] = xu
                    full_P[np.ix_(idx, idx)] = Pu
                    xu, Pu = full_x, full_P
                xs.append(xu)
                Ps.append(Pu)
            x, P = xs, Ps
            mu = np.array(lik) * cbar
            mu = mu / mu.sum()
            probs[k, r] = mu
            means[k, r] = mu[0] * x[0] + mu[1] * x[1]
    return means, probs


def test_cv4_ca6_imm_matches_a_hand_written_reference(generator):
    cv, ca = _cv_ca(q_cv=0.01, q_ca=0.05)
    runs, steps = 3, 25
    x0 = torch.randn(runs, 6, generator=generator) * 5
    P0 = torch.eye(6).expand(runs, 6, 6) * 10
    # a target that accelerates half way
    t = torch.arange(steps, dtype=torch.float64)
    truth = torch.stack([2 * t + (t - 12).clamp_min(0) ** 2, -t], -1)
    zs = truth.unsqueeze(1) + 2 * torch.randn(steps, runs, 2, generator=generator)
    imm = IMM([Embedded(cv, kinematic_index(2, 3, ndim=2), 6), ca], torch.tensor(PI))
    traj = run_filter(imm, imm.initial_belief(GaussianBelief(x0, P0)), zs)
    want_mean, want_probs = _numpy_imm(cv, ca, PI, x0.numpy(), P0.numpy(), zs.numpy())
    np.testing.assert_allclose(traj.estimate().mean.numpy(), want_mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(traj.belief.mode_probs.numpy(), want_probs, rtol=0, atol=1e-12)
    # the CV mode never acquires an acceleration
    comps = traj.belief.components
    assert comps.mean[..., 0, [2, 5]].abs().max() == 0
    assert comps.cov[..., 0, [2, 5], :].abs().max() == 0
    # the CA mode gains once the target accelerates
    early, late = traj.belief.mode_probs[5:12, :, 1].mean(), traj.belief.mode_probs[-5:, :, 1].mean()
    assert late > 0.6 and late > early + 0.2, (early, late)


def test_embedded_banks_work_with_gpb1_and_fill_values(generator):
    cv, ca = _cv_ca()
    embedded = Embedded(cv, kinematic_index(2, 3, ndim=2), 6, fill_cov=torch.full((6,), 0.25))
    gpb = GPB1([embedded, ca], torch.tensor(PI))
    out = gpb.step(gpb.initial_belief(GaussianBelief(torch.zeros(2, 6), torch.eye(6))),
                   torch.randn(2, 2, generator=generator))
    assert torch.equal(out.belief.components.cov[:, 0, 2, 2], torch.full((2,), 0.25))
    assert out.belief.components.cov[:, 0, 2, [0, 1, 3, 4, 5]].abs().max() == 0


def test_different_state_dims_without_embedding_name_the_fix():
    cv, ca = _cv_ca()
    with pytest.raises(ValueError, match="different state_dims.*Embedded"):
        IMM([cv, ca], torch.tensor(PI))
    with pytest.raises(ValueError, match="index: the filter's state has 4 components"):
        Embedded(cv, [0, 1, 3], 6)
    with pytest.raises(ValueError, match="common_dim"):
        Embedded(cv, [0, 1, 3, 6], 6)
    assert kinematic_index(2, 3, ndim=2) == [0, 1, 3, 4]


def test_static_mm_equals_imm_with_an_identity_transition(generator):
    sensors = [PositionMeasurement(2, [0], r) for r in (0.5, 4.0, 25.0)]
    bank = [KalmanFilter(ConstantVelocity(1, q=q), s) for q, s in zip((0.1, 1.0, 3.0), sensors)]
    prior = GaussianBelief(torch.zeros(5, 2), 10 * torch.eye(2))
    z = torch.randn(30, 5, 1, generator=generator) * 3
    z[4, 1] = torch.nan  # a missing datum
    static = StaticMM(bank)
    imm = IMM(bank, torch.eye(3))
    a = run_filter(static, static.initial_belief(prior), z)
    b = run_filter(imm, imm.initial_belief(prior), z)
    torch.testing.assert_close(a.belief.mode_probs, b.belief.mode_probs, rtol=0, atol=1e-12)
    torch.testing.assert_close(a.estimate().mean, b.estimate().mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(a.log_likelihood, b.log_likelihood, rtol=0, atol=1e-12)
    # each mode is its own Kalman filter, untouched by the others
    alone = run_filter(bank[1], prior, z)
    torch.testing.assert_close(a.belief.components.mean[:, :, 1], alone.belief.mean, rtol=0, atol=1e-12)

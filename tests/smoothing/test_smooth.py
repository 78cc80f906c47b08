"""torchmm.smooth: RTS against the joint-Gaussian posterior of the stacked data, the unscented RTS
against RTS on a linear model, the extended RTS against an independent NumPy implementation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from torchmm import (
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    MerweScaledSigmaPoints,
    NonlinearCoordinatedTurn,
    ParticleFilter,
    UnscentedKalmanFilter,
    run_filter,
    smooth,
)
from torchmm.models import ConstantVelocity, PositionMeasurement

T, B = 7, 3


def _linear(dtype=torch.float64):
    cv = ConstantVelocity(1, q=0.3, dtype=dtype)
    sensor = PositionMeasurement(2, [0], 2.0, dtype=dtype)
    m0 = torch.tensor([[0.5, 1.0], [-1.0, 0.2], [2.0, -0.5]], dtype=dtype)
    P0 = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=dtype)
    z = 3 * torch.randn(T, B, 1, generator=torch.Generator().manual_seed(4), dtype=dtype)
    z[2, 1] = float("nan")  # missing data
    z[5, :] = float("nan")
    return cv, sensor, GaussianBelief(m0, P0.expand(B, 2, 2)), z


def _joint_posterior(F, Q, H, R, m0, P0, z):
    """Mean and per-step covariances of x_{1..T} | observed z_{1..T} (stacked Gaussian conditioning)."""
    n = F.shape[0]
    powers = [np.linalg.matrix_power(F, k) for k in range(T + 1)]
    mu = np.concatenate([powers[k] @ m0 for k in range(1, T + 1)])
    S = np.zeros((T * n, T * n))
    for i in range(1, T + 1):
        for j in range(1, T + 1):
            block = powers[i] @ P0 @ powers[j].T
            for l in range(1, min(i, j) + 1):
                block = block + powers[i - l] @ Q @ powers[j - l].T
            S[(i - 1) * n:i * n, (j - 1) * n:j * n] = block
    rows = [k for k in range(T) if np.isfinite(z[k]).all()]
    Hs = np.zeros((len(rows) * H.shape[0], T * n))
    for r, k in enumerate(rows):
        Hs[r * H.shape[0]:(r + 1) * H.shape[0], k * n:(k + 1) * n] = H
    zs = np.concatenate([z[k] for k in rows])
    Rs = np.kron(np.eye(len(rows)), R)
    gain = S @ Hs.T @ np.linalg.inv(Hs @ S @ Hs.T + Rs)
    mean = mu + gain @ (zs - Hs @ mu)
    cov = S - gain @ Hs @ S
    return mean.reshape(T, n), np.stack([cov[k * n:(k + 1) * n, k * n:(k + 1) * n] for k in range(T)])


def test_rts_equals_the_joint_gaussian_posterior_of_the_stacked_data():
    cv, sensor, belief0, z = _linear()
    kf = KalmanFilter(cv, sensor)
    out = smooth(kf, run_filter(kf, belief0, z)).belief
    assert out.mean.shape == (T, B, 2) and out.cov.shape == (T, B, 2, 2)
    F, Q, H, R = (t.numpy() for t in (cv.F, cv.Q, sensor.H, sensor.R))
    for b in range(B):
        mean, cov = _joint_posterior(F, Q, H, R, belief0.mean[b].numpy(), belief0.cov[b].numpy(), z[:, b].numpy())
        np.testing.assert_allclose(out.mean[:, b].numpy(), mean, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(out.cov[:, b].numpy(), cov, rtol=1e-10, atol=1e-10)


def test_unscented_rts_equals_rts_on_a_linear_model():
    cv, sensor, belief0, z = _linear()
    kf = KalmanFilter(cv, sensor)
    ukf = UnscentedKalmanFilter(cv, sensor, MerweScaledSigmaPoints(alpha=0.5, beta=2.0, kappa=1.0))
    rts = smooth(kf, run_filter(kf, belief0, z)).belief
    urts = smooth(ukf, run_filter(ukf, belief0, z)).belief
    torch.testing.assert_close(urts.mean, rts.mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(urts.cov, rts.cov, rtol=1e-10, atol=1e-10)


def _numpy_ekf_erts(f, Q, H, R, m0, P0, z, eps=1e-6):
    """EKF and extended RTS in float64 NumPy, Jacobians by central differences (one run)."""
    def jac(x):
        n = x.size
        return np.stack([(f(x + eps * e) - f(x - eps * e)) / (2 * eps) for e in np.eye(n)], 1)

    m, P = m0, P0
    ms, Ps, mps, Pps, Fs = [], [], [], [], []
    for k in range(len(z)):
        Fk = jac(m)
        mp, Pp = f(m), Fk @ P @ Fk.T + Q
        S = H @ Pp @ H.T + R
        K = Pp @ H.T @ np.linalg.inv(S)
        m, P = mp + K @ (z[k] - H @ mp), Pp - K @ S @ K.T
        ms.append(m), Ps.append(P), mps.append(mp), Pps.append(Pp), Fs.append(Fk)
    sm, sP = [ms[-1]], [Ps[-1]]
    for k in range(len(z) - 2, -1, -1):
        Fk = jac(ms[k])
        G = Ps[k] @ Fk.T @ np.linalg.inv(Pps[k + 1])
        sm.append(ms[k] + G @ (sm[-1] - mps[k + 1]))
        sP.append(Ps[k] + G @ (sP[-1] - Pps[k + 1]) @ G.T)
    return np.stack(sm[::-1]), np.stack(sP[::-1])


def test_extended_rts_agrees_with_an_independent_numpy_implementation():
    motion = NonlinearCoordinatedTurn(dt=1.0, q=0.5, q_omega=1e-3, dtype=torch.float64)
    sensor = PositionMeasurement(5, [0, 2], 25.0, dtype=torch.float64)
    ekf = ExtendedKalmanFilter(motion, sensor)
    m0 = torch.tensor([[0.0, 10.0, 0.0, 5.0, 0.05], [100.0, -3.0, 50.0, 8.0, -0.03]], dtype=torch.float64)
    P0 = torch.diag(torch.tensor([10.0, 2.0, 10.0, 2.0, 1e-3], dtype=torch.float64))
    g = torch.Generator().manual_seed(7)
    truth, x = [], m0.clone()
    for _ in range(12):
        x = motion(x)
        truth.append(x)
    z = torch.stack(truth)[..., [0, 2]] + 5 * torch.randn(12, 2, 2, generator=g, dtype=torch.float64)
    out = smooth(ekf, run_filter(ekf, GaussianBelief(m0, P0.expand(2, 5, 5)), z)).belief

    def f(s):
        return motion(torch.as_tensor(s)).numpy()

    for b in range(2):
        mean, cov = _numpy_ekf_erts(f, motion.Q.numpy(), sensor.H.numpy(), sensor.R.numpy(), m0[b].numpy(),
                                    P0.numpy(), z[:, b].numpy())
        np.testing.assert_allclose(out.mean[:, b].numpy(), mean, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(out.cov[:, b].numpy(), cov, rtol=1e-6, atol=1e-7)


def test_smoothing_is_differentiable_and_keeps_the_data_likelihood():
    cv, sensor, belief0, z = _linear()
    z = torch.nan_to_num(z, nan=0.0)[:4].requires_grad_(True)
    kf = KalmanFilter(cv, sensor)

    def first_mean(data):
        return smooth(kf, run_filter(kf, belief0, data)).belief.mean[0]

    assert torch.autograd.gradcheck(first_mean, (z,))
    traj = run_filter(kf, belief0, z)
    assert smooth(kf, traj).log_likelihood is traj.log_likelihood


def test_clear_errors():
    cv, sensor, belief0, z = _linear()
    kf = KalmanFilter(cv, sensor)
    traj = run_filter(kf, belief0, z)
    with pytest.raises(TypeError, match="filter: no smoother for ConstantVelocity"):
        smooth(cv, traj)
    with pytest.raises(TypeError, match="filter: a ParticleFilter, but a KalmanFilter made this trajectory"):
        smooth(ParticleFilter(cv, sensor, num_particles=10), traj)
    # no record to check against
    with pytest.raises(TypeError, match="trajectory.belief: expected particle beliefs"):
        smooth(ParticleFilter(cv, sensor, num_particles=10), dataclasses.replace(traj, provenance=None))
    with pytest.raises(ValueError, match="trajectory.prior"):
        smooth(kf, run_filter(kf, belief0, z, record=lambda o: o._replace(prior=None)))
    with pytest.raises(ValueError, match="motions: expected one entry per step"):
        smooth(kf, traj, motions=[cv] * 3)
    with pytest.raises(TypeError, match="trajectory"):
        smooth(kf, traj.belief)


# -- Kim's smoother for IMM / GPB banks ------------------------------------------------------------
from torchmm import GPB1, GPB2, IMM, LinearMotion  # noqa: E402


def _bank(qs, dtype=torch.float64):
    cv = ConstantVelocity(1, q=1.0, dtype=dtype)
    G = torch.tensor([[0.5], [1.0]], dtype=dtype)
    Q = torch.stack([q * G @ G.mT for q in qs])
    return LinearMotion(cv.F, Q), cv.F, Q


def test_kim_smoother_with_one_mode_is_rts():
    cv, sensor, belief0, z = _linear()
    kf = KalmanFilter(cv, sensor)
    imm = IMM(KalmanFilter(LinearMotion(cv.F, cv.Q.unsqueeze(0)), sensor), torch.ones(1, 1, dtype=torch.float64))
    rts = smooth(kf, run_filter(kf, belief0, z)).belief
    kim = smooth(imm, run_filter(imm, imm.initial_belief(belief0), z), method="kim").belief
    assert kim.mode_probs.shape == (T, B, 1)
    torch.testing.assert_close(kim.estimate().mean, rts.mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(kim.estimate().cov, rts.cov, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("combinator", [IMM, GPB1, GPB2])
def test_kim_smoother_with_identical_modes_is_rts_for_any_transition(combinator):
    cv, sensor, belief0, z = _linear()
    kf = KalmanFilter(cv, sensor)
    same = LinearMotion(cv.F, cv.Q.expand(3, 2, 2))
    transition = torch.tensor([[0.6, 0.3, 0.1], [0.05, 0.9, 0.05], [0.2, 0.2, 0.6]], dtype=torch.float64)
    mm = combinator(KalmanFilter(same, sensor), transition)
    start = mm.initial_belief(belief0, torch.tensor([0.2, 0.5, 0.3], dtype=torch.float64))
    rts = smooth(kf, run_filter(kf, belief0, z)).belief
    kim = smooth(mm, run_filter(mm, start, z), method="kim").belief
    torch.testing.assert_close(kim.estimate().mean, rts.mean, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(kim.estimate().cov, rts.cov, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(kim.mode_probs.sum(-1), torch.ones(T, B, dtype=torch.float64))


def _exact_switching_smoother(F, Q, sensor, transition, mu0, belief0, z):
    """E[x_k | z_{1:T}] and P(s_k | z_{1:T}) by enumerating every mode sequence: a Kalman filter and
    RTS smoother per sequence (its per-step Q), weighted by prior x marginal likelihood."""
    steps, runs = z.shape[:2]
    seqs = torch.cartesian_prod(*[torch.arange(2)] * steps)  # (S, T)
    S = seqs.shape[0]
    log_prior = torch.logsumexp(mu0.log().unsqueeze(1) + transition.log()[:, seqs[:, 0]], 0)  # s_0 summed out
    for k in range(1, steps):
        log_prior = log_prior + transition.log()[seqs[:, k - 1], seqs[:, k]]
    motions = [LinearMotion(F, Q[seqs[:, k]].unsqueeze(1)) for k in range(steps)]  # batch (S, runs)
    kf = KalmanFilter(motions[0], sensor)
    b0 = GaussianBelief(belief0.mean.expand(S, runs, 2), belief0.cov.expand(S, runs, 2, 2))
    zz = z.unsqueeze(1).expand(steps, S, runs, 1)
    traj = run_filter(kf, b0, zz, motions=motions)
    post = (log_prior.unsqueeze(1) + traj.log_likelihood.sum(0)).softmax(0)  # (S, runs)
    means = smooth(kf, traj, motions=motions).belief.mean  # (T, S, runs, n)
    mean = (post.unsqueeze(-1) * means).sum(1)
    probs = torch.stack([(post.unsqueeze(0) * (seqs.T.unsqueeze(-1) == j)).sum(1) for j in range(2)], -1)
    return mean, probs  # (T, runs, n), (T, runs, 2)


def _switching_data(qs, R, stay, steps, runs, seed):
    """A 2-mode switching system (velocity random walk of variance ``qs[mode]``, position measured
    with variance ``R``), simulated from ``seed``, and its models."""
    motion, F, Q = _bank(qs)
    sensor = PositionMeasurement(2, [0], R, dtype=torch.float64)
    transition = torch.tensor([[stay, 1 - stay], [1 - stay, stay]], dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(runs, 2, dtype=torch.float64)
    mode = torch.randint(0, 2, (runs,), generator=g)
    sd = torch.tensor(qs, dtype=torch.float64).sqrt()
    zs = []
    for _ in range(steps):
        flip = torch.rand(runs, generator=g, dtype=torch.float64) < transition[mode, 1 - mode]
        mode = torch.where(flip, 1 - mode, mode)
        w = torch.randn(runs, 1, generator=g, dtype=torch.float64) * sd[mode, None]
        x = x @ F.mT + w @ torch.tensor([[0.5, 1.0]], dtype=torch.float64)
        zs.append(x[:, :1] + R**0.5 * torch.randn(runs, 1, generator=g, dtype=torch.float64))
    return motion, F, Q, sensor, transition, torch.stack(zs)


@pytest.mark.parametrize("combinator", [IMM, GPB2])
def test_kim_smoother_is_much_closer_to_the_exact_smoother_than_the_filter(combinator):
    """T = 8, 2 modes: against the exact smoother (all 2^8 mode sequences), the smoothed means' error
    is well below the filter's (measured here: about 0.1 of it) and the mode probabilities' too."""
    steps, runs = 8, 20
    motion, F, Q, sensor, transition, z = _switching_data([0.1, 2.0], 1.0, 0.9, steps, runs, seed=0)
    mu0 = torch.tensor([0.5, 0.5], dtype=torch.float64)
    belief0 = GaussianBelief(torch.zeros(runs, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64) * 4)
    exact_mean, exact_probs = _exact_switching_smoother(F, Q, sensor, transition, mu0, belief0, z)
    mm = combinator(KalmanFilter(motion, sensor), transition)
    traj = run_filter(mm, mm.initial_belief(belief0, mu0), z)
    kim = smooth(mm, traj, method="kim").belief
    filter_err = (traj.estimate().mean - exact_mean).norm(dim=-1)[:-1].mean()
    smoother_err = (kim.estimate().mean - exact_mean).norm(dim=-1)[:-1].mean()
    assert smoother_err < 0.3 * filter_err, (smoother_err, filter_err)
    prob_filter = (traj.belief.mode_probs - exact_probs).abs()[:-1].mean()
    prob_smoother = (kim.mode_probs - exact_probs).abs()[:-1].mean()
    assert prob_smoother < 0.6 * prob_filter, (prob_smoother, prob_filter)
    # the last step is the filter's own posterior (nothing after it)
    torch.testing.assert_close(kim.estimate().mean[-1], traj.estimate().mean[-1])


@pytest.mark.parametrize("combinator", [IMM, GPB2])
def test_kim_smoother_is_exact_for_static_modes(combinator):
    """Identity transition (a static multiple-model problem): Kim's smoother is the exact posterior,
    a mixture of one RTS smoother per mode weighted by the final mode probabilities."""
    motion, F, Q, sensor, _, z = _switching_data([0.1, 2.0], 1.0, 0.9, 6, 5, seed=1)
    identity = torch.eye(2, dtype=torch.float64)
    mu0 = torch.tensor([0.3, 0.7], dtype=torch.float64)
    belief0 = GaussianBelief(torch.zeros(5, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64) * 4)
    exact_mean, exact_probs = _exact_switching_smoother(F, Q, sensor, identity, mu0, belief0, z)
    mm = combinator(KalmanFilter(motion, sensor), identity)
    kim = smooth(mm, run_filter(mm, mm.initial_belief(belief0, mu0), z), method="kim").belief
    torch.testing.assert_close(kim.estimate().mean, exact_mean, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(kim.mode_probs, exact_probs, rtol=1e-9, atol=1e-9)


def test_kim_smoother_over_unscented_and_heterogeneous_banks():
    """Identical modes through an unscented bank, and a list bank of a Kalman and an extended
    Kalman filter: both give RTS (NaN measurements included)."""
    cv, sensor, belief0, z = _linear()
    kf = KalmanFilter(cv, sensor)
    rts = smooth(kf, run_filter(kf, belief0, z)).belief
    transition = torch.tensor([[0.7, 0.3], [0.4, 0.6]], dtype=torch.float64)
    ukf_bank = UnscentedKalmanFilter(LinearMotion(cv.F, cv.Q.expand(2, 2, 2)), sensor)
    for mm in (IMM(ukf_bank, transition), IMM([KalmanFilter(cv, sensor), ExtendedKalmanFilter(cv, sensor)],
                                              transition)):
        kim = smooth(mm, run_filter(mm, mm.initial_belief(belief0), z), method="kim").belief
        torch.testing.assert_close(kim.estimate().mean, rts.mean, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(kim.estimate().cov, rts.cov, rtol=1e-9, atol=1e-9)


# -- FFBSm for particle filters --------------------------------------------------------------------
def _numpy_ffbsm(F, Q, particles, log_weights):
    """Brute-force FFBSm weights (every pair of particles, full Gaussian densities), one run."""
    steps, N, n = particles.shape
    Qi = np.linalg.inv(Q)
    norm = -0.5 * np.log(np.linalg.det(2 * np.pi * Q))
    w = np.exp(log_weights - log_weights.max(-1, keepdims=True))
    w /= w.sum(-1, keepdims=True)
    out = [w[-1]]
    for k in range(steps - 2, -1, -1):
        f = np.empty((N, N))
        for i in range(N):
            for j in range(N):
                d = particles[k + 1, j] - F @ particles[k, i]
                f[i, j] = np.exp(norm - 0.5 * d @ Qi @ d)
        denom = w[k] @ f  # (j,)
        ws = w[k] * (f @ (out[-1] / denom))
        out.append(ws / ws.sum())
    return np.stack(out[::-1])


def _pf_setup(num_particles, runs=3, steps=T):
    cv = ConstantVelocity(1, q=0.5, noise="continuous", dtype=torch.float64)  # Q positive definite
    sensor = PositionMeasurement(2, [0], 1.0, dtype=torch.float64)
    g = torch.Generator().manual_seed(5)
    z = torch.cumsum(torch.randn(steps, runs, 1, generator=g, dtype=torch.float64), 0)
    z[3, 0] = float("nan")
    belief0 = GaussianBelief(torch.zeros(runs, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))
    pf = ParticleFilter(cv, sensor, num_particles=num_particles, ess_threshold=0.5)
    traj = run_filter(pf, pf.initial_belief(belief0, generator=g), z, generator=g)
    return cv, sensor, belief0, z, pf, traj


def test_ffbsm_weights_agree_with_a_brute_force_numpy_implementation():
    cv, _, _, _, pf, traj = _pf_setup(40)
    out = smooth(pf, traj).belief
    assert out.particles.shape == traj.belief.particles.shape and out.log_weights.shape == (T, 3, 40)
    for b in range(3):
        want = _numpy_ffbsm(cv.F.numpy(), cv.Q.numpy(), traj.belief.particles[:, b].numpy(),
                            traj.belief.log_weights[:, b].numpy())
        np.testing.assert_allclose(out.log_weights[:, b].exp().numpy(), want, rtol=1e-9, atol=1e-12)


def test_ffbsm_approaches_rts_on_a_linear_gaussian_model():
    """2,000 particles: the smoothed means lie within a small fraction of the posterior sd of RTS's."""
    cv, sensor, belief0, z, pf, traj = _pf_setup(2000)
    kf = KalmanFilter(cv, sensor)
    rts = smooth(kf, run_filter(kf, belief0, z)).belief
    est = smooth(pf, traj).belief.estimate()
    sd = rts.cov.diagonal(dim1=-2, dim2=-1).sqrt()
    assert ((est.mean - rts.mean).abs() / sd).mean() < 0.15
    ratio = est.cov.diagonal(dim1=-2, dim2=-1) / rts.cov.diagonal(dim1=-2, dim2=-1)
    assert ((ratio - 1).abs() < 0.5).all(), ratio


@pytest.mark.parametrize("dtype,offset", [(torch.float64, 6.4e6), (torch.float32, 1e3)])
def test_ffbsm_step_at_large_coordinates_matches_direct_differences(dtype, offset):
    """One FFBSm step with particles near ``offset`` (process sd 0.1) against a float64 NumPy reference on
    the same stored particles by direct differences ``y_j - F x_i``: total variation below 1e-9 (float64)
    and 1e-4 (float32). Before, ``|a|^2 + |b|^2 - 2 a.b`` on absolute whitened coordinates cancelled:
    3e-2 at 6.4e6 in float64, 0.13 at 1e3 in float32. (Further out, float32 rounds ``F x`` itself: at 1e5
    its spacing, 0.008, is no longer small beside the process sd; no shift can undo that.)"""
    from scipy.special import log_softmax, logsumexp

    from torchmm.beliefs import ParticleBelief
    from torchmm.models.linear import LinearMotion
    from torchmm.smooth import ffbsm_step

    rng = np.random.default_rng(0)
    runs, num = 2, 200
    F = np.array([[1.0, 0.1], [0.0, 1.0]])
    Q = 0.01 * np.array([[1.0, 0.3], [0.3, 2.0]])
    x = rng.normal(size=(runs, num, 2)) + offset
    y = x @ F.T + rng.normal(size=(runs, num, 2)) * 0.1
    lw, ls = rng.normal(size=(runs, num)), rng.normal(size=(runs, num))
    motion = LinearMotion(torch.tensor(F, dtype=dtype), torch.tensor(Q, dtype=dtype))
    xs, ys = torch.tensor(x, dtype=dtype), torch.tensor(y, dtype=dtype)
    got = ffbsm_step(motion, ParticleBelief(xs, torch.tensor(lw, dtype=dtype)),
                     ParticleBelief(ys, torch.zeros(runs, num, dtype=dtype)), torch.tensor(ls, dtype=dtype))
    Fs, Qi = torch.tensor(F, dtype=dtype).double().numpy(), np.linalg.inv(torch.tensor(Q, dtype=dtype).double().numpy())
    for b in range(runs):
        d = ys[b].double().numpy()[None, :, :] - (xs[b].double().numpy() @ Fs.T)[:, None, :]  # (i, j, n)
        log_f = -0.5 * np.einsum("ijk,kl,ijl->ij", d, Qi, d)
        lwn = log_softmax(lw[b])
        back = log_softmax(ls[b]) - logsumexp(lwn[:, None] + log_f, axis=0)
        want = log_softmax(lwn + logsumexp(log_f + back[None, :], axis=1))
        tv = 0.5 * np.abs(got[b].double().exp().numpy() - np.exp(want)).sum()
        assert tv < (1e-9 if dtype == torch.float64 else 1e-4), tv


def test_ffbsm_needs_a_positive_definite_process_noise():
    cv = ConstantVelocity(1, q=0.5, dtype=torch.float64)  # discrete white acceleration: Q = q G G^T, rank 1
    sensor = PositionMeasurement(2, [0], 1.0, dtype=torch.float64)
    pf = ParticleFilter(cv, sensor, num_particles=10)
    belief0 = GaussianBelief(torch.zeros(2, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))
    g = torch.Generator().manual_seed(0)
    traj = run_filter(pf, pf.initial_belief(belief0, generator=g), torch.zeros(4, 2, 1, dtype=torch.float64),
                      generator=g)
    with pytest.raises(ValueError, match="positive-definite process noise"):
        smooth(pf, traj)


def _numpy_kim(F, Q, off, transition, mu, means, covs):
    """Kim's smoother in float64 NumPy with loops over modes (one run): ``mu (T, M)``, the forward
    mode-conditioned ``means (T, M, n)`` and ``covs (T, M, n, n)``."""
    steps, M, n = means.shape
    ms, Ps, mus = [means[-1]], [covs[-1]], [mu[-1]]
    for t in range(steps - 2, -1, -1):
        pred = transition.T @ mu[t]  # mu^-_{t+1}(i)
        joint = np.array([[mus[-1][i] * mu[t, j] * transition[j, i] / pred[i] for i in range(M)] for j in range(M)])
        joint /= joint.sum()
        mode = joint.sum(1)
        m_new, P_new = np.zeros((M, n)), np.zeros((M, n, n))
        for j in range(M):
            pair_m, pair_P, w = [], [], joint[j] / mode[j]
            for i in range(M):
                mp = F[i] @ means[t, j] + off[i]
                Pp = F[i] @ covs[t, j] @ F[i].T + Q[i]
                G = covs[t, j] @ F[i].T @ np.linalg.inv(Pp)
                pair_m.append(means[t, j] + G @ (ms[-1][i] - mp))
                pair_P.append(covs[t, j] + G @ (Ps[-1][i] - Pp) @ G.T)
            m_new[j] = sum(w[i] * pair_m[i] for i in range(M))
            P_new[j] = sum(w[i] * (pair_P[i] + np.outer(pair_m[i] - m_new[j], pair_m[i] - m_new[j])) for i in range(M))
        ms.append(m_new), Ps.append(P_new), mus.append(mode)
    return np.stack(mus[::-1]), np.stack(ms[::-1]), np.stack(Ps[::-1])


@pytest.mark.parametrize("combinator", [IMM, GPB2])
def test_kim_smoother_agrees_with_an_independent_numpy_implementation(combinator):
    """Two modes differing in acceleration and noise, 40 steps: the batched Kim step against loops."""
    acc = torch.tensor([[0.0], [2.0]], dtype=torch.float64)
    cv = ConstantVelocity(1, q=0.1, acceleration=acc, dtype=torch.float64)
    G = torch.tensor([[0.5], [1.0]], dtype=torch.float64)
    bank = LinearMotion(cv.F, torch.stack([0.1 * G @ G.mT + 1e-3 * torch.eye(2, dtype=torch.float64),
                                           0.5 * G @ G.mT + 1e-3 * torch.eye(2, dtype=torch.float64)]), offset=cv.offset)
    sensor = PositionMeasurement(2, [0], 100.0, dtype=torch.float64)
    transition = torch.tensor([[0.95, 0.05], [0.1, 0.9]], dtype=torch.float64)
    belief0 = GaussianBelief(torch.tensor([0.0, 10.0], dtype=torch.float64).expand(2, 2),
                             torch.diag(torch.tensor([100.0, 10.0], dtype=torch.float64)).expand(2, 2, 2))
    z = 10 * torch.cumsum(torch.randn(40, 2, 1, generator=torch.Generator().manual_seed(3), dtype=torch.float64), 0)
    mm = combinator(KalmanFilter(bank, sensor), transition)
    traj = run_filter(mm, mm.initial_belief(belief0), z)
    kim = smooth(mm, traj, method="kim").belief
    F = cv.F.expand(2, 2, 2).numpy()
    for b in range(2):
        mu, means, covs = _numpy_kim(F, bank.Q.numpy(), cv.offset.numpy(), transition.numpy(),
                                     traj.belief.mode_probs[:, b].numpy(), traj.belief.components.mean[:, b].numpy(),
                                     traj.belief.components.cov[:, b].numpy())
        np.testing.assert_allclose(kim.mode_probs[:, b].numpy(), mu, rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(kim.components.mean[:, b].numpy(), means, rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(kim.components.cov[:, b].numpy(), covs, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("lag", [0, 1, 3, T - 1, T + 5])
@pytest.mark.parametrize("kind", ["kalman", "unscented"])
def test_fixed_lag_smoothing_is_the_fixed_interval_smoother_of_the_data_so_far(kind, lag):
    """x_{k|k+lag} against brute force: for every k, the fixed-interval smoother of z_{1:k+lag}."""
    cv, sensor, belief0, z = _linear()
    f = KalmanFilter(cv, sensor) if kind == "kalman" else UnscentedKalmanFilter(cv, sensor)
    out = smooth(f, run_filter(f, belief0, z), lag=lag).belief
    for k in range(T):
        last = min(k + lag, T - 1)
        want = smooth(f, run_filter(f, belief0, z[:last + 1])).belief[k]
        torch.testing.assert_close(out.mean[k], want.mean, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(out.cov[k], want.cov, rtol=1e-10, atol=1e-10)
    if lag == 0:
        torch.testing.assert_close(out.mean, run_filter(f, belief0, z).belief.mean)


def test_fixed_lag_errors():
    cv, sensor, belief0, z = _linear()
    kf = KalmanFilter(cv, sensor)
    traj = run_filter(kf, belief0, z)
    with pytest.raises(ValueError, match="lag: expected a non-negative integer"):
        smooth(kf, traj, lag=-1)
    imm = IMM(KalmanFilter(LinearMotion(cv.F, cv.Q.expand(2, 2, 2)), sensor), torch.eye(2, dtype=torch.float64))
    with pytest.raises(ValueError, match="lag: fixed-lag smoothing is implemented for Kalman"):
        smooth(imm, run_filter(imm, imm.initial_belief(belief0), z), lag=2)

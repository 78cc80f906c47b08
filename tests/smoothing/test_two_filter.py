"""The two-filter IMM smoother (torchmm.smooth's default for multiple-model filters): RTS where the
modes cannot be told apart, exact for static modes, far closer to the exact smoother (every mode
sequence enumerated) than the filter and Kim's smoother, equal to an independent NumPy loop
implementation, differentiable, and clear errors."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from torchmm import (
    GPB1,
    GPB2,
    IMM,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    LinearMotion,
    UnscentedKalmanFilter,
    run_filter,
    smooth,
)
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.simulate import simulate_jump_system, simulate_measurements
from torchmm.smooth import diffuse_factor

D = torch.float64


def _linear(steps=9, runs=3):
    cv = ConstantVelocity(1, q=0.3, dtype=D)
    sensor = PositionMeasurement(2, [0], 2.0, dtype=D)
    m0 = torch.tensor([[0.5, 1.0], [-1.0, 0.2], [2.0, -0.5]], dtype=D)[:runs]
    P0 = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=D)
    z = 3 * torch.randn(steps, runs, 1, generator=torch.Generator().manual_seed(4), dtype=D)
    z[2, 1] = float("nan")  # missing data, also at the last step of one run
    z[5, :] = float("nan")
    z[-1, 0] = float("nan")
    return cv, sensor, GaussianBelief(m0, P0.expand(runs, 2, 2)), z


# the backward filter's nearly flat start leaves ~1/diffuse_factor of prior information: 1.5e-8 in float64
TOL = 1e-6


def test_one_mode_is_rts():
    cv, sensor, belief0, z = _linear()
    kf = KalmanFilter(cv, sensor)
    imm = IMM(KalmanFilter(LinearMotion(cv.F, cv.Q.unsqueeze(0)), sensor), torch.ones(1, 1, dtype=D))
    rts = smooth(kf, run_filter(kf, belief0, z)).belief
    out = smooth(imm, run_filter(imm, imm.initial_belief(belief0), z), z).belief
    assert out.mode_probs.shape == (z.shape[0], 3, 1)
    torch.testing.assert_close(out.estimate().mean, rts.mean, rtol=TOL, atol=TOL)
    torch.testing.assert_close(out.estimate().cov, rts.cov, rtol=TOL, atol=TOL)


@pytest.mark.parametrize("combinator", [IMM, GPB1, GPB2])
@pytest.mark.parametrize("bank", ["kalman", "unscented", "list"])
def test_identical_modes_give_rts_for_any_transition(combinator, bank):
    cv, sensor, belief0, z = _linear()
    kf = KalmanFilter(cv, sensor)
    same = LinearMotion(cv.F, cv.Q.expand(3, 2, 2))
    filters = {"kalman": KalmanFilter(same, sensor), "unscented": UnscentedKalmanFilter(same, sensor),
               "list": [KalmanFilter(cv, sensor), ExtendedKalmanFilter(cv, sensor), UnscentedKalmanFilter(cv, sensor)]}
    transition = torch.tensor([[0.6, 0.3, 0.1], [0.05, 0.9, 0.05], [0.2, 0.2, 0.6]], dtype=D)
    mm = combinator(filters[bank], transition)
    start = mm.initial_belief(belief0, torch.tensor([0.2, 0.5, 0.3], dtype=D))
    rts = smooth(kf, run_filter(kf, belief0, z)).belief
    out = smooth(mm, run_filter(mm, start, z), z).belief
    torch.testing.assert_close(out.estimate().mean, rts.mean, rtol=TOL, atol=TOL)
    torch.testing.assert_close(out.estimate().cov, rts.cov, rtol=TOL, atol=TOL)
    torch.testing.assert_close(out.mode_probs.sum(-1), torch.ones(z.shape[:2], dtype=D))


def _exact(motion, sensor, transition, mu0, belief0, z):
    """E[x_k | z_{1:T}] and P(s_k | z_{1:T}) by enumerating every mode sequence: a Kalman filter and
    RTS smoother per sequence (its per-step mode model), weighted by prior x marginal likelihood."""
    steps, runs = z.shape[:2]
    M, n = transition.shape[0], belief0.state_dim
    seqs = torch.cartesian_prod(*[torch.arange(M)] * steps)  # (S, T)
    S = seqs.shape[0]
    log_prior = torch.logsumexp(mu0.log().unsqueeze(1) + transition.log()[:, seqs[:, 0]], 0)  # s_0 summed out
    for k in range(1, steps):
        log_prior = log_prior + transition.log()[seqs[:, k - 1], seqs[:, k]]
    F, Q, off = (t.expand(M, *t.shape[-(2 if t is not motion.offset else 1):]) for t in (motion.F, motion.Q, motion.offset))
    motions = [LinearMotion(F[seqs[:, k]].unsqueeze(1), Q[seqs[:, k]].unsqueeze(1), off[seqs[:, k]].unsqueeze(1))
               for k in range(steps)]  # batch (S, runs)
    kf = KalmanFilter(motions[0], sensor)
    b0 = GaussianBelief(belief0.mean.expand(S, runs, n), belief0.cov.expand(S, runs, n, n))
    traj = run_filter(kf, b0, z.unsqueeze(1).expand(steps, S, runs, z.shape[-1]), motions=motions)
    post = (log_prior.unsqueeze(1) + traj.log_likelihood.sum(0)).softmax(0)  # (S, runs)
    mean = (post.unsqueeze(-1) * smooth(kf, traj, motions=motions).belief.mean).sum(1)
    probs = torch.stack([(post.unsqueeze(0) * (seqs.T.unsqueeze(-1) == j)).sum(1) for j in range(M)], -1)
    return mean, probs  # (T, runs, n), (T, runs, M)


def _maneuvering(steps, runs, seed, transition):
    """Paper 001's two-model target (accelerations 0 and 2, q = 0.1 with the singular discrete
    white-acceleration Q, R = 100), simulated."""
    cv = ConstantVelocity(1, q=0.1, acceleration=[[0.0], [2.0]], dtype=D)
    sensor = PositionMeasurement(2, [0], 100.0, dtype=D)
    init = GaussianBelief(torch.tensor([0.0, 10.0], dtype=D), torch.diag(torch.tensor([100.0, 10.0], dtype=D)))
    g = torch.Generator().manual_seed(seed)
    sim = simulate_jump_system(cv, transition, init, steps, (runs,), generator=g)
    z = simulate_measurements(sensor, sim.states, generator=g)
    return cv, sensor, GaussianBelief(init.mean.expand(runs, 2), init.cov.expand(runs, 2, 2)), z


@pytest.mark.parametrize("combinator", [IMM, GPB2])
def test_far_closer_to_the_exact_smoother_than_the_filter_and_kim(combinator):
    """T = 11 on paper 001's target (asymmetric chain, non-uniform prior, a missing datum), against
    all 2^11 mode sequences. Measured: the two-filter smoother's mean error is 0.06-0.07 of the
    filter's and about 0.2 of Kim's, its mode-probability error about 0.07-0.08 of the filter's."""
    transition = torch.tensor([[0.95, 0.05], [0.1, 0.9]], dtype=D)
    mu0 = torch.tensor([0.7, 0.3], dtype=D)
    cv, sensor, belief0, z = _maneuvering(11, 12, 0, transition)
    z[4, 3] = float("nan")
    exact_mean, exact_probs = _exact(cv, sensor, transition, mu0, belief0, z)
    mm = combinator(KalmanFilter(cv, sensor), transition)
    traj = run_filter(mm, mm.initial_belief(belief0, mu0), z)

    def errors(belief):
        return ((belief.estimate().mean - exact_mean).norm(dim=-1)[:-1].mean(),
                (belief.mode_probs - exact_probs).abs()[:-1].mean())

    two, two_p = errors(smooth(mm, traj, z).belief)
    kim, _ = errors(smooth(mm, traj, method="kim").belief)
    filt, filt_p = errors(traj.belief)
    assert two < 0.15 * filt and two < 0.5 * kim, (two, kim, filt)
    assert two_p < 0.2 * filt_p, (two_p, filt_p)


@pytest.mark.parametrize("method, tol", [(None, (1e-6, 1e-5, 1e-7)), ("two_filter_info", (1e-9, 1e-8, 1e-10))],
                         ids=["two_filter", "two_filter_info"])
@pytest.mark.parametrize("combinator", [IMM, GPB2])
def test_exact_for_static_modes(combinator, method, tol):
    """Identity transition: the smoothed states and mode probabilities are the exact posterior (up to
    the backward filter's nearly flat start; the information form's has none: to rounding), the prior mode
    probabilities read from the trajectory. (Not GPB1: its forward filter collapses the modes before every
    prediction, so even its filtered beliefs are not the exact ones here.)"""
    transition = torch.eye(2, dtype=D)
    mu0 = torch.tensor([0.3, 0.7], dtype=D)
    cv, sensor, belief0, z = _maneuvering(7, 5, 1, torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=D))
    z[3, 1] = float("nan")
    exact_mean, exact_probs = _exact(cv, sensor, transition, mu0, belief0, z)
    mm = combinator(KalmanFilter(cv, sensor), transition)
    out = smooth(mm, run_filter(mm, mm.initial_belief(belief0, mu0), z), z, method=method).belief
    torch.testing.assert_close(out.estimate().mean, exact_mean, rtol=tol[0], atol=tol[1])
    torch.testing.assert_close(out.mode_probs, exact_probs, rtol=tol[0], atol=tol[2])


def _gauss(d, S):
    return math.exp(-0.5 * d @ np.linalg.solve(S, d)) / math.sqrt(np.linalg.det(2 * math.pi * S))


def _numpy_two_filter(F, Q, off, H, R, transition, p0, mu, means, covs, z, kappa):
    """The two-filter smoother in float64 NumPy with loops over modes (one run), written from the
    equations in docs/smoothing.md: forward ``mu (T, M)``, ``means (T, M, n)``, ``covs (T, M, n, n)``,
    data ``z (T, m)`` (NaN: missing), prior mode probabilities ``p0`` at step 0."""
    steps, M, n = means.shape
    prior = [p0]
    for _ in range(steps - 1):
        prior.append(prior[-1] @ transition)

    def update(m, P, y):
        if np.isnan(y).all():
            return m, P, 1.0
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        return m + K @ (y - H @ m), P - K @ S @ K.T, _gauss(y - H @ m, S)

    def moments(w, ms, Ps):
        mean = sum(w[i] * ms[i] for i in range(len(w)))
        return mean, sum(w[i] * (Ps[i] + np.outer(ms[i] - mean, ms[i] - mean)) for i in range(len(w)))

    est_m, est_P = moments(mu[-1], means[-1], covs[-1])
    bm, bP, lik = zip(*[update(est_m, kappa * est_P, z[-1]) for _ in range(M)])
    bmu = prior[-1] * np.array(lik)
    bmu = bmu / bmu.sum()
    out_mu, out_m, out_P = [mu[-1]], [means[-1]], [covs[-1]]
    for t in range(steps - 2, -1, -1):
        pm, pP = [], []
        for i in range(M):  # the motion of mode i, run backwards
            Finv = np.linalg.inv(F[i])
            pm.append(Finv @ (bm[i] - off[i]))
            pP.append(Finv @ (bP[i] + Q[i]) @ Finv.T)
        joint = np.array([[mu[t, j] * transition[j, i] * _gauss(pm[i] - means[t, j], covs[t, j] + pP[i])
                           * bmu[i] / prior[t + 1][i] for i in range(M)] for j in range(M)])
        joint /= joint.sum()
        mode = joint.sum(1)
        ms, Ps = np.zeros((M, n)), np.zeros((M, n, n))
        for j in range(M):
            pair_m, pair_P = [], []
            for i in range(M):
                K = covs[t, j] @ np.linalg.inv(covs[t, j] + pP[i])
                pair_m.append(means[t, j] + K @ (pm[i] - means[t, j]))
                pair_P.append(covs[t, j] - K @ covs[t, j])
            ms[j], Ps[j] = moments(joint[j] / mode[j], pair_m, pair_P)
        out_mu.append(mode), out_m.append(ms), out_P.append(Ps)
        if t > 0:  # the backward IMM: interaction through the reversed chain, then the update with z_t
            back = np.array([[transition[j, i] * prior[t][j] for j in range(M)] for i in range(M)])
            back /= back.sum(1, keepdims=True)  # P(s_t = j | s_{t+1} = i)
            a = np.array([sum(back[i, j] * bmu[i] for i in range(M)) for j in range(M)])
            new = [update(*moments([back[i, j] * bmu[i] / a[j] for i in range(M)], pm, pP), z[t]) for j in range(M)]
            bm, bP = [x[0] for x in new], [x[1] for x in new]
            bmu = a * np.array([x[2] for x in new])
            bmu = bmu / bmu.sum()
    return np.stack(out_mu[::-1]), np.stack(out_m[::-1]), np.stack(out_P[::-1])


@pytest.mark.parametrize("combinator", [IMM, GPB2])
def test_agrees_with_an_independent_numpy_implementation(combinator):
    """Two modes differing in acceleration and noise, an asymmetric chain, missing data, 30 steps."""
    acc = torch.tensor([[0.0], [2.0]], dtype=D)
    cv = ConstantVelocity(1, q=0.1, acceleration=acc, dtype=D)
    G = torch.tensor([[0.5], [1.0]], dtype=D)
    Q = torch.stack([0.1 * G @ G.mT, 0.5 * G @ G.mT + 1e-3 * torch.eye(2, dtype=D)])
    bank = LinearMotion(cv.F, Q, offset=cv.offset)
    sensor = PositionMeasurement(2, [0], 100.0, dtype=D)
    transition = torch.tensor([[0.95, 0.05], [0.1, 0.9]], dtype=D)
    mu0 = torch.tensor([0.6, 0.4], dtype=D)
    belief0 = GaussianBelief(torch.tensor([0.0, 10.0], dtype=D).expand(2, 2),
                             torch.diag(torch.tensor([100.0, 10.0], dtype=D)).expand(2, 2, 2))
    z = 10 * torch.cumsum(torch.randn(30, 2, 1, generator=torch.Generator().manual_seed(3), dtype=D), 0)
    z[7, 0] = z[8, 1] = float("nan")
    mm = combinator(KalmanFilter(bank, sensor), transition)
    traj = run_filter(mm, mm.initial_belief(belief0, mu0), z)
    out = smooth(mm, traj, z).belief
    F = cv.F.expand(2, 2, 2).numpy()
    for b in range(2):
        mu, means, covs = _numpy_two_filter(
            F, Q.numpy(), cv.offset.numpy(), sensor.H.numpy(), sensor.R.numpy(), transition.numpy(),
            (mu0 @ transition).numpy(), traj.belief.mode_probs[:, b].numpy(), traj.belief.components.mean[:, b].numpy(),
            traj.belief.components.cov[:, b].numpy(), z[:, b].numpy(), diffuse_factor(D))
        np.testing.assert_allclose(out.mode_probs[:, b].numpy(), mu, rtol=1e-7, atol=1e-10)
        np.testing.assert_allclose(out.components.mean[:, b].numpy(), means, rtol=1e-7, atol=1e-7)
        np.testing.assert_allclose(out.components.cov[:, b].numpy(), covs, rtol=1e-7, atol=1e-7)


def test_controls_and_per_step_motions_are_the_forward_ones():
    """The accelerations as controls (``B u``) or as per-step models give the smoother of the offsets:
    the prediction k -> k+1 used entry k+1."""
    transition = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=D)
    cv, sensor, belief0, z = _maneuvering(12, 3, 2, transition)
    G = torch.tensor([[0.5], [1.0]], dtype=D)
    ref = IMM(KalmanFilter(cv, sensor), transition)
    want = smooth(ref, run_filter(ref, ref.initial_belief(belief0), z), z).belief
    # controls: u_k = 1 for every step, B = G a_j per mode
    driven = LinearMotion(cv.F, cv.Q, input_matrix=torch.stack([0.0 * G, 2.0 * G]))
    mm = IMM(KalmanFilter(driven, sensor), transition)
    u = torch.ones(12, 3, 1, dtype=D)
    got = smooth(mm, run_filter(mm, mm.initial_belief(belief0), z, controls=u), z, controls=u).belief
    torch.testing.assert_close(got.estimate().mean, want.estimate().mean, rtol=1e-9, atol=1e-9)
    # per-step motions: the reference bank at every step
    plain = IMM(KalmanFilter(LinearMotion(cv.F, cv.Q), sensor), transition)
    motions = [cv] * 12
    got = smooth(plain, run_filter(plain, plain.initial_belief(belief0), z, motions=motions), z, motions=motions)
    torch.testing.assert_close(got.estimate().mean, want.estimate().mean, rtol=1e-9, atol=1e-9)


def test_float32_agrees_with_float64():
    """On data simulated from the model (docs/smoothing.md: 0.0007 / 0.0005 of a posterior sd eager / on the
    kernel); on data far from the model float32 is not this close (there, "Float32 on data far from the
    model": 0.17 / 0.055 sd)."""
    transition = torch.tensor([[0.95, 0.05], [0.05, 0.95]], dtype=D)
    cv, sensor, belief0, z = _maneuvering(60, 20, 3, transition)
    out = {}
    for dtype in (torch.float64, torch.float32):
        mm = IMM(KalmanFilter(cv.to(dtype), sensor.to(dtype)), transition.to(dtype))
        b0 = GaussianBelief(belief0.mean.to(dtype), belief0.cov.to(dtype))
        out[dtype] = smooth(mm, run_filter(mm, mm.initial_belief(b0), z.to(dtype)), z.to(dtype)).belief
    assert out[torch.float32].estimate().mean.dtype == torch.float32
    scale = out[torch.float64].estimate().cov.diagonal(dim1=-2, dim2=-1).sqrt()  # posterior sd
    err = (out[torch.float32].estimate().mean.double() - out[torch.float64].estimate().mean).abs() / scale
    assert err.max() < 0.01, err.max()  # within 1 % of a posterior standard deviation
    assert (out[torch.float32].mode_probs.double() - out[torch.float64].mode_probs).abs().max() < 1e-3


def test_differentiable():
    transition = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=D)
    cv, sensor, belief0, z = _maneuvering(4, 2, 4, transition)
    mm = IMM(KalmanFilter(cv, sensor), transition)

    def smoothed(data):
        out = smooth(mm, run_filter(mm, mm.initial_belief(belief0), data), data).belief
        return out.estimate().mean[0], out.mode_probs[1]

    # finite differences of 1e-3 on data of scale ~100 (R = 100): the backward filter's nearly flat start
    # (covariances ~1e8 times the filter's) leaves rounding noise of ~1e-4 in steps of 1e-6
    assert torch.autograd.gradcheck(smoothed, (z.clone().requires_grad_(True),), eps=1e-3, atol=1e-5, rtol=1e-4)


def test_clear_errors():
    transition = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=D)
    cv, sensor, belief0, z = _maneuvering(5, 2, 5, transition)
    mm = IMM(KalmanFilter(cv, sensor), transition)
    traj = run_filter(mm, mm.initial_belief(belief0), z)
    with pytest.raises(ValueError, match="measurements: the two-filter smoother .* method='kim'"):
        smooth(mm, dataclasses.replace(traj, provenance=None))  # a trajectory without its record of the data
    # carried
    torch.testing.assert_close(smooth(mm, traj).belief.mode_probs, smooth(mm, traj, z).belief.mode_probs)
    with pytest.raises(ValueError, match=r"measurements: expected shape \(5, 2, 1\)"):
        smooth(mm, traj, z[:4])
    with pytest.raises(TypeError, match="measurements: dtype"):
        smooth(mm, traj, z.float())
    with pytest.raises(ValueError, match="method: expected 'two_filter', 'kim' or 'two_filter_info'"):
        smooth(mm, traj, z, method="rts")
    estimate_only = run_filter(mm, mm.initial_belief(belief0), z, record="estimate")
    why = (r"GaussianBelief; run_filter\(..., record='estimate'\) keeps only the combined estimate: smooth a "
           r"run that keeps its beliefs")
    for method in ("two_filter", "kim", "two_filter_info"):
        with pytest.raises(TypeError, match=why):
            smooth(estimate_only, method=method)
    kf = KalmanFilter(ConstantVelocity(1, q=0.1, dtype=D), sensor)
    with pytest.raises(ValueError, match="method: only multiple-model filters"):
        smooth(kf, run_filter(kf, belief0, z), method="kim")
    with pytest.raises(ValueError, match="sensors: expected one entry per step"):
        smooth(mm, traj, z, sensors=[sensor])
    singular = IMM(KalmanFilter(LinearMotion(torch.tensor([[1.0, 1.0], [0.0, 0.0]], dtype=D), torch.eye(2, dtype=D)),
                                sensor), torch.eye(1, dtype=D))
    with pytest.raises(ValueError, match=r"filter: the two-filter smoother .* invertible motion Jacobian; mode\(s\) \[0\]"):
        smooth(singular, run_filter(singular, singular.initial_belief(belief0), z), z)
    # Kim's smoother still needs no measurements
    assert smooth(mm, traj, method="kim").belief.mode_probs.shape == (5, 2, 2)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (runs where a GPU is present)")
def test_on_cuda_equal_the_cpu_ones():
    transition = torch.tensor([[0.95, 0.05], [0.1, 0.9]], dtype=D)
    cv, sensor, belief0, z = _maneuvering(30, 8, 6, transition)
    z[5, 2] = float("nan")
    dev = torch.device("cuda")
    results = {}
    for device in (torch.device("cpu"), dev):
        mm = IMM(KalmanFilter(cv.to(device), sensor.to(device)), transition.to(device))
        b0 = GaussianBelief(belief0.mean.to(device), belief0.cov.to(device))
        traj = run_filter(mm, mm.initial_belief(b0), z.to(device))
        results[device.type] = [smooth(mm, traj, z.to(device)).belief, smooth(mm, traj, method="kim").belief]
    for cpu, gpu in zip(results["cpu"], results["cuda"]):
        torch.testing.assert_close(gpu.estimate().mean.cpu(), cpu.estimate().mean, rtol=1e-7, atol=1e-7)
        torch.testing.assert_close(gpu.mode_probs.cpu(), cpu.mode_probs, rtol=1e-7, atol=1e-9)

"""Joint probabilistic data association (torchmm.association.JPDA, jpda_marginals): exact against
brute-force enumeration of every joint event, the PDA for one track, independent PDAs for tracks
whose gates do not overlap, Stone Soup 1.9's JPDA and JPDAwithLBP, batched against per run."""

from __future__ import annotations

import datetime
import itertools
import math

import numpy as np
import pytest
import torch

from torchmm import GaussianBelief, KalmanFilter, run_filter
from torchmm.association import GNN, JPDA, PDA, jpda_marginals
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.simulate import simulate_detections

R = torch.tensor([[4.0, 0.5], [0.5, 2.0]], dtype=torch.float64)


def _kf():
    return KalmanFilter(ConstantVelocity(2, dt=1.0, q=0.5, dtype=torch.float64), PositionMeasurement(4, [0, 2], R))


def _brute(w: np.ndarray, missed) -> tuple[np.ndarray, float]:
    """Every joint event of ``w (N, D)``: each track one detection (j >= 1) or none (0, weight
    ``missed``: one number, or one a track ``(N,)``), no detection twice; ``beta (N, 1 + D)`` and ``Z``."""
    N, D = w.shape
    missed = np.broadcast_to(np.asarray(missed, dtype=float), (N,))
    beta, Z = np.zeros((N, D + 1)), 0.0
    for event in itertools.product(range(D + 1), repeat=N):
        used = [j for j in event if j]
        if len(used) != len(set(used)):
            continue
        weight = math.prod(w[i, j - 1] if j else missed[i] for i, j in enumerate(event))
        Z += weight
        for i, j in enumerate(event):
            beta[i, j] += weight
    return beta / Z, Z


@pytest.mark.parametrize("N, D", [(1, 3), (2, 2), (3, 4), (4, 5), (5, 3)])
def test_exact_equals_enumeration_of_every_joint_event(N, D):
    from torchmm.runtime import no_host_sync

    gen = torch.Generator().manual_seed(10 * N + D)
    log_w = torch.randn(6, N, D, generator=gen, dtype=torch.float64) * 2
    log_w[torch.rand(6, N, D, generator=gen) < 0.3] = -math.inf  # outside the gates
    log_w[0] = -math.inf  # nothing validated
    for missed in (0.3, 1e-3):
        log_beta, log_z = jpda_marginals(log_w, missed)
        with no_host_sync("the exact marginals"):
            device_form, _ = jpda_marginals(log_w, missed)
        for r in range(6):
            beta, Z = _brute(log_w[r].exp().numpy(), missed)
            np.testing.assert_allclose(log_beta[r].exp().numpy(), beta, rtol=1e-10, atol=1e-12)
            assert float(log_z[r]) == pytest.approx(math.log(Z), rel=1e-10, abs=1e-12)
        torch.testing.assert_close(device_form, log_beta, rtol=1e-12, atol=1e-12)


def test_every_track_detected_and_an_impossible_scan():
    """missed = 0 (P_D P_G = 1): only events that detect every track count; with fewer detections
    than tracks there is none (log Z = -inf)."""
    log_w = torch.log(torch.tensor([[[1.0, 2.0, 0.5], [3.0, 1.0, 1.0]]], dtype=torch.float64))
    log_beta, log_z = jpda_marginals(log_w, 0.0)
    beta, Z = _brute(log_w[0].exp().numpy(), 0.0)
    np.testing.assert_allclose(log_beta[0].exp().numpy(), beta, rtol=1e-12, atol=1e-14)
    assert float(log_z[0]) == pytest.approx(math.log(Z), rel=1e-12)
    _, log_z = jpda_marginals(log_w[..., :1], 0.0)
    assert torch.isneginf(log_z).all()


def test_belief_propagation_is_exact_without_shared_detections_and_close_with():
    gen = torch.Generator().manual_seed(3)
    log_w = torch.full((2, 3, 5), -math.inf, dtype=torch.float64)
    log_w[0, 0, :2] = torch.randn(2, generator=gen, dtype=torch.float64)  # disjoint gates
    log_w[0, 1, 2:4] = torch.randn(2, generator=gen, dtype=torch.float64)
    log_w[0, 2, 4] = 0.3
    log_w[1] = torch.randn(3, 5, generator=gen, dtype=torch.float64) - 1  # every gate shared
    exact, _ = jpda_marginals(log_w, 0.5)
    lbp, none = jpda_marginals(log_w, 0.5, method="lbp")
    assert none is None
    torch.testing.assert_close(lbp[0].exp(), exact[0].exp(), rtol=1e-12, atol=1e-14)
    # where gates overlap it approximates, far better than tracks treated apart (each one's PDA weights)
    apart = torch.cat([torch.full((3, 1), math.log(0.5), dtype=torch.float64), log_w[1]], -1).softmax(-1)
    lbp_error = (lbp[1].exp() - exact[1].exp()).abs().max()
    assert lbp_error < 0.2 * (apart - exact[1].exp()).abs().max()
    torch.testing.assert_close(lbp.exp().sum(-1), torch.ones(2, 3, dtype=torch.float64))


def _tracks(N, seed=0, spread=6.0):
    gen = torch.Generator().manual_seed(seed)
    mean = torch.randn(N, 4, generator=gen, dtype=torch.float64) * spread
    A = torch.randn(N, 4, 4, generator=gen, dtype=torch.float64)
    return GaussianBelief(mean, A @ A.mT + 3 * torch.eye(4, dtype=torch.float64))


def test_one_track_is_the_pda_and_separate_tracks_are_independent_pdas():
    options = {"detection_probability": 0.85, "clutter_density": 2e-3, "gate_probability": 0.99}
    gen = torch.Generator().manual_seed(4)
    one = _tracks(1, seed=1)
    z = one.mean[0, [0, 2]] + 3 * torch.randn(4, 2, generator=gen, dtype=torch.float64)
    got = JPDA(_kf(), **options).update(one, z)
    want = PDA(_kf(), **options).update(one, z.unsqueeze(0))
    torch.testing.assert_close(got.belief.mean, want.belief.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got.belief.cov, want.belief.cov, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got.extras["association"], want.extras["association"], rtol=1e-12, atol=1e-14)
    far = _tracks(3, seed=2, spread=0.0)
    far = GaussianBelief(far.mean + torch.tensor([[0.0], [500.0], [1000.0]], dtype=torch.float64), far.cov)
    z = torch.cat([far.mean[:, [0, 2]] + 2 * torch.randn(3, 2, generator=gen, dtype=torch.float64),
                   far.mean[:, [0, 2]] + 3 * torch.randn(3, 2, generator=gen, dtype=torch.float64)])
    for method in ("exact", "lbp"):
        got = JPDA(_kf(), method=method, **options).update(far, z)
        want = PDA(_kf(), **options).update(far, z.expand(3, 6, 2))
        torch.testing.assert_close(got.belief.mean, want.belief.mean, rtol=1e-12, atol=1e-10)
        torch.testing.assert_close(got.belief.cov, want.belief.cov, rtol=1e-12, atol=1e-10)
        torch.testing.assert_close(got.log_likelihood, want.log_likelihood.sum().expand(3), rtol=1e-12, atol=1e-12)


def _stone_soup_jpda(means, covs, detections, pd, density, pg, lbp: bool):
    from stonesoup.dataassociator.probability import JPDA as SSJPDA
    from stonesoup.dataassociator.probability import JPDAwithLBP
    from stonesoup.hypothesiser.probability import PDAHypothesiser
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel
    from stonesoup.models.transition.linear import ConstantVelocity as SSConstantVelocity
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.types.detection import Detection
    from stonesoup.types.state import GaussianState
    from stonesoup.types.track import Track
    from stonesoup.updater.kalman import KalmanUpdater
    from stonesoup.updater.probability import PDAUpdater

    when = datetime.datetime(2026, 12, 4)
    sensor = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=R.numpy())
    motion = CombinedLinearGaussianTransitionModel([SSConstantVelocity(0.5), SSConstantVelocity(0.5)])
    hypothesiser = PDAHypothesiser(predictor=KalmanPredictor(motion), updater=KalmanUpdater(sensor),
                                   clutter_spatial_density=density, prob_detect=pd, prob_gate=pg)
    class Converged(JPDAwithLBP):  # Stone Soup stops at delta = 1e-3; run it to convergence instead
        @staticmethod
        def _loopy_belief_propagation(likelihood_matrix, n_iterations, delta):
            return JPDAwithLBP._loopy_belief_propagation(likelihood_matrix, n_iterations, 1e-10)

    associator = Converged(hypothesiser=hypothesiser) if lbp else SSJPDA(hypothesiser=hypothesiser)
    tracks = [Track([GaussianState(m.reshape(-1, 1), P, timestamp=when)]) for m, P in zip(means, covs)]
    dets = {Detection(z.reshape(-1, 1), timestamp=when, measurement_model=sensor) for z in detections}
    hypotheses = associator.associate(set(tracks), dets, when)
    updater = PDAUpdater(sensor)
    posts = [updater.update(hypotheses[t]) for t in tracks]
    return (np.stack([np.asarray(p.state_vector, dtype=float).ravel() for p in posts]),
            np.stack([np.asarray(p.covar, dtype=float) for p in posts]))


@pytest.mark.parametrize("method", ["exact", "lbp"])
def test_equals_stone_soup_jpda(method):
    """Stone Soup 1.9's JPDA (every joint event of PDAHypothesiser's hypotheses) and JPDAwithLBP (run
    to convergence, delta 1e-10) with PDAUpdater: three tracks whose gates overlap, near and far detections."""
    pd, density, pg = 0.9, 1e-3, 0.99
    jpda = JPDA(_kf(), detection_probability=pd, clutter_density=density, gate_probability=pg, method=method)
    gen = torch.Generator().manual_seed(7)
    shared = 0
    for trial in range(4):
        tracks = _tracks(3, seed=20 + trial, spread=2.0)
        z = torch.cat([tracks.mean[:, [0, 2]] + 2 * torch.randn(3, 2, generator=gen, dtype=torch.float64),
                       tracks.mean[:1, [0, 2]] + 8 * torch.randn(2, 2, generator=gen, dtype=torch.float64)])
        out = jpda.update(tracks, z)
        mean, cov = _stone_soup_jpda(tracks.mean.numpy(), tracks.cov.numpy(), z.numpy(), pd, density, pg,
                                     lbp=method == "lbp")
        tol = 1e-9 if method == "exact" else 1e-7
        np.testing.assert_allclose(out.belief.mean.numpy(), mean, rtol=tol, atol=tol)
        np.testing.assert_allclose(out.belief.cov.numpy(), cov, rtol=tol, atol=tol)
        shared += int((out.extras["validated"].sum(-2) >= 2).sum())
    assert shared >= 4  # detections validated by two tracks or more: the association is joint


def _scene(steps, runs, N, *, seed, pd=0.9, clutter=4.0):
    motion = ConstantVelocity(2, dt=1.0, q=0.5, dtype=torch.float64)
    sensor = PositionMeasurement(4, [0, 2], R)
    gen = torch.Generator().manual_seed(seed)
    start = torch.zeros(runs, N, 4, dtype=torch.float64)
    start[..., 0] = torch.linspace(-20, 20, N, dtype=torch.float64) if N > 1 else 0.0
    start[..., 1] = 1.0
    start[..., 3] = torch.linspace(1, -1, N, dtype=torch.float64) if N > 1 else 0.0  # crossing targets
    truth = start + torch.cumsum(torch.randn(steps, runs, N, 4, generator=gen, dtype=torch.float64) * 0.2, 0)
    det = simulate_detections(sensor, truth, detection_probability=pd, clutter_rate=clutter,
                              region=torch.tensor([[-60.0, 60.0], [-60.0, 60.0]]), generator=gen)
    prior = GaussianBelief(start, 4 * torch.eye(4, dtype=torch.float64))
    options = {"detection_probability": pd, "clutter_density": clutter / 120**2, "gate_probability": 0.99}
    return motion, sensor, prior, det, truth, options


def test_batched_equals_per_run_through_run_filter():
    motion, sensor, prior, det, truth, options = _scene(12, 5, 3, seed=11)
    for method in ("exact", "lbp"):
        jpda = JPDA(KalmanFilter(motion, sensor), method=method, **options)
        all_runs = run_filter(jpda, prior, det.z)
        assert all_runs.belief.mean.shape == (12, 5, 3, 4)
        assert all_runs.extras["association"].shape == (12, 5, 3, det.z.shape[-2] + 1)
        for r in (0, 3):
            one = run_filter(jpda, prior[r:r + 1], det.z[:, r:r + 1])
            torch.testing.assert_close(all_runs.belief.mean[:, r], one.belief.mean[:, 0], rtol=1e-12, atol=1e-10)
            torch.testing.assert_close(all_runs.log_likelihood[:, r], one.log_likelihood[:, 0], rtol=1e-12, atol=1e-10)
        err = (all_runs.belief.mean[-1][..., [0, 2]] - truth[-1][..., [0, 2]]).norm(dim=-1)
        assert err.median() < 5.0  # the tracks follow their targets through the crossing


def test_a_scan_reads_nothing_on_the_host_and_errors_name_the_argument():
    from torchmm.runtime import no_host_sync

    motion, sensor, prior, det, _, options = _scene(3, 2, 3, seed=12)
    for method in ("exact", "lbp"):
        jpda = JPDA(KalmanFilter(motion, sensor), method=method, **options)
        b = prior
        with no_host_sync(f"the JPDA step ({method})"):
            for k in range(3):
                b = jpda.step(b, det.z[k]).belief
        assert torch.isfinite(b.mean).all()
    jpda = JPDA(KalmanFilter(motion, sensor), max_targets=2, **options)
    with pytest.raises(ValueError, match="belief: 3 tracks"):
        jpda.update(prior, det.z[0])
    with pytest.raises(ValueError, match="belief"):
        JPDA(KalmanFilter(motion, sensor), **options).update(prior[0, 0], det.z[0, 0])
    with pytest.raises(ValueError, match="z"):
        JPDA(KalmanFilter(motion, sensor), **options).update(prior, torch.zeros(7, 4, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="method"):
        JPDA(KalmanFilter(motion, sensor), method="mht", **options)


def test_a_failed_track_fails_its_run_only():
    motion, sensor, prior, det, _, options = _scene(1, 3, 2, seed=13)
    jpda = JPDA(KalmanFilter(motion, sensor), **options)
    bad = GaussianBelief(prior.mean.clone(), prior.cov)
    bad.mean[1, 0, 0] = math.nan
    out = jpda.update(bad, det.z[0])
    assert out.extras["failed"].tolist() == [[False, False], [True, True], [False, False]]
    alone = jpda.update(prior[[0, 2]], det.z[0, [0, 2]])
    torch.testing.assert_close(out.belief.mean[[0, 2]], alone.belief.mean, rtol=0, atol=0)


@pytest.mark.parametrize("method", ["exact", "lbp"])
def test_a_track_whose_covariance_is_not_psd_fails_its_run_only(method):
    """Issue 44: a track of covariance ``-4 I`` gated every detection out and kept its covariance, with
    ``failed`` False. Its innovation covariance is not positive definite (the Kalman update flags it
    ``singular``): its run fails, every track of it (the association is joint), the others untouched;
    GNN alike."""
    motion, sensor, prior, det, _, options = _scene(1, 3, 2, seed=13)
    for assoc in (JPDA(KalmanFilter(motion, sensor), method=method, **options),
                  GNN(KalmanFilter(motion, sensor), **options)):
        cov = prior.cov.expand(*prior.batch_shape, 4, 4).clone()
        cov[1, 0] = -4 * torch.eye(4, dtype=torch.float64)
        bad = GaussianBelief(prior.mean, cov)
        out = assoc.update(bad, det.z[0])
        assert out.extras["failed"].tolist() == [[False, False], [True, True], [False, False]]
        assert torch.isnan(out.log_likelihood[1]).all() and torch.isnan(out.belief.cov[1]).all()
        alone = assoc.update(prior[[0, 2]], det.z[0, [0, 2]])
        torch.testing.assert_close(out.belief.mean[[0, 2]], alone.belief.mean, rtol=0, atol=0)
        torch.testing.assert_close(out.log_likelihood[[0, 2]], alone.log_likelihood, rtol=0, atol=0)


def _imm(modes: int = 2):
    from torchmm import IMM

    acc = [[0.0, 0.0], [0.6, -0.4], [-0.5, 0.3]][:modes]
    bank = ConstantVelocity(2, dt=1.0, q=0.5, acceleration=acc, dtype=torch.float64)
    if modes == 1:
        Pi = torch.ones(1, 1, dtype=torch.float64)
    else:  # 0.9 to stay, 0.1 shared by the others
        off = 0.1 / (modes - 1)
        Pi = torch.full((modes, modes), off, dtype=torch.float64) + (0.9 - off) * torch.eye(modes, dtype=torch.float64)
    return IMM(KalmanFilter(bank, PositionMeasurement(4, [0, 2], R)), Pi)


def test_over_an_imm_is_blom_and_blooms_mixture():
    """PDA over an IMM (the IMM-JPDAF's single-track form) against a float64 NumPy reference of Blom &
    Bloem's update: each mode's Kalman update per detection, beta from the mode-mixed likelihoods, mode
    probabilities sum_k beta_k mu_k^r and components collapsed with weights beta_k mu_k^r."""
    from scipy.stats import multivariate_normal

    imm = _imm(2)
    pd, density, pg = 0.85, 2e-3, 0.99
    pda = PDA(imm, detection_probability=pd, clutter_density=density, gate_probability=pg)
    prior = imm.predict(imm.initial_belief(_tracks(1, seed=30)))[0]
    gen = torch.Generator().manual_seed(31)
    z = prior.components.mean[0, [0, 2]] + 3 * torch.randn(4, 2, generator=gen, dtype=torch.float64)
    out = pda.update(prior, z)
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 2] = 1.0
    mu0 = prior.mode_probs.numpy()
    xs, Ps = prior.components.mean.numpy(), prior.components.cov.numpy()
    gamma = float(PDA(_kf(), detection_probability=pd, clutter_density=density, gate_probability=pg).gate)
    hyps = [(1 - pd * pg, mu0, xs, Ps)]  # (weight, mode probabilities, means, covariances)
    for zj in z.numpy():
        g, post_x, post_P, inside = [], [], [], False
        for r in range(2):
            S = H @ Ps[r] @ H.T + R.numpy()
            K = Ps[r] @ H.T @ np.linalg.inv(S)
            nu = zj - H @ xs[r]
            inside |= nu @ np.linalg.solve(S, nu) <= gamma
            g.append(multivariate_normal(H @ xs[r], S).pdf(zj))
            post_x.append(xs[r] + K @ nu)
            post_P.append(Ps[r] - K @ S @ K.T)
        if inside:
            mixed = float(mu0 @ np.array(g))
            hyps.append((pd * mixed / density, mu0 * np.array(g) / mixed, np.array(post_x), np.array(post_P)))
    beta = np.array([h[0] for h in hyps])
    beta /= beta.sum()
    joint = np.array([b * h[1] for b, h in zip(beta, hyps)])  # (K, M)
    mode_p = joint.sum(0)
    np.testing.assert_allclose(out.belief.mode_probs.numpy(), mode_p, rtol=1e-10, atol=1e-12)
    for r in range(2):
        w = joint[:, r] / mode_p[r]
        mean = sum(wk * h[2][r] for wk, h in zip(w, hyps))
        cov = sum(wk * (h[3][r] + np.outer(h[2][r] - mean, h[2][r] - mean)) for wk, h in zip(w, hyps))
        np.testing.assert_allclose(out.belief.components.mean[r].numpy(), mean, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(out.belief.components.cov[r].numpy(), cov, rtol=1e-10, atol=1e-10)
    assert len(hyps) >= 3  # several detections weighed


def test_imm_jpdaf_one_target_is_the_imm_pdaf_and_one_mode_the_jpdaf():
    """JPDA over an IMM (the IMM-JPDAF): with one target it is the PDA over the IMM; with one mode it
    is the JPDAF of that mode's filter, through run_filter on crossing targets in clutter."""
    motion, sensor, prior, det, truth, options = _scene(10, 3, 3, seed=14)
    imm = _imm(2)
    jpdaf = run_filter(JPDA(imm, **options), imm.initial_belief(prior[:, :1]), det.z)
    pdaf = run_filter(PDA(imm, **options), imm.initial_belief(prior[:, 0]), det.z)
    torch.testing.assert_close(jpdaf.belief.mode_probs[:, :, 0], pdaf.belief.mode_probs, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(jpdaf.belief.components.mean[:, :, 0], pdaf.belief.components.mean, rtol=1e-12,
                               atol=1e-10)
    torch.testing.assert_close(jpdaf.log_likelihood[:, :, 0], pdaf.log_likelihood, rtol=1e-12, atol=1e-12)
    one = _imm(1)
    got = run_filter(JPDA(one, **options), one.initial_belief(prior), det.z)
    want = run_filter(JPDA(KalmanFilter(motion, sensor), **options), prior, det.z)
    torch.testing.assert_close(got.belief.components.mean[..., 0, :], want.belief.mean, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=1e-12, atol=1e-10)
    three = run_filter(JPDA(_imm(3), **options), _imm(3).initial_belief(prior), det.z)
    torch.testing.assert_close(three.belief.mode_probs.sum(-1), torch.ones(10, 3, 3, dtype=torch.float64))
    err = (three.belief.estimate().mean[-1][..., [0, 2]] - truth[-1][..., [0, 2]]).norm(dim=-1)
    assert torch.isfinite(err).all() and err.median() < 5.0


def _brute_best(w: np.ndarray, missed: float) -> tuple[tuple[int, ...], float]:
    """The joint event of largest weight (0: missed, j >= 1: detection j) and its weight."""
    N, D = w.shape
    best, value = None, -1.0
    for event in itertools.product(range(D + 1), repeat=N):
        used = [j for j in event if j]
        if len(used) != len(set(used)):
            continue
        weight = math.prod(w[i, j - 1] if j else missed for i, j in enumerate(event))
        if weight > value:
            best, value = event, weight
    return best, value


def test_gnn_takes_the_best_joint_event_and_updates_with_it_alone():
    """GNN against enumeration of every joint event (random tracks, detections near them and gated-out
    ones), and each track's posterior the Kalman update with its detection (or its prediction)."""
    from torchmm.association import GNN

    options = {"detection_probability": 0.8, "clutter_density": 5e-3, "gate_probability": 0.95}
    gnn, kf = GNN(_kf(), **options), _kf()
    gen = torch.Generator().manual_seed(40)
    missed = 1 - 0.8 * 0.95
    kinds = set()
    for trial in range(8):
        tracks = _tracks(3, seed=40 + trial, spread=3.0)
        z = torch.cat([tracks.mean[:2, [0, 2]] + 2 * torch.randn(2, 2, generator=gen, dtype=torch.float64),
                       tracks.mean[:1, [0, 2]] + 6 * torch.randn(2, 2, generator=gen, dtype=torch.float64)])
        out = gnn.update(tracks, z)
        w = JPDA(_kf(), **options).update(tracks, z)  # the same gates and weights
        log_w = torch.where(w.extras["validated"], kf.update(tracks.unsqueeze(0).expand(4, 3),
                                                               z.unsqueeze(1).expand(4, 3, 2)).log_likelihood.T
                            + math.log(0.8 / 5e-3), -math.inf)
        event, value = _brute_best(log_w.exp().numpy(), missed)
        assert tuple(out.extras["association"].argmax(-1).tolist()) == event
        assert float(out.log_likelihood[0]) == pytest.approx(math.log(value), rel=1e-12)
        for i, j in enumerate(event):
            want = kf.update(tracks[i], z[j - 1]).belief if j else tracks[i]
            torch.testing.assert_close(out.belief.mean[i], want.mean, rtol=1e-12, atol=1e-12)
            torch.testing.assert_close(out.belief.cov[i], want.cov, rtol=1e-12, atol=1e-12)
            kinds.add(j > 0)
    assert kinds == {True, False}  # tracks with a detection and tracks without


def test_gnn_through_run_filter_batched_and_without_host_reads():
    from torchmm.association import GNN
    from torchmm.runtime import no_host_sync

    motion, sensor, prior, det, truth, options = _scene(12, 4, 3, seed=15)
    gnn = GNN(KalmanFilter(motion, sensor), **options)
    out = run_filter(gnn, prior, det.z)
    one = run_filter(gnn, prior[2:3], det.z[:, 2:3])
    torch.testing.assert_close(out.belief.mean[:, 2], one.belief.mean[:, 0], rtol=1e-12, atol=1e-10)
    assert ((out.extras["association"] == 0) | (out.extras["association"] == 1)).all()
    taken = out.extras["association"][..., 1:].sum(-2)  # (T, R, D): no detection taken twice
    assert (taken <= 1).all()
    b = prior
    with no_host_sync("the GNN step"):
        for k in range(2):
            b = gnn.step(b, det.z[k]).belief
    assert torch.isfinite(b.mean).all()


# --- k-best JPDA (issue 46) ------------------------------------------------------------------------------
def _count_events(N: int, D: int) -> int:
    return sum(math.comb(N, r) * math.perm(D, r) for r in range(min(N, D) + 1))


@pytest.mark.parametrize("N, D", [(1, 3), (2, 2), (3, 4), (4, 5), (5, 3)])
def test_kbest_with_every_event_equals_exact_jpda(N, D):
    """k at least the number of joint events: the k-best JPDA is the exact JPDA (1e-12), gates and
    an all-gated-out run included; its gradient too."""
    gen = torch.Generator().manual_seed(7 * N + D)
    log_w = torch.randn(6, N, D, generator=gen, dtype=torch.float64) * 2
    log_w[torch.rand(6, N, D, generator=gen) < 0.3] = -math.inf
    log_w[0] = -math.inf
    for missed in (0.3, 1e-3):
        exact_beta, exact_z = jpda_marginals(log_w, missed)
        beta, z = jpda_marginals(log_w, missed, method="kbest", k=_count_events(N, D))
        torch.testing.assert_close(beta.exp(), exact_beta.exp(), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(z, exact_z, rtol=1e-12, atol=1e-12)
    w = log_w.clone().requires_grad_(True)
    g_exact, = torch.autograd.grad(jpda_marginals(w, 0.3)[1].sum(), w)
    g_kbest, = torch.autograd.grad(jpda_marginals(w, 0.3, method="kbest", k=_count_events(N, D))[1].sum(), w)
    torch.testing.assert_close(g_kbest, g_exact, rtol=1e-10, atol=1e-12)


def test_kbest_with_fewer_events_is_normalised_and_bounded_and_one_event_is_gnn():
    """Fewer events: each track's probabilities sum to one, log Z grows with k up to the exact one; k = 1
    is the best joint event (GNN's)."""
    gen = torch.Generator().manual_seed(3)
    log_w = torch.randn(20, 4, 5, generator=gen, dtype=torch.float64)
    _, exact_z = jpda_marginals(log_w, 0.2)
    previous = None
    for k in (1, 3, 10, 50):
        beta, z = jpda_marginals(log_w, 0.2, method="kbest", k=k)
        torch.testing.assert_close(beta.exp().sum(-1), torch.ones(20, 4, dtype=torch.float64))
        assert bool((z <= exact_z + 1e-12).all())
        if previous is not None:
            assert bool((z >= previous - 1e-12).all())
        previous = z
    one, _ = jpda_marginals(log_w, 0.2, method="kbest", k=1)
    for r in range(20):
        best, _ = _brute_best(log_w[r].exp().numpy(), 0.2)
        assert tuple(int(j) for j in one[r].exp().argmax(-1)) == best


def test_kbest_jpda_tracks_crossing_targets_as_the_exact_one():
    """JPDA(method="kbest") through run_filter: with every event it is the exact JPDA; with 20 of them
    on 3 crossing targets it follows them as closely (a measured check: median errors within 5 %)."""
    motion, sensor, prior, det, truth, options = _scene(12, 5, 3, seed=11)
    exact = run_filter(JPDA(KalmanFilter(motion, sensor), **options), prior, det.z)
    D = det.z.shape[-2]
    full = run_filter(JPDA(KalmanFilter(motion, sensor), method="kbest", k=_count_events(3, D), **options), prior, det.z)
    torch.testing.assert_close(full.belief.mean, exact.belief.mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(full.log_likelihood, exact.log_likelihood, rtol=1e-10, atol=1e-10)
    few = run_filter(JPDA(KalmanFilter(motion, sensor), method="kbest", k=20, **options), prior, det.z)
    err = lambda t: (t.belief.mean[-1][..., [0, 2]] - truth[-1][..., [0, 2]]).norm(dim=-1).median()  # noqa: E731
    assert float(err(few)) <= 1.05 * float(err(exact)) + 1e-9

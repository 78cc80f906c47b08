"""torchmm.association.PDA (issue 32): against the Kalman filter, Stone Soup 1.9's PDA, per-run loops."""

from __future__ import annotations

import datetime
import math

import numpy as np
import pytest
import torch

from torchmm import GaussianBelief, KalmanFilter, UnscentedKalmanFilter, run_filter
from torchmm.association import PDA, chi2_gate
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.simulate import simulate_detections

R = torch.tensor([[4.0, 0.5], [0.5, 2.0]], dtype=torch.float64)


def _kf():
    return KalmanFilter(ConstantVelocity(2, dt=1.0, q=0.5, dtype=torch.float64), PositionMeasurement(4, [0, 2], R))


def _prior(batch=(), seed=0):
    gen = torch.Generator().manual_seed(seed)
    mean = torch.randn(*batch, 4, generator=gen, dtype=torch.float64) * 10
    A = torch.randn(*batch, 4, 4, generator=gen, dtype=torch.float64)
    return GaussianBelief(mean, A @ A.mT + 5 * torch.eye(4, dtype=torch.float64))


def test_certain_detection_without_clutter_or_gate_is_the_kalman_update():
    kf = _kf()
    prior = _prior((5,))
    z = torch.randn(5, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 5
    want = kf.update(prior, z)
    got = PDA(kf, detection_probability=1.0, clutter_density=1.0, gate_probability=1.0).update(prior, z.unsqueeze(-2))
    torch.testing.assert_close(got.belief.mean, want.belief.mean, rtol=1e-13, atol=1e-12)
    torch.testing.assert_close(got.belief.cov, want.belief.cov, rtol=1e-13, atol=1e-12)
    torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=1e-13, atol=1e-12)
    torch.testing.assert_close(got.innovation, want.innovation, rtol=1e-13, atol=1e-12)
    assert torch.equal(got.extras["association"][..., 0], torch.zeros(5, dtype=torch.float64))


def test_no_detection_leaves_the_belief_and_weighs_the_missed_detection():
    pda = PDA(_kf(), detection_probability=0.8, clutter_density=1e-3, gate_probability=0.95)
    prior = _prior((3,))
    out = pda.update(prior, torch.full((3, 4, 2), math.nan, dtype=torch.float64))
    torch.testing.assert_close(out.belief.mean, prior.mean, rtol=0, atol=0)
    torch.testing.assert_close(out.belief.cov, prior.cov, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.log_likelihood, torch.full((3,), math.log1p(-0.8 * 0.95), dtype=torch.float64))
    assert not out.extras["validated"].any()


def test_an_impossible_scan_keeps_the_prior_with_zero_likelihood():
    """P_D = P_G = 1 and nothing detected: impossible under the model; log-likelihood -inf, no NaN belief."""
    pda = PDA(_kf(), detection_probability=1.0, clutter_density=1e-3, gate_probability=1.0)
    prior = _prior((2,))
    out = pda.update(prior, torch.full((2, 3, 2), math.nan, dtype=torch.float64))
    assert torch.isneginf(out.log_likelihood).all()
    torch.testing.assert_close(out.belief.mean, prior.mean, rtol=0, atol=0)
    torch.testing.assert_close(out.belief.cov, prior.cov, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="z"):
        pda.update(prior, torch.zeros(5, 3, 2, dtype=torch.float64))


def test_a_failed_run_is_flagged_and_leaves_the_others():
    pda = PDA(_kf(), detection_probability=0.9, clutter_density=1e-3)
    prior = _prior((3,))
    prior = GaussianBelief(prior.mean.clone(), prior.cov)
    prior.mean[1, 0] = math.nan  # a diverged run
    z = prior.mean[:, [0, 2]].nan_to_num(0.0).unsqueeze(-2) + 1.0
    out = pda.update(prior, z)
    assert out.extras["failed"].tolist() == [False, True, False]
    assert torch.isnan(out.belief.mean[1]).all() and torch.isfinite(out.belief.mean[[0, 2]]).all()
    alone = pda.update(prior[[0, 2]], z[[0, 2]])
    torch.testing.assert_close(out.belief.mean[[0, 2]], alone.belief.mean, rtol=0, atol=0)


def test_a_track_without_a_positive_definite_innovation_covariance_fails_its_run():
    """Issue 44: a track whose covariance is not PSD had its S regularised by the gate's factor, so every
    detection was gated out and the track kept (finite log-likelihood, ``failed`` False). The association
    now fails the run where the wrapped Kalman update flags its innovation covariance ``singular`` (not
    numerically positive definite: no gate, no likelihood): ``failed`` True, a NaN log-likelihood and
    posterior, the other runs as if alone."""
    kf = _kf()
    pda = PDA(kf, detection_probability=0.9, clutter_density=1e-3)
    prior = _prior((5,))
    eye = torch.eye(4, dtype=torch.float64)
    cov = prior.cov.clone()
    cov[1], cov[2], cov[3] = -eye, -4 * eye, -100 * eye  # S = H P H^T + R: PD for -I (this R), not for the others
    bad = GaussianBelief(prior.mean, cov)
    z = prior.mean[:, [0, 2]].unsqueeze(-2) + torch.tensor([[0.5, -0.5], [30.0, 30.0]], dtype=torch.float64)
    singular = kf.update(bad, z[:, 0])
    want = singular.extras["singular"]
    assert want.tolist() == [False, False, True, True, False]
    for scan in (z, z[:, :0]):
        out = pda.update(bad, scan)
        assert torch.equal(out.extras["failed"], want)
        assert torch.isnan(out.log_likelihood[want]).all() and torch.isnan(out.belief.mean[want]).all()
        assert torch.isnan(out.extras["association"][want]).all()
        keep = ~want
        alone = pda.update(bad[keep], scan[keep])
        torch.testing.assert_close(out.belief.mean[keep], alone.belief.mean, rtol=0, atol=0)
        torch.testing.assert_close(out.log_likelihood[keep], alone.log_likelihood, rtol=0, atol=0)


def test_batched_equals_per_run_and_padding_does_not_matter():
    pda = PDA(_kf(), detection_probability=0.9, clutter_density=1e-3, gate_probability=0.99)
    prior = _prior((6,), seed=2)
    gen = torch.Generator().manual_seed(3)
    z = prior.mean[:, [0, 2]].unsqueeze(-2) + 4 * torch.randn(6, 5, 2, generator=gen, dtype=torch.float64)
    z[0, 1:] = math.nan
    z[2, 3] = math.nan
    out = pda.update(prior, z)
    for b in range(6):
        keep = torch.isfinite(z[b]).all(-1)
        one = pda.update(prior[b:b + 1], z[b:b + 1, keep])
        torch.testing.assert_close(out.belief.mean[b], one.belief.mean[0], rtol=1e-13, atol=1e-12)
        torch.testing.assert_close(out.belief.cov[b], one.belief.cov[0], rtol=1e-13, atol=1e-12)
        torch.testing.assert_close(out.log_likelihood[b], one.log_likelihood[0], rtol=1e-13, atol=1e-12)
    weights = out.extras["association"]
    torch.testing.assert_close(weights.sum(-1), torch.ones(6, dtype=torch.float64))
    assert (weights[0, 2:] == 0).all() and (weights[2, 4] == 0)


def _stone_soup_pda(x, P, detections, pd, density, pg):
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
    track = Track([GaussianState(x.reshape(-1, 1), P, timestamp=when)])  # predicted over zero time: itself
    dets = {Detection(z.reshape(-1, 1), timestamp=when, measurement_model=sensor) for z in detections}
    post = PDAUpdater(sensor).update(hypothesiser.hypothesise(track, dets, when))
    return np.asarray(post.state_vector, dtype=float).ravel(), np.asarray(post.covar, dtype=float)


@pytest.mark.parametrize("pd, density, pg", [(0.9, 1e-3, 0.99), (0.6, 1e-2, 0.9), (0.99, 1e-4, 1.0)])
def test_equals_stone_soup_pda(pd, density, pg):
    """Stone Soup 1.9: PDAHypothesiser (gate chi^2 at prob_gate, missed weight 1 - P_D P_G, detections
    P_D N / lambda) and PDAUpdater (the innovation form), the same prior, detections and parameters."""
    gen = torch.Generator().manual_seed(int(100 * pd))
    pda = PDA(_kf(), detection_probability=pd, clutter_density=density, gate_probability=pg)
    validated = gated = 0
    for trial in range(6):
        prior = _prior(seed=trial + 10)
        count = 1 + trial % 4
        spread = 2.0 + 4.0 * torch.arange(count, dtype=torch.float64).unsqueeze(-1)  # near and far detections
        z = prior.mean[[0, 2]] + spread * torch.randn(count, 2, generator=gen, dtype=torch.float64)
        out = pda.update(prior, z)
        mean, cov = _stone_soup_pda(prior.mean.numpy(), prior.cov.numpy(), z.numpy(), pd, density, pg)
        np.testing.assert_allclose(out.belief.mean.numpy(), mean, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(out.belief.cov.numpy(), cov, rtol=1e-9, atol=1e-9)
        validated += int(out.extras["validated"].sum())
        gated += int((~out.extras["validated"]).sum())
    assert validated >= 6 and (gated >= 1 or pg == 1.0)  # both kinds of detection were exercised


def _scan_scenario(steps: int, runs: int, *, seed: int, pd: float, clutter: float):
    """A target per run drifting near the origin, seen with P_D = ``pd`` among ``clutter`` false
    detections a scan over a 60 m square; the models and the PDA options that match."""
    motion = ConstantVelocity(2, dt=1.0, q=0.5, dtype=torch.float64)
    sensor = PositionMeasurement(4, [0, 2], R)
    x0 = GaussianBelief(torch.tensor([0.0, 1.0, 0.0, 1.0], dtype=torch.float64), 10 * torch.eye(4, dtype=torch.float64))
    gen = torch.Generator().manual_seed(seed)
    truth = x0.mean + torch.cumsum(torch.randn(steps, runs, 4, generator=gen, dtype=torch.float64) * 0.3, 0)
    det = simulate_detections(sensor, truth.unsqueeze(-2), detection_probability=pd, clutter_rate=clutter,
                              region=torch.tensor([[-30.0, 30.0], [-30.0, 30.0]]), generator=gen)
    options = {"detection_probability": pd, "clutter_density": clutter / 3600, "gate_probability": 0.99}
    return motion, sensor, x0, det, options


def test_over_any_gaussian_filter_through_run_filter():
    """The unscented filter's PDA on linear models equals the Kalman filter's (sigma points are exact
    for linear maps), through run_filter on simulated detections in clutter."""
    motion, sensor, x0, det, options = _scan_scenario(15, 8, seed=5, pd=0.9, clutter=3.0)
    kf, ukf = PDA(KalmanFilter(motion, sensor), **options), PDA(UnscentedKalmanFilter(motion, sensor), **options)
    a = run_filter(kf, x0.expand(8), det.z)
    b = run_filter(ukf, x0.expand(8), det.z)
    assert a.belief.mean.shape == (15, 8, 4) and a.extras["association"].shape == (15, 8, det.z.shape[-2] + 1)
    torch.testing.assert_close(a.belief.mean, b.belief.mean, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(a.log_likelihood, b.log_likelihood, rtol=1e-9, atol=1e-9)
    assert torch.isfinite(a.belief.mean).all()


def test_gate_and_errors():
    assert chi2_gate(0.99, 2) == pytest.approx(9.210340371976184, rel=1e-13)
    assert chi2_gate(0.95, 1) == pytest.approx(3.841458820694124, rel=1e-13)
    assert chi2_gate(1.0, 3) == math.inf
    with pytest.raises(ValueError, match="detection_probability"):
        PDA(_kf(), detection_probability=0.0, clutter_density=1.0)
    with pytest.raises(ValueError, match="clutter_density"):
        PDA(_kf(), detection_probability=0.9, clutter_density=0.0)
    with pytest.raises(ValueError, match="z"):
        PDA(_kf(), detection_probability=0.9, clutter_density=1.0).update(_prior(), torch.zeros(3))


def test_imm_over_pda_is_the_imm_pdaf():
    """IMM(PDA(...)): the engine puts the mode axis before the detection set (measurement_rank = 2) and
    every scan informs (an empty one too). With one mode it equals the PDAF, with every mode alike it
    equals it too (mode probabilities unchanged), and a 3-mode IMM-PDAF runs through run_filter with
    its mode probabilities summing to one."""
    from torchmm import IMM

    motion, sensor, x0, det, options = _scan_scenario(12, 5, seed=8, pd=0.8, clutter=2.0)
    det.z[4] = math.nan  # an empty scan
    pdaf = run_filter(PDA(KalmanFilter(motion, sensor), **options), x0.expand(5), det.z)
    one = IMM(PDA(KalmanFilter(motion, sensor), **options), torch.ones(1, 1, dtype=torch.float64))
    got = run_filter(one, one.initial_belief(x0.expand(5)), det.z)
    torch.testing.assert_close(got.belief.components.mean[..., 0, :], pdaf.belief.mean, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(got.belief.components.cov[..., 0, :, :], pdaf.belief.cov, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(got.log_likelihood, pdaf.log_likelihood, rtol=1e-12, atol=1e-12)
    assert (got.log_likelihood[4] != 0).all()  # the empty scan is not "missing"
    bank = ConstantVelocity(2, dt=1.0, q=0.5, acceleration=[[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]], dtype=torch.float64)
    Pi = torch.full((3, 3), 0.1, dtype=torch.float64) + 0.7 * torch.eye(3, dtype=torch.float64)
    alike = IMM(PDA(KalmanFilter(bank, sensor), **options), Pi)
    three = run_filter(alike, alike.initial_belief(x0.expand(5)), det.z)
    torch.testing.assert_close(three.estimate().mean, pdaf.belief.mean, rtol=1e-10, atol=1e-9)
    torch.testing.assert_close(three.log_likelihood, pdaf.log_likelihood, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(three.belief.mode_probs, torch.full((12, 5, 3), 1 / 3, dtype=torch.float64))
    turning = ConstantVelocity(2, dt=1.0, q=0.5, acceleration=[[0.0, 0.0], [0.5, 0.0], [-0.5, 0.0]],
                               dtype=torch.float64)
    imm = IMM(PDA(KalmanFilter(turning, sensor), **options), Pi)
    run = run_filter(imm, imm.initial_belief(x0.expand(5)), det.z)
    torch.testing.assert_close(run.belief.mode_probs.sum(-1), torch.ones(12, 5, dtype=torch.float64))
    assert torch.isfinite(run.estimate().mean).all() and run.extras["modes"]["association"].shape == (12, 5, 3, det.z.shape[-2] + 1)


def test_a_scan_reads_nothing_on_the_host():
    """The PDA step and the IMM-PDAF step run asynchronously on a GPU: no host read
    (torchmm.runtime.no_host_sync, which also makes CPU code take its device form)."""
    from torchmm import IMM
    from torchmm.runtime import no_host_sync

    motion, sensor, x0, det, options = _scan_scenario(3, 4, seed=9, pd=0.9, clutter=2.0)
    pda = PDA(KalmanFilter(motion, sensor), **options)
    imm = IMM(PDA(KalmanFilter(ConstantVelocity(2, dt=1.0, q=0.5, acceleration=[[0.0, 0.0], [0.5, -0.5]], dtype=torch.float64), sensor), **options),
              torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=torch.float64))
    b, m = x0.expand(4), imm.initial_belief(x0.expand(4))
    with no_host_sync("the PDA and IMM-PDAF steps"):
        for k in range(3):
            b = pda.step(b, det.z[k]).belief
            m = imm.step(m, det.z[k]).belief
    assert torch.isfinite(b.mean).all() and torch.isfinite(m.estimate().mean).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (runs where a GPU is present)")
def test_on_cuda_equal_the_cpu_and_do_not_synchronise():
    """The PDAF and a 2-mode IMM-PDAF through run_filter on CUDA equal the CPU's; their steps run under
    ``torch.cuda.set_sync_debug_mode("error")``."""
    from torchmm import IMM

    motion, sensor, x0, det, options = _scan_scenario(10, 6, seed=10, pd=0.85, clutter=3.0)
    bank = ConstantVelocity(2, dt=1.0, q=0.5, acceleration=[[0.0, 0.0], [0.5, -0.5]], dtype=torch.float64)
    Pi = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=torch.float64)
    made = {}
    for dev in ("cpu", "cuda"):
        pda = PDA(KalmanFilter(motion.to(dev), sensor.to(dev)), **options)
        imm = IMM(PDA(KalmanFilter(bank.to(dev), sensor.to(dev)), **options), Pi.to(dev))
        z = det.z.to(dev)
        made[dev] = (run_filter(pda, x0.to(dev).expand(6), z), run_filter(imm, imm.initial_belief(x0.to(dev).expand(6)), z))
        if dev == "cuda":
            b, m = x0.to(dev).expand(6), imm.initial_belief(x0.to(dev).expand(6))
            b, m = pda.step(b, z[0]).belief, imm.step(m, z[0]).belief  # (first calls fill caches)
            torch.cuda.synchronize()
            torch.cuda.set_sync_debug_mode("error")
            try:
                for k in range(1, 4):
                    b, m = pda.step(b, z[k]).belief, imm.step(m, z[k]).belief
            finally:
                torch.cuda.set_sync_debug_mode("default")
    for cpu, gpu in zip(made["cpu"], made["cuda"]):
        torch.testing.assert_close(gpu.belief.estimate().mean.cpu(), cpu.belief.estimate().mean, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(gpu.log_likelihood.cpu(), cpu.log_likelihood, rtol=1e-10, atol=1e-10)

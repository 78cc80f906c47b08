"""The association on CUDA (runs where a GPU is present; benchmarks/gpu_session.sh runs it): JPDA
exact and LBP over an IMM, managed IMM tracks (IMM-JIPDA) and the particle JPDA equal the CPU's, and
the Gaussian steps run under ``torch.cuda.set_sync_debug_mode("error")``."""

from __future__ import annotations

import math

import pytest
import torch

from torchmm import IMM, GaussianBelief, KalmanFilter, ParticleFilter, run_filter
from torchmm.association import JIPDA, JPDA, ManagedTracks, ParticleJPDA, position_initiator
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.simulate import simulate_detections

DT = torch.float64
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (runs where a GPU is present)")


def _scene(runs=5, steps=8):
    gen = torch.Generator().manual_seed(0)
    start = torch.tensor([[0.0, 1.0, 0.0, 0.5], [20.0, -1.0, 5.0, 0.0], [5.0, 0.0, 25.0, -1.0]], dtype=DT)
    k = torch.arange(1, steps + 1, dtype=DT)[:, None, None, None]
    velocity = torch.stack([start[:, 1], torch.zeros(3, dtype=DT), start[:, 3], torch.zeros(3, dtype=DT)], -1)
    truth = (start + k * velocity).expand(steps, runs, 3, 4)  # the same targets in every run
    sensor = PositionMeasurement(4, [0, 2], 2.0, dtype=DT)
    det = simulate_detections(sensor, truth, detection_probability=0.9, clutter_rate=3.0,
                              region=torch.tensor([[-20.0, 50.0], [-20.0, 50.0]], dtype=DT), max_clutter=8,
                              generator=gen)
    bank = ConstantVelocity(2, dt=1.0, q=0.2, acceleration=[[0.0, 0.0], [0.5, 0.0]], dtype=DT)
    Pi = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=DT)
    prior = GaussianBelief(start.expand(runs, 3, 4), 4 * torch.eye(4, dtype=DT))
    return bank, sensor, Pi, prior, det.z


def _filters(bank, sensor, Pi, dev):
    imm = IMM(KalmanFilter(bank.to(dev), sensor.to(dev)), Pi.to(dev))
    opts = {"detection_probability": 0.9, "clutter_density": 3.0 / 70**2}
    jipda = JIPDA(imm, survival_probability=0.98, method="lbp", **opts)
    manager = ManagedTracks(jipda, capacity=6, initiate=position_initiator(4, [0, 2], 2.0, 4.0), m_of_n=(2, 3))
    return imm, {"exact": JPDA(imm, **opts), "lbp": JPDA(imm, method="lbp", iterations=30, **opts),
                 "managed": manager}


@needs_cuda
def test_imm_jpda_and_managed_tracks_on_cuda_equal_the_cpu_and_do_not_synchronise():
    bank, sensor, Pi, prior, z = _scene()
    made = {}
    for dev in ("cpu", "cuda"):
        imm, filters = _filters(bank, sensor, Pi, dev)
        zd, start = z.to(dev), imm.initial_belief(prior.to(dev))
        made[dev] = {name: run_filter(f, f.initial_belief((5,), dtype=DT, device=dev) if name == "managed" else start,
                                      zd, record=None) for name, f in filters.items()}
        if dev == "cuda":
            beliefs = {name: (f.initial_belief((5,), dtype=DT, device=dev) if name == "managed" else start)
                       for name, f in filters.items()}
            beliefs = {name: filters[name].step(b, zd[0]).belief for name, b in beliefs.items()}  # caches filled
            torch.cuda.synchronize()
            torch.cuda.set_sync_debug_mode("error")
            try:
                for k in range(1, 4):
                    beliefs = {name: filters[name].step(b, zd[k]).belief for name, b in beliefs.items()}
            finally:
                torch.cuda.set_sync_debug_mode("default")
    for name in made["cpu"]:
        cpu, gpu = made["cpu"][name], made["cuda"][name]
        torch.testing.assert_close(gpu.belief.estimate().mean.cpu(), cpu.belief.estimate().mean, rtol=1e-9,
                                   atol=1e-9)
        torch.testing.assert_close(gpu.log_likelihood.cpu(), cpu.log_likelihood, rtol=1e-9, atol=1e-9)
    assert torch.equal(made["cuda"]["managed"].belief.label.cpu(), made["cpu"]["managed"].belief.label)


@needs_cuda
def test_particle_jpda_on_cuda_equals_the_cpu():
    """Without resampling the update is deterministic: the same particles give the same weights."""
    bank, sensor, _, prior, z = _scene(runs=3, steps=1)
    motion = ConstantVelocity(2, dt=1.0, q=0.2, noise="continuous", dtype=DT)
    pf = ParticleFilter(motion, sensor, ess_threshold=0.0, generator=torch.Generator().manual_seed(1))
    particles = pf.initial_belief(prior, 500)
    out = {}
    for dev in ("cpu", "cuda"):
        f = ParticleJPDA(ParticleFilter(motion.to(dev), sensor.to(dev), ess_threshold=0.0), detection_probability=0.9,
                         clutter_density=3.0 / 70**2)
        out[dev] = f.update(particles.to(dev), z[0].to(dev))
    torch.testing.assert_close(out["cuda"].belief.log_weights.cpu(), out["cpu"].belief.log_weights, rtol=1e-9,
                               atol=1e-9)
    torch.testing.assert_close(out["cuda"].extras["association"].cpu(), out["cpu"].extras["association"], rtol=1e-9,
                               atol=1e-9)
    assert math.isfinite(float(out["cuda"].log_likelihood.sum()))

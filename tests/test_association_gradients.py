"""Gradients through the association (docs/tracking.md, "Gradients"): the log-likelihood and the
posterior means of PDA, JPDA (exact and LBP), JIPDA and the IMM-JPDAF, differentiated by autograd,
against central finite differences in float64."""

from __future__ import annotations

import math

import pytest
import torch

from torchmm import IMM, GaussianBelief, KalmanFilter, ParticleFilter, run_filter
from torchmm.association import JIPDA, JPDA, PDA, ParticleJPDA
from torchmm.models import ConstantVelocity, PositionMeasurement

DT = torch.float64
OPTS = {"detection_probability": 0.9, "clutter_density": 1e-3}


def _scans():
    z = torch.randn(6, 2, 5, 2, generator=torch.Generator().manual_seed(0), dtype=DT) * 3
    z[..., 3:, :] = math.nan
    return z


def _objective(kind: str, r: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    """A scalar of the run: the log-likelihood plus the final means, as functions of the sensor noise
    ``r`` and the first track's start position ``start``."""
    sensor = PositionMeasurement(4, [0, 2], r * torch.eye(2, dtype=DT))
    z = _scans()
    means = torch.stack([torch.stack([start, torch.zeros((), dtype=DT), torch.zeros((), dtype=DT),
                                      torch.zeros((), dtype=DT)]),
                         torch.tensor([3.0, 0.0, 1.0, 0.0], dtype=DT)])
    prior = GaussianBelief(means.expand(2, 2, 4), 5 * torch.eye(4, dtype=DT))
    cv = ConstantVelocity(2, dt=1.0, q=0.7, dtype=DT)
    if kind == "pda":
        filt, prior, z = PDA(KalmanFilter(cv, sensor), **OPTS), prior[:, 0], z
    elif kind in ("exact", "lbp"):
        filt = JPDA(KalmanFilter(cv, sensor), method=kind, **OPTS)
    elif kind == "jipda":
        filt = JIPDA(KalmanFilter(cv, sensor), method="lbp", survival_probability=0.95, **OPTS)
        prior = filt.initial_belief(prior, 0.7)
    else:  # the IMM-JPDAF
        bank = ConstantVelocity(2, dt=1.0, q=0.7, acceleration=[[0.0, 0.0], [1.0, 0.0]], dtype=DT)
        imm = IMM(KalmanFilter(bank, sensor), torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=DT))
        filt, prior = JPDA(imm, **OPTS), imm.initial_belief(prior)
    out = run_filter(filt, prior, z, record=None)
    final = out.belief.estimate().mean[-1] if hasattr(out.belief, "estimate") else out.belief.mean[-1]
    return out.log_likelihood.sum() + final.sum()


@pytest.mark.parametrize("kind", ["pda", "exact", "lbp", "jipda", "imm"])
def test_gradients_equal_finite_differences(kind):
    r = torch.tensor(2.0, dtype=DT, requires_grad=True)
    start = torch.tensor(0.5, dtype=DT, requires_grad=True)
    _objective(kind, r, start).backward()
    h = 1e-6
    with torch.no_grad():
        fd_r = (_objective(kind, torch.tensor(2.0 + h, dtype=DT), start) -
                _objective(kind, torch.tensor(2.0 - h, dtype=DT), start)) / (2 * h)
        fd_s = (_objective(kind, r, torch.tensor(0.5 + h, dtype=DT)) -
                _objective(kind, r, torch.tensor(0.5 - h, dtype=DT))) / (2 * h)
    assert torch.isfinite(r.grad) and torch.isfinite(start.grad)
    assert float(r.grad) == pytest.approx(float(fd_r), rel=1e-6, abs=1e-7)
    assert float(start.grad) == pytest.approx(float(fd_s), rel=1e-6, abs=1e-7)


def test_particle_jpda_log_likelihood_has_a_finite_gradient():
    """The particle weights are differentiable in the sensor noise (the particles themselves are drawn):
    a finite gradient through the joint events, equal to finite differences with the draws fixed."""
    cv = ConstantVelocity(2, dt=1.0, q=0.7, noise="continuous", dtype=DT)

    def value(r):
        pf = ParticleFilter(cv, PositionMeasurement(4, [0, 2], r * torch.eye(2, dtype=DT)), ess_threshold=0.0,
                            generator=torch.Generator().manual_seed(1))
        prior = pf.initial_belief(GaussianBelief(torch.tensor([[0.0, 0, 0, 0], [3.0, 0, 1, 0]], dtype=DT),
                                                 5 * torch.eye(4, dtype=DT)), 300)
        return ParticleJPDA(pf, **OPTS).update(prior, _scans()[0, 0]).log_likelihood.sum()

    r = torch.tensor(2.0, dtype=DT, requires_grad=True)
    value(r).backward()
    h = 1e-6
    fd = (value(torch.tensor(2.0 + h, dtype=DT)) - value(torch.tensor(2.0 - h, dtype=DT))) / (2 * h)
    assert float(r.grad) == pytest.approx(float(fd), rel=1e-6, abs=1e-8)

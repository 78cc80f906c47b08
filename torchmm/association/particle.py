r"""PDA for particle filters: each particle weighed by the scan's likelihood under the PDA model.

For a particle ``x`` the scan's likelihood against "all clutter" is
``(1 - P_D) + sum_k P_D p(z_k | x) / lambda``, with ``p(z_k | x)`` the sensor's density: exactly the
PDA's mixture over "no detection is the target's" and "detection ``k`` is", evaluated per particle, so
no Gaussian collapse and no gate (every detection weighs; ``P_G = 1``). The particles are then weighed,
resampled and flagged as the bootstrap filter's update does (:meth:`ParticleFilter.reweight`), and the
step's log-likelihood is the log-evidence of the scan (against all clutter).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.association.pda import DetectionSets
from torchmm.beliefs import ParticleBelief
from torchmm.contract import Of, Real, entry_point
from torchmm.filters.base import StepOutput
from torchmm.filters.particle import ParticleFilter, particle_log_likelihood

__all__ = ["ParticlePDA"]


class ParticlePDA(DetectionSets):
    r"""PDA over a :class:`~torchmm.ParticleFilter` (the module docstring gives the update).

    Args:
        filter: the particle filter; its ``predict`` is used as it is.
        detection_probability: ``P_D`` in (0, 1].
        clutter_density: ``lambda`` > 0, false detections per unit volume of measurement space.

    Shapes:
        belief: :class:`~torchmm.beliefs.ParticleBelief` ``(*B, Np, n)``; ``z``: ``(*B, D, m)`` (a row with a
        non-finite entry is no detection). ``innovation`` and ``innovation_cov`` are None; ``extras``:
        the particle filter's flags (``ess``, ``resampled``, ``degenerate``, ``failed``).

    Examples:
        >>> from torchmm import GaussianBelief
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> pf = ParticleFilter(ConstantVelocity(1, noise="continuous"), PositionMeasurement(2, [0], 1.0),
        ...                     generator=torch.Generator().manual_seed(0))
        >>> ppda = ParticlePDA(pf, detection_probability=0.9, clutter_density=0.01)
        >>> belief = pf.initial_belief(GaussianBelief(torch.zeros(2), torch.eye(2)), 500)
        >>> out = ppda.step(belief, torch.tensor([[0.2], [7.0], [float("nan")]]))
        >>> out.belief.particles.shape
        torch.Size([500, 2])
    """

    @entry_point(filter=Of(ParticleFilter), detection_probability=Real(0.0, 1.0), clutter_density=Real(positive=True))
    def __init__(self, filter: ParticleFilter, *, detection_probability: float, clutter_density: float):
        super().__init__()
        if not 0.0 < detection_probability <= 1.0:
            raise ValueError(f"detection_probability: expected a probability in (0, 1], got {detection_probability}")
        self.filter = filter
        self.detection_probability = float(detection_probability)
        self.clutter_density = float(clutter_density)

    @property
    def detections_dim(self) -> int:
        return self.filter.measurement.meas_dim

    def initial_belief(self, belief, *args, **kwargs):
        return self.filter.initial_belief(belief, *args, **kwargs)

    def predict(self, belief: ParticleBelief, *, u: Tensor | None = None,
                generator: torch.Generator | None = None) -> ParticleBelief:
        return self.filter.predict(belief, u=u, generator=generator)

    def update(self, belief: ParticleBelief, z: Tensor, *, generator: torch.Generator | None = None) -> StepOutput:
        if not isinstance(belief, ParticleBelief):
            raise TypeError(f"belief: ParticlePDA needs a ParticleBelief, got {type(belief).__name__}")
        m = self.detections_dim
        if not isinstance(z, Tensor) or z.dim() < 2 or z.shape[-1] != m:
            raise ValueError(f"z: expected a padded set of detections (*B, D, {m}), got "
                             f"{tuple(z.shape) if isinstance(z, Tensor) else type(z).__name__}")
        z = z.to(belief.particles.dtype)
        present = torch.isfinite(z).all(-1).movedim(-1, 0)  # (D, *B)
        zs = torch.where(torch.isfinite(z), z, 0.0).movedim(-2, 0)  # (D, *B, m): absent rows masked below
        loglik, _ = particle_log_likelihood(self.filter.measurement, zs, belief.particles,
                                            self.filter.state_dependent_noise, need_predicted=False)
        neg_inf = torch.full((), -math.inf, dtype=loglik.dtype, device=loglik.device)
        loglik = torch.where(present.reshape(*present.shape, *[1] * (loglik.dim() - present.dim())), loglik, neg_inf)
        pd = self.detection_probability
        miss = torch.full_like(loglik[:1], math.log1p(-pd) if pd < 1 else -math.inf)
        scan = torch.logsumexp(torch.cat([miss, loglik + (math.log(pd) - math.log(self.clutter_density))]), 0)
        every = torch.ones(scan.shape[:-1], dtype=torch.bool, device=scan.device)
        posterior, log_evidence, extras = self.filter.reweight(belief, scan, every, generator=generator)
        return StepOutput(posterior, belief, log_evidence, None, None, extras)

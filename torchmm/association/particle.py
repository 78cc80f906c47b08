r"""PDA and JPDA for particle filters: each particle weighed by the scan's likelihood under the
association model.

For a particle ``x`` the scan's likelihood against "all clutter" is
``(1 - P_D) + sum_k P_D p(z_k | x) / lambda``, with ``p(z_k | x)`` the sensor's density: exactly the
PDA's mixture over "no detection is the target's" and "detection ``k`` is", evaluated per particle, so
no Gaussian collapse and no gate (every detection weighs; ``P_G = 1``). The particles are then weighed,
resampled and flagged as the bootstrap filter's update does (:meth:`ParticleFilter.reweight`), and the
step's log-likelihood is the log-evidence of the scan (against all clutter).

:class:`ParticleJPDA` is the joint form over a run's tracks, the Monte Carlo JPDAF (Vermaak, Godsill &
Pérez, IEEE TAES 41(1), 2005): track ``i``'s predicted likelihood of detection ``j`` is the particle
average ``l_ij = sum_p w_p p(z_j | x_p)``; JPDA's joint events over ``P_D l_ij / lambda`` (a detection
taken) and ``1 - P_D`` (a track without one) give the marginals ``beta_ij``; each particle of track
``i`` is then weighed by ``beta_i0 + sum_j beta_ij p(z_j | x) / l_ij``, the association-weighted
mixture of its detections' likelihoods. With one track this is :class:`ParticlePDA`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.association.jpda import check_scan, exact_marginals, flat_runs, lbp_marginals
from torchmm.association.pda import DetectionSets, check_detections
from torchmm.beliefs import ParticleBelief, normalize_log_probs
from torchmm.contract import Choice, Int, Of, Real, entry_point
from torchmm.filters.base import StepOutput
from torchmm.filters.particle import ParticleFilter
from torchmm.filters.particle_ops import particle_log_likelihood
from torchmm.validation import check_filter_dtype

__all__ = ["ParticleJPDA", "ParticlePDA"]


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

    @entry_point(filter=Of(ParticleFilter, what="a ParticleFilter (for a Gaussian filter: PDA)"),
                 detection_probability=Real(0.0, 1.0), clutter_density=Real(positive=True))
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
        check_filter_dtype(self.filter, belief, "belief")
        z = check_detections(z, self.detections_dim, belief.batch_shape, belief.particles.dtype)
        present = torch.isfinite(z).all(-1).movedim(-1, 0)  # (D, *B)
        zs = torch.where(torch.isfinite(z), z, 0.0).movedim(-2, 0)  # (D, *B, m): absent rows masked below
        loglik, _ = particle_log_likelihood(self.filter.measurement, zs, belief.particles,
                                            self.filter.state_dependent_noise, need_predicted=False)
        neg_inf = torch.full((), -math.inf, dtype=loglik.dtype, device=loglik.device)
        loglik = torch.where(present.reshape(*present.shape, *[1] * (loglik.dim() - present.dim())), loglik, neg_inf)
        pd = self.detection_probability
        miss = loglik.new_full((1, *loglik.shape[1:]), math.log1p(-pd) if pd < 1 else -math.inf)  # (D may be 0)
        scan = torch.logsumexp(torch.cat([miss, loglik + (math.log(pd) - math.log(self.clutter_density))]), 0)
        every = torch.ones(scan.shape[:-1], dtype=torch.bool, device=scan.device)
        posterior, log_evidence, extras = self.filter.reweight(belief, scan, every, generator=generator)
        return StepOutput(posterior, belief, log_evidence, None, None, extras)


class ParticleJPDA(ParticlePDA):
    r"""JPDA over a :class:`~torchmm.ParticleFilter`: the Monte Carlo JPDAF (the module docstring gives
    the update). No gate: every detection weighs.

    Args:
        filter, detection_probability, clutter_density: as for :class:`ParticlePDA`.
        method: ``"exact"`` (every joint event, up to ``max_targets`` tracks, cost ``2^N``) or ``"lbp"``
            (loopy belief propagation), as for :class:`~torchmm.association.JPDA`.
        max_targets, iterations, tolerance: as for :class:`~torchmm.association.JPDA`.

    Shapes:
        belief: :class:`~torchmm.beliefs.ParticleBelief` with batch ``(*B, N)``, the run's tracks last
        (particles ``(*B, N, Np, n)``); ``z``: ``(*B, D, m)``, one scan per run. The log-likelihood is
        the run's, ``(*B, N)`` (the same for each of its tracks); ``extras``: the particle filter's flags
        and ``"association"`` ``(*B, N, 1 + D)``, the marginals ``beta`` (missed first). An impossible
        scan (``P_D = 1`` and fewer detections than tracks, or no joint event with weight) has likelihood
        0 (log-likelihood ``-inf``, not failed) and every track keeps its particles, as
        :class:`~torchmm.association.JPDA` keeps its priors.

    Examples:
        >>> from torchmm import GaussianBelief
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> pf = ParticleFilter(ConstantVelocity(1, noise="continuous"), PositionMeasurement(2, [0], 1.0),
        ...                     generator=torch.Generator().manual_seed(0))
        >>> jpda = ParticleJPDA(pf, detection_probability=0.9, clutter_density=0.01)
        >>> tracks = pf.initial_belief(GaussianBelief(torch.tensor([[0.0, 0.0], [5.0, 0.0]]), torch.eye(2)), 500)
        >>> out = jpda.step(tracks, torch.tensor([[0.2], [5.3], [float("nan")]]))
        >>> out.belief.particles.shape, out.extras["association"].shape
        (torch.Size([2, 500, 2]), torch.Size([2, 4]))
    """

    joint = True

    @entry_point(filter=Of(ParticleFilter, what="a ParticleFilter (for a Gaussian filter: JPDA)"),
                 detection_probability=Real(0.0, 1.0), clutter_density=Real(positive=True),
                 method=Choice("exact", "lbp"), max_targets=Int(1), iterations=Int(1), tolerance=Real(minimum=0.0))
    def __init__(self, filter: ParticleFilter, *, detection_probability: float, clutter_density: float,
                 method: str = "exact", max_targets: int = 12, iterations: int = 100, tolerance: float = 1e-13):
        super().__init__(filter, detection_probability=detection_probability, clutter_density=clutter_density)
        self.method, self.max_targets = method, int(max_targets)
        self.iterations, self.tolerance = int(iterations), float(tolerance)

    def update(self, belief: ParticleBelief, z: Tensor, *, generator: torch.Generator | None = None) -> StepOutput:
        if not isinstance(belief, ParticleBelief):
            raise TypeError(f"belief: ParticleJPDA needs a ParticleBelief, got {type(belief).__name__}")
        batch = belief.batch_shape
        z = check_scan(self, batch, z, belief.particles.dtype)
        check_filter_dtype(self.filter, belief, "belief")
        *runs, N = batch
        D, m = z.shape[-2:]
        present = torch.isfinite(z).all(-1)  # (*R, D)
        zs = torch.where(present.unsqueeze(-1), z, 0.0).movedim(-2, 0).unsqueeze(-2).expand(D, *runs, N, m)
        loglik, _ = particle_log_likelihood(self.filter.measurement, zs, belief.particles,
                                            self.filter.state_dependent_noise, need_predicted=False)  # (D, *R, N, Np)
        neg_inf = torch.full((), -math.inf, dtype=loglik.dtype, device=loglik.device)
        absent = ~present.movedim(-1, 0)[..., None, None]  # (D, *R, 1, 1)
        loglik = torch.where(absent, neg_inf, loglik)
        log_l = torch.logsumexp(loglik + normalize_log_probs(belief.log_weights), -1)  # (D, *R, N): l_ij
        pd = self.detection_probability
        log_w = (log_l + (math.log(pd) - math.log(self.clutter_density))).movedim(0, -1)  # (*R, N, D)
        log_missed = math.log1p(-pd) if pd < 1 else -math.inf
        flat = flat_runs(log_w, 2)
        if self.method == "exact":
            log_beta, log_z = exact_marginals(flat, log_missed)
        else:
            log_beta = lbp_marginals(flat, log_missed, self.iterations, self.tolerance)
            log_z = torch.logsumexp(torch.cat([flat.new_full((*flat.shape[:-1], 1), log_missed), flat], -1), -1).sum(-1)
        log_beta, log_z = log_beta.reshape(*runs, N, 1 + D), log_z.reshape(runs)
        # an impossible scan (P_D = 1 and fewer detections than tracks, or no joint event with weight): the
        # scan's likelihood is 0 and every track keeps its particles and weights, as JPDA keeps its priors and
        # as ParticlePDA does for one track
        if pd == 1:
            log_z = torch.where(present.sum(-1) < N, -math.inf, log_z)
        impossible = torch.isneginf(log_z)[..., None, None]
        missed_only = torch.where(torch.arange(1 + D, device=z.device) == 0, 0.0, -math.inf).to(log_beta.dtype)
        log_beta = torch.where(impossible, missed_only, log_beta)
        # each particle: beta_i0 + sum_j beta_ij p(z_j | x) / l_ij
        ratio = loglik - torch.where(torch.isneginf(log_l), 0.0, log_l).unsqueeze(-1)  # (D, *R, N, Np)
        Np = ratio.shape[-1]
        scan = torch.logsumexp(torch.cat([log_beta[..., :1].unsqueeze(0).expand(1, *runs, N, Np),
                                          ratio + log_beta[..., 1:].movedim(-1, 0).unsqueeze(-1)]), 0)
        every = torch.ones(batch, dtype=torch.bool, device=scan.device)
        posterior, _, extras = self.filter.reweight(belief, scan, every, generator=generator)
        failed = extras["failed"] | torch.isnan(log_z).unsqueeze(-1)
        log_z = torch.where(failed, math.nan, log_z.unsqueeze(-1).expand(*runs, N))
        extras = dict(extras, failed=failed, association=log_beta.exp())
        return StepOutput(posterior, belief, log_z, None, None, extras)

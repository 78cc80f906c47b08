r"""Particle filters: the bootstrap filter of the common interface and a multiple-model PF.

:class:`ParticleFilter` is a bootstrap (SIR) filter over a :class:`~torchmm.beliefs.ParticleBelief`:
particles are propagated through the motion model with sampled process noise, weighted by the
measurement likelihood in log space, and resampled per batch element when the effective sample
size drops below ``ess_threshold * Np`` (static shapes, ``torch.where``). It implements
``predict`` / ``update`` / ``step`` like the Kalman filters, so IMM / GPB and the other combinators
accept it as a mode filter (with a mode bank as motion model, all modes in one call).

The multiple-model particle filter of paper 003 (``Np`` particles per model, the two-stage
interaction) is :class:`torchmm.multimodel.MultipleModelParticleFilter`; the helpers it shares
with this filter (likelihoods, propagation, checks) are the public functions below.

Random numbers come from the ``generator`` argument of each call (``initial_belief``, ``predict``,
``update``, ``step``, :func:`~torchmm.run_filter`); a ``generator`` given to the constructor is only
the default of calls that pass none.

All-underflow guard: if every weight of a batch element is zero (``-inf`` log-weight, e.g. a
measurement so far out that every particle's likelihood underflows), that element keeps its prior
weights, the step reports ``extras["degenerate"] = True`` and ``log_likelihood = -inf`` for it,
:func:`~torchmm.run_filter` logs one warning per run with the count, and no NaN is produced.

A model failure is not an underflow: where a datum is present and a particle's likelihood is NaN or
``+inf`` (non-finite particles, a NaN ``h(x)``, a state-dependent ``R(x)`` that is not positive
definite, a user likelihood with a point mass), the step reports ``extras["failed"] = True`` and a
NaN ``log_likelihood`` for that element, the weights drop those particles (the prior weights are kept
where none is left) and ``extras["degenerate"]`` is not set (docs/robustness.md).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief, ParticleBelief
from torchmm.beliefs.ops import normalize_log_probs
from torchmm.filters.base import Filter, StepOutput
from torchmm.filters.resampling import (
    RESAMPLING_SCHEMES,
    apply_indices,
    resample,
    resample_where_needed,
)
from torchmm.contract import BeliefArg, Choice, DType, Flag, Gen, Int, Of, Real, entry_point
from torchmm.linalg import any_observed
from torchmm.models.base import MeasurementModel, MotionModel, check_model_pair
from torchmm.filters.particle_ops import (  # (re-exported: the operations the particle filters share)
    cached_noise_factor,
    check_generator,
    check_likelihood_noise,
    check_noise_dtype,
    check_particle_prior,
    degenerate_guard,
    particle_batch,
    particle_innovation,
    particle_log_likelihood,
    gaussian_log_likelihood,
    noise_factor,
    particle_failure,
    propagate_particles,
    sample_gaussian,
    standard_normal,
    usable_loglik,
    whitening,
)
from torchmm.validation import as_float, as_int, check_measurement

__all__ = [
    "ParticleFilter",
    "cached_noise_factor",
    "check_generator",
    "check_likelihood_noise",
    "check_noise_dtype",
    "check_particle_prior",
    "degenerate_guard",
    "particle_batch",
    "particle_innovation",
    "particle_log_likelihood",
    "gaussian_log_likelihood",
    "noise_factor",
    "propagate_particles",
    "sample_gaussian",
    "standard_normal",
    "whitening",
]


class ParticleFilter(Filter):
    r"""Bootstrap particle filter (sampling importance resampling) in log space.

    Predict: ``x^i_k = f(x^i_{k-1}, u_k) + w^i_k`` (prior as proposal). Update:
    ``log w^i_k = log w^i_{k-1} + log p(z_k | x^i_k) - log p(z_k | z_{1:k-1})`` with
    ``log p(z_k | z_{1:k-1}) = logsumexp_i(log w^i_{k-1} + log p(z_k | x^i_k))``; then resampling
    of the batch elements whose ESS is below ``ess_threshold * Np``.

    Args:
        motion, measurement: the models (a mode bank broadcasts against a belief batch ``(*B, M)``).
        resampling: ``"systematic"`` (default), ``"stratified"``, ``"multinomial"``, ``"residual"``.
        ess_threshold: resample when ``ESS < ess_threshold * Np`` (0: never; > 1: every step).
        num_particles: if given, :meth:`predict` first resamples a belief with a different particle
            count to this many (e.g. after IMM mixing, which concatenates mode particle sets).
        generator: the random stream (``torch.Generator`` on the belief's device).
        state_dependent_noise: use the measurement model's own ``log_likelihood`` per particle
            (noise depending on the state); default: ``R = measurement.noise_cov()`` shared.
        noise_dtype: dtype of the process-noise normals (``torch.float32``: ~4x faster draws on
            CPU, see :func:`standard_normal`); default the particles' dtype.

    Shapes:
        belief: :class:`ParticleBelief`, particles ``(*B, Np, n)``, log_weights ``(*B, Np)``;
        z: ``(*B, m)`` (NaN = missing); the step's ``log_likelihood`` is ``(*B,)``, ``innovation``
        ``(*B, m)``, ``innovation_cov`` ``(*B, m, m)``; ``extras``: ``"ess"`` (before resampling),
        ``"resampled"``, ``"degenerate"`` and ``"failed"`` ``(*B,)`` (a present datum and a NaN or
        ``+inf`` particle likelihood - a model failure -: the log-likelihood is NaN).

    Examples:
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> g = torch.Generator().manual_seed(0)
        >>> pf = ParticleFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0), generator=g)
        >>> belief = pf.initial_belief(GaussianBelief(torch.zeros(4, 2), torch.eye(2)), 500)
        >>> out = pf.step(belief, torch.randn(4, 1, generator=g))
        >>> out.belief.particles.shape, out.log_likelihood.shape
        (torch.Size([4, 500, 2]), torch.Size([4]))
    """

    smoother = "particles"  # (torchmm.smooth's backward pass: Filter.smoother)

    @entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel),
                 resampling=Choice(*sorted(RESAMPLING_SCHEMES)),
                 ess_threshold=Real(minimum=0.0), num_particles=Int(1, optional=True), generator=Gen(),
                 state_dependent_noise=Flag(), noise_dtype=DType(strings=True))
    def __init__(self, motion: MotionModel, measurement: MeasurementModel, *, resampling: str = "systematic",
                 ess_threshold: float = 0.5, num_particles: int | None = None,
                 generator: torch.Generator | None = None, state_dependent_noise: bool = False,
                 noise_dtype: torch.dtype | None = None):
        super().__init__()
        check_model_pair(motion, measurement)
        ess_threshold = as_float(ess_threshold, "ess_threshold", minimum=0.0)
        if num_particles is not None:
            num_particles = as_int(num_particles, "num_particles", minimum=1)
        self.motion, self.measurement = motion, measurement
        self.resampling, self.ess_threshold = resampling, ess_threshold
        self.num_particles = num_particles
        self.generator = check_generator(generator)
        self.state_dependent_noise = bool(state_dependent_noise)
        self.noise_dtype = check_noise_dtype(noise_dtype)
        if not self.state_dependent_noise:
            check_likelihood_noise(measurement)

    def check_bank_member(self, name: str, num_modes: int) -> None:
        if self.num_particles is None and num_modes > 1:
            raise ValueError(f"{name}: a ParticleFilter inside IMM/GPB needs num_particles= (mixing merges the "
                             "M particle sets into M * Np particles; the filter resamples back to num_particles)")

    uses_generator = True

    @entry_point(belief=BeliefArg(), num_particles=Int(1, optional=True), generator=Gen())
    def initial_belief(self, belief: GaussianBelief, num_particles: int | None = None, *,
                       generator: torch.Generator | None = None) -> ParticleBelief:
        """Sample a particle belief from a Gaussian prior (uniform weights).

        Shapes:
            belief: batch ``(*B,)`` -> particles ``(*B, Np, n)``
        """
        if isinstance(belief, ParticleBelief) and num_particles is None:  # already particles (e.g. in a bank)
            particle_batch(belief, self.motion.state_dim)
            return belief.validate("belief")
        num = self.num_particles if num_particles is None else as_int(num_particles, "num_particles", minimum=1)
        if num is None:
            raise ValueError("num_particles: give it here or to the filter")
        check_particle_prior(self, belief)
        particles = sample_gaussian(belief, num, generator=self._generator(generator))
        log_w = torch.full(particles.shape[:-1], -math.log(num), dtype=particles.dtype, device=particles.device)
        return ParticleBelief(particles, log_w)

    def predict(self, belief: ParticleBelief, *, u: Tensor | None = None, motion: MotionModel | None = None,
                generator: torch.Generator | None = None) -> ParticleBelief:
        if motion is not None:
            return self.with_motion(motion).predict(belief, u=u, generator=generator)
        generator = self._generator(generator)
        particle_batch(belief, self.motion.state_dim)
        if self.num_particles is not None and belief.num_particles != self.num_particles:
            indices = resample(belief.log_weights, self.resampling, self.num_particles, generator=generator)
            belief = apply_indices(belief, indices)
        particles = propagate_particles(self.motion, belief.particles, u=u, generator=generator,
                                        noise_dtype=self.noise_dtype)
        log_w = belief.log_weights.expand(particles.shape[:-1])
        return ParticleBelief(particles, log_w)

    def update(self, belief: ParticleBelief, z: Tensor, *, sensor: MeasurementModel | None = None,
               generator: torch.Generator | None = None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z, generator=generator)
        z = check_measurement(z, self.measurement.meas_dim, particle_batch(belief, self.motion.state_dim),
                              belief.particles)
        loglik, predicted = particle_log_likelihood(self.measurement, z, belief.particles,
                                                     self.state_dependent_noise)
        posterior, log_evidence, extras = self.reweight(belief, loglik, any_observed(z), generator=generator)
        prior_log_w = normalize_log_probs(belief.log_weights)
        cov = None if self.state_dependent_noise else self.measurement.noise_cov()
        innovation, innovation_cov = particle_innovation(z, predicted, prior_log_w, cov)
        return StepOutput(belief=posterior, prior=belief, log_likelihood=log_evidence, innovation=innovation,
                          innovation_cov=innovation_cov, extras=extras)

    def reweight(self, belief: ParticleBelief, loglik: Tensor, present: Tensor, *,
                 generator: torch.Generator | None = None) -> tuple[ParticleBelief, Tensor, dict]:
        """The update's weighting with the particles' log-likelihoods of the datum (the bootstrap
        update after the likelihood; :class:`~torchmm.association.ParticlePDA` gives a scan's):
        the posterior (resampled where the ESS is low), the log-evidence (0 where ``present`` is
        False) and the flags ``ess``, ``resampled``, ``degenerate``, ``failed``.

        Shapes:
            loglik: ``(*B, Np)``; present: ``(*B,)`` -> the posterior, ``(*B,)``, flags ``(*B,)``
        """
        prior_log_w = normalize_log_probs(belief.log_weights)
        # a NaN or +inf particle likelihood for a present datum: the model failed (non-finite particles,
        # an R(x) not positive definite, a point mass), not an all-underflow
        failed = particle_failure(loglik, present)
        loglik = usable_loglik(loglik)
        joint = prior_log_w + loglik
        log_evidence = torch.logsumexp(joint, dim=-1)
        log_evidence = torch.where(present, log_evidence, 0.0)  # exactly 0 without a datum
        degenerate = degenerate_guard(log_evidence)
        post_log_w = torch.where(degenerate.unsqueeze(-1), prior_log_w, joint - log_evidence.unsqueeze(-1))
        log_evidence = torch.where(failed, math.nan, log_evidence)
        degenerate = degenerate & ~failed
        posterior = ParticleBelief(belief.particles, post_log_w)
        posterior, resampled, ess = resample_where_needed(posterior, self.ess_threshold, self.resampling,
                                                          generator=self._generator(generator))
        return posterior, log_evidence, {"ess": ess, "resampled": resampled, "degenerate": degenerate,
                                         "failed": failed}


    def _generator(self, generator: torch.Generator | None) -> torch.Generator | None:
        """The call's random stream; the filter's ``generator`` (a default) when none is given."""
        return self.generator if generator is None else check_generator(generator)

r"""The multiple-model particle filter of paper 003: ``Np`` particles per model, one joint weight set.

:class:`MultipleModelParticleFilter` keeps ``Np`` particles **per model**, ``(*B, M, Np, n)``
(paper 003's "NP particles for every model", eqs. (32)-(34)). Its belief is a
:class:`~torchmm.beliefs.ModeBelief` whose components are per-model particle sets. One step:

1. interaction: the ``Np`` particles of model ``i`` are drawn from the mixture of all particles of
   the previous step with weights ``mu_a pi_ai w_{b|a}`` (model ``a``, particle ``b``), i.e. the
   predicted density of model ``i``; this is one inverse-CDF resampling of the product
   distribution (ancestor model, then particle inside it) per ``(run, i)`` (:func:`mixing_indices`);
2. propagation with model ``i`` and its process noise;
3. weights (33)-(34): ``w_{ij} ∝ c_i p(z_k | x_{ij})`` with ``c_i = sum_a mu_a pi_ai``, normalised
   jointly over models and particles; mode probabilities are the per-model sums.

It computes the estimator ``IMM(ParticleFilter(bank, num_particles=Np, ess_threshold=0))`` would
(the same interaction in distribution, the same weights), with the interaction drawn directly
from the product distribution (no ``M Np`` mixture to resample) and the weights in few passes:
the fast path of the engine for particle banks. The all-underflow guard is
:func:`~torchmm.filters.particle_ops.degenerate_guard`'s.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

import torchmm.kernels as kernels
import torchmm.kernels.particle as particle_stages
from torchmm.beliefs import GaussianBelief, ModeBelief, ParticleBelief
from torchmm.beliefs.ops import live_log, normalize_log_probs
from torchmm.contract import BeliefArg, Choice, DType, Finite, Flag, Gen, Int, Of, Stochastic, entry_point
from torchmm.filters.base import StepOutput
from torchmm.filters.particle import ParticleFilter
from torchmm.filters.particle_ops import (
    cached_noise_factor,
    check_generator,
    check_particle_prior,
    degenerate_guard,
    particle_batch,
    particle_innovation,
    particle_log_likelihood,
    propagate_particles,
    sample_gaussian,
    whitening,
)
from torchmm.linalg import any_observed
from torchmm.models.base import MeasurementModel, MotionModel, check_model_pair
from torchmm.models.linear import LinearMeasurement, LinearMotion, plain_linear
from torchmm.multimodel.imm import MultipleModelFilter
from torchmm.multimodel.particle_mixing import INVERSE_CDF_SCHEMES, ParticleMixing, mixing_indices  # (re-exported)
from torchmm.runtime import host_reads_ok
from torchmm.validation import as_int, check_measurement, check_probabilities

__all__ = ["MultipleModelParticleFilter", "ParticleMixing", "mixing_indices"]


@kernels.joins("linear_particles", ("step", "_propagate", "_weigh"))
class MultipleModelParticleFilter(MultipleModelFilter):
    r"""Interacting multiple-model particle filter with ``Np`` particles per model.

    The engine's :class:`~torchmm.multimodel.MultipleModelFilter` over a bank of particle filters
    with the :class:`ParticleMixing` interaction, and the fused joint update of (33)-(34) (the
    weights of every model's particles normalised together in a few passes, instead of one
    normalisation per model and one over the models).

    It joins the ``"linear_particles"`` kernels (:mod:`torchmm.kernels.particle`): on the CPU, with
    linear-Gaussian models, its propagation and likelihoods run as one compiled pass (the same draws,
    the same numbers); a subclass that overrides ``step``, ``_propagate`` or ``_weigh`` leaves them.

    Paper 003 eqs. (32)-(34): every model of the set carries ``Np`` particles; the weight of
    particle ``j`` of model ``i`` is ``c_i p(z_k | x^j_k(m_i))`` (33), normalised over all models
    and particles (34). The interaction step draws model ``i``'s particles from the previous
    mixture (see :func:`mixing_indices`), so every model keeps exactly ``Np`` particles (static
    shapes) and the model probabilities carry the evidence.

    Args:
        motion: a mode bank (parameter batch ``(M,)``, e.g. ``ConstantVelocity(..., acceleration=A)``)
            or any motion model whose parameters broadcast against ``(*B, M)``.
        measurement: the measurement model (shared by all modes).
        transition: ``(M, M)`` row-stochastic matrix or :class:`~torchmm.multimodel.ModeTransition`.
        num_particles: ``Np`` per model.
        mixing: scheme of the interaction (``"systematic"``, ``"stratified"``, ``"multinomial"``:
            inverse CDF of the product distribution; ``"two_stage"``: systematic over the
            ancestor models, then a per-model systematic resample, no search; see
            :func:`mixing_indices`).
        generator: the random stream.
        innovation_stats: compute the step's innovation and its covariance (one extra pass over
            the particles); ``False`` returns None for both.
        noise_dtype: dtype of the process-noise normals (``torch.float32``: ~4x faster draws on
            CPU, see :func:`standard_normal`); default the particles' dtype.

    Shapes:
        belief: :class:`ModeBelief` with ``mode_log_probs (*B, M)`` and components
        ``ParticleBelief(particles (*B, M, Np, n), log_weights (*B, M, Np))`` (normalised within
        each model); z: ``(*B, m)``; ``log_likelihood`` ``(*B,)``; ``extras``: ``"ess"`` (of the
        joint weights, ``(*B,)``), ``"mode_log_likelihood"`` ``(*B, M)``, ``"degenerate"`` ``(*B,)``,
        ``"failed"`` ``(*B,)`` (a present datum and NaN particle likelihoods - non-finite particles -:
        the log-likelihood is NaN, docs/robustness.md),
        ``"joint_log_weights"`` (33) before normalisation ``(*B, M, Np)``.

    Examples:
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> g = torch.Generator().manual_seed(0)
        >>> motion = ConstantVelocity(1, acceleration=[[0.5], [0.0], [-0.5]])
        >>> pi = torch.full((3, 3), 0.05) + 0.85 * torch.eye(3)
        >>> mmpf = MultipleModelParticleFilter(motion, PositionMeasurement(2, [0], 1.0), pi, 200, generator=g)
        >>> belief = mmpf.initial_belief(GaussianBelief(torch.zeros(5, 2), torch.eye(2)))
        >>> out = mmpf.step(belief, torch.randn(5, 1, generator=g))
        >>> out.belief.components.particles.shape, out.belief.mode_probs.sum(-1).shape
        (torch.Size([5, 3, 200, 2]), torch.Size([5]))
    """

    @entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel), transition=Stochastic(),
                 num_particles=Int(1), mixing=Choice(*INVERSE_CDF_SCHEMES), generator=Gen(),
                 innovation_stats=Flag(), noise_dtype=DType(strings=True))
    def __init__(self, motion: MotionModel, measurement: MeasurementModel, transition, num_particles: int, *,
                 mixing: str = "systematic", generator: torch.Generator | None = None,
                 innovation_stats: bool = True, noise_dtype: torch.dtype | None = None):
        check_model_pair(motion, measurement)
        num_particles = as_int(num_particles, "num_particles", minimum=1)
        # the mode filters: one bootstrap PF over the mode bank (it never resamples: the interaction does)
        bank = ParticleFilter(motion, measurement, num_particles=num_particles, ess_threshold=0.0,
                              noise_dtype=noise_dtype)
        super().__init__(bank, transition,
                         ParticleMixing(mixing, num_particles))
        self.num_particles = num_particles
        self.mixing, self.generator = mixing, check_generator(generator)
        self.innovation_stats = bool(innovation_stats)
        self.noise_dtype = bank.noise_dtype
        self._check_motion()

    @property
    def motion(self) -> MotionModel:
        """The mode bank's motion model (the particle filters')."""
        return self.bank.filter.motion

    @property
    def measurement(self) -> MeasurementModel:
        return self.bank.filter.measurement

    def _motion_modes(self) -> int:
        """How many models the motion bank holds (all ``M``; a subclass may build some per step)."""
        return self.num_modes

    def _check_motion(self) -> None:
        shape = getattr(self.motion, "param_batch_shape", None)
        expected = self._motion_modes()
        if shape is not None and len(shape) > 0 and shape[-1] not in (1, expected):
            raise ValueError(f"motion: parameter batch {tuple(shape)} does not match {expected} modes")

    @property
    def uses_generator(self) -> bool:
        return True

    def _generator(self, generator: torch.Generator | None) -> torch.Generator | None:
        """The call's random stream; the filter's ``generator`` (a default) when none is given."""
        return self.generator if generator is None else check_generator(generator)

    @entry_point(belief=BeliefArg(), mode_probs=Finite(optional=True, check=False), generator=Gen())
    def initial_belief(self, belief: GaussianBelief, mode_probs=None, *,
                       generator: torch.Generator | None = None) -> ModeBelief:
        """``Np`` particles per model, each set drawn independently from the Gaussian prior (32).

        Shapes:
            belief: batch ``(*B,)``; mode_probs ``(M,)`` or ``(*B, M)``, default uniform
            -> :class:`ModeBelief` with components of batch ``(*B, M)``
        """
        check_particle_prior(self, belief)
        M, batch = self.num_modes, belief.batch_shape
        expanded = belief.unsqueeze(-1).expand(*batch, M)
        particles = sample_gaussian(expanded, self.num_particles, generator=self._generator(generator))
        log_w = torch.full(particles.shape[:-1], -math.log(self.num_particles), dtype=belief.dtype,
                           device=belief.device)
        if mode_probs is None:
            log_probs = torch.full((*batch, M), -math.log(M), dtype=belief.dtype, device=belief.device)
        else:
            probs = check_probabilities(mode_probs, "mode_probs", M, dtype=belief.dtype, device=belief.device)
            try:
                log_probs = live_log(probs, 0.0).expand(*batch, M)  # (a zero: no NaN gradient)
            except RuntimeError:
                raise ValueError(f"mode_probs: shape {tuple(probs.shape)} does not broadcast to the belief's "
                                 f"batch {tuple(batch)} x {M} modes") from None
        return ModeBelief(log_probs, ParticleBelief(particles, log_w))

    def _propagate(self, particles: Tensor, *, u: Tensor | None, log_cbar: Tensor,
                   generator: torch.Generator | None = None) -> Tensor:
        """Propagate each model's particles with its own model. ``(*B, M, Np, n)``."""
        return propagate_particles(self.motion, particles, u=None if u is None else u.unsqueeze(-2),
                                   generator=generator, noise_dtype=self.noise_dtype)

    def _check_belief(self, belief) -> torch.Size:
        """Batch ``(*B,)`` of a per-model particle belief, checked (shapes only)."""
        if not isinstance(belief, ModeBelief) or not isinstance(belief.components, ParticleBelief):
            raise TypeError(f"belief: expected a ModeBelief over per-model particle sets (from initial_belief), "
                            f"got {type(belief).__name__}")
        comps = belief.components
        if comps.particles.dim() < 3 or comps.particles.shape[-3] != self.num_modes:
            raise ValueError(f"belief: particles {tuple(comps.particles.shape)} must be (*B, {self.num_modes}, Np, n)")
        particle_batch(comps, self.motion.state_dim)
        return belief.mode_log_probs.shape[:-1]

    def predict(self, belief: ModeBelief, *, u: Tensor | None = None, motion: MotionModel | None = None,
                generator: torch.Generator | None = None) -> ModeBelief:
        if motion is not None:
            return self.with_motion(motion).predict(belief, u=u, generator=generator)
        generator = self._generator(generator)
        self._check_belief(belief)
        mixed = self.mix(belief, generator)  # ParticleMixing: Np ancestors per model, uniform weights
        start = mixed.components
        particles = self._propagate(start.particles, u=u, log_cbar=mixed.mode_log_probs, generator=generator)
        return ModeBelief(mixed.mode_log_probs, ParticleBelief(particles, start.log_weights))

    def step(self, belief: ModeBelief, z: Tensor, *, u: Tensor | None = None, motion=None, sensor=None,
             generator=None) -> StepOutput:
        if u is None and motion is None and sensor is None:
            fused = self._fused_prior(belief, z, generator)
            if fused is not None:  # the same prior and log-likelihoods from one compiled pass
                prior, loglik = fused
                return self._update(self._as_prior(prior), z, generator, loglik)
        prior = self.predict(belief, u=u, motion=motion, generator=generator)
        return self.update(prior, z, sensor=sensor, generator=generator)

    def _as_prior(self, prior: ModeBelief) -> ModeBelief:
        """The predicted belief as :meth:`predict` returns it (a subclass may add to it)."""
        return prior

    def linear_particles(self) -> particle_stages.LinearParticles | str:
        """This filter's description for the ``"linear_particles"`` kernels (:mod:`torchmm.kernels`):
        its models' matrices, or the reason it has none (innovation statistics asked for, a model
        that is not a plain linear-Gaussian one, a control input)."""
        motion, measurement = self.motion, self.measurement
        if self.innovation_stats:
            return "innovation_stats=True"
        if not isinstance(self.interaction, ParticleMixing):
            return "not the particle interaction"
        if not (isinstance(motion, LinearMotion) and plain_linear(motion)) or motion.input_matrix is not None:
            return "the motion is not a LinearMotion (its own forward and noise) without a control input"
        if not (isinstance(measurement, LinearMeasurement) and plain_linear(measurement)):
            return "the measurement is not a LinearMeasurement (its own forward and noise)"
        return particle_stages.LinearParticles(motion.F, motion.offset, motion.noise_cov(), measurement.H,
                                               measurement.noise_cov())

    def _fused_prior(self, belief: ModeBelief, z: Tensor, generator) -> tuple[ModeBelief, Tensor] | None:
        """:meth:`predict` and the particles' log-likelihoods of ``z`` through
        :func:`torchmm.kernels.particle.propagate_log_likelihood` (the same draws, the same numbers);
        None where it does not apply: the filter's description (:meth:`linear_particles`, through
        :func:`torchmm.kernels.describe`), the kernel's conditions
        (:meth:`~torchmm.kernels.particle.LinearParticles.why_not`), complete data."""
        described = kernels.describe(self, "linear_particles")
        if (isinstance(described, str) or not isinstance(z, Tensor) or not isinstance(belief, ModeBelief)
                or not isinstance(belief.components, ParticleBelief)):
            return None
        particles = belief.components.particles
        M = self.num_modes
        if described.why_not(particles, z, M):
            return None
        F, H, Q, R, offset = described.F, described.H, described.Q, described.R, described.offset
        n = particles.shape[-1]
        batch = self._check_belief(belief)
        if z.shape[:-1] != batch or not bool(torch.isfinite(z).all()):  # a host read: CPU tensors only here
            return None
        generator = self._generator(generator)
        flat, log_cbar, num = self.interaction._indices(belief, self.transition, generator, defer=True)
        factor = cached_noise_factor(Q)
        # the draw of standard_normal, left in its dtype (the kernel widens each normal as it reads it);
        # a two_stage interaction's kernel runs meanwhile in a worker thread
        eps = torch.randn((*batch, M, num, factor.shape[-1]), dtype=self.noise_dtype or particles.dtype,
                          generator=generator)
        flat = flat() if callable(flat) else flat
        inv, logdet = whitening(R)
        rows = batch.numel()
        source = particles.expand(*batch, *particles.shape[-3:])
        x, loglik, nan = particle_stages.propagate_log_likelihood(
            source.reshape(rows, -1, n), flat.reshape(rows, M, num), eps.reshape(rows, M, num, -1), factor,
            offset.expand(M, n), F, (inv @ H).contiguous(), -(z.unsqueeze(-2) @ inv.mT).reshape(rows, -1),
            float(logdet + H.shape[0] * math.log(2 * math.pi)), with_nan=True)
        log_w = torch.full((), -math.log(num), dtype=x.dtype).expand(*batch, M, num)
        prior = ModeBelief(log_cbar, ParticleBelief(x.view(*batch, M, num, n), log_w))
        # (complete data here: a NaN log-likelihood is a failure of its run)
        return prior, (loglik.view(*batch, M, num), nan.view(*batch, M).any(-1))

    def _weigh(self, prior: ModeBelief, z: Tensor, loglik: tuple[Tensor, Tensor] | None = None):
        """Weights (33)-(34) as per-model quantities (few passes over the particles).

        Returns ``(joint, per_model, log_evidence, degenerate, predicted, prior_within, prior_mode,
        failed)`` with the unnormalised joint log-weights ``(*B, M, Np)`` and their per-model
        ``logsumexp`` ``(*B, M)``; ``failed (*B,)``: a present datum and a NaN or ``+inf``
        particle log-likelihood (non-finite particles; the log-likelihood is NaN there, those particles
        get zero weight, docs/robustness.md). ``loglik``: ``(log-likelihoods, failure flags (*B,))``
        where already computed (a fresh tensor, NaN and ``+inf`` mapped to ``-inf``).
        """
        comps = prior.components
        predicted = None
        present = any_observed(z)
        if loglik is None:
            loglik, predicted = particle_log_likelihood(self.measurement, z.unsqueeze(-2), comps.particles, False,
                                                         need_predicted=self.innovation_stats)
            # one pass: the sum is NaN or +inf iff a likelihood is NaN or +inf (a model failure, as the
            # ParticleFilter's particle_failure; -inf is an underflow)
            nan = ~(loglik.sum((-2, -1)) < math.inf)
            loglik = torch.nan_to_num(loglik, nan=-math.inf, posinf=-math.inf, neginf=-math.inf)  # (fresh)
        else:
            loglik, nan = loglik
        failed = nan & present
        lw = comps.log_weights
        prior_mode = normalize_log_probs(prior.mode_log_probs)
        if lw.dim() > 0 and lw.stride(-1) == 0 and lw.shape[-1] > 0:
            # constant along the particles (the predict of this filter): normalised is -log Np
            prior_within = torch.full((), -math.log(lw.shape[-1]), dtype=lw.dtype, device=lw.device).expand(lw.shape)
            joint = loglik.add_((prior_mode - math.log(lw.shape[-1])).unsqueeze(-1))  # (33), unnormalised
        else:
            prior_within = normalize_log_probs(lw)
            joint = (prior_within + prior_mode.unsqueeze(-1)) + loglik  # (33), unnormalised
        per_model = torch.logsumexp(joint, dim=-1)
        log_evidence = torch.logsumexp(per_model, dim=-1)
        log_evidence = torch.where(present, log_evidence, 0.0)  # exactly 0 without a datum
        degenerate = degenerate_guard(log_evidence)
        # on a device applied whether or not a run degenerated (no host synchronisation)
        if not host_reads_ok(degenerate) or bool(degenerate.any()):  # on the CPU: only where a run degenerated
            joint = torch.where(degenerate[..., None, None], prior_within + prior_mode.unsqueeze(-1), joint)
        per_model = torch.where(degenerate[..., None], prior_mode, per_model)
        return joint, per_model, log_evidence, degenerate, predicted, prior_within, prior_mode, failed

    def update(self, belief: ModeBelief, z: Tensor, *, sensor: MeasurementModel | None = None,
               generator: torch.Generator | None = None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z, generator=generator)
        return self._update(belief, z, generator)

    def _update(self, belief: ModeBelief, z: Tensor, generator, loglik: Tensor | None = None) -> StepOutput:
        """:meth:`update` with this model's sensor; ``loglik``: the prior particles' log-likelihoods of
        ``z`` where :meth:`step` computed them with the prior (:meth:`_fused_prior`)."""
        z = check_measurement(z, self.measurement.meas_dim, self._check_belief(belief), belief.components.particles)
        joint, per_model, log_evidence, degenerate, predicted, prior_within, prior_mode, failed = self._weigh(
            belief, z, loglik)
        safe_ev = torch.where(degenerate, torch.zeros_like(log_evidence), log_evidence)
        mode_log_probs = per_model - safe_ev.unsqueeze(-1)  # (34) summed over particles
        within = joint - per_model.unsqueeze(-1)
        lost = ~torch.isfinite(per_model)
        if not host_reads_ok(lost) or bool(lost.any()):  # on the CPU: only where a model lost every particle
            within = within.masked_fill_(lost.unsqueeze(-1), -math.log(within.shape[-1]))
        innovation = innovation_cov = None
        if self.innovation_stats:
            flat_prior = (prior_within + prior_mode.unsqueeze(-1)).flatten(-2)
            innovation, innovation_cov = particle_innovation(z, predicted.flatten(-3, -2), flat_prior,
                                                     self.measurement.noise_cov())
        # ESS of the normalised joint weights: 1 / sum_j p_j^2 sum_l v_jl^2 (within <= 0: exp is safe)
        sq = (2 * mode_log_probs).exp().mul_((2 * within).exp_().sum(-1)).sum(-1)
        extras = {"ess": 1.0 / sq, "mode_log_likelihood": per_model - prior_mode,
                  "degenerate": degenerate & ~failed, "failed": failed, "joint_log_weights": joint}
        return StepOutput(
            belief=ModeBelief(mode_log_probs, ParticleBelief(belief.components.particles, within)),
            prior=belief,
            log_likelihood=torch.where(failed, math.nan, log_evidence),
            innovation=innovation,
            innovation_cov=innovation_cov,
            extras=extras,
        )

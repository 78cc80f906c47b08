r"""Particle filters: the bootstrap filter of the common interface and a multiple-model PF.

:class:`ParticleFilter` is a bootstrap (SIR) filter over a :class:`~torchmm.beliefs.ParticleBelief`:
particles are propagated through the motion model with sampled process noise, weighted by the
measurement likelihood in log space, and resampled per batch element when the effective sample
size drops below ``ess_threshold * Np`` (static shapes, ``torch.where``). It implements
``predict`` / ``update`` / ``step`` like the Kalman filters, so IMM / GPB and the other combinators
accept it as a mode filter (with a mode bank as motion model, all modes in one call).

:class:`MultipleModelParticleFilter` keeps ``Np`` particles **per model**, ``(*B, M, Np, n)``
(paper 003's "NP particles for every model", eqs. (32)-(34)). Its belief is a
:class:`~torchmm.beliefs.ModeBelief` whose components are per-model particle sets. One step:

1. interaction: the ``Np`` particles of model ``i`` are drawn from the mixture of all particles of
   the previous step with weights ``mu_a pi_ai w_{b|a}`` (model ``a``, particle ``b``), i.e. the
   predicted density of model ``i``; this is one inverse-CDF resampling of the product
   distribution (ancestor model, then particle inside it) per ``(run, i)``;
2. propagation with model ``i`` and its process noise;
3. weights (33)-(34): ``w_{ij} ∝ c_i p(z_k | x_{ij})`` with ``c_i = sum_a mu_a pi_ai``, normalised
   jointly over models and particles; mode probabilities are the per-model sums.

Random numbers come from the ``generator`` given to the filter (an explicit
``torch.Generator``; the filter module itself holds no state between calls).

All-underflow guard: if every weight of a batch element is zero (``-inf`` log-weight, e.g. a
measurement impossible under every particle, or NaN likelihoods), that element keeps its prior
weights, the step reports ``extras["degenerate"] = True`` and ``log_likelihood = -inf`` for it, a
warning is logged, and no NaN is produced.
"""

from __future__ import annotations

import logging
import math

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief, ModeBelief, ParticleBelief, psd_sqrt, symmetrize
from torchmm.beliefs.ops import normalize_log_probs
from torchmm.filters.base import Filter, StepOutput
from torchmm.linalg import any_observed, cholesky
from torchmm.filters.resampling import (
    RESAMPLING_SCHEMES,
    apply_indices,
    resample,
    resample_where_needed,
    searchsorted_rows,
    systematic_search,
)
from torchmm.models.base import MeasurementModel, MotionModel, check_model_pair
from torchmm.models.linear import LinearMeasurement, LinearMotion
from torchmm.multimodel.transition import as_transition
from torchmm.validation import (
    as_float,
    as_int,
    broadcast_shape,
    check_covariance,
    check_filter_dtype,
    check_measurement,
    check_probabilities,
    gaussian_batch,
)

__all__ = [
    "MultipleModelParticleFilter",
    "ParticleFilter",
    "gaussian_log_likelihood",
    "noise_factor",
    "propagate_particles",
    "sample_gaussian",
    "standard_normal",
]

log = logging.getLogger("torchmm")

_INVERSE_CDF_SCHEMES = ("multinomial", "stratified", "systematic", "two_stage")


def noise_factor(cov: Tensor, rtol: float = 1e-10) -> Tensor:
    """A factor ``L`` with ``L L^T = cov``, dropping null directions shared by every matrix.

    Full-rank matrices get their Cholesky factor; rank-deficient process noise such as
    ``q G G^T`` gets an eigen-factor with only the ``r < n`` significant directions (eigenvalues
    above ``rtol`` times the largest), so it is sampled from ``r`` normals.

    Shapes:
        cov: ``(..., n, n)`` -> ``(..., n, r)``
    """
    eigvals, eigvecs = torch.linalg.eigh(symmetrize(cov))
    scale = eigvals.amax(-1, keepdim=True).clamp_min(torch.finfo(cov.dtype).tiny)
    rank = max(int((eigvals > rtol * scale).sum(-1).max()), 1)
    if rank == cov.shape[-1]:
        chol, info = torch.linalg.cholesky_ex(cov)
        if not bool((info != 0).any()):
            return chol
    # keep the r significant directions *before* the square root: sqrt has an infinite derivative
    # at the (numerically) zero eigenvalues, which would turn gradients w.r.t. Q into NaN
    top = eigvals[..., -rank:].clamp_min(torch.finfo(cov.dtype).tiny)
    return eigvecs[..., -rank:] * top.sqrt().unsqueeze(-2)


def sample_gaussian(belief: GaussianBelief, num_particles: int, *,
                    generator: torch.Generator | None = None) -> Tensor:
    """``num_particles`` draws from every Gaussian of a batch.

    Shapes:
        belief: mean ``(*B, n)``, cov ``(*B, n, n)`` -> ``(*B, Np, n)``
    """
    num_particles = as_int(num_particles, "num_particles", minimum=1)
    root = psd_sqrt(belief.cov)
    batch, n = belief.batch_shape, belief.state_dim
    eps = torch.randn(*batch, int(num_particles), n, dtype=belief.dtype, device=belief.device,
                      generator=generator)
    return belief.mean.unsqueeze(-2) + eps @ root.mT


def standard_normal(shape, like: Tensor, *, generator: torch.Generator | None = None,
                    noise_dtype: torch.dtype | None = None) -> Tensor:
    """Standard normals of ``shape`` in ``like``'s dtype, optionally drawn in ``noise_dtype``.

    ``noise_dtype=torch.float32`` draws float32 normals and casts them: on CPU about 4x faster
    than float64 draws (torch's vectorised float32 Box-Muller), at the cost of 24-bit normals
    whose tails end near 5.8 sigma (``sqrt(-2 ln 2^-24)``), which a particle filter's process
    noise does not notice. ``None`` draws in ``like``'s dtype.

    Shapes:
        -> ``shape``
    """
    dtype = like.dtype if noise_dtype is None else noise_dtype
    eps = torch.randn(shape, dtype=dtype, device=like.device, generator=generator)
    return eps if dtype == like.dtype else eps.to(like.dtype)


def _add(a: Tensor, b: Tensor) -> Tensor:
    """``a + b``, in place into the fresh temporary ``a`` when the shapes allow it."""
    if broadcast_shape(a.shape, b.shape) == a.shape and a.dtype == b.dtype:
        return a.add_(b)
    return a + b


def propagate_particles(motion: MotionModel, particles: Tensor, *, u: Tensor | None = None,
                        generator: torch.Generator | None = None,
                        noise_dtype: torch.dtype | None = None) -> Tensor:
    """``x_k = f(x_{k-1}, u_k) + w_k``, ``w_k ~ N(0, Q)``, for particle sets.

    The model's parameter batch ``*P`` broadcasts against the particle sets' batch ``*B`` (a bank
    of ``M`` modes against ``(*B, M)``). Linear models are applied as one matmul on the particle
    layout (with an unbatched ``F``: one ``addmm`` that also adds the noise and offset); any other
    model is called with the particle axis leftmost (the torchmm convention for sample axes). The
    process noise ``Q = motion.noise_cov()`` is taken as state-independent; its standard normals
    are drawn in ``noise_dtype`` (see :func:`standard_normal`).

    Shapes:
        particles: ``(*B, Np, n)``; u: ``(*B, k)`` -> ``(*B, Np, n)``
    """
    factor = noise_factor(motion.noise_cov())  # (*P, n, r), shared by the particles of a set
    eps = standard_normal((*particles.shape[:-1], factor.shape[-1]), particles, generator=generator,
                          noise_dtype=noise_dtype)
    # x @ A^T with an unbatched A as `linear` (a contiguous operand: ~3x faster than a matmul with
    # the transposed view for millions of rows on CPU)
    noise = torch.nn.functional.linear(eps, factor.contiguous()) if factor.dim() == 2 else eps @ factor.mT
    if isinstance(motion, LinearMotion):
        noise = _add(noise, motion.offset.unsqueeze(-2))
        if u is not None:
            if motion.input_matrix is None:
                raise ValueError("u: this LinearMotion has no input_matrix")
            noise = _add(noise, u.unsqueeze(-2) @ motion.input_matrix.mT)
        F = motion.F
        if F.dim() == 2 and noise.shape == particles.shape:
            n = particles.shape[-1]
            # in place into the fresh noise tensor: one GEMM with beta = 1, no copy of the input
            rows = particles.shape[:-1].numel()
            return noise.view(rows, n).addmm_(particles.reshape(rows, n), F.mT.contiguous()).view(particles.shape)
        return particles @ F.mT + noise
    out = motion(particles.movedim(-2, 0), u=None if u is None else u.unsqueeze(0)).movedim(0, -2)
    return out + noise


def _predicted_measurement(measurement: MeasurementModel, particles: Tensor) -> Tensor:
    """``h(x)`` for particle sets ``(*B, Np, n)`` -> ``(*B, Np, m)``."""
    if isinstance(measurement, LinearMeasurement):
        return particles @ measurement.H.mT
    return measurement(particles.movedim(-2, 0)).movedim(0, -2)


def _sum_squares(x: Tensor) -> Tensor:
    """``(x ** 2).sum(-1)``; for a short last axis as a chain of ``addcmul`` over its columns, which
    on CPU is several times faster than a reduction over a tiny innermost axis."""
    m = x.shape[-1]
    if m > 8:
        return x.square().sum(-1)
    out = x[..., 0] * x[..., 0]
    for j in range(1, m):  # over the measurement components (m <= 8), not over runs or particles
        out = torch.addcmul(out, x[..., j], x[..., j])
    return out


def _whitening(cov: Tensor) -> tuple[Tensor, Tensor]:
    """``(L^{-1}, log det cov)`` with ``L L^T = cov``. Shapes: ``(..., m, m)`` -> same, ``(...)``.

    The factor is :func:`~torchmm.linalg.cholesky` (never raises; regularised where
    ``cov`` is not numerically positive definite)."""
    chol = cholesky(cov)
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    inv = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
    return inv, 2 * chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)


def gaussian_log_likelihood(resid: Tensor, cov: Tensor, observed: Tensor | None = None) -> Tensor:
    """Gaussian log-density of residuals of particle sets, with per-batch missing components.

    ``observed`` marks the measured components of each batch element (NaN = missing); missing
    components are marginalised out exactly (an all-missing element gives 0).

    Shapes:
        resid: ``(*B, Np, m)``; cov: ``(*P, m, m)`` broadcasting with ``*B``;
        observed: ``(*B, m)`` bool or None -> ``(*B, Np)``
    """
    m = resid.shape[-1]
    if observed is None:
        inv, logdet = _whitening(cov)
        count = torch.tensor(float(m), dtype=resid.dtype, device=resid.device)
    else:
        eye = torch.eye(m, dtype=resid.dtype, device=resid.device)
        resid = torch.where(observed.unsqueeze(-2), resid, torch.zeros((), dtype=resid.dtype, device=resid.device))
        pair = observed.unsqueeze(-1) & observed.unsqueeze(-2)
        inv, logdet = _whitening(torch.where(pair, cov, eye))
        count = observed.sum(-1).to(resid.dtype).unsqueeze(-1)
    white = resid @ inv.mT
    return -0.5 * (_sum_squares(white) + logdet.unsqueeze(-1) + count * math.log(2 * math.pi))


def _particle_log_likelihood(measurement: MeasurementModel, z: Tensor, particles: Tensor,
                             state_dependent_noise: bool, *,
                             need_predicted: bool = True) -> tuple[Tensor, Tensor | None]:
    """``log p(z | x)`` per particle and the predicted measurements (None unless ``need_predicted``
    or needed anyway).

    A linear measurement with unbatched ``H`` and ``R`` and no missing data is whitened before the
    particles are touched: ``L^{-1}(z - H x) = L^{-1} z - (L^{-1} H) x``, one matmul over them.

    Shapes:
        z: ``(*B, m)`` (NaN = missing); particles ``(*B, Np, n)`` -> ``(*B, Np)``, ``(*B, Np, m)``
    """
    missing = ~torch.isfinite(z)
    any_missing = bool(missing.any())
    if (not need_predicted and not state_dependent_noise and not any_missing
            and isinstance(measurement, LinearMeasurement) and measurement.H.dim() == 2):
        cov = measurement.noise_cov()
        if cov.dim() == 2:
            inv, logdet = _whitening(cov)
            white = torch.nn.functional.linear(particles, (inv @ measurement.H).contiguous())  # (*B, Np, m)
            white = _add(white, -(z @ inv.mT).unsqueeze(-2))
            m = z.shape[-1]
            const = logdet + m * math.log(2 * math.pi)
            return _sum_squares(white).add_(const).mul_(-0.5), None
    predicted = _predicted_measurement(measurement, particles)
    if state_dependent_noise:
        loglik = measurement.log_likelihood(z.unsqueeze(0), particles.movedim(-2, 0)).movedim(0, -1)
        return loglik, predicted
    observed = None if not any_missing else ~missing
    resid = z.unsqueeze(-2) - predicted
    return gaussian_log_likelihood(resid, measurement.noise_cov(), observed), predicted


def _check_noise_dtype(noise_dtype):
    if noise_dtype is None:
        return None
    if isinstance(noise_dtype, str):
        noise_dtype = getattr(torch, noise_dtype, None)
    if not isinstance(noise_dtype, torch.dtype) or not noise_dtype.is_floating_point:
        raise ValueError(f"noise_dtype: expected a floating-point torch dtype (e.g. torch.float32), got {noise_dtype!r}")
    return noise_dtype


def _check_generator(generator):
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"generator: expected a torch.Generator or None, got {type(generator).__name__}")
    return generator


def _check_likelihood_noise(measurement: MeasurementModel) -> None:
    """The particle weights need a positive definite measurement noise (a singular ``R`` makes the
    likelihood a point mass)."""
    try:
        cov = measurement.noise_cov()
    except (TypeError, ValueError, RuntimeError):
        return  # state-dependent by construction: checked when evaluated
    if isinstance(cov, Tensor):
        check_covariance(cov, "measurement.R", definite=True)


def _check_prior(filter: Filter, belief) -> None:
    """Entry-point checks of the Gaussian prior particles are drawn from."""
    if not isinstance(belief, GaussianBelief):
        raise TypeError(f"belief: expected a GaussianBelief prior to sample from, got {type(belief).__name__}")
    gaussian_batch(belief, filter.motion.state_dim)
    belief.validate("belief")
    check_filter_dtype(filter, belief, "belief")


def _particle_batch(belief, state_dim: int, name: str = "belief") -> torch.Size:
    """Batch shape of a particle belief, checked against the state dimension (shapes only)."""
    if not isinstance(belief, ParticleBelief):
        raise TypeError(f"{name}: expected a ParticleBelief, got {type(belief).__name__}")
    if belief.particles.shape[-1] != state_dim:
        raise ValueError(f"{name}: particles have state dimension {belief.particles.shape[-1]}, the model "
                         f"{state_dim}")
    return belief.log_weights.shape[:-1]


def _guard(log_evidence: Tensor, where: str) -> Tensor:
    degenerate = ~torch.isfinite(log_evidence)
    if bool(degenerate.any()):
        log.warning("%s: all particle weights vanished in %d of %d batch elements; their prior weights "
                    "are kept (extras['degenerate'])", where, int(degenerate.sum()), degenerate.numel())
    return degenerate


def _innovation(z: Tensor, predicted: Tensor, log_w: Tensor, cov: Tensor | None) -> tuple[Tensor, Tensor | None]:
    """Innovation ``z - E[h(x)]`` and ``Cov[h(x)] + R`` under normalised log-weights ``(*B, Np)``."""
    w = log_w.exp().unsqueeze(-1)
    mean = (w * predicted).sum(-2)
    if cov is None:
        return z - mean, None
    diff = predicted - mean.unsqueeze(-2)
    spread = (diff * w).mT @ diff
    return z - mean, symmetrize(spread + cov)


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
        ``"resampled"`` and ``"degenerate"`` ``(*B,)``.

    Examples:
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> g = torch.Generator().manual_seed(0)
        >>> pf = ParticleFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0), generator=g)
        >>> belief = pf.initial_belief(GaussianBelief(torch.zeros(4, 2), torch.eye(2)), 500)
        >>> out = pf.step(belief, torch.randn(4, 1, generator=g))
        >>> out.belief.particles.shape, out.log_likelihood.shape
        (torch.Size([4, 500, 2]), torch.Size([4]))
    """

    def __init__(self, motion: MotionModel, measurement: MeasurementModel, *, resampling: str = "systematic",
                 ess_threshold: float = 0.5, num_particles: int | None = None,
                 generator: torch.Generator | None = None, state_dependent_noise: bool = False,
                 noise_dtype: torch.dtype | None = None):
        super().__init__()
        check_model_pair(motion, measurement)
        if resampling not in RESAMPLING_SCHEMES:
            raise ValueError(f"resampling: expected one of {sorted(RESAMPLING_SCHEMES)}, got {resampling!r}")
        ess_threshold = as_float(ess_threshold, "ess_threshold", minimum=0.0)
        if num_particles is not None:
            num_particles = as_int(num_particles, "num_particles", minimum=1)
        self.motion, self.measurement = motion, measurement
        self.resampling, self.ess_threshold = resampling, ess_threshold
        self.num_particles = num_particles
        self.generator = _check_generator(generator)
        self.state_dependent_noise = bool(state_dependent_noise)
        self.noise_dtype = _check_noise_dtype(noise_dtype)
        if not self.state_dependent_noise:
            _check_likelihood_noise(measurement)

    def check_bank_member(self, name: str, num_modes: int) -> None:
        if self.num_particles is None and num_modes > 1:
            raise ValueError(f"{name}: a ParticleFilter inside IMM/GPB needs num_particles= (mixing merges the "
                             "M particle sets into M * Np particles; the filter resamples back to num_particles)")

    uses_generator = True

    def initial_belief(self, belief: GaussianBelief, num_particles: int | None = None, *,
                       generator: torch.Generator | None = None) -> ParticleBelief:
        """Sample a particle belief from a Gaussian prior (uniform weights).

        Shapes:
            belief: batch ``(*B,)`` -> particles ``(*B, Np, n)``
        """
        if isinstance(belief, ParticleBelief) and num_particles is None:  # already particles (e.g. in a bank)
            _particle_batch(belief, self.motion.state_dim)
            return belief.validate("belief")
        num = self.num_particles if num_particles is None else as_int(num_particles, "num_particles", minimum=1)
        if num is None:
            raise ValueError("num_particles: give it here or to the filter")
        _check_prior(self, belief)
        particles = sample_gaussian(belief, num, generator=self._generator(generator))
        log_w = torch.full(particles.shape[:-1], -math.log(num), dtype=particles.dtype, device=particles.device)
        return ParticleBelief(particles, log_w)

    def predict(self, belief: ParticleBelief, *, u: Tensor | None = None, motion: MotionModel | None = None,
                generator: torch.Generator | None = None) -> ParticleBelief:
        if motion is not None:
            return self.with_motion(motion).predict(belief, u=u, generator=generator)
        generator = self._generator(generator)
        _particle_batch(belief, self.motion.state_dim)
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
        z = check_measurement(z, self.measurement.meas_dim, _particle_batch(belief, self.motion.state_dim),
                              belief.particles)
        prior_log_w = normalize_log_probs(belief.log_weights)
        loglik, predicted = _particle_log_likelihood(self.measurement, z, belief.particles,
                                                     self.state_dependent_noise)
        loglik = torch.where(torch.isnan(loglik), -math.inf, loglik)
        joint = prior_log_w + loglik
        log_evidence = torch.logsumexp(joint, dim=-1)
        log_evidence = torch.where(any_observed(z), log_evidence, 0.0)  # exactly 0 without a datum
        degenerate = _guard(log_evidence, "ParticleFilter.update")
        post_log_w = torch.where(degenerate.unsqueeze(-1), prior_log_w, joint - log_evidence.unsqueeze(-1))
        posterior = ParticleBelief(belief.particles, post_log_w)
        posterior, resampled, ess = resample_where_needed(posterior, self.ess_threshold, self.resampling,
                                                          generator=self._generator(generator))
        cov = None if self.state_dependent_noise else self.measurement.noise_cov()
        innovation, innovation_cov = _innovation(z, predicted, prior_log_w, cov)
        return StepOutput(
            belief=posterior,
            prior=belief,
            log_likelihood=log_evidence,
            innovation=innovation,
            innovation_cov=innovation_cov,
            extras={"ess": ess, "resampled": resampled, "degenerate": degenerate},
        )


    def _generator(self, generator: torch.Generator | None) -> torch.Generator | None:
        """The call's random stream; the filter's ``generator`` (a default) when none is given."""
        return self.generator if generator is None else _check_generator(generator)


def _forced_cdf(probs: Tensor) -> Tensor:
    """Cumulative sums along -1, normalised, last entry exactly 1."""
    cdf = torch.cumsum(probs, dim=-1)
    cdf = cdf / cdf[..., -1:].clamp_min(torch.finfo(cdf.dtype).tiny)
    return torch.cat([cdf[..., :-1], torch.ones_like(cdf[..., -1:])], dim=-1)


def _stratified_points(shape, scheme: str, like: Tensor, generator) -> Tensor:
    """Points in ``[0, 1)`` for inverse-CDF sampling along the last axis of ``shape``."""
    n = shape[-1]
    if scheme == "multinomial":
        return torch.rand(shape, dtype=like.dtype, device=like.device, generator=generator)
    offsets = torch.arange(n, dtype=like.dtype, device=like.device)
    if scheme == "stratified":
        u = torch.rand(shape, dtype=like.dtype, device=like.device, generator=generator)
    else:  # systematic
        u = torch.rand((*shape[:-1], 1), dtype=like.dtype, device=like.device, generator=generator)
    return (offsets + u) / n


def mixing_indices(mode_log_probs: Tensor, log_transition: Tensor, within_log_weights: Tensor,
                   num_particles: int, scheme: str = "systematic", *,
                   generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    r"""Ancestors of the interaction step of a multiple-model particle filter.

    For every target model ``i``, ``Np`` ancestors ``(a, b)`` (model ``a``, particle ``b``) are drawn
    from ``p(a, b | i) = mu_a pi_ai w_{b|a} / c_i`` by one inverse-CDF pass over the product
    distribution (lexicographic in ``(a, b)``), with the points ``u`` of ``scheme`` (multinomial,
    stratified or systematic): the ancestor model ``a`` is the segment of the model CDF that holds
    ``u`` (for systematic points found by counting, see :func:`systematic_search`), and the
    particle is found by searching ``a + (u - C_{a-1}) / mu_{a|i}`` in the within-model CDFs laid
    end to end (row ``a`` shifted to ``(a, a + 1]``). Computed in float64 whatever the input dtype.

    ``scheme="two_stage"`` takes the same systematic points over the ancestor models, but the
    particle inside ancestor ``a`` is entry ``floor(Np_prev * inner)`` of one systematic resample of
    ``a``'s particles (drawn per run and model, shared by all targets ``i``; ``inner`` is the
    position of ``u`` inside ``a``'s segment): no search, ``O(1)`` per particle. It is unbiased,
    ``E[count of (a, b) for target i] = Np mu_{a|i} w_{b|a}`` (the resample's offset is uniform
    and independent of the cell ``floor(Np_prev * inner)``, whose expected number of hits is
    ``mu_{a|i}``), and keeps the systematic schemes' low variance; draws of different targets from
    the same ancestor share its resample.

    Returns:
        ``(indices, log_cbar)``: flat indices ``a * Np_prev + b`` ``(*B, M, Np)`` and the predicted
        mode log-probabilities ``log c_i = logsumexp_a(log mu_a + log pi_ai)`` ``(*B, M)``.

    Shapes:
        mode_log_probs: ``(*B, M)`` (normalised; inactive models ``-inf``);
        log_transition: ``(M, M)``; within_log_weights: ``(*B, M, Np_prev)`` -> see Returns
    """
    if scheme not in _INVERSE_CDF_SCHEMES:
        raise ValueError(f"scheme: the interaction step supports {_INVERSE_CDF_SCHEMES}, got {scheme!r}")
    joint = (mode_log_probs.unsqueeze(-1) + log_transition).double()  # (*B, a, i)
    log_cbar = torch.logsumexp(joint, dim=-2)  # (*B, i)
    mixing = normalize_log_probs(joint.mT, dim=-1).exp()  # (*B, i, a): mu_{a|i}
    cdf_models = _forced_cdf(mixing)
    batch, num_models = mixing.shape[:-2], mixing.shape[-1]
    shape = (*batch, num_models, num_particles)
    if scheme in ("systematic", "two_stage"):
        u0 = torch.rand((*shape[:-1], 1), dtype=torch.float64, device=cdf_models.device, generator=generator)
        u = torch.arange(num_particles, dtype=torch.float64, device=u0.device).add(u0).div_(num_particles)
        ancestor = systematic_search(cdf_models, u0, num_particles)  # (*B, i, Np)
    else:
        u = _stratified_points(shape, scheme, cdf_models, generator)
        ancestor = torch.searchsorted(cdf_models, u, right=True).clamp_max(num_models - 1)
    # position inside the ancestor's segment [C_{a-1}, C_a): per (run, i, a) tables, two gathers
    low = torch.cat([torch.zeros_like(cdf_models[..., :1]), cdf_models[..., :-1]], dim=-1)
    inv_width = (cdf_models - low).clamp_min_(torch.finfo(torch.float64).tiny).reciprocal_()
    eps = torch.finfo(torch.float64).eps
    inner = u.sub_(torch.gather(low, -1, ancestor)).mul_(torch.gather(inv_width, -1, ancestor)).clamp_(0.0, 1.0 - eps)
    # within-model CDFs (*B', M, Np_prev), last entry exactly 1
    w = within_log_weights.double()
    top = w.amax(-1, keepdim=True)
    if bool(((top <= 0) & (top > -100)).all()):  # normalised-like: exp cannot overflow or all underflow
        w = w.exp()
    else:
        w = (w - torch.where(torch.isfinite(top), top, torch.zeros_like(top))).exp_()
    cdf_within = torch.cumsum(w, dim=-1)
    cdf_within.div_(cdf_within[..., -1:].clamp_min(torch.finfo(torch.float64).tiny))
    cdf_within[..., -1] = 1.0
    num_prev = w.shape[-1]
    if scheme == "two_stage":
        # a systematic resample of every model's particles (one per run and model, by counting),
        # then the particle at index floor(Np_prev * inner) of the ancestor's resample: no search
        v0 = torch.rand((*batch, num_models, 1), dtype=torch.float64, device=w.device, generator=generator)
        resampled = systematic_search(cdf_within.expand(*batch, num_models, num_prev), v0, num_prev)
        base = ancestor.mul_(num_prev)  # a * Np_prev (ancestor is not used afterwards)
        slot = inner.mul_(num_prev).long().add_(base)  # inner <= 1 - eps: floor < Np_prev
        particle = torch.gather(resampled.flatten(-2), -1, slot.flatten(-2)).view(shape)
        return particle.add_(base), log_cbar.to(mode_log_probs.dtype)
    values = inner.add_(ancestor).flatten(-2)  # a + inner, (*B, M * Np)
    # rows shifted to (a, a + 1] and laid end to end: (*B', M * Np_prev)
    cdf_within.add_(torch.arange(num_models, dtype=torch.float64, device=w.device).unsqueeze(-1))
    cdf_within = cdf_within.flatten(-2).expand(*batch, num_models * w.shape[-1]).contiguous()
    flat = searchsorted_rows(cdf_within, values).clamp_max_(cdf_within.shape[-1] - 1)
    return flat.view(shape), log_cbar.to(mode_log_probs.dtype)


class MultipleModelParticleFilter(Filter):
    r"""Interacting multiple-model particle filter with ``Np`` particles per model.

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

    def __init__(self, motion: MotionModel, measurement: MeasurementModel, transition, num_particles: int, *,
                 mixing: str = "systematic", generator: torch.Generator | None = None,
                 innovation_stats: bool = True, noise_dtype: torch.dtype | None = None):
        super().__init__()
        check_model_pair(motion, measurement)
        if mixing not in _INVERSE_CDF_SCHEMES:
            raise ValueError(f"mixing: expected one of {_INVERSE_CDF_SCHEMES}, got {mixing!r}")
        num_particles = as_int(num_particles, "num_particles", minimum=1)
        self.motion, self.measurement = motion, measurement
        self.transition = as_transition(transition)
        self.num_modes = self.transition.num_modes
        self.num_particles = num_particles
        self.mixing, self.generator = mixing, _check_generator(generator)
        _check_likelihood_noise(measurement)
        self.innovation_stats = bool(innovation_stats)
        self.noise_dtype = _check_noise_dtype(noise_dtype)
        self._check_motion()

    def _check_motion(self) -> None:
        shape = getattr(self.motion, "param_batch_shape", None)
        if shape is not None and len(shape) > 0 and shape[-1] not in (1, self.num_modes):
            raise ValueError(f"motion: parameter batch {tuple(shape)} does not match {self.num_modes} modes")

    uses_generator = True

    def _generator(self, generator: torch.Generator | None) -> torch.Generator | None:
        """The call's random stream; the filter's ``generator`` (a default) when none is given."""
        return self.generator if generator is None else _check_generator(generator)

    def initial_belief(self, belief: GaussianBelief, mode_probs=None, *,
                       generator: torch.Generator | None = None) -> ModeBelief:
        """``Np`` particles per model, each set drawn independently from the Gaussian prior (32).

        Shapes:
            belief: batch ``(*B,)``; mode_probs ``(M,)`` or ``(*B, M)``, default uniform
            -> :class:`ModeBelief` with components of batch ``(*B, M)``
        """
        _check_prior(self, belief)
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
                log_probs = probs.log().expand(*batch, M)
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
        _particle_batch(comps, self.motion.state_dim)
        return belief.mode_log_probs.shape[:-1]

    def predict(self, belief: ModeBelief, *, u: Tensor | None = None, motion: MotionModel | None = None,
                generator: torch.Generator | None = None) -> ModeBelief:
        if motion is not None:
            return self.with_motion(motion).predict(belief, u=u, generator=generator)
        generator = self._generator(generator)
        self._check_belief(belief)
        comps = belief.components
        mode_log_probs = normalize_log_probs(belief.mode_log_probs)
        flat, log_cbar = mixing_indices(mode_log_probs, self.transition.log_matrix(), comps.log_weights,
                                        self.num_particles, self.mixing, generator=generator)
        batch = flat.shape[:-2]
        source = comps.particles.expand(*batch, *comps.particles.shape[-3:])
        n, per_run = source.shape[-1], source.shape[-3] * source.shape[-2]
        # one row gather over all runs: index into the (runs * M * Np_prev, n) particle table
        runs = torch.arange(batch.numel(), device=flat.device).view(*batch, 1, 1) * per_run
        ancestors = torch.index_select(source.reshape(source.shape[:-1].numel(), n), 0, (flat + runs).reshape(-1))
        ancestors = ancestors.view(*batch, self.num_modes, self.num_particles, n)
        particles = self._propagate(ancestors, u=u, log_cbar=log_cbar, generator=generator)
        # uniform within-model weights as a broadcast view (no memory; `_weigh` recognises it)
        log_w = torch.full((), -math.log(self.num_particles), dtype=particles.dtype,
                           device=particles.device).expand(particles.shape[:-1])
        return ModeBelief(log_cbar, ParticleBelief(particles, log_w))

    def _weigh(self, prior: ModeBelief, z: Tensor):
        """Weights (33)-(34) as per-model quantities (few passes over the particles).

        Returns ``(joint, per_model, log_evidence, degenerate, predicted, prior_within)`` with the
        unnormalised joint log-weights ``(*B, M, Np)`` and their per-model ``logsumexp`` ``(*B, M)``.
        """
        comps = prior.components
        loglik, predicted = _particle_log_likelihood(self.measurement, z.unsqueeze(-2), comps.particles, False,
                                                     need_predicted=self.innovation_stats)
        loglik = torch.nan_to_num(loglik, nan=-math.inf, posinf=math.inf, neginf=-math.inf)  # fresh, for add_
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
        log_evidence = torch.where(any_observed(z), log_evidence, 0.0)  # exactly 0 without a datum
        degenerate = _guard(log_evidence, type(self).__name__)
        if bool(degenerate.any()):
            keep = degenerate[..., None, None]
            joint = torch.where(keep, prior_within + prior_mode.unsqueeze(-1), joint)
            per_model = torch.where(degenerate[..., None], prior_mode, per_model)
        return joint, per_model, log_evidence, degenerate, predicted, prior_within, prior_mode

    def update(self, belief: ModeBelief, z: Tensor, *, sensor: MeasurementModel | None = None,
               generator: torch.Generator | None = None) -> StepOutput:
        if sensor is not None:
            return self.with_sensor(sensor).update(belief, z)
        z = check_measurement(z, self.measurement.meas_dim, self._check_belief(belief), belief.components.particles)
        joint, per_model, log_evidence, degenerate, predicted, prior_within, prior_mode = self._weigh(belief, z)
        safe_ev = torch.where(degenerate, torch.zeros_like(log_evidence), log_evidence)
        mode_log_probs = per_model - safe_ev.unsqueeze(-1)  # (34) summed over particles
        within = joint - per_model.unsqueeze(-1)
        finite = torch.isfinite(per_model)
        if not bool(finite.all()):
            within = torch.where(finite.unsqueeze(-1), within, torch.full_like(within, -math.log(within.shape[-1])))
        innovation = innovation_cov = None
        if self.innovation_stats:
            flat_prior = (prior_within + prior_mode.unsqueeze(-1)).flatten(-2)
            innovation, innovation_cov = _innovation(z, predicted.flatten(-3, -2), flat_prior,
                                                     self.measurement.noise_cov())
        # ESS of the normalised joint weights: 1 / sum_j p_j^2 sum_l v_jl^2 (within <= 0: exp is safe)
        sq = (2 * mode_log_probs).exp().mul_((2 * within).exp_().sum(-1)).sum(-1)
        extras = {"ess": 1.0 / sq, "mode_log_likelihood": per_model - prior_mode, "degenerate": degenerate,
                  "joint_log_weights": joint}
        return StepOutput(
            belief=ModeBelief(mode_log_probs, ParticleBelief(belief.components.particles, within)),
            prior=belief,
            log_likelihood=log_evidence,
            innovation=innovation,
            innovation_cov=innovation_cov,
            extras=extras,
        )

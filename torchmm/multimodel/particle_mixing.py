r"""The particle interaction of paper 003's multiple-model particle filter (split from
:mod:`torchmm.multimodel.particle` by concern, issue 47; re-exported there): the ``Np`` particles of model ``i``
drawn from the mixture of all particles of the previous step with weights ``mu_a pi_ai w_{b|a}``, one
inverse-CDF resampling of the product distribution (ancestor model, then particle inside it) per
``(run, i)`` (:func:`mixing_indices`), as an interaction of the engine (:class:`ParticleMixing`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

import torchmm.kernels.particle as particle_stages
from torchmm.beliefs import ModeBelief, ParticleBelief
from torchmm.beliefs.ops import normalize_log_probs
from torchmm.contract import Choice, Int, entry_point
from torchmm.filters.resampling import searchsorted_rows, systematic_search
from torchmm.multimodel.imm import Interaction
from torchmm.runtime import host_reads_ok
from torchmm.validation import as_int

__all__ = ["INVERSE_CDF_SCHEMES", "ParticleMixing", "mixing_indices"]

INVERSE_CDF_SCHEMES = ("multinomial", "stratified", "systematic", "two_stage")


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
                   generator: torch.Generator | None = None, _defer: bool = False) -> tuple[Tensor, Tensor]:
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
        (``_defer``, internal: where the compiled ``two_stage`` kernel runs, the indices come as a
        zero-argument callable that waits for them; the kernel runs meanwhile in a worker thread.)

    Shapes:
        mode_log_probs: ``(*B, M)`` (normalised; inactive models ``-inf``);
        log_transition: ``(M, M)``; within_log_weights: ``(*B, M, Np_prev)`` -> see Returns
    """
    if scheme not in INVERSE_CDF_SCHEMES:
        raise ValueError(f"scheme: the interaction step supports {INVERSE_CDF_SCHEMES}, got {scheme!r}")
    joint = (mode_log_probs.unsqueeze(-1) + log_transition).double()  # (*B, a, i)
    log_cbar = torch.logsumexp(joint, dim=-2)  # (*B, i)
    mixing = normalize_log_probs(joint.mT, dim=-1).exp()  # (*B, i, a): mu_{a|i}
    cdf_models = _forced_cdf(mixing)
    batch, num_models = mixing.shape[:-2], mixing.shape[-1]
    shape = (*batch, num_models, num_particles)
    # two_stage on CPU tensors: the points, ancestors and slots in one compiled pass (below)
    fused = scheme == "two_stage" and particle_stages.applies(cdf_models)
    if scheme in ("systematic", "two_stage"):
        u0 = torch.rand((*shape[:-1], 1), dtype=torch.float64, device=cdf_models.device, generator=generator)
        if not fused:
            u = torch.arange(num_particles, dtype=torch.float64, device=u0.device).add(u0).div_(num_particles)
            ancestor = systematic_search(cdf_models, u0, num_particles)  # (*B, i, Np)
    else:
        u = _stratified_points(shape, scheme, cdf_models, generator)
        ancestor = torch.searchsorted(cdf_models, u, right=True).clamp_max(num_models - 1)
    if not fused:
        # position inside the ancestor's segment [C_{a-1}, C_a): per (run, i, a) tables, two gathers
        low = torch.cat([torch.zeros_like(cdf_models[..., :1]), cdf_models[..., :-1]], dim=-1)
        inv_width = (cdf_models - low).clamp_min_(torch.finfo(torch.float64).tiny).reciprocal_()
        eps = torch.finfo(torch.float64).eps
        inner = u.sub_(torch.gather(low, -1, ancestor)).mul_(torch.gather(inv_width, -1, ancestor))
        inner = inner.clamp_(0.0, 1.0 - eps)
    # within-model CDFs (*B', M, Np_prev), last entry exactly 1
    w = within_log_weights.double()
    top = w.amax(-1, keepdim=True)
    # normalised-like weights (exp can neither overflow nor all underflow) are exponentiated as they
    # are, others after subtracting their maximum: one pass, decided without a host read
    normalised_like = ((top <= 0) & (top > -100)).all()
    if host_reads_ok(w) and bool(normalised_like):  # on the CPU: the shift is 0, skip its pass
        w = w.exp()
    else:
        w = (w - torch.where(normalised_like | ~torch.isfinite(top), 0.0, top)).exp_()
    num_prev = w.shape[-1]
    if fused:  # the CDFs, points, ancestors and slots in one compiled pass (torchmm.kernels.particle)
        v0 = torch.rand((*batch, num_models, 1), dtype=torch.float64, device=w.device, generator=generator)
        rows = batch.numel()
        flat = particle_stages.two_stage_indices(
            cdf_models.reshape(rows, num_models, num_models), u0.reshape(rows, num_models),
            w.expand(*batch, num_models, num_prev).reshape(rows, num_models, num_prev),
            v0.reshape(rows, num_models), num_particles, background=_defer)
        if _defer:
            return (lambda: flat.result().view(shape)), log_cbar.to(mode_log_probs.dtype)
        return flat.view(shape), log_cbar.to(mode_log_probs.dtype)
    cdf_within = torch.cumsum(w, dim=-1)
    cdf_within.div_(cdf_within[..., -1:].clamp_min(torch.finfo(torch.float64).tiny))
    cdf_within[..., -1:].fill_(1.0)  # (fill_ with a Python number: no host-to-device copy on a GPU)
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


class ParticleMixing(Interaction):
    """The particle interaction of paper 003 (27)/(33): the ``Np`` particles of model ``i`` drawn
    from the mixture of every model's particles with weights ``mu_a pi_ai w_{b|a} / c_i`` in one
    inverse-CDF pass over the product distribution (:func:`mixing_indices`).

    An :class:`~torchmm.multimodel.Interaction` for particle banks: ``MultipleModelFilter(
    ParticleFilter(bank, measurement, num_particles=Np), transition, ParticleMixing())`` is the
    multiple-model PF over the engine's generic update (:class:`MultipleModelParticleFilter` is the
    same estimator with its fused joint-weight update).

    Args:
        scheme: ``"systematic"`` (default), ``"stratified"``, ``"multinomial"`` or ``"two_stage"``.
        num_particles: ``Np`` per model after the interaction (default: the previous count).

    Shapes:
        belief: mode belief over particle sets ``(*B, M, Np_prev, n)`` -> start beliefs
        ``(*B, M, Np, n)`` with uniform weights (a broadcast view) and ``log c_i`` ``(*B, M)``
    """

    uses_generator = True

    @entry_point(scheme=Choice(*INVERSE_CDF_SCHEMES), num_particles=Int(1, optional=True))
    def __init__(self, scheme: str = "systematic", num_particles: int | None = None):
        self.scheme = scheme
        self.num_particles = None if num_particles is None else as_int(num_particles, "num_particles", minimum=1)

    def _indices(self, belief: ModeBelief, transition, generator=None, defer: bool = False):
        """The ancestors without the gather: ``(flat, log_cbar)`` of :func:`mixing_indices` (with
        ``defer``: ``flat`` may be a callable that waits for it) and the number drawn per model."""
        comps = belief.components
        if not isinstance(comps, ParticleBelief):
            raise TypeError(f"belief: ParticleMixing needs particle mode filters, got {type(comps).__name__} components")
        num = comps.particles.shape[-2] if self.num_particles is None else self.num_particles
        mode_log_probs = normalize_log_probs(belief.mode_log_probs)
        flat, log_cbar = mixing_indices(mode_log_probs, transition.log_matrix(), comps.log_weights, num,
                                        self.scheme, generator=generator, _defer=defer)
        return flat, log_cbar, num

    def __call__(self, belief: ModeBelief, transition, generator=None) -> ModeBelief:
        flat, log_cbar, num = self._indices(belief, transition, generator)
        comps = belief.components
        batch = flat.shape[:-2]
        source = comps.particles.expand(*batch, *comps.particles.shape[-3:])
        n, per_run = source.shape[-1], source.shape[-3] * source.shape[-2]
        # one row gather over all runs: index into the (runs * M * Np_prev, n) particle table
        runs = torch.arange(batch.numel(), device=flat.device).view(*batch, 1, 1) * per_run
        ancestors = torch.index_select(source.reshape(source.shape[:-1].numel(), n), 0, (flat + runs).reshape(-1))
        ancestors = ancestors.view(*batch, flat.shape[-2], num, n)
        # uniform within-model weights as a broadcast view (no memory; the joint update recognises it)
        log_w = torch.full((), -math.log(num), dtype=ancestors.dtype, device=ancestors.device).expand(ancestors.shape[:-1])
        return ModeBelief(log_cbar, ParticleBelief(ancestors, log_w))

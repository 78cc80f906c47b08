"""Particle belief: weighted samples with log-weights and an arbitrary batch shape."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from torchmm.beliefs.base import Belief, register_belief
from torchmm.beliefs.gaussian import GaussianBelief
from torchmm.beliefs.ops import effective_sample_size, normalize_log_probs, symmetrize

__all__ = ["ParticleBelief"]


@register_belief
@dataclass(frozen=True)
class ParticleBelief(Belief):
    """A batch of weighted particle sets.

    Log-weights need not be normalised; every statistic normalises them first.

    Shapes:
        particles: ``(*B, Np, n)``
        log_weights: ``(*B, Np)``
    """

    particles: Tensor
    log_weights: Tensor

    event_dims: ClassVar[dict[str, int]] = {"particles": 2, "log_weights": 1}

    def __post_init__(self):
        p, w = self.particles, self.log_weights
        if p.dim() < 2 or w.dim() < 1 or w.shape[-1] != p.shape[-2]:
            raise ValueError(f"log_weights: expected shape (*B, Np) for particles (*B, Np, n); got particles "
                             f"{tuple(p.shape)}, log_weights {tuple(w.shape)}")

    def validate(self, name: str = "belief") -> ParticleBelief:
        """Finite particles; log-weights not NaN or ``+inf``, at least one finite per particle set."""
        self.batch_shape
        if self.particles.shape[-2] == 0:
            raise ValueError(f"{name}.particles: a particle set needs at least one particle, got shape "
                             f"{tuple(self.particles.shape)}")
        if not bool(torch.isfinite(self.particles.detach()).all()):
            raise ValueError(f"{name}.particles: contains NaN or infinite entries")
        w = self.log_weights.detach()
        if bool(torch.isnan(w).any()) or bool((w == math.inf).any()):
            raise ValueError(f"{name}.log_weights: contains NaN or +inf (log-weights are finite or -inf)")
        if w.numel() and not bool(torch.isfinite(w).any(-1).all()):
            raise ValueError(f"{name}.log_weights: a particle set has no particle of positive weight")
        return self

    @property
    def state_dim(self) -> int:
        return self.particles.shape[-1]

    @property
    def num_particles(self) -> int:
        return self.particles.shape[-2]

    def normalized(self) -> ParticleBelief:
        """Same belief with log-weights normalised to ``logsumexp = 0``."""
        return ParticleBelief(self.particles, normalize_log_probs(self.log_weights))

    def effective_sample_size(self) -> Tensor:
        """``1 / sum(w^2)`` of the normalised weights (:func:`torchmm.beliefs.ops.effective_sample_size`:
        exactly ``Np`` for equal weights). Shape ``(*B,)``."""
        return effective_sample_size(self.log_weights)

    def entropy(self) -> Tensor:
        """Shannon entropy of the normalised weights ``-sum_i w_i log w_i``, shape ``(*B,)``."""
        log_w = normalize_log_probs(self.log_weights)
        p = log_w.exp()
        return -torch.where(p > 0, p * log_w, torch.zeros_like(p)).sum(-1)

    def estimate(self) -> GaussianBelief:
        """Weighted mean and covariance as a Gaussian belief with batch ``(*B,)``."""
        weights = normalize_log_probs(self.log_weights).exp()
        mean = torch.einsum("...p,...pn->...n", weights, self.particles)
        diff = self.particles - mean.unsqueeze(-2)
        cov = torch.einsum("...p,...pn,...pm->...nm", weights, diff, diff)
        return GaussianBelief(mean, symmetrize(cov))

    def mix(self, weights: Tensor) -> ParticleBelief:
        """Exact mixtures over batch axis -1: the union of the K particle sets, reweighted.

        The particle count grows to ``K * Np``; a particle filter resamples back.

        Shapes:
            self: batch ``(*B, K)``; weights: ``(*B, K, J)`` (columns sum to one)
            -> batch ``(*B, J)``, ``K * Np`` particles
        """
        log_w = normalize_log_probs(self.log_weights)  # (*B, K, Np)
        combined = weights.log().unsqueeze(-1) + log_w.unsqueeze(-2)  # (*B, K, J, Np)
        combined = combined.movedim(-3, -2)  # (*B, J, K, Np)
        batch, num_k, num_p, n = self.particles.shape[:-3], *self.particles.shape[-3:]
        num_j = weights.shape[-1]
        particles = self.particles.unsqueeze(-4).expand(*batch, num_j, num_k, num_p, n)
        return ParticleBelief(
            particles.reshape(*batch, num_j, num_k * num_p, n),
            combined.reshape(*combined.shape[:-2], num_k * num_p),
        )

    def collapse(self, weights: Tensor) -> ParticleBelief:
        """The mixture over batch axis -1 as one particle set. ``weights``: ``(*B, K)``."""
        return self.mix(weights.unsqueeze(-1)).select(-1, 0)

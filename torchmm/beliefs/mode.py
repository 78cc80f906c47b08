"""Mode belief: a discrete mode distribution with one component belief per mode."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from torchmm.beliefs.base import Belief, register_belief
from torchmm.beliefs.gaussian import GaussianBelief
from torchmm.beliefs.ops import normalize_log_probs, symmetrize
from torchmm.beliefs.particle import ParticleBelief
from torchmm.validation import STOCHASTIC_ATOL, broadcast_shape, host_array

__all__ = ["ModeBelief", "ModelSetBelief"]


@register_belief
@dataclass(frozen=True)
class ModeBelief(Belief):
    """Mode log-probabilities and per-mode component beliefs (any belief type).

    The mode axis is the last batch axis of ``components``, so mixing over modes is one
    ``einsum`` whatever the component type is (Gaussian for IMM/GPB, particles for MM-PF).

    Shapes:
        mode_log_probs: ``(*B, M)`` (normalised: ``logsumexp = 0``)
        components: a belief with batch ``(*B, M)``
    """

    mode_log_probs: Tensor
    components: Belief

    event_dims: ClassVar[dict[str, int]] = {"mode_log_probs": 1}

    def __post_init__(self):
        if self.mode_log_probs.dim() < 1:
            raise ValueError(f"mode_log_probs: expected shape (*B, M), got {tuple(self.mode_log_probs.shape)}")
        if not isinstance(self.components, Belief):
            raise TypeError(f"components: expected a belief with batch (*B, M), got {type(self.components).__name__}")

    def validate(self, name: str = "belief") -> ModeBelief:
        """Mode log-probabilities normalised (not NaN, probabilities summing to 1 within 1e-5), the
        components' batch ending with the ``M`` modes, and the components valid themselves."""
        lp = self.mode_log_probs.detach()
        small = host_array(lp)  # (a small CPU tensor: in NumPy, microseconds)
        if small is not None:
            bad = not (small < math.inf).all()  # (NaN or +inf: -inf is a probability 0)
            # (clipped at 1: no overflow, and a log-probability above 1 is unnormalised either way)
            unnormalised = not bad and small.size and bool(
                (np.abs(np.exp(np.minimum(small, 1.0)).sum(-1) - 1) > STOCHASTIC_ATOL).any())
        else:
            bad = bool(torch.isnan(lp).any()) or bool((lp == math.inf).any())
            unnormalised = lp.numel() and bool(((lp.exp().sum(-1) - 1).abs() > STOCHASTIC_ATOL).any())
        if bad:
            raise ValueError(f"{name}.mode_log_probs: contains NaN or +inf")
        if unnormalised:
            raise ValueError(f"{name}.mode_log_probs: probabilities must sum to 1 (normalised log-probabilities)")
        comp_batch = self.components.batch_shape
        if not comp_batch or comp_batch[-1] not in (1, self.num_modes):
            raise ValueError(f"{name}.components: batch {tuple(comp_batch)} must end with the {self.num_modes} "
                             "modes")
        try:  # (the batch shape of the mode belief: its components' without the modes, once)
            broadcast_shape(lp.shape[:-1], comp_batch[:-1])
        except RuntimeError:
            self.batch_shape  # (the error naming every field's batch)
        self.components.validate(f"{name}.components")
        return self

    @property
    def num_modes(self) -> int:
        return self.mode_log_probs.shape[-1]

    @property
    def mode_probs(self) -> Tensor:
        """``exp(mode_log_probs)``, shape ``(*B, M)``."""
        return self.mode_log_probs.exp()

    def output_log_weights(self) -> Tensor:
        """The log-weights of the output combination ``(*B, M)``: :meth:`collapse` (and, for Gaussian
        components, :meth:`estimate`) is the components' moment-matched mixture with these weights.
        Here the mode log-probabilities."""
        return self.mode_log_probs

    def collapse(self) -> Belief:
        """The mode-marginal belief (moment-matched for Gaussian components), batch ``(*B,)``."""
        return self.components.collapse(self.output_log_weights().exp())

    def estimate(self) -> GaussianBelief:
        """Overall mean and covariance (the IMM output combination), batch ``(*B,)``."""
        return self.collapse().estimate()


@register_belief
@dataclass(frozen=True)
class ModelSetBelief(ModeBelief):
    """A :class:`ModeBelief` with the model set a variable-structure policy selected.

    ``mode_log_probs`` are the probabilities the recursion carries (restricted to the set when the
    selection is fed back, ``-inf`` outside it); :meth:`estimate` is always over the set (paper
    003's (31) for particle components; the moment-matched collapse over the set otherwise).

    Shapes:
        mode_log_probs: ``(*B, M)``; components: any belief with batch ``(*B, M)`` (for particle
        components ``ParticleBelief`` with particles ``(*B, M, Np, n)``); active: ``(*B, M)`` bool
    """

    active: Tensor

    event_dims: ClassVar[dict[str, int]] = {"mode_log_probs": 1, "active": 1}

    def restricted_log_probs(self) -> Tensor:
        """Mode log-probabilities renormalised on the active set, ``(*B, M)``."""
        restricted = torch.where(self.active, self.mode_log_probs, -math.inf)
        return normalize_log_probs(restricted)

    def output_log_weights(self) -> Tensor:
        """The active set's renormalised log-probabilities (:meth:`restricted_log_probs`)."""
        return self.restricted_log_probs()

    def estimate(self) -> GaussianBelief:
        """Weighted mean and covariance over the active models, batch ``(*B,)``."""
        comps = self.components
        if not isinstance(comps, ParticleBelief):
            return self.collapse().estimate()
        # particles: (31), the weighted moments of every active model's particles in one pass
        w = (self.restricted_log_probs().unsqueeze(-1) + normalize_log_probs(comps.log_weights)).exp()
        w = w.flatten(-2)
        particles = comps.particles.flatten(-3, -2)
        mean = (w.unsqueeze(-1) * particles).sum(-2)
        diff = particles - mean.unsqueeze(-2)
        cov = (diff * w.unsqueeze(-1)).mT @ diff
        return GaussianBelief(mean, symmetrize(cov))

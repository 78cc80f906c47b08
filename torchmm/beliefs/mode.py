"""Mode belief: a discrete mode distribution with one component belief per mode."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from torch import Tensor

from torchmm.beliefs.base import Belief, register_belief
from torchmm.beliefs.gaussian import GaussianBelief

__all__ = ["ModeBelief"]


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

    @property
    def num_modes(self) -> int:
        return self.mode_log_probs.shape[-1]

    @property
    def mode_probs(self) -> Tensor:
        """``exp(mode_log_probs)``, shape ``(*B, M)``."""
        return self.mode_log_probs.exp()

    def collapse(self) -> Belief:
        """The mode-marginal belief (moment-matched for Gaussian components), batch ``(*B,)``."""
        return self.components.collapse(self.mode_probs)

    def estimate(self) -> GaussianBelief:
        """Overall mean and covariance (the IMM output combination), batch ``(*B,)``."""
        return self.collapse().estimate()

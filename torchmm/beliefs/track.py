"""A target-side mode belief with a separate source-only track (the multi-rate baselines IMM-FU, VSIMM)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

from torch import Tensor

from torchmm.beliefs.base import Belief, register_belief
from torchmm.beliefs.gaussian import GaussianBelief
from torchmm.beliefs.mode import ModeBelief

__all__ = ["SourceTrackBelief"]


@register_belief
@dataclass(frozen=True)
class SourceTrackBelief(Belief):
    """A target-side mode belief and the separate source-only IMM track, same batch ``(*B,)``.

    ``estimate()``, ``mode_log_probs`` and ``mode_probs`` are the target side's.

    Shapes:
        target: :class:`ModeBelief`, batch ``(*B,)``; source: :class:`ModeBelief`, batch ``(*B,)``
    """

    target: ModeBelief
    source: ModeBelief

    event_dims: ClassVar[dict[str, int]] = {}

    def map_tensors(self, fn: Callable[[Tensor, int], Tensor]) -> SourceTrackBelief:
        return SourceTrackBelief(self.target.map_tensors(fn), self.source.map_tensors(fn))

    @property
    def mode_log_probs(self) -> Tensor:
        return self.target.mode_log_probs

    @property
    def mode_probs(self) -> Tensor:
        return self.target.mode_probs

    def estimate(self) -> GaussianBelief:
        return self.target.estimate()

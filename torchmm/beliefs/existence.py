"""Track beliefs with the probability that the target exists (IPDA, JIPDA): over one Gaussian
(:class:`ExistenceBelief`) or over an IMM's modes (:class:`ModeExistenceBelief`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from torchmm.beliefs.base import Belief, register_belief
from torchmm.beliefs.gaussian import GaussianBelief
from torchmm.beliefs.mode import ModeBelief
from torchmm.validation import check_covariance

__all__ = ["ExistenceBelief", "ModeExistenceBelief", "with_existence"]


@register_belief
@dataclass(frozen=True)
class ExistenceBelief(Belief):
    """The target's state given that it exists, ``N(mean, cov)``, and the probability that it exists.

    Shapes:
        mean ``(*B, n)``, cov ``(*B, n, n)``, log_existence ``(*B,)`` (``log P(exists)``)
    """

    mean: Tensor
    cov: Tensor
    log_existence: Tensor

    event_dims: ClassVar[dict[str, int]] = {"mean": 1, "cov": 2, "log_existence": 0}

    def __post_init__(self):
        mean, cov = self.mean, self.cov
        if mean.dim() < 1 or cov.dim() < 2 or cov.shape[-2:] != (mean.shape[-1], mean.shape[-1]):
            raise ValueError(f"cov: expected shape (*B, n, n) for mean (*B, n); got mean {tuple(mean.shape)}, "
                             f"cov {tuple(cov.shape)}")

    def validate(self, name: str = "belief") -> ExistenceBelief:
        """Finite mean, PSD ``cov`` and ``log_existence`` in ``[-inf, 0]`` (``-inf``: existence 0)."""
        check_existence_belief(self, name)
        return self

    @property
    def existence(self) -> Tensor:
        """``P(exists)``, ``(*B,)``."""
        return self.log_existence.exp()

    @property
    def state(self) -> GaussianBelief:
        """The state belief given existence."""
        return GaussianBelief(self.mean, self.cov)

    def estimate(self) -> GaussianBelief:
        """The state estimate given existence (what a confirmed track reports)."""
        return self.state


@register_belief
@dataclass(frozen=True)
class ModeExistenceBelief(Belief):
    """An IMM track's state given that the target exists (mode log-probabilities and per-mode
    components, as :class:`~torchmm.ModeBelief`) and the probability that it exists (IMM-IPDA).

    Shapes:
        mode_log_probs ``(*B, M)``, components: a belief with batch ``(*B, M)``, log_existence ``(*B,)``
    """

    mode_log_probs: Tensor
    components: Belief
    log_existence: Tensor

    event_dims: ClassVar[dict[str, int]] = {"mode_log_probs": 1, "log_existence": 0}

    def validate(self, name: str = "belief") -> ModeExistenceBelief:
        """The mode belief's checks and ``log_existence`` in ``[-inf, 0]``."""
        check_existence_belief(self, name)
        return self

    @property
    def existence(self) -> Tensor:
        """``P(exists)``, ``(*B,)``."""
        return self.log_existence.exp()

    @property
    def state(self) -> ModeBelief:
        """The mode belief given existence."""
        return ModeBelief(self.mode_log_probs, self.components)

    def estimate(self) -> GaussianBelief:
        """The moment-matched state estimate given existence."""
        return self.state.estimate()


def with_existence(state, log_existence: Tensor) -> ExistenceBelief | ModeExistenceBelief:
    """``state`` (a :class:`~torchmm.GaussianBelief` or a :class:`~torchmm.ModeBelief`) with
    ``log P(exists)``.

    Shapes: state batch ``(*B,)``, log_existence ``(*B,)``."""
    if isinstance(state, GaussianBelief):
        return ExistenceBelief(state.mean, state.cov, log_existence)
    if isinstance(state, ModeBelief):
        return ModeExistenceBelief(state.mode_log_probs, state.components, log_existence)
    raise TypeError(f"belief: a target's existence goes with a GaussianBelief or an IMM's ModeBelief, got "
                    f"{type(state).__name__}")


def check_existence_belief(belief, name: str) -> None:
    """The values of a belief with a ``state`` and ``log_existence`` (an entry point's check)."""
    try:
        belief.batch_shape
    except ValueError as err:
        raise ValueError(f"{name}: {err}") from None
    state = belief.state
    if isinstance(state, GaussianBelief):
        if not bool(torch.isfinite(belief.mean.detach()).all()):
            raise ValueError(f"{name}.mean: contains NaN or infinite entries")
        check_covariance(belief.cov, f"{name}.cov")
    else:
        state.validate(name)
    log_e = belief.log_existence.detach()
    if bool((log_e > 0).any()) or bool(log_e.isnan().any()):
        raise ValueError(f"{name}.log_existence: must be a log-probability (<= 0, not NaN; -inf: existence 0)")

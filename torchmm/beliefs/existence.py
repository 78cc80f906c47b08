"""A Gaussian track belief with the probability that its target exists (IPDA)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from torchmm.beliefs.base import Belief, register_belief
from torchmm.beliefs.gaussian import GaussianBelief
from torchmm.validation import check_covariance

__all__ = ["ExistenceBelief"]


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


def check_existence_belief(belief, name: str) -> None:
    """The values of a belief with ``mean``, ``cov`` and ``log_existence`` (an entry point's check)."""
    try:
        belief.batch_shape
    except ValueError as err:
        raise ValueError(f"{name}: {err}") from None
    if not bool(torch.isfinite(belief.mean.detach()).all()):
        raise ValueError(f"{name}.mean: contains NaN or infinite entries")
    check_covariance(belief.cov, f"{name}.cov")
    log_e = belief.log_existence.detach()
    if bool((log_e > 0).any()) or bool(log_e.isnan().any()):
        raise ValueError(f"{name}.log_existence: must be a log-probability (<= 0, not NaN; -inf: existence 0)")

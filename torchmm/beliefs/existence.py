"""A Gaussian track belief with the probability that its target exists (IPDA)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

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
        """Finite mean, PSD ``cov`` and ``log_existence`` in ``[-inf, 0]``."""
        super().validate(name)
        check_covariance(self.cov, f"{name}.cov")
        if bool((self.log_existence.detach() > 0).any()) or bool(self.log_existence.detach().isnan().any()):
            raise ValueError(f"{name}.log_existence: must be a log-probability (<= 0, not NaN)")
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

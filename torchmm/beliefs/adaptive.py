"""The Gaussian state belief with an inverse-Wishart posterior of the measurement noise (VBAKF-PR)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from torch import Tensor

from torchmm.beliefs.base import Belief, register_belief
from torchmm.beliefs.gaussian import GaussianBelief
from torchmm.validation import check_covariance

__all__ = ["AdaptiveGaussianBelief"]


@register_belief
@dataclass(frozen=True)
class AdaptiveGaussianBelief(Belief):
    """Gaussian state belief plus the inverse-Wishart posterior ``IW(r_dof, r_scale)`` of ``R``.

    Shapes:
        mean ``(*B, n)``, cov ``(*B, n, n)``, r_dof ``(*B,)``, r_scale ``(*B, m, m)``
    """

    mean: Tensor
    cov: Tensor
    r_dof: Tensor
    r_scale: Tensor

    event_dims: ClassVar[dict[str, int]] = {"mean": 1, "cov": 2, "r_dof": 0, "r_scale": 2}

    def __post_init__(self):
        mean, cov, scale = self.mean, self.cov, self.r_scale
        if mean.dim() < 1 or cov.dim() < 2 or cov.shape[-2:] != (mean.shape[-1], mean.shape[-1]):
            raise ValueError(f"cov: expected shape (*B, n, n) for mean (*B, n); got mean {tuple(mean.shape)}, "
                             f"cov {tuple(cov.shape)}")
        if scale.dim() < 2 or scale.shape[-1] != scale.shape[-2]:
            raise ValueError(f"r_scale: expected shape (*B, m, m), got {tuple(scale.shape)}")

    def validate(self, name: str = "belief") -> AdaptiveGaussianBelief:
        """Finite fields, PSD ``cov``, positive definite ``r_scale`` and ``r_dof > m + 1``."""
        super().validate(name)
        check_covariance(self.cov, f"{name}.cov")
        check_covariance(self.r_scale, f"{name}.r_scale", definite=True)
        m = self.r_scale.shape[-1]
        if bool((self.r_dof.detach() <= m + 1).any()):
            raise ValueError(f"{name}.r_dof: must exceed m + 1 = {m + 1} (a proper inverse-Wishart mean)")
        return self

    @property
    def state_dim(self) -> int:
        return self.mean.shape[-1]

    def estimate(self) -> GaussianBelief:
        return GaussianBelief(self.mean, self.cov)

    def noise_cov(self) -> Tensor:
        """``R^ = U / (u - m - 1)``. Shapes: ``(*B, m, m)``."""
        m = self.r_scale.shape[-1]
        return self.r_scale / (self.r_dof - m - 1)[..., None, None]

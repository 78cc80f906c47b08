"""Gaussian belief: mean and covariance with an arbitrary batch shape."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from torchmm.beliefs.base import Belief, register_belief
from torchmm.beliefs.ops import mix_gaussians
from torchmm.linalg import cholesky, cholesky_diagonal
from torchmm.validation import as_tensor, broadcast_shape, check_covariance, check_shape
from torchmm.contract import Cov, DType, Device, Finite, entry_point

__all__ = ["GaussianBelief"]


def _floating(value, name: str, like=None) -> Tensor:
    """``value`` as a floating tensor (lists, integer tensors: the default dtype or ``like``'s)."""
    if isinstance(value, Tensor):
        if value.is_floating_point():
            return value
        if value.is_complex():
            raise TypeError(f"{name}: expected real numbers, got dtype {value.dtype}")
    elif isinstance(value, str) or value is None:
        raise TypeError(f"{name}: expected a tensor, got {type(value).__name__}")
    dtype = like.dtype if isinstance(like, Tensor) and like.is_floating_point() else torch.get_default_dtype()
    try:
        return torch.as_tensor(value, dtype=dtype)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"{name}: cannot convert to a tensor ({err})") from None


@register_belief
@dataclass(frozen=True)
class GaussianBelief(Belief):
    """A batch of Gaussian beliefs ``N(mean, cov)``.

    Shapes:
        mean: ``(*B, n)``
        cov: ``(*B, n, n)``

    Batch dims of ``mean`` and ``cov`` broadcast (a shared covariance may be ``(n, n)``).

    Examples:
        >>> b = GaussianBelief(torch.zeros(4, 2), torch.eye(2).expand(4, 2, 2))
        >>> b.batch_shape, b.state_dim
        (torch.Size([4]), 2)
    """

    mean: Tensor
    cov: Tensor

    event_dims: ClassVar[dict[str, int]] = {"mean": 1, "cov": 2}
    finite_checked_by_subclass: ClassVar[tuple[str, ...]] = ("cov",)  # (check_covariance: finite first)

    def __post_init__(self):
        # shapes only (no values: this runs at every step); lists and integer tensors are converted
        mean, cov = self.mean, self.cov
        if not (isinstance(mean, Tensor) and mean.is_floating_point()):
            mean = _floating(mean, "mean")
            object.__setattr__(self, "mean", mean)
        if not (isinstance(cov, Tensor) and cov.is_floating_point()):
            cov = _floating(cov, "cov", mean)
            object.__setattr__(self, "cov", cov)
        if mean.dim() < 1 or cov.dim() < 2 or cov.shape[-1] != mean.shape[-1] or cov.shape[-2] != mean.shape[-1]:
            raise ValueError(f"cov: expected shape (*B, n, n) for mean (*B, n); got mean {tuple(mean.shape)}, "
                             f"cov {tuple(cov.shape)}")

    def validate(self, name: str = "belief") -> GaussianBelief:
        """Finite mean, symmetric PSD covariance (see :meth:`Belief.validate`; the covariance's finiteness is
        its own check's, with the same message)."""
        super().validate(name)
        check_covariance(self.cov, f"{name}.cov")
        return self

    @classmethod
    @entry_point(mean=Finite(check=False), cov=Cov(check=False), dtype=DType(), device=Device())
    def create(cls, mean, cov, *, dtype=None, device=None) -> GaussianBelief:
        """Validated constructor: converts to tensors, checks shapes and that ``cov`` is PSD."""
        mean = as_tensor(mean, "mean", dtype=dtype, device=device)
        cov = as_tensor(cov, "cov", dtype=mean.dtype, device=mean.device)
        if mean.dim() < 1:
            raise ValueError(f"mean: expected shape (*B, n), got {tuple(mean.shape)}")
        check_shape(cov, "cov", (mean.shape[-1], mean.shape[-1]))
        check_covariance(cov, "cov")
        try:
            broadcast_shape(mean.shape[:-1], cov.shape[:-2])
        except RuntimeError:
            raise ValueError(
                f"cov: batch shape {tuple(cov.shape[:-2])} does not broadcast with mean batch "
                f"shape {tuple(mean.shape[:-1])}"
            ) from None
        return cls(mean, cov)

    @property
    def state_dim(self) -> int:
        return self.mean.shape[-1]

    def estimate(self) -> GaussianBelief:
        """The point estimate with its covariance (the belief itself)."""
        return self

    def mix(self, weights: Tensor) -> GaussianBelief:
        """Moment-matched mixtures over batch axis -1, one per column of ``weights``.

        Shapes:
            self: batch ``(*B, K)``; weights: ``(*B, K, J)`` (columns sum to one over K)
            -> batch ``(*B, J)``
        """
        mean, cov = mix_gaussians(self.mean, self.cov, weights)
        return GaussianBelief(mean, cov)

    def collapse(self, weights: Tensor) -> GaussianBelief:
        """Moment-matched single Gaussian of the mixture over batch axis -1.

        Shapes:
            self: batch ``(*B, K)``; weights: ``(*B, K)`` (summing to one) -> batch ``(*B,)``
        """
        return self.mix(weights.unsqueeze(-1)).select(-1, 0)

    def entropy(self) -> Tensor:
        """Differential entropy ``(1/2) log det(2 pi e P)``, shape ``(*B,)`` (regularised factor:
        never raises; ``-inf``-free for a numerically singular ``P`` only up to the repair)."""
        if self.state_dim <= 2:  # the factor's diagonal without the factor; a + b is .sum(-1) of two
            diagonal = cholesky_diagonal(self.cov)
            half_logdet = diagonal[0].log() if self.state_dim == 1 else diagonal[0].log() + diagonal[1].log()
        else:
            half_logdet = cholesky(self.cov).diagonal(dim1=-2, dim2=-1).log().sum(-1)
        return half_logdet + 0.5 * self.state_dim * (1.0 + math.log(2 * math.pi))

    def log_prob(self, x: Tensor) -> Tensor:
        """Log-density at ``x``.

        Shapes:
            x: ``(*B, n)`` (broadcast with the batch) -> ``(*B,)``
        """
        chol = torch.linalg.cholesky(self.cov)
        diff = (x - self.mean).unsqueeze(-1)
        white = torch.linalg.solve_triangular(chol, diff, upper=False).squeeze(-1)
        half_logdet = chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        return -0.5 * (white.square().sum(-1) + self.state_dim * math.log(2 * math.pi)) - half_logdet

"""Input validation with errors that name the offending argument.

Every public constructor in torchmm validates its tensors once, at construction time, with these
helpers; filter steps never validate (they sit on the hot path). All checks work on detached
values, so tensors that require grad (learnable parameters, ``gradcheck`` inputs) pass through.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = [
    "as_tensor",
    "check_covariance",
    "check_shape",
    "check_square",
    "check_stochastic_rows",
]

#: Absolute tolerance on row sums and symmetry. Loose enough for float32 inputs and for the
#: one-sided perturbations of ``torch.autograd.gradcheck`` (1e-6), tight enough to catch a typo.
STOCHASTIC_ATOL = 1e-5
SYMMETRY_RTOL = 1e-5


def as_tensor(value, name: str, *, dtype: torch.dtype | None = None, device=None) -> Tensor:
    """Convert ``value`` to a floating tensor; raise ``ValueError`` naming ``name`` if it cannot be.

    Tensors keep their dtype unless ``dtype`` is given (autograd history is preserved).
    """
    if isinstance(value, Tensor):
        out = value
        if dtype is not None or device is not None:
            out = out.to(dtype=dtype or out.dtype, device=device or out.device)
    else:
        try:
            out = torch.as_tensor(value, dtype=dtype or torch.get_default_dtype(), device=device)
        except (TypeError, ValueError, RuntimeError) as err:
            raise ValueError(f"{name}: cannot convert to a tensor ({err})") from None
    if not out.is_floating_point():
        out = out.to(torch.get_default_dtype())
    if not bool(torch.isfinite(out.detach()).all()):
        raise ValueError(f"{name}: contains NaN or infinite entries")
    return out


def check_shape(tensor: Tensor, name: str, trailing: Sequence[int | None]) -> None:
    """Check that the trailing dimensions of ``tensor`` equal ``trailing`` (``None`` = any size)."""
    k = len(trailing)
    if tensor.dim() < k:
        raise ValueError(
            f"{name}: expected at least {k} dimensions with trailing shape {tuple(trailing)}, "
            f"got shape {tuple(tensor.shape)}"
        )
    got = tuple(tensor.shape[tensor.dim() - k :]) if k else ()
    for want, have in zip(trailing, got):
        if want is not None and want != have:
            raise ValueError(
                f"{name}: expected trailing shape {tuple(trailing)}, got shape {tuple(tensor.shape)}"
            )


def check_square(tensor: Tensor, name: str) -> int:
    """Check that the last two dimensions are equal; return their size."""
    if tensor.dim() < 2 or tensor.shape[-1] != tensor.shape[-2]:
        raise ValueError(f"{name}: expected a square matrix (..., d, d), got shape {tuple(tensor.shape)}")
    return tensor.shape[-1]


def check_covariance(tensor: Tensor, name: str, *, definite: bool = False) -> None:
    """Check that ``tensor`` (..., d, d) is symmetric positive semi-definite (or definite).

    Raises:
        ValueError: naming ``name`` and the failed property.
    """
    check_square(tensor, name)
    value = tensor.detach().to(torch.float64)
    scale = value.abs().amax(dim=(-1, -2), keepdim=True).clamp_min(1.0)
    if bool(((value - value.mT).abs() > SYMMETRY_RTOL * scale).any()):
        raise ValueError(f"{name}: covariance is not symmetric")
    eigvals = torch.linalg.eigvalsh(0.5 * (value + value.mT))
    tol = 1e-10 * scale.squeeze(-1)
    if definite and bool((eigvals <= tol).any()):
        raise ValueError(
            f"{name}: covariance is not positive definite (smallest eigenvalue "
            f"{eigvals.min().item():.3g})"
        )
    if bool((eigvals < -tol).any()):
        raise ValueError(
            f"{name}: covariance is not positive semi-definite (smallest eigenvalue "
            f"{eigvals.min().item():.3g})"
        )


def check_stochastic_rows(matrix: Tensor, name: str) -> None:
    """Check a (..., M, M) matrix of probabilities whose rows sum to one."""
    check_square(matrix, name)
    value = matrix.detach()
    if bool((value < 0).any()):
        raise ValueError(f"{name}: has negative entries")
    row_sums = value.sum(-1)
    if bool(((row_sums - 1).abs() > STOCHASTIC_ATOL).any()):
        raise ValueError(
            f"{name}: rows must sum to 1 (P[i, j] = P(mode_k = j | mode_k-1 = i)); "
            f"row sums are {row_sums.tolist()}"
        )

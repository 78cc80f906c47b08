"""Moment matching and small tensor helpers shared by beliefs and filters."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["symmetrize", "mix_gaussians", "normalize_log_probs", "psd_sqrt"]


def symmetrize(matrix: Tensor) -> Tensor:
    """Return ``(A + A^T) / 2``.

    Shapes:
        matrix: ``(..., d, d)`` -> ``(..., d, d)``
    """
    return (matrix + matrix.mT).mul_(0.5)


def normalize_log_probs(log_probs: Tensor, dim: int = -1) -> Tensor:
    """Subtract ``logsumexp`` along ``dim`` so that ``exp`` sums to one.

    A slice that is ``-inf`` everywhere (no finite evidence at all) becomes uniform instead of NaN.

    Shapes:
        log_probs: ``(..., K, ...)`` -> same shape
    """
    norm = torch.logsumexp(log_probs, dim=dim, keepdim=True)
    out = log_probs - norm
    bad = ~torch.isfinite(norm)
    if bool(bad.any()):
        uniform = -torch.log(torch.tensor(float(log_probs.shape[dim]), dtype=out.dtype))
        out = torch.where(bad, uniform.to(out.device), out)
    return out


def mix_gaussians(mean: Tensor, cov: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    r"""Moment-match weighted Gaussian mixtures: one output per column of ``weights``.

    .. math::
        \bar x_j = \sum_k w_{kj} x_k, \qquad
        \bar P_j = \sum_k w_{kj} \left[P_k + (x_k - \bar x_j)(x_k - \bar x_j)^\top\right]

    Columns of ``weights`` must sum to one over ``k``. The spread term is formed from centred
    differences (no ``E[xx^T] - \bar x \bar x^T`` cancellation in float32); all contractions are
    batched matmuls.

    Shapes:
        mean: ``(*B, K, n)``; cov: ``(*B, K, n, n)``; weights: ``(*B, K, J)``
        -> mean ``(*B, J, n)``, cov ``(*B, J, n, n)``
    """
    n = mean.shape[-1]
    wt = weights.mT  # (*B, J, K)
    mixed_mean = wt @ mean
    mixed_cov = (wt @ cov.flatten(-2)).unflatten(-1, (n, n))
    diff = mean.unsqueeze(-3) - mixed_mean.unsqueeze(-2)  # (*B, J, K, n)
    spread = (diff * wt.unsqueeze(-1)).mT @ diff
    return mixed_mean, mixed_cov + spread


def psd_sqrt(cov: Tensor) -> Tensor:
    """A square root ``L`` with ``L L^T = cov`` for symmetric PSD (possibly singular) matrices.

    Uses Cholesky where it succeeds and a symmetric eigendecomposition elsewhere (negative
    eigenvalues of a matrix indefinite by rounding clamped to 0), so that rank-deficient process
    noise such as ``G G^T`` can be sampled. Never raises: a matrix with NaN or infinite entries
    gets a NaN factor (that batch element only).

    Shapes:
        cov: ``(..., d, d)`` -> ``(..., d, d)``
    """
    chol, info = torch.linalg.cholesky_ex(cov)
    if not bool((info != 0).any()):
        return chol
    finite = torch.isfinite(cov).all(-1).all(-1)
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    safe = torch.where(finite[..., None, None], symmetrize(cov), eye)  # eigh raises on NaN input
    eigvals, eigvecs = torch.linalg.eigh(safe)
    eig_sqrt = eigvecs * eigvals.clamp_min(0).sqrt().unsqueeze(-2)
    eig_sqrt = torch.where(finite[..., None, None], eig_sqrt, torch.full_like(eig_sqrt, math.nan))
    return torch.where((info != 0)[..., None, None], eig_sqrt, chol)

"""Moment matching and small tensor helpers shared by beliefs and filters."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.linalg import psd_sqrt, symmetrize

__all__ = ["symmetrize", "mix_gaussians", "normalize_log_probs", "psd_sqrt", "safe_log_normalize",
           "dead_safe_logsumexp", "live_log", "effective_sample_size"]


def normalize_log_probs(log_probs: Tensor, dim: int = -1) -> Tensor:
    """Subtract ``logsumexp`` along ``dim`` so that ``exp`` sums to one.

    A slice that is ``-inf`` everywhere (no finite evidence at all) becomes uniform instead of NaN.

    Shapes:
        log_probs: ``(..., K, ...)`` -> same shape
    """
    norm = torch.logsumexp(log_probs, dim=dim, keepdim=True)
    out = log_probs - norm
    # no host synchronisation: the repair is one masked pass, applied whether or not a slice needs it
    return out.masked_fill_(~torch.isfinite(norm), -math.log(log_probs.shape[dim]))


def effective_sample_size(log_weights: Tensor) -> Tensor:
    r"""Kong-Liu-Wong effective sample size ``1 / sum w_i^2`` of the normalised weights, from
    unnormalised log-weights: ``s (s / q)`` with ``s = sum v_i``, ``q = sum v_i^2`` and
    ``v_i = exp(l_i - max l)``. Equal weights give exactly ``Np`` (every ``v_i`` is 1; the former
    ``exp(2 logsumexp(l) - logsumexp(2 l))`` gave 4.999999999999999 for 5 and made ``ess_threshold=1``
    resample a uniform set); an all ``-inf`` (or NaN) slice gives 0.

    Shapes:
        log_weights: ``(*B, Np)`` -> ``(*B,)``
    """
    top = log_weights.amax(-1, keepdim=True)
    v = torch.exp(log_weights - top)
    s, q = v.sum(-1), v.square().sum(-1)
    ess = s * (s / q)
    zero = torch.zeros((), dtype=ess.dtype, device=ess.device)
    return torch.where(torch.isfinite(top.squeeze(-1)), ess, zero)


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


def live_log(p: Tensor, tiny: Tensor | float) -> Tensor:
    """``p.log()``, the same values, with no gradient through an entry at or below ``tiny`` (the smallest normal
    number): a mode no run can reach has ``p = 0``, where ``log``'s ``1 / p`` times its zero adjoint is NaN
    and would reach every live mode (the IMM's predicted mode probabilities ``c_j``, eager and batch-last;
    the linear kernel's reverse pass floors ``c_j`` alike; tests/kernels/test_unreachable_mode.py)."""
    return torch.where(p > tiny, p, p.detach()).log()


def dead_safe_logsumexp(x: Tensor, dim: int) -> Tensor:
    """``torch.logsumexp(x, dim)``, the same values, whose gradient is 0 (not NaN) where every entry along ``dim``
    is ``-inf`` (a mode no run can reach: logsumexp's backward ``exp(x - out)`` is ``exp(-inf + inf) = NaN``
    there, and it reached every parameter of the live modes; tests/kernels/test_unreachable_mode.py)."""
    dead = torch.isneginf(x).all(dim, keepdim=True)
    out = torch.logsumexp(torch.where(dead, 0.0, x), dim)
    return torch.where(dead.squeeze(dim), -math.inf, out)


def safe_log_normalize(joint: Tensor, norm: Tensor) -> Tensor:
    """``joint - norm`` where ``norm = logsumexp`` of ``joint`` over the axes ``norm`` keeps with size 1;
    groups that are all ``-inf`` (``-inf - -inf = NaN``; or NaN) become uniform, ``-inf`` entries of
    a finite group stay ``-inf``. One fused pass, no host synchronisation."""
    size = joint.numel() // max(norm.numel(), 1)
    uniform = -math.log(size) if size else 0.0
    return (joint - norm).nan_to_num_(nan=uniform, posinf=math.inf, neginf=-math.inf)

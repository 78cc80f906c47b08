r"""Batched Monte Carlo metrics.

The papers' RMSE is per time step over Monte Carlo runs, then averaged over time:

.. math::
    \mathrm{RMSE}_k = \sqrt{\tfrac1N \textstyle\sum_{r=1}^N \|\hat x^{(r)}_k - x^{(r)}_k\|^2_{\mathcal C}},
    \qquad \mathrm{ARMSE} = \tfrac1T \textstyle\sum_k \mathrm{RMSE}_k

where ``C`` selects the components (e.g. both position axes). Paper 000's Table 1 ("average RMSEs
per sample") and paper 004's ARMSE are this ARMSE.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief
from torchmm.linalg import cholesky, solve_lower

__all__ = ["armse", "mode_accuracy", "mode_hits", "nees", "nis", "rmse", "squared_error"]


def squared_error(estimate: Tensor, truth: Tensor, components: Sequence[int] | None = None) -> Tensor:
    """``||estimate - truth||^2`` over ``components`` (default all).

    Shapes:
        estimate, truth: ``(..., n)`` -> ``(...)``
    """
    if estimate.shape[-1] != truth.shape[-1]:
        raise ValueError(f"truth: state dim {truth.shape[-1]} differs from the estimate's {estimate.shape[-1]}")
    err = estimate - truth
    if components is not None:
        err = err[..., list(components)]
    return err.square().sum(-1)


def rmse(estimate: Tensor, truth: Tensor, components: Sequence[int] | None = None) -> Tensor:
    """Per-step RMSE over all runs.

    Shapes:
        estimate, truth: ``(T, *B, n)`` -> ``(T,)`` (mean over every batch dim ``*B``)
    """
    se = squared_error(estimate, truth, components)
    return se.flatten(1).mean(-1).sqrt()


def armse(estimate: Tensor, truth: Tensor, components: Sequence[int] | None = None) -> Tensor:
    """Time average of the per-step RMSE (the papers' "average RMSE"). Returns a scalar tensor."""
    return rmse(estimate, truth, components).mean()


def _quadratic(residual: Tensor, cov: Tensor) -> Tensor:
    """``r^T C^{-1} r`` by a Cholesky solve; NaN entries of ``r`` are skipped."""
    observed = ~torch.isnan(residual)
    r = torch.where(observed, residual, 0.0)
    pair = observed.unsqueeze(-1) & observed.unsqueeze(-2)
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    cov = torch.where(pair, cov, eye)
    white = solve_lower(cholesky(cov), r.unsqueeze(-1)).squeeze(-1)
    out = white.square().sum(-1)
    return torch.where(observed.any(-1), out, torch.nan)


def nees(estimate: GaussianBelief, truth: Tensor) -> Tensor:
    """Normalised estimation error squared ``e^T P^{-1} e`` per step and run.

    Its mean over runs is ``chi^2_n``-distributed-ish around ``n`` for a consistent filter.

    Shapes:
        estimate: batch ``(T, *B)``; truth ``(T, *B, n)`` -> ``(T, *B)``
    """
    return _quadratic(estimate.mean - truth, estimate.cov)


def nis(innovation: Tensor, innovation_cov: Tensor) -> Tensor:
    """Normalised innovation squared ``nu^T S^{-1} nu``; NaN where the measurement was missing.

    Shapes:
        innovation ``(..., m)``, innovation_cov ``(..., m, m)`` -> ``(...)``
    """
    return _quadratic(innovation, innovation_cov)


def mode_hits(mode_probs: Tensor, true_modes: Tensor) -> Tensor:
    """1 where the true mode is the most probable one, ``1/k`` where it ties with ``k - 1`` others,
    0 elsewhere.

    Modes within ``1e-9`` (relative) of the largest value count as tied. Exactly equal probabilities
    (e.g. identical modes, or no datum yet) are then scored the same on every processor and for any
    batch size, where an ``argmax`` would let rounding pick the winner.

    Shapes:
        mode_probs (or log-probs): ``(*B, M)``; true_modes ``(*B)`` -> ``(*B)``
    """
    top = mode_probs.amax(-1, keepdim=True)
    tied = mode_probs >= top - 1e-9 * top.abs()
    true = tied.gather(-1, true_modes.long().unsqueeze(-1)).squeeze(-1)
    return true.to(mode_probs.dtype) / tied.sum(-1).to(mode_probs.dtype)


def mode_accuracy(mode_probs: Tensor, true_modes: Tensor) -> Tensor:
    """Fraction of runs whose most probable mode is the true one, per step (a tie of ``k`` modes
    that includes the true one counts ``1/k``, :func:`mode_hits`).

    Shapes:
        mode_probs (or log-probs): ``(T, *B, M)``; true_modes ``(T, *B)`` -> ``(T,)``
    """
    return mode_hits(mode_probs, true_modes).flatten(1).mean(-1)

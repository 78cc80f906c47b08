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
from torchmm.contract import Cov, Finite, Indices, Labels, Of, Values, entry_point
from torchmm.linalg import cholesky, solve_lower
from torchmm.metrics.sets import gospa, gospa_switching, ospa
from torchmm.validation import SYMMETRY_RTOL, broadcast_shape

__all__ = ["armse", "gospa", "gospa_switching", "mode_accuracy", "mode_hits", "nees", "nis", "ospa", "rmse", "squared_error"]

# The kinds: an estimate may be NaN or infinite (a diverged run is scored, not refused), and so may
# mode (log-)probabilities (-inf) and innovations (NaN = missing); the truth is finite.
_ERROR_KINDS = {"estimate": Values(), "truth": Finite(), "components": Indices(optional=True)}


def _tensor(value) -> Tensor:
    """A tensor-like (a NumPy array, a list) that its kind has checked as a tensor (a tensor is kept)."""
    return value if isinstance(value, Tensor) else torch.as_tensor(value, dtype=torch.get_default_dtype())


def _check_error_args(estimate: Tensor, truth: Tensor, components) -> None:
    if estimate.dim() < 1:
        raise ValueError(f"estimate: expected shape (..., n), got {tuple(estimate.shape)}")
    if truth.dim() < 1 or estimate.shape[-1] != truth.shape[-1]:
        raise ValueError(f"truth: state dim {truth.shape[-1] if truth.dim() else None} differs from the "
                         f"estimate's {estimate.shape[-1]}")
    try:
        broadcast_shape(estimate.shape, truth.shape)
    except RuntimeError:
        raise ValueError(f"truth: shape {tuple(truth.shape)} does not broadcast with the estimate's "
                         f"{tuple(estimate.shape)}") from None
    if components is not None:
        n = estimate.shape[-1]
        bad = [int(c) for c in components if int(c) >= n]
        if bad:
            raise ValueError(f"components: indices {bad} out of range for a state of dimension {n}")


def _check_modes(mode_probs: Tensor, true_modes: Tensor) -> None:
    if mode_probs.dim() < 1 or mode_probs.shape[-1] < 1:
        raise ValueError(f"mode_probs: expected shape (*B, M), got {tuple(mode_probs.shape)}")
    if true_modes.shape != mode_probs.shape[:-1]:
        raise ValueError(f"true_modes: expected shape {tuple(mode_probs.shape[:-1])} (mode_probs without its "
                         f"mode axis), got {tuple(true_modes.shape)}")
    M = mode_probs.shape[-1]
    if true_modes.numel() and bool((true_modes >= M).any()):
        raise ValueError(f"true_modes: mode indices must be < {M}, got {int(true_modes.max())}")


@entry_point(**_ERROR_KINDS)
def squared_error(estimate: Tensor, truth: Tensor, components: Sequence[int] | None = None) -> Tensor:
    """``||estimate - truth||^2`` over ``components`` (default all).

    Shapes:
        estimate, truth: ``(..., n)`` -> ``(...)``; ``estimate`` may hold NaN or infinite entries (a
        diverged run), which propagate.
    """
    truth = _tensor(truth)
    _check_error_args(estimate, truth, components)
    return _squared_error(estimate, truth, components)


def _squared_error(estimate: Tensor, truth: Tensor, components: Sequence[int] | None = None) -> Tensor:
    err = estimate - truth
    if components is not None:
        err = err[..., list(components)]
    return err.square().sum(-1)


@entry_point(**_ERROR_KINDS)
def rmse(estimate: Tensor, truth: Tensor, components: Sequence[int] | None = None) -> Tensor:
    """Per-step RMSE over all runs.

    Shapes:
        estimate, truth: ``(T, *B, n)`` tensors (or NumPy arrays) -> ``(T,)`` (mean over every batch
        dim ``*B``)
    """
    truth = _tensor(truth)
    _check_error_args(estimate, truth, components)
    if estimate.dim() < 2:
        raise ValueError(f"estimate: expected shape (T, *B, n), got {tuple(estimate.shape)}")
    return _rmse(estimate, truth, components)


def _rmse(estimate: Tensor, truth: Tensor, components: Sequence[int] | None = None) -> Tensor:
    se = _squared_error(estimate, truth, components)
    return se.reshape(se.shape[0], -1).mean(-1).sqrt()


@entry_point(**_ERROR_KINDS)
def armse(estimate: Tensor, truth: Tensor, components: Sequence[int] | None = None) -> Tensor:
    """Time average of the per-step RMSE (the papers' "average RMSE"). Returns a scalar tensor."""
    return rmse.__wrapped__(estimate, truth, components).mean()


def _quadratic(residual: Tensor, cov: Tensor, *, definite_only: bool = False) -> Tensor:
    """``r^T C^{-1} r`` by a Cholesky solve; NaN entries of ``r`` are skipped. ``definite_only``: NaN where
    ``C`` (over the observed components) is not numerically positive definite, instead of the regularised
    factor's answer (which can be ~1e300)."""
    observed = ~torch.isnan(residual)
    r = torch.where(observed, residual, 0.0)
    pair = observed.unsqueeze(-1) & observed.unsqueeze(-2)
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    cov = torch.where(pair, cov, eye)
    L, singular = cholesky(cov, with_flag=True)
    white = solve_lower(L, r.unsqueeze(-1)).squeeze(-1)
    out = white.square().sum(-1)
    keep = observed.any(-1) & ~singular if definite_only else observed.any(-1)
    return torch.where(keep, out, torch.nan)


@entry_point(estimate=Of(GaussianBelief), truth=Finite())
def nees(estimate: GaussianBelief, truth: Tensor) -> Tensor:
    """Normalised estimation error squared ``e^T P^{-1} e`` per step and run.

    Its mean over runs is ``chi^2_n``-distributed-ish around ``n`` for a consistent filter.

    Shapes:
        estimate: batch ``(T, *B)``; truth ``(T, *B, n)`` (or a shape that broadcasts to it) ->
        ``(T, *B)``: NaN where the estimate's mean or covariance has a NaN or infinite entry (a
        diverged run is scored NaN, never over its finite components only), and where its covariance is
        not numerically positive definite (a particle cloud collapsed onto one particle, a diverged
        filter: that run's step has no value, and the other runs are scored; before 2026-12-08 the
        regularised factor gave up to 1e308)

    Raises:
        ValueError: naming ``estimate.cov`` where a finite covariance is not symmetric (beyond
            ``1e-5`` of its largest entry: a mistake in the argument, not a run's trouble; checked here,
            once), ``truth`` where its shape does not broadcast to the estimate's ``(T, *B, n)``.
    """
    truth = _tensor(truth)
    mean, cov = estimate.mean, estimate.cov
    n = mean.shape[-1]
    if truth.dim() < 1 or truth.shape[-1] != n:
        raise ValueError(f"truth: expected shape (T, *B, {n}), got {tuple(truth.shape)}")
    try:
        batch = broadcast_shape(mean.shape[:-1], cov.shape[:-2])
    except RuntimeError:
        raise ValueError(f"estimate: mean batch {tuple(mean.shape[:-1])} and covariance batch "
                         f"{tuple(cov.shape[:-2])} do not broadcast") from None
    try:
        fits = broadcast_shape(batch, truth.shape[:-1]) == batch
    except RuntimeError:
        fits = False
    if not fits:
        raise ValueError(f"truth: shape {tuple(truth.shape)} does not broadcast to the estimate's "
                         f"{(*batch, n)}")
    finite = torch.isfinite(cov.detach()).all(-1).all(-1) & torch.isfinite(mean.detach()).all(-1)
    eye = torch.eye(n, dtype=cov.dtype, device=cov.device)
    scored = torch.where(finite[..., None, None], cov.detach(), eye)  # (a diverged run is not checked)
    scale = scored.abs().amax((-2, -1), keepdim=True)
    if bool(((scored - scored.mT).abs() > SYMMETRY_RTOL * scale).any()):
        raise ValueError("estimate.cov: covariance is not symmetric")
    out = _quadratic(mean - truth, torch.where(finite[..., None, None], cov, eye), definite_only=True)
    return torch.where(finite, out, torch.nan)


@entry_point(innovation=Values(), innovation_cov=Cov(definite=True))
def nis(innovation: Tensor, innovation_cov: Tensor) -> Tensor:
    """Normalised innovation squared ``nu^T S^{-1} nu``; NaN where the measurement was missing.

    Shapes:
        innovation ``(..., m)``, innovation_cov ``(..., m, m)`` (tensors or NumPy arrays; the two
        batches broadcast) -> ``(...)``
    """
    innovation_cov = _tensor(innovation_cov)
    m = innovation_cov.shape[-1]
    if innovation.dim() < 1 or innovation.shape[-1] != m:
        raise ValueError(f"innovation: expected shape (..., {m}) for a {m}x{m} innovation_cov, "
                         f"got {tuple(innovation.shape)}")
    try:
        broadcast_shape(innovation.shape[:-1], innovation_cov.shape[:-2])
    except RuntimeError:
        raise ValueError(f"innovation_cov: batch {tuple(innovation_cov.shape[:-2])} does not broadcast with "
                         f"the innovation's {tuple(innovation.shape[:-1])}") from None
    return _quadratic(innovation, innovation_cov)


@entry_point(mode_probs=Values(), true_modes=Labels())
def mode_hits(mode_probs: Tensor, true_modes: Tensor) -> Tensor:
    """1 where the true mode is the most probable one, ``1/k`` where it ties with ``k - 1`` others,
    0 elsewhere.

    Modes within ``1e-9`` (relative) of the largest value count as tied. Exactly equal probabilities
    (e.g. identical modes, or no datum yet) are then scored the same on every processor and for any
    batch size, where an ``argmax`` would let rounding pick the winner.

    Shapes:
        mode_probs (or log-probs): ``(*B, M)``; true_modes ``(*B)`` -> ``(*B)``
    """
    _check_modes(mode_probs, true_modes)
    return _mode_hits(mode_probs, true_modes)


def _mode_hits(mode_probs: Tensor, true_modes: Tensor) -> Tensor:
    top = mode_probs.amax(-1, keepdim=True)
    tied = mode_probs >= top - 1e-9 * top.abs()
    true = tied.gather(-1, true_modes.long().unsqueeze(-1)).squeeze(-1)
    return true.to(mode_probs.dtype) / tied.sum(-1).to(mode_probs.dtype)


@entry_point(mode_probs=Values(), true_modes=Labels())
def mode_accuracy(mode_probs: Tensor, true_modes: Tensor) -> Tensor:
    """Fraction of runs whose most probable mode is the true one, per step (a tie of ``k`` modes
    that includes the true one counts ``1/k``, :func:`mode_hits`).

    Shapes:
        mode_probs (or log-probs): ``(T, *B, M)``; true_modes ``(T, *B)`` -> ``(T,)``
    """
    _check_modes(mode_probs, true_modes)
    if mode_probs.dim() < 2:
        raise ValueError(f"mode_probs: expected shape (T, *B, M), got {tuple(mode_probs.shape)}")
    hits = _mode_hits(mode_probs, true_modes)
    return hits.reshape(hits.shape[0], -1).mean(-1)

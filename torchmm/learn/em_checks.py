"""The arguments of :func:`~torchmm.learn.em` checked once at entry (split from :mod:`torchmm.learn.em` by
concern): the ``fixed`` masks (:func:`fixed_masks`, a covariance's pattern one with a closed-form M-step), a
shared start's fields (:func:`start_masks`) and the batch axes a start field is one value along
(:func:`pooled_axes`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief
from torchmm.filters.kalman import KalmanFilter

__all__ = ["covariance_mask", "fixed_masks", "pooled_axes", "start_masks"]


def covariance_mask(name: str, mask: Tensor, value: Tensor) -> None:
    """A covariance's fixed entries must leave a closed-form M-step: symmetric, the free entries whole
    diagonal blocks (a block-diagonal covariance: each block's estimate is the block of the unrestricted
    one, exactly, the likelihood factorising over the blocks) and the fixed entries off those blocks 0."""
    free = ~mask
    if not torch.equal(free, free.mT):
        raise ValueError(f"fixed[{name!r}]: a covariance's mask must be symmetric")
    n = free.shape[-1]
    for i in range(n):  # (once, at entry)
        block = free[i]
        if bool(block.any()) and not (bool(block[i]) and torch.equal(free[block][:, block],
                                                                       torch.ones(int(block.sum()), int(block.sum()),
                                                                                  dtype=torch.bool))
                                     and bool((free[block].sum(0) == 0)[~block].all())):
            raise ValueError(f"fixed[{name!r}]: the free entries of a covariance must form diagonal blocks (e.g. "
                             "a diagonal covariance: every off-diagonal entry fixed at 0); other patterns have no "
                             "closed-form M-step: use torchmm.learn.estimate")
    rows = free.any(-1)
    off = mask & (rows.unsqueeze(-1) | rows.unsqueeze(-2)) & ~torch.eye(n, dtype=torch.bool)
    if bool((value.detach().expand(*value.shape[:-2], n, n)[..., off] != 0).any()):
        raise ValueError(f"fixed[{name!r}]: the fixed entries between a free block and the rest must be 0 (the "
                         "blocks are independent)")


def fixed_masks(filter: KalmanFilter, belief0: GaussianBelief, parameters: Sequence[str],
                fixed: Mapping[str, Any] | None) -> dict[str, Tensor]:
    """:func:`em`'s ``fixed`` checked against the filter and the start (each mask a boolean tensor of its
    parameter's shape, for an estimated parameter, not every entry fixed, a covariance's pattern one with
    a closed-form M-step): ``{name: mask}`` of the masks that fix something. A ``ValueError`` naming
    ``fixed[name]`` otherwise (the study's dry construction calls it before anything runs)."""
    motion, sensor = filter.motion, filter.measurement
    current = {"H": sensor.H, "R": sensor.R, "F": motion.F, "offset": motion.offset, "Q": motion.Q,
               "initial_mean": belief0.mean, "initial_cov": belief0.cov}
    masks = {}
    if fixed is None:
        return masks
    if not isinstance(fixed, Mapping):
        raise TypeError(f"fixed: expected a mapping {{parameter name: boolean mask}}, got {type(fixed).__name__}")
    for name, mask in fixed.items():
        if name not in parameters:
            raise ValueError(f"fixed[{name!r}]: not an estimated parameter ({', '.join(parameters)})")
        event = 1 if name in ("offset", "initial_mean") else 2
        shape = tuple(current[name].shape[-event:])
        try:
            mask = torch.as_tensor(mask, dtype=torch.bool).expand(shape).clone()
        except (RuntimeError, TypeError, ValueError):
            raise ValueError(f"fixed[{name!r}]: expected a boolean mask of shape {shape}") from None
        if bool(mask.all()):
            raise ValueError(f"fixed[{name!r}]: every entry is fixed (leave {name} out of parameters)")
        if name in ("Q", "R", "initial_cov"):
            covariance_mask(name, mask, current[name])
        if bool(mask.any()):
            masks[name] = mask
    weights = {"H": "R", "F": "Q", "offset": "Q", "initial_mean": "initial_cov"}
    for name in masks:
        if name in weights:  # (once, at entry) the weighted M-step needs an invertible weight
            weight = current[weights[name]].detach()
            if bool((torch.linalg.cholesky_ex(weight).info != 0).any()):
                raise ValueError(f"fixed[{name!r}]: with fixed entries the M-step of {name} is a least squares "
                                 f"weighted by {weights[name]}, which must be positive definite (a singular "
                                 f"{weights[name]}, e.g. ConstantVelocity's rank-deficient Q, has no unique one)")
    return masks


def pooled_axes(value: Tensor, batch: torch.Size, event: int) -> tuple[int, ...]:
    """The batch axes along which a start field is one value (an expanded view: stride 0, or an axis it
    lacks), as :class:`~torchmm.learn.entries.StartFields` holds them for :func:`~torchmm.learn.estimate`."""
    full = value.expand(*batch, *value.shape[value.dim() - event:])
    return tuple(i for i, n in enumerate(batch) if n > 1 and full.stride(i) == 0)


def start_masks(belief0: GaussianBelief, parameters: Sequence[str]) -> None:
    """With shared parameters an estimated start mean broadcast over series (one value
    for them) needs one covariance over them too: broadcast as well, or held (not estimated) with
    the same value for each, else a ``ValueError`` naming ``belief0`` (once, at entry: the pooled mean with a
    covariance per series would be a precision-weighted one, not implemented)."""
    batch, n = belief0.batch_shape, belief0.mean.shape[-1]
    if "initial_mean" not in parameters or batch.numel() < 2:
        return
    cov = belief0.cov.detach().expand(*batch, n, n)
    for axis in set(pooled_axes(belief0.mean, batch, 1)) - set(pooled_axes(belief0.cov, batch, 2)):
        if "initial_cov" in parameters or not bool((cov == cov.narrow(axis, 0, 1)).all()):
            raise ValueError("belief0: its mean is one value for the series (an expanded view: estimated as "
                             "one shared start mean) but its covariance is one per series; expand the "
                             "covariance too (belief0.expand), or materialise the mean (a start mean per "
                             "series)")

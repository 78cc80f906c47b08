"""Measurement models: linear position sensors and a nonlinear range-bearing sensor."""

from __future__ import annotations

import torch
from torch import Tensor

from torchmm.models.base import MeasurementModel, store_tensor
from torchmm.models.linear import LinearMeasurement
from torchmm.validation import as_tensor, check_covariance, check_shape

__all__ = ["PositionMeasurement", "RangeBearing"]


class PositionMeasurement(LinearMeasurement):
    """Measure the state components ``indices`` (e.g. positions ``(0, 2)`` of ``[x, vx, y, vy]``).

    Args:
        state_dim: ``n``.
        indices: measured components, ``m`` of them.
        R: noise covariance ``(*P, m, m)``, or a number ``r`` for ``r I``.
    """

    def __init__(self, state_dim: int, indices, R, *, dtype=None):
        indices = list(indices)
        if not indices or any(not 0 <= i < state_dim for i in indices):
            raise ValueError(f"indices: must be a non-empty list of components < {state_dim}, got {indices}")
        dtype = dtype or (R.dtype if isinstance(R, Tensor) else torch.get_default_dtype())
        R = as_tensor(R, "R", dtype=dtype)
        H = torch.zeros(len(indices), state_dim, dtype=dtype, device=R.device)
        H[torch.arange(len(indices)), torch.tensor(indices)] = 1.0
        if R.dim() == 0:
            R = R * torch.eye(len(indices), dtype=dtype, device=R.device)
        super().__init__(H, R)
        self.indices = indices


class RangeBearing(MeasurementModel):
    """Range and bearing of the position ``(x[i], x[j])`` from a sensor at ``origin``.

    ``h(x) = [sqrt(dx^2 + dy^2), atan2(dy, dx)]``. Bearing residuals are *not* wrapped here;
    keep bearings away from +-pi or wrap measurements upstream.

    Args:
        state_dim: ``n``.
        R: ``(2, 2)`` covariance of ``[range, bearing]``.
        position_indices: components holding ``x`` and ``y``; default ``(0, 2)``.
        origin: sensor position ``(2,)``; default the origin.
    """

    def __init__(self, state_dim: int, R, position_indices=(0, 2), origin=(0.0, 0.0), *, dtype=None):
        super().__init__()
        R = as_tensor(R, "R", dtype=dtype)
        check_shape(R, "R", (2, 2))
        check_covariance(R, "R", definite=True)
        store_tensor(self, "R", R)
        store_tensor(self, "origin", as_tensor(origin, "origin", dtype=R.dtype, device=R.device))
        self.position_indices = tuple(position_indices)
        self.state_dim, self.meas_dim = state_dim, 2

    def forward(self, x: Tensor) -> Tensor:
        dx = x[..., self.position_indices[0]] - self.origin[0]
        dy = x[..., self.position_indices[1]] - self.origin[1]
        return torch.stack([torch.sqrt(dx.square() + dy.square()), torch.atan2(dy, dx)], dim=-1)

    def noise_cov(self, x: Tensor | None = None) -> Tensor:
        return self.R

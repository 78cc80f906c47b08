"""Measurement models: linear position sensors and a nonlinear range-bearing sensor."""

from __future__ import annotations

import torch
from torch import Tensor

from torchmm.contract import Cov, DType, Finite, Indices, Int, entry_point
from torchmm.models.base import MeasurementModel, store_tensor
from torchmm.models.linear import LinearMeasurement
from torchmm.validation import as_int, as_tensor, check_covariance, check_shape

__all__ = ["PositionMeasurement", "RangeBearing"]


def _indices(indices, name: str, state_dim: int) -> list[int]:
    """A non-empty list of state components ``0 <= i < state_dim`` (integers)."""
    if isinstance(indices, (str, bytes)):
        raise TypeError(f"{name}: expected a list of integer state components, got {indices!r}")
    try:
        values = list(indices)
    except TypeError:
        raise TypeError(f"{name}: expected a list of integer state components, got {indices!r}") from None
    out = [as_int(i, f"{name}[{k}]") for k, i in enumerate(values)]
    if not out or any(not 0 <= i < state_dim for i in out):
        raise ValueError(f"{name}: must be a non-empty list of components in [0, {state_dim}), got {values}")
    return out


class PositionMeasurement(LinearMeasurement):
    """Measure the state components ``indices`` (e.g. positions ``(0, 2)`` of ``[x, vx, y, vy]``).

    Args:
        state_dim: ``n``.
        indices: measured components, ``m`` of them.
        R: noise covariance ``(*P, m, m)``, or a number ``r`` for ``r I``.
    """

    @entry_point(state_dim=Int(1), indices=Indices(), R=Finite(check=False), dtype=DType())
    def __init__(self, state_dim: int, indices, R, *, dtype=None):
        state_dim = as_int(state_dim, "state_dim", minimum=1)
        indices = _indices(indices, "indices", state_dim)
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

    @entry_point(state_dim=Int(1), R=Cov(definite=True, check=False), position_indices=Indices(),
                 origin=Finite(check=False), dtype=DType())
    def __init__(self, state_dim: int, R, position_indices=(0, 2), origin=(0.0, 0.0), *, dtype=None):
        super().__init__()
        state_dim = as_int(state_dim, "state_dim", minimum=1)
        R = as_tensor(R, "R", dtype=dtype)
        check_shape(R, "R", (2, 2))
        check_covariance(R, "R", definite=True)
        store_tensor(self, "R", R)
        origin = as_tensor(origin, "origin", dtype=R.dtype, device=R.device)
        if origin.shape != (2,):
            raise ValueError(f"origin: expected the sensor position (2,), got shape {tuple(origin.shape)}")
        store_tensor(self, "origin", origin)
        position_indices = _indices(position_indices, "position_indices", state_dim)
        if len(position_indices) != 2 or position_indices[0] == position_indices[1]:
            raise ValueError(f"position_indices: expected two different components (x, y), got {position_indices}")
        self.position_indices = tuple(position_indices)
        self.state_dim, self.meas_dim = state_dim, 2

    def forward(self, x: Tensor) -> Tensor:
        return torch.stack(self.forward_entries(x.unbind(-1)), dim=-1)

    def forward_entries(self, x) -> list[Tensor]:
        """:meth:`forward` one component at a time (the same operations)."""
        dx = x[self.position_indices[0]] - self.origin[0]
        dy = x[self.position_indices[1]] - self.origin[1]
        return [torch.sqrt(dx.square() + dy.square()), torch.atan2(dy, dx)]

    def jacobian(self, x: Tensor) -> Tensor:
        """Closed-form ``dh/dx``: ``[dx, dy] / r`` and ``[-dy, dx] / r^2`` in the position columns, zero
        elsewhere; differentiable (in the state and the origin), equal to autograd to rounding.

        Shapes: ``x: (*B, n)`` -> ``(*B, 2, n)``
        """
        rows = self.jacobian_entries(x.unbind(-1))
        zero = torch.zeros_like(rows[0][self.position_indices[0]])
        entries = [zero if isinstance(e, float) else e for row in rows for e in row]
        return torch.stack(entries, dim=-1).unflatten(-1, (2, self.state_dim))

    def jacobian_entries(self, x) -> list[list[Tensor | float]]:
        """:meth:`jacobian` entry by entry (``0.0`` outside the position columns)."""
        i, j = self.position_indices
        dx = x[i] - self.origin[0]
        dy = x[j] - self.origin[1]
        r2 = dx.square() + dy.square()
        r = torch.sqrt(r2)
        rows = [[0.0] * self.state_dim for _ in range(2)]
        rows[0][i], rows[0][j] = dx / r, dy / r
        rows[1][i], rows[1][j] = -dy / r2, dx / r2
        return rows

    def noise_cov(self, x: Tensor | None = None) -> Tensor:
        return self.R

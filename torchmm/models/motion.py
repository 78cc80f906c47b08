"""Kinematic motion models: constant velocity / acceleration, coordinated turn.

State ordering is per axis, position first: ``[x, vx]`` (1-D), ``[x, vx, y, vy]`` (2-D CV and CT),
``[x, vx, ax, y, vy, ay]`` (2-D CA). Process noise is either ``"discrete"`` (piecewise-constant
white acceleration/jerk over the sample, ``Q = q G G^T``) or ``"continuous"`` (continuous white
noise integrated over ``dt``). The default is ``"discrete"``, the model of papers 000 and 003.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.contract import Choice, DType, Finite, Int, Real, entry_point
from torchmm.models.base import MotionModel, store_tensor
from torchmm.models.linear import LinearMotion
from torchmm.validation import as_float, as_int, as_tensor

__all__ = [
    "ConstantVelocity",
    "ConstantAcceleration",
    "CoordinatedTurn",
    "NonlinearCoordinatedTurn",
    "kinematic_matrices",
]


@entry_point(order=Int(1), dt=Real(positive=True), q=Real(minimum=0.0),
             noise=Choice("discrete", "continuous"), dtype=DType())
def kinematic_matrices(order: int, dt: float, q: float, noise: str, dtype=None) -> tuple[Tensor, Tensor, Tensor]:
    """One-axis kinematic ``F``, noise gain ``G`` and ``Q`` for a state of ``order`` derivatives.

    ``order = 2`` is ``[p, v]`` (CV), ``order = 3`` is ``[p, v, a]`` (CA).

    Returns:
        ``F (order, order)``, ``G (order,)`` (the input gain of the highest derivative's driving
        noise, e.g. ``[dt^2/2, dt]`` for CV) and ``Q (order, order)``.
    """
    dtype = dtype or torch.get_default_dtype()
    dt = as_float(dt, "dt", positive=True)
    q = as_float(q, "q", minimum=0.0)
    F = torch.zeros(order, order, dtype=dtype)
    for i in range(order):
        for j in range(i, order):
            F[i, j] = dt ** (j - i) / math.factorial(j - i)
    G = torch.tensor([dt ** (order - i) / math.factorial(order - i) for i in range(order)], dtype=dtype)
    if noise == "discrete":
        Q = q * torch.outer(G, G)
    elif noise == "continuous":
        Q = torch.zeros(order, order, dtype=dtype)
        for i in range(order):
            for j in range(order):
                p = (order - 1 - i) + (order - 1 - j) + 1
                Q[i, j] = q * dt**p / (p * math.factorial(order - 1 - i) * math.factorial(order - 1 - j))
    else:
        raise ValueError(f"noise: expected 'discrete' or 'continuous', got {noise!r}")
    return F, G, Q


def _block_diag_axes(block: Tensor, ndim: int) -> Tensor:
    return torch.block_diag(*([block] * ndim))


class ConstantVelocity(LinearMotion):
    """Constant-velocity model in ``ndim`` axes, optionally with known acceleration inputs.

    With ``acceleration`` of shape ``(*P, ndim)`` the model is a bank of acceleration modes
    ``x_k = F x_{k-1} + G a_j + G w_k`` (paper 000, eq. (37); paper 003's 21 models).

    Args:
        ndim: number of spatial axes.
        dt: sample period.
        q: acceleration-noise intensity (variance for ``noise="discrete"``, PSD otherwise).
        noise: ``"discrete"`` (``Q = q G G^T``) or ``"continuous"``.
        acceleration: known acceleration per mode, ``(*P, ndim)``; default none.
    """

    @entry_point(ndim=Int(1), dt=Real(positive=True), q=Real(minimum=0.0),
                 noise=Choice("discrete", "continuous"), acceleration=Finite(optional=True), dtype=DType())
    def __init__(self, ndim: int = 1, dt: float = 1.0, q: float = 1.0, *, noise: str = "discrete",
                 acceleration=None, dtype=None):
        ndim = as_int(ndim, "ndim", minimum=1)
        F1, G1, Q1 = kinematic_matrices(2, dt, q, noise, dtype)
        F = _block_diag_axes(F1, ndim)
        Q = _block_diag_axes(Q1, ndim)
        gain = _block_diag_axes(G1.unsqueeze(-1), ndim)  # (2 ndim, ndim)
        offset = None
        if acceleration is not None:
            acceleration = as_tensor(acceleration, "acceleration", dtype=F.dtype, device=F.device)
            if acceleration.dim() < 1 or acceleration.shape[-1] != ndim:
                raise ValueError(
                    f"acceleration: expected shape (*P, {ndim}), got {tuple(acceleration.shape)}"
                )
            offset = (gain @ acceleration.unsqueeze(-1)).squeeze(-1)
        super().__init__(F, Q, offset=offset)
        store_tensor(self, "noise_gain", gain)
        self.ndim, self.dt, self.q = ndim, float(dt), float(q)


class ConstantAcceleration(LinearMotion):
    """Constant-acceleration (Wiener-process acceleration) model in ``ndim`` axes.

    State per axis ``[p, v, a]``; ``q`` drives the jerk.
    """

    @entry_point(ndim=Int(1), dt=Real(positive=True), q=Real(minimum=0.0),
                 noise=Choice("discrete", "continuous"), dtype=DType())
    def __init__(self, ndim: int = 1, dt: float = 1.0, q: float = 1.0, *, noise: str = "discrete", dtype=None):
        ndim = as_int(ndim, "ndim", minimum=1)
        F1, _, Q1 = kinematic_matrices(3, dt, q, noise, dtype)
        super().__init__(_block_diag_axes(F1, ndim), _block_diag_axes(Q1, ndim))
        self.ndim, self.dt, self.q = ndim, float(dt), float(q)


#: below this |omega dt| the turn terms are evaluated by their Taylor series (exact derivatives at 0)
_TURN_SERIES_BELOW = 0.1


def _turn_terms(omega: Tensor, dt: float, *, derivatives: bool = False) -> tuple[Tensor, ...]:
    r"""``s = sin(w T) / w`` and ``c = (1 - cos(w T)) / w``, cancellation-free, with exact derivatives.

    For ``|w T| >= 0.1`` the closed forms ``sin(w T) / w`` and ``2 sin^2(w T / 2) / w`` (no
    ``1 - cos`` cancellation); below, their Taylor series in ``theta = w T``,
    ``s = T (1 - theta^2/3! + theta^4/5! - theta^6/7! + theta^8/9!)`` and
    ``c = T (theta/2! - theta^3/4! + theta^5/6! - theta^7/8! + theta^9/10!)``, whose truncation error
    (``< theta^10 / 11!`` relative, ``2.5e-18`` at the switch) is below float64 rounding. Both
    branches are smooth, so autograd (reverse and forward mode) gives ``ds/dw`` and ``dc/dw``
    exactly, ``T^2 / 2`` for ``dc/dw`` at ``w = 0``. The closed form is evaluated at a safe
    ``w`` where the series is used (``torch.where`` then passes no NaN gradient).

    With ``derivatives`` also ``ds/dw = (T cos(w T) - s) / w`` and ``dc/dw = (T sin(w T) - c) / w``
    in closed form (from ``|w T| >= 0.1``; their cancellation costs at most ``1e-15 T^2`` there) and
    below by the series ``T^2 (-theta/3 + theta^3/30 - theta^5/840 + theta^7/45360 - theta^9/3991680)``
    and ``T^2 (1/2 - theta^2/8 + theta^4/144 - theta^6/5760 + theta^8/403200 - theta^10/43545600)``
    (truncation below ``1e-18`` relative), and ``cos(w T)``, ``sin(w T)``: what the coordinated turn's
    closed-form Jacobian needs (:meth:`NonlinearCoordinatedTurn.jacobian`).

    Shapes:
        omega: ``(*P,)`` -> two ``(*P,)`` tensors (six with ``derivatives``: ``s, c, ds, dc, cos, sin``)
    """
    theta = omega * dt
    small = theta.abs() < _TURN_SERIES_BELOW
    safe = torch.where(small, torch.ones_like(omega), omega)
    safe_theta = safe * dt
    sin_closed = torch.sin(safe_theta)
    s_closed = sin_closed / safe
    c_closed = 2 * torch.sin(0.5 * safe_theta).square() / safe
    t = torch.where(small, theta, torch.zeros_like(theta))
    t2 = t * t
    # Horner forms of the series (coefficients 1/(2k+1)! and 1/(2k+2)!)
    s_series = dt * (1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42 * (1 - t2 / 72))))
    c_series = dt * t * (0.5 - t2 / 24 * (1 - t2 / 30 * (1 - t2 / 56 * (1 - t2 / 90))))
    s, c = torch.where(small, s_series, s_closed), torch.where(small, c_series, c_closed)
    if not derivatives:
        return s, c
    cos, sin = torch.cos(theta), torch.sin(theta)
    ds_closed = (dt * cos - s_closed) / safe  # cos(theta) = cos(safe_theta) wherever this branch is kept
    dc_closed = (dt * sin_closed - c_closed) / safe
    dt2 = dt * dt
    # derivatives of the series: coefficients -2k/(2k+1)! and (2k+1)/(2k+2)!, Horner
    ds_series = -dt2 * t / 3 * (1 - t2 / 10 * (1 - t2 / 28 * (1 - t2 / 54 * (1 - t2 / 88))))
    dc_series = dt2 * 0.5 * (1 - t2 / 4 * (1 - t2 / 18 * (1 - t2 / 40 * (1 - t2 / 70 * (1 - t2 / 108)))))
    return (s, c, torch.where(small, ds_series, ds_closed), torch.where(small, dc_series, dc_closed), cos, sin)


def turn_matrix(omega: Tensor, dt: float) -> Tensor:
    """Known-turn-rate transition for ``[x, vx, y, vy]``; ``omega: (*P,)`` -> ``(*P, 4, 4)``.

    ``omega = 0`` is exactly the constant-velocity matrix; values and derivatives with respect to
    ``omega`` are accurate to rounding at every ``omega`` (see :func:`_turn_terms`).
    """
    s, c = _turn_terms(omega, dt)
    wt = omega * dt
    cos, sin = torch.cos(wt), torch.sin(wt)
    one, zero = torch.ones_like(omega), torch.zeros_like(omega)
    rows = [
        [one, s, zero, -c],
        [zero, cos, zero, -sin],
        [zero, c, one, s],
        [zero, sin, zero, cos],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


class CoordinatedTurn(LinearMotion):
    """Coordinated turn with known turn rate ``omega`` (rad per unit time), state ``[x, vx, y, vy]``.

    ``omega`` may be a tensor ``(*P,)`` for a bank of turn rates; ``omega = 0`` is CV.
    Process noise is white acceleration on both axes (``noise`` as in :class:`ConstantVelocity`).
    """

    @entry_point(omega=Finite(), dt=Real(positive=True), q=Real(minimum=0.0),
                 noise=Choice("discrete", "continuous"), dtype=DType())
    def __init__(self, omega, dt: float = 1.0, q: float = 1.0, *, noise: str = "discrete", dtype=None):
        _, _, Q1 = kinematic_matrices(2, dt, q, noise, dtype)
        omega = as_tensor(omega, "omega", dtype=Q1.dtype, device=Q1.device)
        super().__init__(turn_matrix(omega, float(dt)), _block_diag_axes(Q1, 2))
        store_tensor(self, "omega", omega)
        self.dt, self.q = float(dt), float(q)


class NonlinearCoordinatedTurn(MotionModel):
    """Coordinated turn with the turn rate in the state: ``[x, vx, y, vy, omega]`` (nonlinear).

    For EKF/UKF. ``q`` is the white-acceleration intensity on both axes, ``q_omega`` the
    turn-rate random-walk variance per step.
    """

    @entry_point(dt=Real(positive=True), q=Real(minimum=0.0), q_omega=Real(minimum=0.0),
                 noise=Choice("discrete", "continuous"), dtype=DType())
    def __init__(self, dt: float = 1.0, q: float = 1.0, q_omega: float = 1e-4, *, noise: str = "discrete",
                 dtype=None):
        super().__init__()
        _, _, Q1 = kinematic_matrices(2, dt, q, noise, dtype)
        Q = torch.zeros(5, 5, dtype=Q1.dtype)
        Q[:4, :4] = _block_diag_axes(Q1, 2)
        Q[4, 4] = as_float(q_omega, "q_omega", minimum=0.0)
        store_tensor(self, "Q", Q)
        self.state_dim, self.dt = 5, float(dt)

    def forward(self, x: Tensor, *, u: Tensor | None = None) -> Tensor:
        # turn_matrix(omega) @ [x, vx, y, vy] written out: no dense (*B, 4, 4) matrix per state (or
        # per sigma point), which cost more than all the arithmetic (docs/performance.md)
        return torch.stack(self.forward_entries(x.unbind(-1)), dim=-1)

    def forward_entries(self, x, *, u: Tensor | None = None) -> list[Tensor]:
        """:meth:`forward` one component at a time (the same operations)."""
        px, vx, py, vy, omega = x
        s, c = _turn_terms(omega, self.dt)
        wt = omega * self.dt
        cos, sin = torch.cos(wt), torch.sin(wt)
        return [px + s * vx - c * vy, cos * vx - sin * vy, py + c * vx + s * vy, sin * vx + cos * vy, omega]

    def jacobian(self, x: Tensor, *, u: Tensor | None = None) -> Tensor:
        """Closed-form ``df/dx`` (the turn terms' derivatives from :func:`_turn_terms`, exact at and
        near ``omega = 0``); differentiable, equal to forward-mode autograd to rounding.

        Shapes: ``x: (*B, 5)`` -> ``(*B, 5, 5)``
        """
        rows = self.jacobian_entries(x.unbind(-1))
        like = rows[0][1]
        one, zero = torch.ones_like(like), torch.zeros_like(like)
        entries = [e if isinstance(e, Tensor) else one if e == 1.0 else zero for row in rows for e in row]
        return torch.stack(entries, dim=-1).unflatten(-1, (5, 5))

    def jacobian_entries(self, x, *, u: Tensor | None = None) -> list[list[Tensor | float]]:
        """:meth:`jacobian` entry by entry: 13 of its 25 entries are exactly 0 or 1."""
        _, vx, _, vy, omega = x
        s, c, ds, dc, cos, sin = _turn_terms(omega, self.dt, derivatives=True)
        dt = self.dt
        return [
            [1.0, s, 0.0, -c, vx * ds - vy * dc],
            [0.0, cos, 0.0, -sin, -dt * (vx * sin + vy * cos)],
            [0.0, c, 1.0, s, vx * dc + vy * ds],
            [0.0, sin, 0.0, cos, dt * (vx * cos - vy * sin)],
            [0.0, 0.0, 0.0, 0.0, 1.0],
        ]

    def noise_cov(self, x: Tensor | None = None) -> Tensor:
        return self.Q

"""Model interfaces: motion and measurement models are stateless ``nn.Module`` s.

Broadcasting convention: a model may carry a batch of parameters (e.g. ``F: (M, n, n)`` for a
bank of ``M`` modes). Parameters broadcast against the *leading* batch dims of the state, so a
belief with batch ``(*B, M)`` is predicted by all ``M`` modes in one call. Filters that add sample
axes (sigma points, particles) put those axes leftmost when they call a model.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

__all__ = ["MeasurementModel", "MotionModel", "check_model_pair", "check_parameter_dtype", "forward_jacobian",
           "store_tensor"]


def store_tensor(module: nn.Module, name: str, value: Tensor) -> None:
    """Register ``value`` as a parameter if it is an ``nn.Parameter``, else as a buffer."""
    if isinstance(value, nn.Parameter):
        module.register_parameter(name, value)
    else:
        module.register_buffer(name, value)


def check_parameter_dtype(value, name: str, dtype: torch.dtype, owner: str) -> None:
    """``TypeError`` naming ``name`` if ``value`` is a floating tensor of another dtype than ``dtype``
    (the model's, from ``owner``, e.g. ``"F"``): a model converts numbers, lists and arrays to its
    dtype, but a tensor's dtype is a choice it does not override (a float32 ``Q`` next to a float64
    ``F`` is refused as a float32 ``F`` next to a float64 belief is)."""
    if isinstance(value, Tensor) and value.is_floating_point() and value.dtype != dtype:
        raise TypeError(f"{name}: dtype {value.dtype} differs from {owner}'s {dtype} (the model takes "
                        f"{owner}'s); convert one of them ({name}.to({dtype}), or {owner} to {value.dtype})")


def forward_jacobian(fn, x: Tensor) -> Tensor:
    """Jacobian of a batched, element-wise-in-batch function by forward-mode autograd.

    ``fn`` maps ``(*B, n) -> (*B, k)`` and must treat batch elements independently (any model
    does). All ``n`` directional derivatives are taken in one call on a ``(n, *B, n)`` input, so
    model parameters keep broadcasting against the batch, and the result is differentiable with
    respect to the model's parameters (usable when training through an EKF).

    Shapes:
        x: ``(*B, n)`` -> ``(*B, k, n)``
    """
    n = x.shape[-1]
    primal = x.unsqueeze(0).expand(n, *x.shape).clone()
    basis = torch.eye(n, dtype=x.dtype, device=x.device)
    tangent = basis.reshape(n, *([1] * (x.dim() - 1)), n).expand(n, *x.shape).clone()
    _, columns = torch.func.jvp(fn, (primal,), (tangent,))
    return columns.movedim(0, -1)


class MotionModel(nn.Module):
    """State transition ``x_k = f(x_{k-1}, u_k) + w_k``, ``w_k ~ N(0, Q)``.

    Subclasses implement :meth:`forward` and :meth:`noise_cov`; :meth:`jacobian` defaults to
    forward-mode autograd and is overridden by linear models.
    """

    state_dim: int

    def forward(self, x: Tensor, *, u: Tensor | None = None) -> Tensor:
        """Propagate states. Shapes: ``x: (*B, n)`` -> ``(*B, n)``."""
        raise NotImplementedError

    def noise_cov(self, x: Tensor | None = None) -> Tensor:
        """Process-noise covariance ``Q``, broadcastable to ``(*B, n, n)``."""
        raise NotImplementedError

    def jacobian(self, x: Tensor, *, u: Tensor | None = None) -> Tensor:
        """``df/dx`` at ``x``. Shapes: ``x: (*B, n)`` -> ``(*B, n, n)``."""
        return forward_jacobian(lambda s: self(s, u=u), x)

    def forward_entries(self, x: Sequence[Tensor], *, u: Tensor | None = None) -> list[Tensor]:
        """:meth:`forward` one state component at a time, for the kernels that keep each component in
        its own tensor (the batch-last IMM over extended and unscented banks,
        :mod:`torchmm.kernels.batch_last.nonlinear`). The default stacks the components and calls
        :meth:`forward`; a model overrides it with the same arithmetic to skip the stack.

        Shapes: ``x``: ``n`` tensors ``(*B,)`` (broadcasting) -> ``n`` tensors broadcasting to ``(*B,)``.
        """
        return list(self(torch.stack(torch.broadcast_tensors(*x), -1), u=u).unbind(-1))

    def jacobian_entries(self, x: Sequence[Tensor], *, u: Tensor | None = None) -> list[list[Tensor | float]]:
        """:meth:`jacobian` entry by entry (see :meth:`forward_entries`): rows ``J[a][e]`` of tensors, or
        the Python numbers ``0.0`` and ``1.0`` where the entry is exactly that at every state (the
        kernels skip those products, exactly). The default takes every entry of :meth:`jacobian`.

        Shapes: ``x``: ``n`` tensors ``(*B,)`` -> ``n`` rows of ``n`` entries broadcasting to ``(*B,)``.
        """
        J = self.jacobian(torch.stack(torch.broadcast_tensors(*x), -1), u=u)
        return [list(row.unbind(-1)) for row in J.unbind(-2)]


class MeasurementModel(nn.Module):
    """Measurement ``z_k = h(x_k) + v_k``, ``v_k ~ N(0, R)``."""

    state_dim: int
    meas_dim: int

    def forward(self, x: Tensor) -> Tensor:
        """Predicted measurement. Shapes: ``x: (*B, n)`` -> ``(*B, m)``."""
        raise NotImplementedError

    def noise_cov(self, x: Tensor | None = None) -> Tensor:
        """Measurement-noise covariance ``R``, broadcastable to ``(*B, m, m)``."""
        raise NotImplementedError

    def jacobian(self, x: Tensor) -> Tensor:
        """``dh/dx`` at ``x``. Shapes: ``x: (*B, n)`` -> ``(*B, m, n)``."""
        return forward_jacobian(self, x)

    def forward_entries(self, x: Sequence[Tensor]) -> list[Tensor]:
        """:meth:`forward` one state component at a time (:meth:`MotionModel.forward_entries`).

        Shapes: ``x``: ``n`` tensors ``(*B,)`` (broadcasting) -> ``m`` tensors broadcasting to ``(*B,)``.
        """
        return list(self(torch.stack(torch.broadcast_tensors(*x), -1)).unbind(-1))

    def jacobian_entries(self, x: Sequence[Tensor]) -> list[list[Tensor | float]]:
        """:meth:`jacobian` entry by entry (:meth:`MotionModel.jacobian_entries`: ``0.0`` and ``1.0`` for
        entries exactly that at every state).

        Shapes: ``x``: ``n`` tensors ``(*B,)`` -> ``m`` rows of ``n`` entries broadcasting to ``(*B,)``.
        """
        J = self.jacobian(torch.stack(torch.broadcast_tensors(*x), -1))
        return [list(row.unbind(-1)) for row in J.unbind(-2)]

    def log_likelihood(self, z: Tensor, x: Tensor) -> Tensor:
        """Gaussian ``log p(z | x)``; NaN components of ``z`` are treated as missing.

        Shapes:
            z: ``(*B, m)``, x: ``(*B, n)`` (e.g. particles ``(Np, *B, n)`` with ``z`` broadcast)
            -> ``(*B,)``
        """
        resid = z - self(x)
        observed = ~torch.isnan(resid)
        resid = torch.where(observed, resid, 0.0)
        cov = self.noise_cov(x)
        pair = observed.unsqueeze(-1) & observed.unsqueeze(-2)
        eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
        cov = torch.where(pair, cov, eye)
        chol = torch.linalg.cholesky(cov)
        white = torch.linalg.solve_triangular(chol, resid.unsqueeze(-1), upper=False).squeeze(-1)
        logdet = 2 * chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        count = observed.sum(-1).to(resid.dtype)
        return -0.5 * (white.square().sum(-1) + logdet + count * math.log(2 * math.pi))


def check_model_pair(motion, measurement) -> None:
    """Check the model types of a filter and that their state dimensions agree."""
    if not isinstance(motion, MotionModel):
        raise ValueError(f"motion: expected a MotionModel, got {type(motion).__name__}")
    if not isinstance(measurement, MeasurementModel):
        raise ValueError(f"measurement: expected a MeasurementModel, got {type(measurement).__name__}")
    if motion.state_dim != measurement.state_dim:
        raise ValueError(
            f"measurement: state_dim {measurement.state_dim} does not match the motion model's "
            f"{motion.state_dim}"
        )

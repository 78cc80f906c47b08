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

from torchmm.validation import adds_no_runs

__all__ = ["MeasurementModel", "MotionModel", "check_entries", "check_model_pair", "check_output",
           "check_parameter_dtype", "forward_jacobian", "store_tensor"]


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
        states = torch.stack(torch.broadcast_tensors(*x), -1)
        return list(check_output(self, self(states, u=u), states, "motion").unbind(-1))

    def jacobian_entries(self, x: Sequence[Tensor], *, u: Tensor | None = None) -> list[list[Tensor | float]]:
        """:meth:`jacobian` entry by entry (see :meth:`forward_entries`): rows ``J[a][e]`` of tensors, or
        the Python numbers ``0.0`` and ``1.0`` where the entry is exactly that at every state (the
        kernels skip those products, exactly). The default takes every entry of :meth:`jacobian`.

        Shapes: ``x``: ``n`` tensors ``(*B,)`` -> ``n`` rows of ``n`` entries broadcasting to ``(*B,)``.
        """
        states = torch.stack(torch.broadcast_tensors(*x), -1)
        J = check_output(self, self.jacobian(states, u=u), states, "motion", "jacobian")
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
        states = torch.stack(torch.broadcast_tensors(*x), -1)
        return list(check_output(self, self(states), states, "measurement").unbind(-1))

    def jacobian_entries(self, x: Sequence[Tensor]) -> list[list[Tensor | float]]:
        """:meth:`jacobian` entry by entry (:meth:`MotionModel.jacobian_entries`: ``0.0`` and ``1.0`` for
        entries exactly that at every state).

        Shapes: ``x``: ``n`` tensors ``(*B,)`` -> ``m`` rows of ``n`` entries broadcasting to ``(*B,)``.
        """
        states = torch.stack(torch.broadcast_tensors(*x), -1)
        J = check_output(self, self.jacobian(states), states, "measurement", "jacobian")
        return [list(row.unbind(-1)) for row in J.unbind(-2)]

    def log_likelihood(self, z: Tensor, x: Tensor) -> Tensor:
        """Gaussian ``log p(z | x)`` with ``R = noise_cov(x)``; non-finite components of ``z`` (NaN or
        ``+-inf``) are missing and marginalised out exactly (an all-missing ``z`` gives 0).

        Missingness comes from ``z`` alone (docs/robustness.md): a NaN ``h(x)`` of a measured
        component, or an ``R(x)`` that is not positive definite (``torch.linalg.cholesky_ex`` fails on
        its measured block), gives a NaN log-likelihood for that state only - a particle filter then
        flags its run failed (``extras["failed"]``) - never a ``LinAlgError`` for the whole batch.

        Shapes:
            z: ``(*B, m)``, x: ``(*B, n)`` (e.g. particles ``(Np, *B, n)`` with ``z`` broadcast)
            -> ``(*B,)``
        """
        resid = z - check_output(self, self(x), x, "measurement")
        observed = torch.isfinite(z).expand_as(resid)
        resid = torch.where(observed, resid, 0.0)
        cov = check_output(self, self.noise_cov(x), x, "measurement", "noise_cov")
        pair = observed.unsqueeze(-1) & observed.unsqueeze(-2)
        eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
        cov = torch.where(pair, cov, eye)
        # where the factorisation fails (or R(x) is NaN), factor the identity instead (finite values and
        # gradients) and return NaN; a positive definite R(x) gets torch.linalg.cholesky's factor
        bad = torch.linalg.cholesky_ex(cov.detach())[1] != 0
        chol = torch.linalg.cholesky_ex(torch.where(bad[..., None, None], eye, cov))[0]
        white = torch.linalg.solve_triangular(chol, resid.unsqueeze(-1), upper=False).squeeze(-1)
        logdet = 2 * chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        count = observed.sum(-1).to(resid.dtype)
        loglik = -0.5 * (white.square().sum(-1) + logdet + count * math.log(2 * math.pi))
        return torch.where(bad, math.nan, loglik)


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


# -- the models' outputs, where a filter calls them ---------------------------------------------------
_FORMS = {"forward": ("", "(*B, {k})"), "jacobian": (".jacobian", "(*B, {k}, n)"),
          "noise_cov": (".noise_cov", "(*B, {k}, {k}) (a batch broadcasting to *B)")}


def _dims(model) -> tuple[int, int, str, str]:
    """``(k, n)`` of a model's outputs, the symbol of ``k`` and the words naming the dimensions."""
    n = model.state_dim
    if isinstance(model, MeasurementModel):
        return model.meas_dim, n, "m", f"meas_dim {model.meas_dim}, state_dim {n}"
    return n, n, "n", f"state_dim {n}"


def _dtype_error(what: str, got: torch.dtype, dtype: torch.dtype) -> TypeError:
    return TypeError(f"{what}: returned dtype {got} for states of dtype {dtype}: a model returns the states' "
                     f"dtype (build it in {dtype}, or convert it: model.to({dtype}))")


def check_output(model: nn.Module, out, x: Tensor | None, name: str, kind: str = "forward", *,
                 batch: Sequence[int] | None = None, dtype: torch.dtype | None = None) -> Tensor:
    """A model's output, as a filter receives it, against the states it was evaluated at: a tensor of the
    states' dtype whose shape is ``(*B', *event)`` with ``*B'`` broadcasting to the states' batch ``*B``
    without adding runs (a shared output ``(1, m)`` or ``(m,)`` is fine, and so are leading unit axes; a
    batch that adds or mixes runs is not). ``TypeError`` / ``ValueError`` naming ``name`` (the filter's
    slot, ``"motion"`` or ``"measurement"``) otherwise; returns ``out`` unchanged. Reads shapes and dtypes
    only: no host read, nothing computed, so the filters check every call (docs/robustness.md, "A model's
    outputs").

    Args:
        model: the :class:`MotionModel` (``k = state_dim``) or :class:`MeasurementModel` (``k = meas_dim``).
        out: what ``model``'s ``kind`` returned: ``"forward"`` (event ``(k,)``), ``"jacobian"`` (``(k, n)``)
            or ``"noise_cov"`` (``(k, k)``).
        x: the states ``(*B, n)``; None where the model had none (``noise_cov()``: only the event and
            ``dtype`` are checked).
        batch: ``*B`` where it is not ``x.shape[:-1]`` (a belief whose covariance carries the batch).
        dtype: the expected dtype where ``x`` is None.

    Shapes:
        x: ``(*B, n)`` -> ``out``: ``(*B', *event)``, ``*B'`` broadcasting to ``*B``
    """
    n = model.state_dim
    k = model.meas_dim if isinstance(model, MeasurementModel) else n
    event = (k,) if kind == "forward" else (k, n) if kind == "jacobian" else (k, k)
    if x is not None:
        dtype = x.dtype
        batch = x.shape[:-1] if batch is None else batch
    if isinstance(out, Tensor) and (dtype is None or out.dtype == dtype):
        shape, e = out.shape, len(event)
        if shape[max(out.dim() - e, 0):] == event and (batch is None or adds_no_runs(shape[:-e], batch)):
            return out  # (the usual case: a few comparisons of Python values)
    suffix, form = _FORMS[kind]
    k, n, symbol, dims = _dims(model)
    if not isinstance(out, Tensor):
        raise TypeError(f"{name}{suffix}: returned {type(out).__name__}, expected a tensor "
                        f"{form.format(k=symbol)}")
    if dtype is not None and out.dtype != dtype:
        raise _dtype_error(f"{name}{suffix}", out.dtype, dtype)
    shape = out.shape
    expected = "" if batch is None else f"expected {tuple((*batch, *event))} - "
    states = "" if x is None else f" for states {tuple(x.shape)}"
    hint = ""
    if kind == "forward" and k == 1 and x is not None and tuple(shape) == tuple(x.shape[:-1]):
        hint = " (the event axis is missing: return x[..., :1] or h.unsqueeze(-1), not x[..., 0])"
    elif kind == "jacobian":
        hint = f" (autograd's Jacobian of forward: does forward return (*B, {symbol}) for every batch (*B,)?)"
    raise ValueError(f"{name}{suffix}: returned shape {tuple(shape)}{states}: {expected}"
                     f"{form.format(k=symbol)} with {dims}{hint}")


def check_entries(model: nn.Module, entries, x: Sequence[Tensor], name: str, kind: str = "forward") -> list:
    """:func:`check_output` of a model's ``forward_entries`` (``k`` tensors) or ``jacobian_entries`` (``k``
    rows of ``n`` entries, each a tensor or a Python number) at the components ``x``: each tensor of the
    components' dtype, broadcasting to their batch without adding runs. Returns ``entries``.

    Shapes:
        x: ``n`` tensors broadcasting to ``(*B,)`` -> entries broadcasting to ``(*B,)``
    """
    k, n, _, dims = _dims(model)
    batch, dtype = x[0].shape, x[0].dtype
    for t in x[1:]:
        if t.shape != batch:
            batch = torch.broadcast_shapes(batch, t.shape)
    method = f"{name}.{kind}_entries"
    jacobian = kind == "jacobian"
    if not isinstance(entries, (list, tuple)) or len(entries) != k:
        what = "row(s)" if jacobian else "tensor(s)"
        raise ValueError(f"{method}: returned {_count(entries)}, expected {k} {what} ({dims})")
    for row in entries if jacobian else [entries]:
        if not isinstance(row, (list, tuple)) or len(row) != (n if jacobian else k):
            raise ValueError(f"{method}: returned a row of {_count(row)}, expected {n} entries ({dims})")
        for entry in row:
            if isinstance(entry, Tensor):
                if entry.dtype != dtype:
                    raise _dtype_error(method, entry.dtype, dtype)
                if entry.shape != batch and not adds_no_runs(entry.shape, batch):
                    raise ValueError(f"{method}: returned an entry of shape {tuple(entry.shape)} for "
                                     f"components {tuple(batch)}: each entry broadcasts to their batch (*B,)")
            elif not jacobian or not isinstance(entry, (int, float)):
                raise TypeError(f"{method}: returned a {type(entry).__name__} entry, expected a tensor"
                                + (" or a Python number" if jacobian else ""))
    return entries


def _count(value) -> str:
    return f"{len(value)} items" if isinstance(value, (list, tuple)) else f"a {type(value).__name__}"

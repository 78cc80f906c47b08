"""Input validation with errors that name the offending argument.

Two kinds of checks, with different costs (``docs/robustness.md`` lists where each runs):

* **Shape, type and dtype checks** read no tensor values (a few Python comparisons), so they run
  everywhere, also inside every filter step: :func:`check_measurement`, :func:`gaussian_batch`,
  :func:`check_same_dtype`.
* **Value checks** (finite entries, symmetric PSD covariances, stochastic matrices,
  probabilities) synchronise with the device, so they run once at the entry points a user calls -
  constructors, ``initial_belief``, the start of :func:`~torchmm.run_filter` - and never inside a
  step: :func:`as_tensor`, :func:`check_covariance`, :func:`check_stochastic_rows`,
  :func:`check_probabilities`.

Every error is a ``ValueError`` (a wrong value or shape) or ``TypeError`` (a wrong type or dtype)
whose message starts with the name of the argument the user passed. All checks work on detached
values, so tensors that require grad (learnable parameters, ``gradcheck`` inputs) pass through.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "adds_no_runs",
    "as_choice",
    "as_float",
    "as_int",
    "as_tensor",
    "broadcast_shape",
    "check_covariance",
    "check_data_batch",
    "check_filter_dtype",
    "check_measurement",
    "check_parameter_batch",
    "check_probabilities",
    "check_same_dtype",
    "check_shape",
    "check_square",
    "check_stochastic_rows",
    "gaussian_batch",
]

#: Absolute tolerance on row sums and symmetry. Loose enough for float32 inputs and for the
#: one-sided perturbations of ``torch.autograd.gradcheck`` (1e-6), tight enough to catch a typo.
STOCHASTIC_ATOL = 1e-5
SYMMETRY_RTOL = 1e-5


# -- numbers and options -------------------------------------------------------------------------
def as_int(value, name: str, *, minimum: int | None = None) -> int:
    """An integer argument (``int``, NumPy integer, integral 0-d tensor; not ``bool`` or ``1.5``).

    Raises:
        TypeError: if ``value`` is not an integer; ValueError: if it is below ``minimum``.
    """
    if isinstance(value, Tensor) and value.dim() == 0 and not value.is_floating_point() \
            and value.dtype != torch.bool:
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name}: expected an integer, got {value!r}")
    value = int(value)
    if minimum is not None and value < minimum:
        raise ValueError(f"{name}: must be >= {minimum}, got {value}")
    return value


def as_float(value, name: str, *, minimum: float | None = None, maximum: float | None = None,
             positive: bool = False) -> float:
    """A finite real argument, optionally bounded (``positive``: strictly above 0).

    Raises:
        TypeError: if ``value`` is not a real number; ValueError: if it is not finite or out of range.
    """
    if isinstance(value, Tensor) and value.numel() == 1:
        value = value.detach().reshape(()).item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name}: expected a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name}: must be finite, got {value}")
    if positive and not value > 0:
        raise ValueError(f"{name}: must be positive, got {value}")
    if minimum is not None and value < minimum:
        raise ValueError(f"{name}: must be >= {minimum}, got {value}")
    if maximum is not None and value > maximum:
        raise ValueError(f"{name}: must be <= {maximum}, got {value}")
    return value


def as_choice(value, name: str, choices: Sequence[str]) -> str:
    """One of ``choices`` (strings). Raises ``ValueError`` listing them."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name}: expected one of {list(choices)}, got {value!r}")
    return value


# -- tensors (values read: entry points only) ------------------------------------------------------
def as_tensor(value, name: str, *, dtype: torch.dtype | None = None, device=None) -> Tensor:
    """Convert ``value`` to a floating tensor; raise ``ValueError`` naming ``name`` if it cannot be
    or if it has NaN or infinite entries.

    Tensors keep their dtype unless ``dtype`` is given (autograd history is preserved); integer and
    boolean inputs become the default floating dtype.
    """
    if isinstance(value, Tensor):
        out = value
        if dtype is not None or device is not None:
            out = out.to(dtype=dtype or out.dtype, device=device or out.device)
    else:
        if isinstance(value, str):
            raise TypeError(f"{name}: expected numbers, got the string {value!r}")
        try:
            out = torch.as_tensor(value, dtype=dtype or torch.get_default_dtype(), device=device)
        except (TypeError, ValueError, RuntimeError) as err:
            raise ValueError(f"{name}: cannot convert to a tensor ({err})") from None
    if not out.is_floating_point():
        if out.is_complex():
            raise TypeError(f"{name}: expected real numbers, got dtype {out.dtype}")
        out = out.to(dtype or torch.get_default_dtype())
    if not bool(torch.isfinite(out.detach()).all()):
        raise ValueError(f"{name}: contains NaN or infinite entries")
    return out


def check_shape(tensor: Tensor, name: str, trailing: Sequence[int | None]) -> None:
    """Check that the trailing dimensions of ``tensor`` equal ``trailing`` (``None`` = any size)."""
    k = len(trailing)
    if tensor.dim() < k:
        raise ValueError(
            f"{name}: expected at least {k} dimensions with trailing shape {tuple(trailing)}, "
            f"got shape {tuple(tensor.shape)}"
        )
    got = tuple(tensor.shape[tensor.dim() - k :]) if k else ()
    for want, have in zip(trailing, got):
        if want is not None and want != have:
            raise ValueError(
                f"{name}: expected trailing shape {tuple(trailing)}, got shape {tuple(tensor.shape)}"
            )


def check_square(tensor: Tensor, name: str) -> int:
    """Check that the last two dimensions are equal and non-zero; return their size."""
    if tensor.dim() < 2 or tensor.shape[-1] != tensor.shape[-2]:
        raise ValueError(f"{name}: expected a square matrix (..., d, d), got shape {tuple(tensor.shape)}")
    if tensor.shape[-1] == 0:
        raise ValueError(f"{name}: expected a non-empty square matrix, got shape {tuple(tensor.shape)}")
    return tensor.shape[-1]


def _distinct(tensor: Tensor) -> Tensor:
    """``tensor`` with every broadcast batch axis (stride 0: one matrix repeated, e.g. a prior
    ``expand``-ed over the runs) narrowed to one entry: the same matrices, each checked once."""
    for dim in range(tensor.dim() - 2):
        if tensor.stride(dim) == 0 and tensor.shape[dim] > 1:
            tensor = tensor.narrow(dim, 0, 1)
    return tensor


#: a CPU tensor of at most this many entries is checked in NumPy at an entry point: its few small
#: operations cost about a microsecond each there, several in torch (issue 47: the one-shot call's cost)
SMALL_CHECK = 1 << 16
_NUMPY_DTYPES = (torch.float64, torch.float32, torch.float16)


def host_array(tensor: Tensor) -> np.ndarray | None:
    """``tensor``'s values as a NumPy array (sharing memory, read-only use) when it is a small CPU
    floating tensor (:data:`SMALL_CHECK` entries), else None (check it in torch)."""
    if not tensor.is_cpu or tensor.dtype not in _NUMPY_DTYPES or tensor.numel() > SMALL_CHECK:
        return None
    try:
        return (tensor.detach() if tensor.requires_grad else tensor).numpy()
    except (RuntimeError, TypeError):  # a view with a pending negation, or any other non-plain storage
        return None


def all_finite(tensor: Tensor) -> bool:
    """Whether every entry of a floating ``tensor`` is finite (one host read)."""
    array = host_array(tensor)
    if array is not None:
        return bool(np.isfinite(array).all())
    return bool(torch.isfinite(tensor.detach()).all())


def check_covariance(tensor: Tensor, name: str, *, definite: bool = False) -> None:
    """Check that ``tensor`` (..., d, d) is finite, symmetric and positive semi-definite (or definite).

    Both tolerances are relative to the matrix's largest entry, never absolute: symmetry to
    ``1e-5`` times it (float32 inputs pass), the eigenvalues to ``-1e-10`` times it (``<= 1e-10``
    times it fails ``definite``), so ``1e-12 I`` and ``1e-300 I`` are positive definite.

    Raises:
        ValueError: naming ``name`` and the failed property.
    """
    check_square(tensor, name)
    array = host_array(tensor)
    if array is not None:
        return _check_covariance_numpy(array, name, definite)
    value = _distinct(tensor.detach()).to(torch.float64)
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name}: contains NaN or infinite entries")
    if value.numel() == 0:
        return
    # relative to each matrix's own scale: R = 1e-12 I is as valid as I (an absolute floor would
    # call every tiny covariance indefinite); the all-zero matrix has scale 0 and passes as PSD
    scale = value.abs().amax(dim=(-1, -2), keepdim=True)
    if bool(((value - value.mT).abs() > SYMMETRY_RTOL * scale).any()):
        raise ValueError(f"{name}: covariance is not symmetric")
    eigvals = torch.linalg.eigvalsh(0.5 * (value + value.mT))
    tol = 1e-10 * scale.squeeze(-1)
    if definite and bool((eigvals <= tol).any()):
        raise ValueError(
            f"{name}: covariance is not positive definite (smallest eigenvalue "
            f"{eigvals.min().item():.3g})"
        )
    if bool((eigvals < -tol).any()):
        raise ValueError(
            f"{name}: covariance is not positive semi-definite (smallest eigenvalue "
            f"{eigvals.min().item():.3g})"
        )


def _check_covariance_numpy(array: np.ndarray, name: str, definite: bool) -> None:
    """:func:`check_covariance` of a small CPU tensor's values, in NumPy (the same tests and messages)."""
    value = array.astype(np.float64, copy=False)
    for axis in range(array.ndim - 2):  # (a broadcast prior: each matrix once, as _distinct)
        if array.strides[axis] == 0 and array.shape[axis] > 1:
            value = value[(slice(None),) * axis + (slice(0, 1),)]
    if not np.isfinite(value).all():
        raise ValueError(f"{name}: contains NaN or infinite entries")
    if value.size == 0:
        return
    scale = np.abs(value).max(axis=(-1, -2), keepdims=True)
    if value.shape[-1] == 1:  # (a variance: symmetric, its own eigenvalue)
        eigvals = value[..., 0]
    else:
        transposed = np.swapaxes(value, -1, -2)
        if (np.abs(value - transposed) > SYMMETRY_RTOL * scale).any():
            raise ValueError(f"{name}: covariance is not symmetric")
        eigvals = _small_eigvalsh(0.5 * (value + transposed), scale)
    tol = 1e-10 * scale[..., 0]
    if definite and (eigvals <= tol).any():
        raise ValueError(f"{name}: covariance is not positive definite (smallest eigenvalue {eigvals.min():.3g})")
    if (eigvals < -tol).any():
        raise ValueError(f"{name}: covariance is not positive semi-definite (smallest eigenvalue "
                         f"{eigvals.min():.3g})")


def _small_eigvalsh(sym: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The eigenvalues of symmetric ``sym (..., d, d)``: in closed form for ``d <= 2`` (``np.linalg.eigvalsh``'s
    call costs ten microseconds at any size: the one-shot call's check of a scalar or planar state), on
    the matrices divided by their ``scale`` (their largest entry, ``(..., 1, 1)``) so that no square
    overflows or underflows, then multiplied back (only the smallest is tested, to 1e-10 of the scale)."""
    d = sym.shape[-1]
    if d > 2:
        return np.linalg.eigvalsh(sym)
    if d == 1:
        return sym[..., 0]
    unit = np.where(scale > 0, scale, 1.0)[..., 0, 0]
    a, b, c = sym[..., 0, 0] / unit, sym[..., 1, 0] / unit, sym[..., 1, 1] / unit
    half, radius = 0.5 * (a + c), np.hypot(0.5 * (a - c), b)
    return np.stack([half - radius, half + radius], axis=-1) * unit[..., None]


def check_stochastic_rows(matrix: Tensor, name: str) -> None:
    """Check a finite (..., M, M) matrix of probabilities whose rows sum to one."""
    check_square(matrix, name)
    value = matrix.detach()
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name}: contains NaN or infinite entries")
    if bool((value < 0).any()):
        raise ValueError(f"{name}: has negative entries")
    row_sums = value.sum(-1)
    if bool(((row_sums - 1).abs() > STOCHASTIC_ATOL).any()):
        raise ValueError(
            f"{name}: rows must sum to 1 (P[i, j] = P(mode_k = j | mode_k-1 = i)); "
            f"row sums are {row_sums.tolist()}"
        )


def check_probabilities(probs, name: str, size: int, *, dtype=None, device=None) -> Tensor:
    """Convert and check a probability vector ``(size,)`` or a batch ``(*B, size)``.

    Finite, non-negative, summing to one (to ``1e-5``) along the last axis.

    Raises:
        ValueError: naming ``name``.
    """
    probs = as_tensor(probs, name, dtype=dtype, device=device)
    if probs.dim() < 1 or probs.shape[-1] != size:
        raise ValueError(f"{name}: expected {size} modes, shape ({size},) or (*B, {size}); "
                         f"got shape {tuple(probs.shape)}")
    value = probs.detach()
    if bool((value < 0).any()) or bool(((value.sum(-1) - 1).abs() > STOCHASTIC_ATOL).any()):
        raise ValueError(f"{name}: must be non-negative and sum to 1")
    return probs


# -- per-step shape checks (no values read) ----------------------------------------------------------
def broadcast_shape(*shapes) -> torch.Size:
    """``torch.broadcast_shapes`` in plain Python (several times faster for the few short shapes
    of a filter step). Raises ``RuntimeError`` like it when the shapes do not broadcast."""
    if shapes and all(s == shapes[0] for s in shapes):  # (the usual case: one batch shape)
        return torch.Size(shapes[0])
    ndim = max((len(s) for s in shapes), default=0)
    out = [1] * ndim
    for shape in shapes:
        offset = ndim - len(shape)
        for i, size in enumerate(shape):
            j = offset + i
            if size != out[j]:
                if out[j] == 1:
                    out[j] = size
                elif size != 1:
                    raise RuntimeError(f"shapes {[tuple(s) for s in shapes]} do not broadcast")
    return torch.Size(out)


def gaussian_batch(belief, state_dim: int, name: str = "belief") -> torch.Size:
    """Batch shape of a Gaussian-type belief (``mean (*B, n)``, ``cov (*B, n, n)``), checked against
    the model's state dimension. Reads shapes only.

    Raises:
        TypeError: ``belief`` has no ``mean``/``cov`` tensors; ValueError: wrong state dimension.
    """
    mean, cov = getattr(belief, "mean", None), getattr(belief, "cov", None)
    if not isinstance(mean, Tensor) or not isinstance(cov, Tensor):
        raise TypeError(f"{name}: expected a GaussianBelief (mean, cov), got {type(belief).__name__}")
    if mean.shape[-1] != state_dim:
        raise ValueError(f"{name}: state dimension {mean.shape[-1]} does not match the model's "
                         f"state_dim {state_dim} (mean has shape {tuple(mean.shape)})")
    mb, cb = mean.shape[:-1], cov.shape[:-2]
    if mb == cb:
        return mb
    try:
        return broadcast_shape(mb, cb)
    except RuntimeError:
        raise ValueError(f"{name}: batch shapes of mean {tuple(mb)} and cov {tuple(cb)} do not "
                         "broadcast") from None


def check_measurement(z, meas_dim: int, batch: torch.Size, like: Tensor, name: str = "z") -> Tensor:
    """Check a measurement ``(*B', m)`` against the sensor and the belief; return it as a tensor.

    Reads shapes only. ``z``'s last axis must be the sensor's ``m`` and its batch must broadcast
    *to* the belief's batch ``batch`` (a measurement shared by all runs is allowed; a measurement
    batch that would enlarge the belief's batch - ``(B, 1, m)`` against ``(B,)`` runs - is not).
    Lists and integer tensors are converted, other floating dtypes cast to ``like``'s dtype.
    Non-finite components (NaN, ``+-inf``) are missing data; they are not touched here.

    Raises:
        ValueError: naming ``name``, with the expected and the given shapes.
    """
    if not isinstance(z, Tensor):
        if z is None or isinstance(z, str):
            raise TypeError(f"{name}: expected a tensor of shape (*B, {meas_dim}), got {type(z).__name__}")
        try:
            z = torch.as_tensor(z, dtype=like.dtype, device=like.device)
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(f"{name}: cannot convert to a tensor ({err})") from None
    elif z.dtype != like.dtype:
        if z.is_complex():
            raise TypeError(f"{name}: expected real numbers, got dtype {z.dtype}")
        z = z.to(like.dtype)
    if z.dim() == 0 or z.shape[-1] != meas_dim:
        hint = " (a scalar sensor's measurements need their event axis: z.unsqueeze(-1))" \
            if meas_dim == 1 and z.dim() >= 1 else ""
        raise ValueError(f"{name}: expected shape (*B, {meas_dim}) for a {meas_dim}-dimensional "
                         f"sensor, got {tuple(z.shape)}{hint}")
    check_data_batch(z.shape[:-1], batch, name, (*batch, meas_dim))
    if z.device != like.device:
        z = z.to(like.device)
    return z


def check_data_batch(shape: torch.Size, batch: torch.Size, name: str, expected: tuple) -> None:
    """``ValueError`` naming ``name`` unless a datum's batch ``shape`` broadcasts *to* the belief's ``batch``
    (shared by runs: yes; one that would enlarge the batch: no). Reads shapes only; ``expected``: the
    datum's full shape, for the message. :func:`check_measurement`'s test, and ``run_filter``'s of
    ``controls``."""
    if shape == batch:
        return
    try:
        ok = broadcast_shape(shape, batch) == batch
    except RuntimeError:
        ok = False
    if not ok:
        raise ValueError(f"{name}: batch shape {tuple(shape)} does not broadcast to the belief's batch "
                         f"{tuple(batch)} (expected shape {expected}; to filter several runs from one prior, "
                         "expand the prior: belief.expand(runs))")


def adds_no_runs(shape: Sequence[int], batch: Sequence[int]) -> bool:
    """Whether a batch ``shape`` (a model parameter's, or a model output's) broadcasts with the runs' ``batch``
    without adding runs: to ``batch`` itself, or to ``batch`` behind unit axes (a parameter batch ``(1,)`` next
    to a belief of batch ``()``, as the steps broadcast it; tests/filters/test_broadcast_batches.py). Python
    values only (the filters ask it at every model call).

    Examples:
        >>> adds_no_runs((1, 3), (3,)), adds_no_runs((2, 1), (3,)), adds_no_runs((4,), (3,))
        (True, False, False)
    """
    if shape == batch:
        return True
    extra = len(shape) - len(batch)
    if extra > 0 and any(s != 1 for s in shape[:extra]):
        return False
    return all(s == b or s == 1 for s, b in zip(reversed(shape), reversed(batch)))


def check_parameter_batch(shape: torch.Size, batch: torch.Size, name: str, *, exact: bool = False) -> None:
    """``ValueError`` naming ``name`` unless a model parameter's batch ``shape`` broadcasts with the belief's
    ``batch`` (``belief0``'s at :func:`~torchmm.run_filter`'s entry) without adding runs: per-run
    parameters of the belief's batch, or broadcasting to it, are fine; unit axes a parameter adds are the
    run's (a ``Q (1, n, n)`` with one run of batch ``()``: tests/filters/test_broadcast_batches.py) unless
    ``exact`` (the batch must stay ``batch``: a transition's). Reads shapes only.

    Examples:
        >>> check_parameter_batch(torch.Size([2, 1]), torch.Size([3]), "motion.F")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: motion.F: parameter batch (2, 1) would enlarge belief0's batch (3,) to (2, 3): ...
    """
    if shape == batch or not shape or (not exact and adds_no_runs(shape, batch)):
        return
    hint = ("per-run parameters have belief0's batch or broadcast to it (to filter several runs from one "
            "prior, expand it: belief0.expand(runs))")
    try:
        wide = broadcast_shape(shape, batch)
    except RuntimeError:
        raise ValueError(f"{name}: parameter batch {tuple(shape)} does not broadcast with belief0's batch "
                         f"{tuple(batch)}: {hint}") from None
    if not exact or wide != batch:
        raise ValueError(f"{name}: parameter batch {tuple(shape)} would enlarge belief0's batch "
                         f"{tuple(batch)} to {tuple(wide)}: {hint}")


def check_same_dtype(tensor: Tensor, name: str, like: Tensor, what: str = "the belief") -> None:
    """``TypeError`` naming ``name`` if ``tensor``'s floating dtype differs from ``like``'s."""
    if tensor.dtype != like.dtype:
        raise TypeError(f"{name}: dtype {tensor.dtype} differs from {what}'s {like.dtype}; convert one "
                        f"of them (e.g. filter.to({like.dtype}) or belief.to({tensor.dtype}))")


def module_tensors(module: torch.nn.Module) -> list[tuple[str, Tensor]]:
    """``(name, tensor)`` of a module's parameters, then its buffers, as ``named_parameters()`` and
    ``named_buffers()`` list them (each tensor and module once), from the modules' own dictionaries:
    a few microseconds where the two generators cost tens (read at every ``run_filter`` call)."""
    params: list = []
    buffers: list = []
    seen: set = set()
    seen_params: set = set()
    seen_buffers: set = set()

    def walk(prefix: str, mod: torch.nn.Module) -> None:
        if id(mod) in seen:
            return
        seen.add(id(mod))
        for key, t in mod._parameters.items():
            if t is not None and id(t) not in seen_params:
                seen_params.add(id(t))
                params.append((prefix + key, t))
        for key, t in mod._buffers.items():
            if t is not None and id(t) not in seen_buffers:
                seen_buffers.add(id(t))
                buffers.append((prefix + key, t))
        for key, child in mod._modules.items():
            if child is not None:
                walk(prefix + key + ".", child)

    walk("", module)
    return params + buffers


def check_filter_dtype(filter, belief, name: str, tensors: list | None = None) -> None:
    """``TypeError`` naming ``name`` if the filter's floating tensors and the belief differ in dtype.

    Reads dtypes only (an entry-point check: it walks the filter's parameters and buffers, or takes
    ``tensors``, :func:`module_tensors`' list of them, where the caller has it).
    """
    dtype = getattr(belief, "dtype", None)
    if dtype is None:
        return
    for tensor_name, tensor in module_tensors(filter) if tensors is None else tensors:
        if tensor.is_floating_point() and tensor.dtype != dtype:
            raise TypeError(f"{name}: dtype {dtype} differs from the filter's {tensor.dtype} ({tensor_name}); "
                            f"convert one of them, e.g. filter.to({dtype}) or {name}.to({tensor.dtype})")


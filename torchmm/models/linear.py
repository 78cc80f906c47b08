"""Linear-Gaussian motion and measurement models, optionally stacked into per-mode banks."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchmm.contract import Cov, Finite, entry_point
from torchmm.models.base import MeasurementModel, MotionModel, check_parameter_dtype, store_tensor
from torchmm.validation import as_tensor, broadcast_shape, check_covariance, check_shape, check_square

__all__ = ["LinearMeasurement", "LinearMotion", "matvec", "plain_linear"]


def matvec(A: Tensor, x: Tensor) -> Tensor:
    """``A @ x`` for a matrix ``A (*P, r, c)`` and vectors ``x (*B, c)`` -> ``(*B, r)``.

    An unbatched ``A`` is applied as ``x @ A^T``, which folds every batch dim into one matmul
    (much faster than a broadcast batched matmul over many tiny matrices).
    """
    if A.dim() == 2:
        return x @ A.mT
    return (A @ x.unsqueeze(-1)).squeeze(-1)


def _param_batch(name_shapes: dict[str, torch.Size], event: dict[str, int], owner: str) -> torch.Size:
    shapes = {k: s[: len(s) - event[k]] for k, s in name_shapes.items()}
    try:
        return broadcast_shape(*shapes.values())
    except RuntimeError:
        raise ValueError(
            f"{owner}: parameter batch shapes do not broadcast: "
            + ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items())
        ) from None


class LinearMotion(MotionModel):
    r"""Linear-Gaussian motion ``x_k = F x_{k-1} + B u_k + b + w_k``, ``w_k ~ N(0, Q)``.

    A *bank* of modes is the same object with leading parameter dims: ``F: (M, n, n)``,
    ``offset: (M, n)`` (e.g. ``G a_j`` for acceleration modes), ``Q: (M, n, n)``; any of them may
    also be shared (unbatched). One call then predicts every mode of a belief with batch
    ``(*B, M)``.

    Args:
        F: transition matrix, ``(*P, n, n)`` in math orientation (``x_out = F x_in``).
        Q: process-noise covariance, ``(*P, n, n)``, symmetric PSD (may be singular). ``Q``,
            ``offset`` and ``input_matrix`` take ``F``'s dtype (numbers, lists and arrays are
            converted; a tensor of another floating dtype is refused, a TypeError naming it).
        offset: constant input ``b``, ``(*P, n)``; default zero.
        input_matrix: ``B`` for a time-varying control ``u_k``, ``(*P, n, k)``; default none.

    Shapes:
        forward: ``x (*B, n)``, ``u (*B, k)`` -> ``(*B, n)``; ``*P`` broadcasts with ``*B``.
    """

    #: each parameter's number of event (trailing) axes, the rest its batch (``Filter.check_parameter_batch``)
    param_events = {"F": 2, "Q": 2, "offset": 1, "input_matrix": 2}

    @entry_point(F=Finite(square=True, check=False), Q=Cov(check=False),
                 offset=Finite(optional=True, check=False), input_matrix=Finite(optional=True, check=False))
    def __init__(self, F, Q, offset=None, input_matrix=None):
        super().__init__()
        F = as_tensor(F, "F")
        n = check_square(F, "F")
        for name, value in (("Q", Q), ("offset", offset), ("input_matrix", input_matrix)):
            check_parameter_dtype(value, name, F.dtype, "F")
        Q = as_tensor(Q, "Q", dtype=F.dtype, device=F.device)
        check_shape(Q, "Q", (n, n))
        check_covariance(Q, "Q")
        if offset is None:
            offset = torch.zeros(n, dtype=F.dtype, device=F.device)
        else:
            offset = as_tensor(offset, "offset", dtype=F.dtype, device=F.device)
        check_shape(offset, "offset", (n,))
        shapes = {"F": F.shape, "Q": Q.shape, "offset": offset.shape}
        events = {"F": 2, "Q": 2, "offset": 1}
        if input_matrix is not None:
            input_matrix = as_tensor(input_matrix, "input_matrix", dtype=F.dtype, device=F.device)
            check_shape(input_matrix, "input_matrix", (n, None))
            shapes["input_matrix"] = input_matrix.shape
            events["input_matrix"] = 2
        self.param_batch_shape = _param_batch(shapes, events, "LinearMotion")
        self.state_dim = n
        store_tensor(self, "F", F)
        store_tensor(self, "Q", Q)
        store_tensor(self, "offset", offset)
        self.input_matrix: Tensor | None
        if input_matrix is None:
            self.input_matrix = None
        else:
            store_tensor(self, "input_matrix", input_matrix)

    def forward(self, x: Tensor, *, u: Tensor | None = None) -> Tensor:
        out = matvec(self.F, x) + self.offset
        if u is not None:
            if self.input_matrix is None:
                raise ValueError("u: this LinearMotion has no input_matrix")
            if u.dim() == 0 or u.shape[-1] != self.input_matrix.shape[-1]:
                raise ValueError(f"u: expected shape (*B, {self.input_matrix.shape[-1]}) for input_matrix "
                                 f"{tuple(self.input_matrix.shape)}, got {tuple(u.shape)}")
            out = out + matvec(self.input_matrix, u)
        return out

    def noise_cov(self, x: Tensor | None = None) -> Tensor:
        return self.Q

    def jacobian(self, x: Tensor, *, u: Tensor | None = None) -> Tensor:
        return self.F.expand(*broadcast_shape(x.shape[:-1], self.F.shape[:-2]), -1, -1)

    def select_mode(self, index: int) -> LinearMotion:
        """The single model ``index`` of a bank (parameters indexed on the parameter batch)."""
        shape = self.param_batch_shape
        if len(shape) != 1:
            raise ValueError(f"index: select_mode needs a bank with one parameter axis, got {tuple(shape)}")
        if not -shape[0] <= index < shape[0]:
            raise ValueError(f"index: {index} out of range for a bank of {shape[0]} modes")

        def pick(t: Tensor, event: int) -> Tensor:
            return t.expand(*shape, *t.shape[t.dim() - event :])[index]

        inputs = None if self.input_matrix is None else pick(self.input_matrix, 2)
        return LinearMotion(pick(self.F, 2), pick(self.Q, 2), offset=pick(self.offset, 1), input_matrix=inputs)

    @classmethod
    def stack(cls, models: Sequence[LinearMotion]) -> LinearMotion:
        """A bank whose leading parameter axis enumerates ``models`` (all unbatched)."""
        _check_stackable(models, cls, "models")
        if any(m.input_matrix is not None for m in models) and not all(
            m.input_matrix is not None for m in models
        ):
            raise ValueError("models: either all or none of the models must have an input_matrix")
        inputs = None
        if models[0].input_matrix is not None:
            inputs = torch.stack([m.input_matrix for m in models])
        return LinearMotion(
            F=torch.stack([m.F for m in models]),
            Q=torch.stack([m.Q for m in models]),
            offset=torch.stack([m.offset for m in models]),
            input_matrix=inputs,
        )

    def extra_repr(self) -> str:
        return f"state_dim={self.state_dim}, param_batch_shape={tuple(self.param_batch_shape)}"


class LinearMeasurement(MeasurementModel):
    """Linear-Gaussian measurement ``z_k = H x_k + v_k``, ``v_k ~ N(0, R)``.

    Args:
        H: measurement matrix ``(*P, m, n)``.
        R: measurement-noise covariance ``(*P, m, m)``, symmetric PSD, in ``H``'s dtype (a tensor of
            another floating dtype is refused, a TypeError naming ``R``).
    """

    #: each parameter's number of event (trailing) axes (``Filter.check_parameter_batch``)
    param_events = {"H": 2, "R": 2}

    @entry_point(H=Finite(check=False), R=Cov(check=False))
    def __init__(self, H, R):
        super().__init__()
        H = as_tensor(H, "H")
        if H.dim() < 2:
            raise ValueError(f"H: expected shape (*P, m, n), got {tuple(H.shape)}")
        m, n = H.shape[-2:]
        check_parameter_dtype(R, "R", H.dtype, "H")
        R = as_tensor(R, "R", dtype=H.dtype, device=H.device)
        check_shape(R, "R", (m, m))
        check_covariance(R, "R")
        self.param_batch_shape = _param_batch(
            {"H": H.shape, "R": R.shape}, {"H": 2, "R": 2}, "LinearMeasurement"
        )
        self.state_dim, self.meas_dim = n, m
        store_tensor(self, "H", H)
        store_tensor(self, "R", R)

    @classmethod
    def unchecked(cls, H: Tensor, R: Tensor) -> LinearMeasurement:
        """A pseudo-measurement built inside a step from a filter's own tensors (e.g. a track's
        estimate fused as a datum with ``R`` = its covariance): shapes are checked, values are not
        (no device synchronisation; ``R`` is a covariance by construction).

        Shapes:
            H: ``(*P, m, n)``; R: ``(*P, m, m)``
        """
        self = cls.__new__(cls)
        MeasurementModel.__init__(self)
        m, n = H.shape[-2:]
        check_shape(R, "R", (m, m))
        self.param_batch_shape = torch.Size(broadcast_shape(H.shape[:-2], R.shape[:-2]))
        self.state_dim, self.meas_dim = n, m
        store_tensor(self, "H", H)
        store_tensor(self, "R", R)
        return self

    def forward(self, x: Tensor) -> Tensor:
        return matvec(self.H, x)

    def noise_cov(self, x: Tensor | None = None) -> Tensor:
        return self.R

    def jacobian(self, x: Tensor) -> Tensor:
        return self.H.expand(*broadcast_shape(x.shape[:-1], self.H.shape[:-2]), -1, -1)

    @classmethod
    def stack(cls, models: Sequence[LinearMeasurement]) -> LinearMeasurement:
        """A bank whose leading parameter axis enumerates ``models`` (all unbatched)."""
        _check_stackable(models, cls, "models")
        return LinearMeasurement(H=torch.stack([m.H for m in models]), R=torch.stack([m.R for m in models]))

    def extra_repr(self) -> str:
        return (
            f"state_dim={self.state_dim}, meas_dim={self.meas_dim}, "
            f"param_batch_shape={tuple(self.param_batch_shape)}"
        )


def _check_stackable(models, cls, name: str) -> None:
    models = list(models)
    if not models:
        raise ValueError(f"{name}: need at least one model")
    for i, m in enumerate(models):
        if not isinstance(m, cls):
            raise ValueError(f"{name}[{i}]: expected {cls.__name__}, got {type(m).__name__}")
        if len(m.param_batch_shape):
            raise ValueError(f"{name}[{i}]: is already a bank (param batch {tuple(m.param_batch_shape)})")
    dims = {(m.state_dim, getattr(m, "meas_dim", None)) for m in models}
    if len(dims) > 1:
        raise ValueError(f"{name}: models have different dimensions {sorted(dims)}")


def plain_linear(model) -> bool:
    """Whether ``model`` is a :class:`LinearMotion` or :class:`LinearMeasurement` whose ``forward``,
    ``noise_cov`` and ``jacobian`` are the base class's own: it computes ``F x + b`` (``H x``) with
    its matrices, so a kernel may use the matrices instead of calling it. A subclass that only builds
    the matrices (``ConstantVelocity``) is plain; one that overrides them is not."""
    kind = type(model)
    known = _PLAIN.get(kind)
    if known is None:  # (a class's methods are fixed once it is defined: answered once a class)
        base = LinearMotion if issubclass(kind, LinearMotion) else LinearMeasurement if issubclass(
            kind, LinearMeasurement) else None
        known = _PLAIN[kind] = base is not None and all(getattr(kind, name) is getattr(base, name)
                                                        for name in ("forward", "noise_cov", "jacobian"))
    return known


_PLAIN: dict = {}  # plain_linear's answers by class

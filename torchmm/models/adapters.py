r"""Adapters: any ``nn.Module`` as a motion or measurement model, and learnable noise covariances.

Two pieces:

* **Covariance parametrisations** that are PSD by construction, registered on a model's noise
  tensor with :mod:`torch.nn.utils.parametrize` (so ``model.Q`` / ``model.R`` is *computed* from
  an unconstrained ``nn.Parameter`` on every access, and every filter that reads it - KF, EKF,
  UKF, particle filters, IMM banks - sees the learned value):

  ===============================  =====================================================  ==========
  class                            covariance from the unconstrained parameter ``theta``  ``theta``
  ===============================  =====================================================  ==========
  :class:`CholeskyCovariance`      ``L L^T``, ``L = tril(theta, -1) + diag(exp(diag theta))``  ``(*P, d, d)``
  :class:`LogDiagonalCovariance`   ``diag(exp(theta))``                                   ``(*P, d)``
  :class:`LogScaleCovariance`      ``exp(theta) C_0`` for a fixed structure ``C_0``       ``(*S,)``
  ===============================  =====================================================  ==========

  :func:`learnable_noise` attaches one of them to any model attribute (``"Q"`` of a
  :class:`~torchmm.models.LinearMotion`, ``"R"`` of a measurement model, ...).

* :class:`LearnedMotion` / :class:`LearnedMeasurement`: wrap a user network ``net`` mapping
  ``(*B, n) -> (*B, n)`` (or ``(*B, m)``) into a model. Jacobians for the EKF come from autograd
  (:func:`~torchmm.models.forward_jacobian`, differentiable w.r.t. the network's parameters); the
  UKF and particle filters just call the network (sigma points / particles on a leading axis, so
  the network must treat leading dims as batch, as ``nn.Linear`` does).

A learned mode and analytic modes may share one IMM/GPB bank: pass a list of filters
(``[KalmanFilter(cv, sensor), ExtendedKalmanFilter(learned, sensor), ...]``) and
:func:`~torchmm.multimodel.make_bank` builds a :class:`~torchmm.multimodel.ListBank`.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from torchmm.models.base import MeasurementModel, MotionModel, check_parameter_dtype
from torchmm.validation import as_int, as_tensor, broadcast_shape, check_covariance, check_shape
from torchmm.contract import Choice, Cov, Flag, Indices, Int, Of, Text, entry_point

__all__ = [
    "CholeskyCovariance",
    "LearnedMeasurement",
    "LearnedMotion",
    "LogDiagonalCovariance",
    "LogScaleCovariance",
    "learnable_noise",
    "noise_parametrization",
]


class CholeskyCovariance(nn.Module):
    r"""Full covariance ``L L^T + delta I`` from an unconstrained square matrix (positive definite).

    ``L = tril(theta, -1) + diag(exp(diag(theta)))``: the strict lower triangle of ``theta`` is
    ``L``'s, its diagonal holds ``log L_ii``; the upper triangle is unused (zero gradient).

    What it promises in floating point: ``L L^T`` is positive definite in exact arithmetic, but
    formed in floating point it is only PSD up to rounding (``d eps tr(L L^T)``), so a badly
    conditioned ``L`` (a large negative log-diagonal next to large entries) can come out with a
    slightly negative eigenvalue. The floor ``delta = 16 d eps tr(L L^T)`` (``eps`` of the dtype;
    a relative change of ``6e-14`` for ``d = 4`` in float64) keeps every covariance this returns
    positive definite to working precision: its computed eigenvalues and its Cholesky
    factorisation see it as positive definite, for any finite ``theta``.

    Shapes:
        theta ``(*P, d, d)`` -> covariance ``(*P, d, d)``
    """

    #: ``delta = FLOOR * d * eps * tr(L L^T)``
    FLOOR = 16.0

    def forward(self, theta: Tensor) -> Tensor:
        lower = torch.tril(theta, -1) + torch.diag_embed(theta.diagonal(dim1=-2, dim2=-1).exp())
        cov = lower @ lower.mT
        d = cov.shape[-1]
        delta = self.FLOOR * d * torch.finfo(cov.dtype).eps * lower.square().sum((-1, -2))
        eye = torch.eye(d, dtype=cov.dtype, device=cov.device)
        return cov + delta[..., None, None] * eye

    def right_inverse(self, cov: Tensor) -> Tensor:
        chol, info = torch.linalg.cholesky_ex(cov)
        if bool((info != 0).any()):
            raise ValueError("CholeskyCovariance needs a positive definite initial covariance")
        return torch.tril(chol, -1) + torch.diag_embed(chol.diagonal(dim1=-2, dim2=-1).log())


class LogDiagonalCovariance(nn.Module):
    """Diagonal covariance ``diag(exp(theta))`` (independent log-variances).

    Shapes:
        theta ``(*P, d)`` -> covariance ``(*P, d, d)``
    """

    def forward(self, theta: Tensor) -> Tensor:
        return torch.diag_embed(theta.exp())

    def right_inverse(self, cov: Tensor) -> Tensor:
        diag = cov.diagonal(dim1=-2, dim2=-1)
        off = cov - torch.diag_embed(diag)
        if bool((off.detach().abs() > 1e-12 * (1 + diag.detach().abs().amax())).any()):
            raise ValueError("LogDiagonalCovariance needs a diagonal initial covariance")
        if bool((diag.detach() <= 0).any()):
            raise ValueError("LogDiagonalCovariance needs positive variances")
        return diag.log()


class LogScaleCovariance(nn.Module):
    r"""A fixed-structure covariance with a learnable scale: ``exp(theta) C_0``.

    ``C_0`` is the covariance at registration (it may be singular, e.g. ``G G^T`` of white
    acceleration noise); ``theta`` starts at 0. This learns a noise *level* such as the ``q`` of
    ``Q = q G G^T``: the learned ``q`` is ``q_0 exp(theta)``.

    Args:
        structure: ``C_0``, ``(*P, d, d)`` symmetric PSD.
        scale_shape: shape ``*S`` of ``theta``; it must broadcast against ``*P`` (``()`` = one
            scale shared by every mode of a bank, ``(M,)`` = one per mode).

    Shapes:
        theta ``(*S,)`` -> covariance ``(*broadcast(S, P), d, d)``
    """

    @entry_point(structure=Cov(), scale_shape=Indices(empty=True))
    def __init__(self, structure: Tensor, scale_shape=()):
        super().__init__()
        self.register_buffer("structure", structure.detach().clone())
        self.scale_shape = torch.Size(scale_shape)

    def forward(self, theta: Tensor) -> Tensor:
        return theta.exp()[..., None, None] * self.structure

    def right_inverse(self, cov: Tensor) -> Tensor:
        """``log(tr(cov) / tr(C_0))``, reduced to ``scale_shape`` (0 for ``cov = C_0``)."""
        trace = self.structure.diagonal(dim1=-2, dim2=-1).sum(-1)
        log_ratio = (cov.diagonal(dim1=-2, dim2=-1).sum(-1) / trace).log()
        if log_ratio.shape == self.scale_shape:
            return log_ratio
        if not len(self.scale_shape):
            return log_ratio.mean()
        return log_ratio.expand(self.scale_shape).clone()

    def scale(self, theta: Tensor) -> Tensor:
        """``exp(theta)``: the factor applied to ``C_0``."""
        return theta.exp()


def noise_parametrization(kind: str, value: Tensor, *, scale_shape=()) -> nn.Module:
    """The parametrisation module for ``kind`` in ``{"cholesky", "log_diagonal", "scale"}``."""
    if kind == "cholesky":
        return CholeskyCovariance()
    if kind == "log_diagonal":
        return LogDiagonalCovariance()
    if kind == "scale":
        return LogScaleCovariance(value, scale_shape)
    raise ValueError(f"kind: expected 'cholesky', 'log_diagonal' or 'scale', got {kind!r}")


@entry_point(model=Of(torch.nn.Module, what="an nn.Module"), name=Text(),
             kind=Choice("cholesky", "log_diagonal", "scale"), scale_shape=Indices(empty=True))
def learnable_noise(model: nn.Module, name: str = "Q", kind: str = "cholesky", *,
                    scale_shape=()) -> nn.Module:
    """Make the covariance tensor ``model.<name>`` learnable and PSD by construction (in place).

    The current value is the initial value. Afterwards ``model.<name>`` is computed from an
    unconstrained ``nn.Parameter`` (``model.parametrizations.<name>.original``) on every access;
    optimise ``model.parameters()`` as usual. Inside ``torch.nn.utils.parametrize.cached()`` the
    value is computed once per forward pass (the training utilities in :mod:`torchmm.learn` do
    this).

    Args:
        model: any module with a covariance attribute (``LinearMotion.Q``, ``LinearMeasurement.R``,
            :class:`LearnedMotion`, a user model, ...).
        name: the attribute, e.g. ``"Q"`` or ``"R"``.
        kind: ``"cholesky"`` (full, positive definite), ``"log_diagonal"`` (diagonal) or
            ``"scale"`` (fixed structure times a learnable level, see :class:`LogScaleCovariance`).
        scale_shape: for ``kind="scale"``: shape of the level parameter (``()`` shared).

    Returns:
        ``model`` (for chaining).

    Shapes:
        ``model.<name>``: ``(*P, d, d)`` before and after.

    Examples:
        >>> from torchmm.models import ConstantVelocity
        >>> cv = learnable_noise(ConstantVelocity(1, q=2.0), "Q", "scale")
        >>> [n for n, _ in cv.named_parameters()]
        ['parametrizations.Q.original']
        >>> torch.allclose(cv.Q, ConstantVelocity(1, q=2.0).Q)
        True
    """
    if not hasattr(model, name):
        raise ValueError(f"name: {type(model).__name__} has no attribute {name!r}")
    if parametrize.is_parametrized(model, name):
        raise ValueError(f"name: {name!r} of {type(model).__name__} is already parametrised")
    value = getattr(model, name)
    if not isinstance(value, Tensor):
        raise ValueError(f"name: {type(model).__name__}.{name} is not a tensor")
    check_covariance(value, name)
    param = noise_parametrization(kind, value, scale_shape=scale_shape)
    if kind == "scale":
        try:
            broadcast_shape(param.scale_shape, value.shape[:-2])
        except RuntimeError:
            raise ValueError(
                f"scale_shape: {tuple(param.scale_shape)} does not broadcast with {name}'s batch "
                f"{tuple(value.shape[:-2])}"
            ) from None
    # The tensor becomes a Parameter; parametrize replaces its value by right_inverse(value) (the
    # unconstrained parameter) and computes model.<name> = param(original) on every access.
    delattr(model, name)
    model.register_parameter(name, nn.Parameter(value.detach().clone()))
    try:
        parametrize.register_parametrization(model, name, param, unsafe=(kind == "scale"))
    except ValueError as err:  # the initial value does not fit the parametrisation: restore it
        delattr(model, name)
        model.register_buffer(name, value)
        raise ValueError(f"{name}: {err}") from None
    return model


NOISE_KINDS = ("cholesky", "log_diagonal", "scale", "fixed")


def _noise_kind(noise) -> str:
    if noise not in NOISE_KINDS:
        raise ValueError(f"noise: expected one of {list(NOISE_KINDS)}, got {noise!r}")
    return noise


def _check_net(net, name: str) -> nn.Module:
    if not callable(net):
        raise ValueError(f"{name}: expected a callable nn.Module, got {type(net).__name__}")
    return net


def _noise_tensor(noise, dim: int, name: str, like: Tensor | None) -> Tensor:
    kwargs = {} if like is None else {"dtype": like.dtype, "device": like.device}
    if like is not None:
        check_parameter_dtype(noise, name, like.dtype, "the network")
    value = as_tensor(noise, name, **kwargs)
    if value.dim() == 0:
        value = value * torch.eye(dim, dtype=value.dtype, device=value.device)
    check_shape(value, name, (dim, dim))
    check_covariance(value, name)
    return value


def _first_tensor(net: nn.Module) -> Tensor | None:
    if isinstance(net, nn.Module):
        for t in net.parameters():
            return t
        for t in net.buffers():
            return t
    return None


class LearnedMotion(MotionModel):
    r"""A motion model ``x_k = f_\theta(x_{k-1}[, u_k]) + w_k``, ``w_k ~ N(0, Q)``, around any network.

    Args:
        net: a module (or callable) mapping ``x (*B, n) -> (*B, n)``; with ``uses_input=True`` it
            is called as ``net(x, u)``. It must treat all leading dims as batch (sigma points and
            particles add a leading axis; the EKF Jacobian adds one too).
        state_dim: ``n``.
        Q: initial process-noise covariance ``(*P, n, n)`` (a number ``q`` means ``q I``), in the
            network's dtype (a tensor of another floating dtype is refused, naming ``Q``).
        noise: ``"cholesky"``, ``"log_diagonal"``, ``"scale"`` (learnable, see
            :func:`learnable_noise`) or ``"fixed"`` (a buffer).
        residual: if true, ``f(x) = x + net(x)`` (a network initialised near zero then starts
            at the random walk).
        uses_input: pass the control ``u`` to ``net``.

    Shapes:
        forward: ``x (*B, n)`` [, ``u (*B, k)``] -> ``(*B, n)``; ``noise_cov()`` -> ``(*P, n, n)``.

    Examples:
        >>> net = torch.nn.Sequential(torch.nn.Linear(2, 8), torch.nn.Tanh(), torch.nn.Linear(8, 2))
        >>> motion = LearnedMotion(net, 2, Q=0.1, noise="log_diagonal", residual=True)
        >>> motion(torch.zeros(5, 2)).shape, motion.jacobian(torch.zeros(5, 2)).shape
        (torch.Size([5, 2]), torch.Size([5, 2, 2]))
        >>> motion.noise_cov().diagonal()
        tensor([0.1000, 0.1000], grad_fn=<DiagonalBackward0>)
    """

    @entry_point(net=Of(callable_ok=True, what="a callable (an nn.Module)"), state_dim=Int(1),
                 Q=Cov(check=False), noise=Choice("cholesky", "log_diagonal", "scale", "fixed"),
                 residual=Flag(), uses_input=Flag())
    def __init__(self, net, state_dim: int, Q, *, noise: str = "cholesky", residual: bool = False,
                 uses_input: bool = False):
        super().__init__()
        self.net = _check_net(net, "net")
        self.state_dim = as_int(state_dim, "state_dim", minimum=1)
        self.residual, self.uses_input = bool(residual), bool(uses_input)
        self.register_buffer("Q", _noise_tensor(Q, self.state_dim, "Q", _first_tensor(net)))
        self.noise = _noise_kind(noise)
        if noise != "fixed":
            learnable_noise(self, "Q", noise)

    def forward(self, x: Tensor, *, u: Tensor | None = None) -> Tensor:
        out = self.net(x, u) if self.uses_input else self.net(x)
        if out.shape[-1] != self.state_dim:
            raise ValueError(f"net: returned last dim {out.shape[-1]}, expected state_dim {self.state_dim}")
        return x + out if self.residual else out

    def noise_cov(self, x: Tensor | None = None) -> Tensor:
        return self.Q


class LearnedMeasurement(MeasurementModel):
    r"""A measurement model ``z_k = h_\theta(x_k) + v_k``, ``v_k ~ N(0, R)``, around any network.

    Args:
        net: module mapping ``x (*B, n) -> (*B, m)`` (leading dims are batch).
        state_dim: ``n``; meas_dim: ``m``.
        R: initial noise covariance ``(*P, m, m)`` (a number ``r`` means ``r I``), in the network's
            dtype (a tensor of another floating dtype is refused, naming ``R``).
        noise: ``"cholesky"``, ``"log_diagonal"``, ``"scale"`` or ``"fixed"``.

    Shapes:
        forward: ``x (*B, n)`` -> ``(*B, m)``; ``noise_cov()`` -> ``(*P, m, m)``.

    Examples:
        >>> sensor = LearnedMeasurement(torch.nn.Linear(4, 2), 4, 2, R=25.0)
        >>> sensor(torch.zeros(3, 4)).shape, sensor.jacobian(torch.zeros(3, 4)).shape
        (torch.Size([3, 2]), torch.Size([3, 2, 4]))
    """

    @entry_point(net=Of(callable_ok=True, what="a callable (an nn.Module)"), state_dim=Int(1),
                 meas_dim=Int(1), R=Cov(check=False),
                 noise=Choice("cholesky", "log_diagonal", "scale", "fixed"))
    def __init__(self, net, state_dim: int, meas_dim: int, R, *, noise: str = "cholesky"):
        super().__init__()
        self.net = _check_net(net, "net")
        self.state_dim = as_int(state_dim, "state_dim", minimum=1)
        self.meas_dim = as_int(meas_dim, "meas_dim", minimum=1)
        self.register_buffer("R", _noise_tensor(R, self.meas_dim, "R", _first_tensor(net)))
        self.noise = _noise_kind(noise)
        if noise != "fixed":
            learnable_noise(self, "R", noise)

    def forward(self, x: Tensor) -> Tensor:
        out = self.net(x)
        if out.shape[-1] != self.meas_dim:
            raise ValueError(f"net: returned last dim {out.shape[-1]}, expected meas_dim {self.meas_dim}")
        return out

    def noise_cov(self, x: Tensor | None = None) -> Tensor:
        return self.R

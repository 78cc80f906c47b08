r"""Multi-sensor linear system with time-correlated multiplicative noise (paper 002, (1)-(3)).

.. math::
    x(t+1) = A x(t) + \Gamma w(t), \qquad
    y_i(t) = (C_i + \tilde C_i r_i(t)) x(t) + v_i(t), \qquad
    r_i(t+1) = h_i r_i(t) + p_i(t), \quad i = 1..L

``w`` (``p``-dim), ``v_i`` (``m``-dim) and the scalars ``p_i`` are zero-mean white noises with
``E[w v_j^T] = R_j``, ``E[v_i v_j^T] = Q^v_{ij}`` (cross-sensor correlated), ``E[p_i p_j] =
Q^p_i \delta_{ij}``; ``r_i(0)`` has mean 0 and variance ``Q^{r_0}_i``; ``x(0)`` has mean ``mu0`` and
covariance ``P0`` (assumptions 1-3). All sensors share one measurement dimension ``m`` so that
the sensor axis is a batch axis (pad a smaller sensor with zero rows of ``C``, ``C~`` and unit
noise if needed).

The examples' noise model ``v_i = d_i w + eta_i`` (``eta_i`` independent, variance ``Q^eta_i``) is
built by :meth:`MultiSensorSystem.from_correlation`: ``R_i = Q^w d_i^T``,
``Q^v_{ij} = d_i Q^w d_j^T + \delta_{ij} Q^eta_i``.

Second moments used by the estimators (Lemma 1): ``Xi(t) = E[x x^T]`` (10), ``Q^r_i(t) = E[r_i^2]``
(11) and the virtual process noise covariance ``Q^xi_i(t)`` (9) of ``x^r_i = r_i x``,
``x^r_i(t+1) = h_i A x^r_i(t) + xi_i(t)`` (5).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from torchmm.beliefs.ops import psd_sqrt, symmetrize
from torchmm.contract import Cov, Device, DType, Finite, Gen, Int, Mask, Of, Shape, Values, entry_point
from torchmm.validation import as_tensor, check_covariance, check_shape, check_square

__all__ = [
    "MultiSensorSystem",
    "FusionSimulation",
    "MeasurementSequence",
    "measurement_pattern",
    "measurement_sequence",
    "simulate_fusion",
]


@dataclass(frozen=True)
class MultiSensorSystem:
    r"""System (1)-(3) with ``L`` sensors batched on a leading sensor axis.

    Shapes:
        A: ``(n, n)``; Gamma: ``(n, p)``; Qw: ``(p, p)``
        C, Ct: ``(L, m, n)`` (``C_i`` and ``C~_i``); h, Qp, Qr0: ``(L,)``
        R: ``(L, p, m)`` (``R_i = E[w v_i^T]``); Qv: ``(L, L, m, m)`` (``Q^v_ij``)
        mu0: ``(n,)``; P0: ``(n, n)``

    Build with :meth:`create` (validated) or :meth:`from_correlation`.

    Example:
        >>> import torch
        >>> sys = MultiSensorSystem.from_correlation(
        ...     A=[[0.5]], Gamma=[[1.0]], Qw=[[1.0]], C=[[[1.0]], [[1.0]]], Ct=[[[0.5]], [[0.2]]],
        ...     h=[0.6, 0.7], Qp=[0.1, 0.1], d=[[[0.0]], [[0.3]]], Q_eta=[[[1.0]], [[2.0]]],
        ...     mu0=[0.0], P0=[[1.0]])
        >>> sys.num_sensors, sys.state_dim, sys.meas_dim
        (2, 1, 1)
    """

    A: Tensor
    Gamma: Tensor
    Qw: Tensor
    C: Tensor
    Ct: Tensor
    h: Tensor
    Qp: Tensor
    Qr0: Tensor
    R: Tensor
    Qv: Tensor
    mu0: Tensor
    P0: Tensor

    def __post_init__(self):
        # create / from_correlation convert and validate; a direct call takes the tensors themselves
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, Tensor):
                raise TypeError(f"{f.name}: expected a tensor, got {type(value).__name__}; build a system "
                                "from numbers or lists with MultiSensorSystem.create(...) or "
                                ".from_correlation(...)")

    # -- construction ------------------------------------------------------------------------
    @classmethod
    @entry_point(A=Finite(square=True), Gamma=Finite(), Qw=Cov(), C=Finite(), Ct=Finite(), h=Finite(),
                 Qp=Finite(), R=Finite(), Qv=Finite(square=True), mu0=Finite(), P0=Cov(),
                 Qr0=Finite(optional=True), dtype=DType(), device=Device())
    def create(cls, A, Gamma, Qw, C, Ct, h, Qp, R, Qv, mu0, P0, Qr0=None, *, dtype=None, device=None):
        """Validate and build. ``Qr0=None`` means the stationary variance ``Qp / (1 - h^2)``.

        Raises:
            ValueError: naming the argument whose shape or value is invalid (non-PSD noise,
            ``|h_i| >= 1`` with ``Qr0=None``, mismatched dimensions).
        """
        kw = dict(dtype=dtype, device=device)
        A = as_tensor(A, "A", **kw)
        dtype, device = A.dtype, A.device
        kw = dict(dtype=dtype, device=device)
        n = check_square(A, "A")
        if A.dim() != 2:
            raise ValueError(f"A: expected shape (n, n), got {tuple(A.shape)}")
        Gamma = as_tensor(Gamma, "Gamma", **kw)
        if Gamma.dim() != 2 or Gamma.shape[0] != n:
            raise ValueError(f"Gamma: expected shape ({n}, p), got {tuple(Gamma.shape)}")
        p = Gamma.shape[1]
        Qw = as_tensor(Qw, "Qw", **kw)
        check_shape(Qw, "Qw", (p, p))
        check_covariance(Qw, "Qw")
        C = as_tensor(C, "C", **kw)
        if C.dim() != 3 or C.shape[-1] != n:
            raise ValueError(f"C: expected shape (L, m, {n}), got {tuple(C.shape)}")
        L, m = C.shape[0], C.shape[1]
        Ct = as_tensor(Ct, "Ct", **kw)
        if tuple(Ct.shape) != (L, m, n):
            raise ValueError(f"Ct: expected shape {(L, m, n)} like C, got {tuple(Ct.shape)}")
        h = as_tensor(h, "h", **kw).reshape(-1)
        Qp = as_tensor(Qp, "Qp", **kw).reshape(-1)
        for name, val in (("h", h), ("Qp", Qp)):
            if val.shape != (L,):
                raise ValueError(f"{name}: expected {L} values (one per sensor), got {tuple(val.shape)}")
        if bool((Qp < 0).any()):
            raise ValueError("Qp: multiplicative-noise variances must be >= 0")
        if Qr0 is None:
            if bool((h.abs() >= 1).any()):
                raise ValueError(
                    "h: |h_i| >= 1 makes r_i non-stationary (no stationary variance for Qr0=None); "
                    "pass Qr0 explicitly"
                )
            Qr0 = Qp / (1 - h**2)
        Qr0 = as_tensor(Qr0, "Qr0", **kw).reshape(-1)
        if Qr0.shape != (L,) or bool((Qr0 < 0).any()):
            raise ValueError(f"Qr0: expected {L} non-negative variances, got {Qr0.tolist()}")
        R = as_tensor(R, "R", **kw)
        check_shape(R, "R", (L, p, m))
        Qv = as_tensor(Qv, "Qv", **kw)
        check_shape(Qv, "Qv", (L, L, m, m))
        mu0 = as_tensor(mu0, "mu0", **kw).reshape(-1)
        if mu0.shape != (n,):
            raise ValueError(f"mu0: expected shape ({n},), got {tuple(mu0.shape)}")
        P0 = as_tensor(P0, "P0", **kw)
        check_shape(P0, "P0", (n, n))
        check_covariance(P0, "P0")
        sys = cls(A, Gamma, Qw, C, Ct, h, Qp, Qr0, R, Qv, mu0, P0)
        joint = sys.joint_noise_cov()
        try:
            check_covariance(joint, "Qv")
        except ValueError as err:
            raise ValueError(f"R, Qv: the joint covariance of [w; v_1..v_L] is invalid ({err})") from None
        diag = Qv.diagonal(dim1=0, dim2=1).diagonal(dim1=0, dim2=1)  # (m, L)
        if bool((diag <= 0).any()):
            raise ValueError("Qv: every sensor needs positive measurement-noise variances Qv[i, i]")
        return sys

    @classmethod
    @entry_point(A=Finite(square=True), Gamma=Finite(), Qw=Cov(), C=Finite(), Ct=Finite(), h=Finite(),
                 Qp=Finite(), d=Finite(), Q_eta=Cov(), mu0=Finite(), P0=Cov(), Qr0=Finite(optional=True),
                 dtype=DType(), device=Device())
    def from_correlation(cls, A, Gamma, Qw, C, Ct, h, Qp, d, Q_eta, mu0, P0, Qr0=None, *, dtype=None,
                         device=None):
        r"""Build from ``v_i = d_i w + eta_i``: ``R_i = Q^w d_i^T``,
        ``Q^v_ij = d_i Q^w d_j^T + delta_ij Q^eta_i``.

        Shapes:
            d: ``(L, m, p)``; Q_eta: ``(L, m, m)``; the rest as in :class:`MultiSensorSystem`
        """
        A_t = as_tensor(A, "A", dtype=dtype, device=device)
        kw = dict(dtype=A_t.dtype, device=A_t.device)
        Qw_t = as_tensor(Qw, "Qw", **kw)
        d = as_tensor(d, "d", **kw)
        Q_eta = as_tensor(Q_eta, "Q_eta", **kw)
        if d.dim() != 3 or d.shape[-1] != Qw_t.shape[-1]:
            raise ValueError(f"d: expected shape (L, m, p) with p = {Qw_t.shape[-1]}, got {tuple(d.shape)}")
        L, m = d.shape[0], d.shape[1]
        check_shape(Q_eta, "Q_eta", (L, m, m))
        check_covariance(Q_eta, "Q_eta")
        R = Qw_t @ d.mT  # (L, p, m)
        Qv = torch.einsum("iap,pq,jbq->ijab", d, Qw_t, d)
        Qv = Qv + torch.diag_embed(torch.ones(L, **kw)).unsqueeze(-1).unsqueeze(-1) * Q_eta.unsqueeze(1)
        return cls.create(A_t, Gamma, Qw_t, C, Ct, h, Qp, R, Qv, mu0, P0, Qr0)

    # -- sizes ---------------------------------------------------------------------------------
    @property
    def num_sensors(self) -> int:
        return self.C.shape[0]

    @property
    def state_dim(self) -> int:
        return self.A.shape[0]

    @property
    def meas_dim(self) -> int:
        return self.C.shape[1]

    @property
    def noise_dim(self) -> int:
        return self.Gamma.shape[1]

    @property
    def Phi(self) -> Tensor:
        """``Phi_i = h_i A``, ``(L, n, n)``."""
        return self.h[:, None, None] * self.A

    @property
    def GQG(self) -> Tensor:
        """``Gamma Q^w Gamma^T``, ``(n, n)``."""
        return self.Gamma @ self.Qw @ self.Gamma.T

    def joint_noise_cov(self) -> Tensor:
        """Covariance of ``[w; v_1; ...; v_L]``, ``(p + L m, p + L m)``."""
        L, m, p = self.num_sensors, self.meas_dim, self.noise_dim
        Rcat = self.R.permute(1, 0, 2).reshape(p, L * m)
        Qv = self.Qv.permute(0, 2, 1, 3).reshape(L * m, L * m)
        top = torch.cat([self.Qw, Rcat], dim=1)
        bottom = torch.cat([Rcat.T, Qv], dim=1)
        return torch.cat([top, bottom], dim=0)

    def stacked_Qv(self) -> Tensor:
        """``[Q^v_ij]`` as one ``(L m, L m)`` matrix."""
        L, m = self.num_sensors, self.meas_dim
        return self.Qv.permute(0, 2, 1, 3).reshape(L * m, L * m)

    # -- second moments (Lemma 1) -------------------------------------------------------------
    def second_moments(self, steps: int) -> tuple[Tensor, Tensor, Tensor]:
        r"""``Xi(t)`` (10), ``Q^r_i(t)`` (11) and ``Q^xi_i(t)`` (9) for ``t = 0..steps-1``.

        ``Q^xi_i(t) = h_i^2 Q^r_i(t) GQG^T + Q^p_i A Xi(t) A^T + Q^p_i GQG^T`` with
        ``Xi(0) = P0 + mu0 mu0^T`` and ``Q^r_i(0) = Q^{r_0}_i``.

        Shapes:
            -> Xi ``(T, n, n)``, Qr ``(T, L)``, Qxi ``(T, L, n, n)``
        """
        Xi = [self.P0 + torch.outer(self.mu0, self.mu0)]
        Qr = [self.Qr0]
        GQG = self.GQG
        for _ in range(steps - 1):
            Xi.append(symmetrize(self.A @ Xi[-1] @ self.A.T + GQG))
            Qr.append(self.h**2 * Qr[-1] + self.Qp)
        Xi_t, Qr_t = torch.stack(Xi), torch.stack(Qr)
        return Xi_t, Qr_t, self.virtual_noise_cov(Xi_t, Qr_t)

    def virtual_noise_cov(self, Xi: Tensor, Qr: Tensor) -> Tensor:
        """Lemma 1 (9) from given moments. Shapes: Xi ``(*T, n, n)``, Qr ``(*T, L)`` -> ``(*T, L, n, n)``."""
        GQG = self.GQG
        AXA = (self.A @ Xi @ self.A.T).unsqueeze(-3)
        hq = (self.h**2 * Qr)[..., None, None]
        Qp = self.Qp[:, None, None]
        return symmetrize(hq * GQG + Qp * AXA + Qp * GQG)

    def prior_covariance(self, steps: int) -> Tensor:
        """Covariance of ``x(t)`` without data, ``A P A^T + GQG^T`` from ``P0``: ``(T, n, n)``."""
        P = [self.P0]
        for _ in range(steps - 1):
            P.append(symmetrize(self.A @ P[-1] @ self.A.T + self.GQG))
        return torch.stack(P)


# the generated constructor (create and from_correlation validate shapes and the joint noise; a direct
# call is checked by kind: finite matrices, PSD Qw and P0)
MultiSensorSystem.__init__ = entry_point(
    A=Finite(square=True), Gamma=Finite(), Qw=Cov(), C=Finite(), Ct=Finite(), h=Finite(), Qp=Finite(),
    Qr0=Finite(), R=Finite(), Qv=Finite(square=True), mu0=Finite(), P0=Cov())(MultiSensorSystem.__init__)

SYSTEM_ARG = Of(MultiSensorSystem, what="a MultiSensorSystem (MultiSensorSystem.create or .from_correlation)")


@dataclass(frozen=True)
class FusionSimulation:
    """Ground truth and measurements of :func:`simulate_fusion`.

    Shapes:
        x: ``(T, *B, n)``; r: ``(T, *B, L)``; y: ``(T, *B, L, m)``
    """

    x: Tensor
    r: Tensor
    y: Tensor

    def to(self, dtype: torch.dtype) -> "FusionSimulation":
        """The simulation in ``dtype`` (float64 data for a float32 study: common random numbers)."""
        return FusionSimulation(self.x.to(dtype), self.r.to(dtype), self.y.to(dtype))


@entry_point(system=SYSTEM_ARG, steps=Int(1), batch_shape=Shape(), generator=Gen())
def simulate_fusion(system: MultiSensorSystem, steps: int, batch_shape=(),
                    generator: torch.Generator | None = None) -> FusionSimulation:
    r"""Simulate (1)-(3) for ``t = 0..steps-1`` (measurements at every ``t``, the first at ``t = 0``).

    ``x(0) ~ N(mu0, P0)``, ``r_i(0) ~ N(0, Q^{r_0}_i)``, ``p_i ~ N(0, Q^p_i)`` and ``[w; v_1..v_L]``
    jointly Gaussian with :meth:`MultiSensorSystem.joint_noise_cov` (singular covariances are
    sampled through an eigendecomposition square root). The only Python loop is over time.

    Shapes:
        -> x ``(T, *B, n)``, r ``(T, *B, L)``, y ``(T, *B, L, m)``

    Example:
        >>> import torch
        >>> sys = MultiSensorSystem.from_correlation(
        ...     A=[[0.5]], Gamma=[[1.0]], Qw=[[1.0]], C=[[[1.0]], [[1.0]]], Ct=[[[0.5]], [[0.2]]],
        ...     h=[0.6, 0.7], Qp=[0.1, 0.1], d=[[[0.0]], [[0.3]]], Q_eta=[[[1.0]], [[2.0]]],
        ...     mu0=[0.0], P0=[[1.0]])
        >>> sim = simulate_fusion(sys, 5, (3,), torch.Generator().manual_seed(0))
        >>> tuple(sim.y.shape)
        (5, 3, 2, 1)
    """
    B = tuple(batch_shape)
    dtype, device = system.A.dtype, system.A.device
    kw = dict(dtype=dtype, device=device, generator=generator)
    n, L, m, p = system.state_dim, system.num_sensors, system.meas_dim, system.noise_dim
    x = system.mu0 + torch.randn(*B, n, **kw) @ psd_sqrt(system.P0).T
    r = torch.randn(*B, L, **kw) * system.Qr0.sqrt()
    joint_sqrt = psd_sqrt(system.joint_noise_cov())
    qp_sqrt = system.Qp.sqrt()
    xs, rs, ys = [], [], []
    for _ in range(steps):
        noise = torch.randn(*B, p + L * m, **kw) @ joint_sqrt.T
        w, v = noise[..., :p], noise[..., p:].unflatten(-1, (L, m))
        gain = system.C + system.Ct * r[..., None, None]  # (*B, L, m, n)
        y = (gain @ x.unsqueeze(-2).unsqueeze(-1)).squeeze(-1) + v
        xs.append(x), rs.append(r), ys.append(y)
        x = x @ system.A.T + w @ system.Gamma.T
        r = system.h * r + torch.randn(*B, L, **kw) * qp_sqrt
    return FusionSimulation(torch.stack(xs), torch.stack(rs), torch.stack(ys))


@dataclass(frozen=True)
class MeasurementSequence:
    r"""Per-step measurement model with missing components masked out.

    A missing component (NaN in ``y``) is the same as a measurement row with ``C = C~ = 0``, no
    correlation (``R``, ``Q^v_ij`` rows zero) and an independent unit-variance noise, observed as 0:
    the paper's equations then hold unchanged with time-varying matrices, and the gains of missing
    components are exactly zero. The pattern must be the same for all runs (the gains are shared).

    Shapes:
        C, Ct: ``(T, L, m, n)``; R: ``(T, L, p, m)``; Qv: ``(T, L, L, m, m)``;
        present: ``(T, L, m)`` bool, or ``None`` (complete data)
    """

    C: Tensor
    Ct: Tensor
    R: Tensor
    Qv: Tensor
    present: Tensor | None = None

    def at(self, t: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        k = 0 if self.C.shape[0] == 1 else t
        return self.C[k], self.Ct[k], self.R[k], self.Qv[k]


@entry_point(system=SYSTEM_ARG, steps=Int(1), present=Mask(optional=True))
def measurement_sequence(system: MultiSensorSystem, steps: int,
                         present: Tensor | None = None) -> MeasurementSequence:
    """Build the :class:`MeasurementSequence` of ``steps`` steps (``present (T, L, m)`` or ``None``)."""
    if present is None:
        T = steps
        return MeasurementSequence(system.C.expand(T, *system.C.shape), system.Ct.expand(T, *system.Ct.shape),
                                   system.R.expand(T, *system.R.shape), system.Qv.expand(T, *system.Qv.shape))
    L, m = system.num_sensors, system.meas_dim
    if tuple(present.shape) != (steps, L, m):
        raise ValueError(f"present: expected shape {(steps, L, m)}, got {tuple(present.shape)}")
    M = present.to(system.C.dtype)
    C = M[..., None] * system.C
    Ct = M[..., None] * system.Ct
    R = system.R * M[:, :, None, :]
    eye_L = torch.eye(L, dtype=M.dtype, device=M.device)[..., None, None]
    Qv = (M[:, :, None, :, None] * system.Qv * M[:, None, :, None, :]
          + eye_L * torch.diag_embed(1 - M)[:, :, None])
    return MeasurementSequence(C, Ct, R, Qv, present.clone())


@entry_point(system=SYSTEM_ARG, y=Values())
def measurement_pattern(system: MultiSensorSystem, y: Tensor) -> Tensor | None:
    """Missing-data pattern ``(T, L, m)`` of ``y (T, *B, L, m)`` (``None`` when complete).

    Raises:
        ValueError: if ``y`` has the wrong shape or the pattern differs between runs.
    """
    if y.dim() < 3 or tuple(y.shape[-2:]) != (system.num_sensors, system.meas_dim):
        raise ValueError(
            f"y: expected shape (T, *B, {system.num_sensors}, {system.meas_dim}), got {tuple(y.shape)}"
        )
    missing = torch.isnan(y)
    if not bool(missing.any()):
        return None
    flat = missing.reshape(y.shape[0], -1, *y.shape[-2:])
    if not bool((flat == flat[:, :1]).all()):
        raise ValueError(
            "y: the missing (NaN) pattern differs between runs; the fusion estimators share their "
            "gains across runs and support missing measurements only with one pattern for all runs"
        )
    return ~flat[:, 0]

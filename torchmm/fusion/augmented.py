r"""Augmented formulation (12)-(15) and centralized fusion (Remark 10), paper 002.

Both are a standard Kalman filter for correlated process/measurement noise on an augmented state,
written here in *filter form* (measurement update, then a time update that removes the
``w``-``v`` correlation), independently of the predictor-form recursions of :mod:`.local`:

.. math::
    Q^\epsilon = H P H^T + Q^v,\quad K = P H^T (Q^\epsilon)^{-1},\quad
    \hat x(t|t) = \hat x(t|t-1) + K \epsilon,\quad P(t|t) = P - K Q^\epsilon K^T,\\
    J = G S (Q^\epsilon)^{-1},\quad \hat x(t+1|t) = \Phi \hat x(t|t) + J \epsilon,\\
    P(t+1|t) = \Phi P(t|t) \Phi^T + G Q(t) G^T - J Q^\epsilon J^T - \Phi K S^T G^T - G S K^T \Phi^T.

Local augmented system of sensor ``i``: ``x^-_i = [x; x^r_i]``, ``Phi^-_i = diag(A, h_i A)``,
``G = diag(Gamma, I_n)``, ``Q_i(t) = diag(Q^w, Q^xi_i(t))``, ``S_i = [R_i; 0]``, ``H = [C_i, C~_i]``.
Centralized: ``[x; x^r_1; ..; x^r_L]`` with the stacked measurements of all sensors.

Smoothing on the augmented state: ``x^(t|t+k) = x^(t|t+k-1) + Omega(t+k) H^T (Q^eps)^{-1} eps(t+k)``,
``Omega <- Omega (Phi - L^- H)^T`` with the one-step gain ``L^- = Phi K + J``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchmm.beliefs.ops import symmetrize
from torchmm.contract import Cov, Finite, Int, Values, entry_point
from torchmm.linalg import solve_right
from torchmm.fusion.local import check_measurements
from torchmm.fusion.system import SYSTEM_ARG, MultiSensorSystem, measurement_sequence
from torchmm.validation import as_tensor, broadcast_shape

__all__ = [
    "CorrelatedKFResult",
    "correlated_kf",
    "correlated_kf_estimates",
    "augmented_local_estimates",
    "centralized_estimates",
    "augmented_system",
    "centralized_system",
    "augmented_cross_predictor",
]


@dataclass(frozen=True)
class CorrelatedKFResult:
    """Outputs of :func:`correlated_kf` (``*S``: system batch, e.g. sensors).

    Shapes:
        x_pred, x_filt: ``(T, *B, *S, d)``; eps: ``(T, *B, *S, m)``
        P_pred, P_filt: ``(T, *S, d, d)``; innovation_cov ``Q^eps``: ``(T, *S, m, m)``; gain: ``(T, *S, d, m)`` (one-step ``L^-``)
    """

    x_pred: Tensor
    x_filt: Tensor
    eps: Tensor
    P_pred: Tensor
    P_filt: Tensor
    innovation_cov: Tensor
    gain: Tensor


@entry_point(Phi=Finite(square=True), G=Finite(), Q=Cov(), S=Finite(), Qv=Cov(), H=Finite(), x0=Finite(),
             P0=Cov(), y=Finite())
def correlated_kf(Phi, G, Q, S, Qv, H, x0, P0, y) -> CorrelatedKFResult:
    r"""Kalman filter (filter form) for ``x(t+1) = Phi x + G w``, ``y = H x + v``, ``E[w v^T] = S``.

    ``Q``, ``S``, ``Qv`` and ``H`` are given per step (a missing measurement component is a zero row
    of ``H`` and ``S^T`` with unit, uncorrelated noise and a zero value, see
    :class:`~torchmm.fusion.system.MeasurementSequence`).

    Shapes:
        Phi: ``(*S, d, d)``; G: ``(*S, d, q)``; Q: ``(T, *S, q, q)``; S: ``(T, *S, q, m)``;
        Qv: ``(T, *S, m, m)``; H: ``(T, *S, m, d)``; x0: ``(*S, d)``; P0: ``(*S, d, d)``;
        y: ``(T, *B, *S, m)``

    Raises:
        TypeError / ValueError: naming the argument that is not finite (``Q``, ``Qv``, ``P0``: not
        symmetric PSD), not of ``Phi``'s dtype, or whose shape does not fit the others'.
    """
    return _correlated_kf(*_kf_inputs(Phi=Phi, G=G, Q=Q, S=S, Qv=Qv, H=H, x0=x0, P0=P0, y=y))


def _kf_inputs(**named) -> list[Tensor]:
    """:func:`correlated_kf`'s arguments as tensors of ``Phi``'s dtype whose shapes fit (no value read:
    the kinds checked the values)."""
    out = {}
    for name, value in named.items():
        tensor = value if isinstance(value, Tensor) else as_tensor(value, name)
        if out and tensor.dtype != out["Phi"].dtype:
            raise TypeError(f"{name}: dtype {tensor.dtype} differs from Phi's {out['Phi'].dtype}")
        out[name] = tensor
    Phi, G, Q, S, Qv, H, x0, P0, y = out.values()
    d = Phi.shape[-1]

    def need(name, tensor, lead, trailing, text):
        if tensor.dim() < lead + len(trailing) or any(
                want is not None and got != want
                for got, want in zip(tensor.shape[tensor.dim() - len(trailing):], trailing)) \
                or (lead and tensor.shape[0] != y.shape[0]):
            raise ValueError(f"{name}: expected shape {text}, got {tuple(tensor.shape)}")

    if y.dim() < 2 or y.shape[0] < 1:
        raise ValueError(f"y: expected shape (T, *B, *S, m) with T >= 1, got {tuple(y.shape)}")
    T, m = y.shape[0], y.shape[-1]
    need("G", G, 0, (d, None), f"(*S, {d}, q)")
    q = G.shape[-1]
    need("Q", Q, 1, (q, q), f"({T}, *S, {q}, {q})")
    need("S", S, 1, (q, m), f"({T}, *S, {q}, {m})")
    need("Qv", Qv, 1, (m, m), f"({T}, *S, {m}, {m})")
    need("H", H, 1, (m, d), f"({T}, *S, {m}, {d})")
    need("x0", x0, 0, (d,), f"(*S, {d})")
    need("P0", P0, 0, (d, d), f"(*S, {d}, {d})")
    return [Phi, G, Q, S, Qv, H, x0, P0, y]


def _correlated_kf(Phi, G, Q, S, Qv, H, x0, P0, y) -> CorrelatedKFResult:
    T = y.shape[0]
    x = x0.expand(*y.shape[1:-1], x0.shape[-1])
    P = P0
    xs, xfs, es, Ps, Pfs, Qs, gains = [], [], [], [], [], [], []
    for t in range(T):
        Ht, GS = H[t], G @ S[t]
        Qe = symmetrize(Ht @ P @ Ht.mT + Qv[t])
        K = solve_right(P @ Ht.mT, Qe)
        J = solve_right(GS, Qe)
        eps = y[t] - (Ht @ x.unsqueeze(-1)).squeeze(-1)
        xf = x + (K @ eps.unsqueeze(-1)).squeeze(-1)
        Pf = symmetrize(P - K @ Qe @ K.mT)
        xs.append(x), xfs.append(xf), es.append(eps), Ps.append(P), Pfs.append(Pf), Qs.append(Qe)
        gains.append(Phi @ K + J)
        x = (Phi @ xf.unsqueeze(-1) + J @ eps.unsqueeze(-1)).squeeze(-1)
        PhiKSG = Phi @ K @ GS.mT
        P = symmetrize(Phi @ Pf @ Phi.mT + G @ Q[t] @ G.mT - J @ Qe @ J.mT - PhiKSG - PhiKSG.mT)
    st = torch.stack
    return CorrelatedKFResult(st(xs), st(xfs), st(es), st(Ps), st(Pfs), st(Qs), st(gains))


def correlated_kf_estimates(res: CorrelatedKFResult, Phi, G, Q, H, x0, P0, N: int):
    r"""N-step estimates on the augmented state from a :func:`correlated_kf` run.

    ``N < 0``: ``Phi^{-N-1}`` applied to ``x^(t+N+1|t+N)`` (prior ``x0, P0`` before the data);
    ``N = 0``: the filter; ``N > 0``: the innovations smoother (one batched update per lag).

    Shapes:
        -> mean ``(T, *B, *S, d)``, cov ``(T, *S, d, d)``
    """
    T = res.x_pred.shape[0]
    if N < 0:
        mean, cov = res.x_pred, res.P_pred
        for _ in range(-N - 1):
            mean = torch.cat([x0.expand_as(mean[:1]), (Phi @ mean[:-1].unsqueeze(-1)).squeeze(-1)], 0)
            step = symmetrize(Phi @ cov[:-1] @ Phi.mT + G @ Q[:-1] @ G.mT)
            cov = torch.cat([P0.expand_as(cov[:1]), step], 0)
        return mean, cov
    mean, cov, Om = res.x_pred, res.P_pred, res.P_pred
    Psi = Phi - res.gain @ H
    for k in range(N + 1):
        valid = (torch.arange(T, device=mean.device) + k < T).to(mean.dtype)
        idx = torch.clamp(torch.arange(T, device=mean.device) + k, max=T - 1)
        Kg = solve_right(Om @ H[idx].mT, res.innovation_cov[idx]) * valid.reshape(T, *([1] * (Om.dim() - 1)))
        Kb = Kg.reshape(T, *([1] * (mean.dim() - Kg.dim() + 1)), *Kg.shape[1:])
        mean = mean + (Kb @ res.eps[idx].unsqueeze(-1)).squeeze(-1)
        cov = symmetrize(cov - Kg @ res.innovation_cov[idx] @ Kg.mT)
        Om = Om @ Psi[idx].mT
    return mean, cov


def block_diagonal2(a: Tensor, b: Tensor) -> Tensor:
    """``diag(a, b)`` batched: ``a (*S, p, q)``, ``b (*S, r, s)``."""
    batch = broadcast_shape(a.shape[:-2], b.shape[:-2])
    a, b = a.expand(*batch, *a.shape[-2:]), b.expand(*batch, *b.shape[-2:])
    top = torch.cat([a, a.new_zeros(*batch, a.shape[-2], b.shape[-1])], -1)
    bottom = torch.cat([b.new_zeros(*batch, b.shape[-2], a.shape[-1]), b], -1)
    return torch.cat([top, bottom], -2)


def augmented_system(system: MultiSensorSystem, steps: int, present: Tensor | None = None):
    """Matrices (14)-(15) of every sensor's augmented system, sensor axis ``L`` as ``*S``.

    Returns ``(Phi (L, 2n, 2n), G (L, 2n, p+n), Q (T, L, p+n, p+n), S (T, L, p+n, m),
    Qv (T, L, m, m), H (T, L, m, 2n), x0 (L, 2n), P0 (L, 2n, 2n))``; ``present (T, L, m)`` masks
    missing components.
    """
    meas = measurement_sequence(system, steps, present)
    n, L = system.state_dim, system.num_sensors
    Xi, _, Qxi = system.second_moments(steps)
    eye = torch.eye(n, dtype=Xi.dtype, device=Xi.device)
    Phi = block_diagonal2(system.A.expand(L, n, n), system.Phi)
    G = block_diagonal2(system.Gamma.expand(L, *system.Gamma.shape), eye.expand(L, n, n))
    Q = block_diagonal2(system.Qw.expand(steps, L, *system.Qw.shape), Qxi)
    S = torch.cat([meas.R, meas.R.new_zeros(steps, L, n, system.meas_dim)], dim=-2)
    Qv = meas.Qv.diagonal(dim1=1, dim2=2).permute(0, 3, 1, 2)
    H = torch.cat([meas.C, meas.Ct], dim=-1)
    x0 = torch.cat([system.mu0.expand(L, n), system.mu0.new_zeros(L, n)], -1)
    P0 = block_diagonal2(system.P0.expand(L, n, n), system.Qr0[:, None, None] * Xi[0])
    return Phi, G, Q, S, Qv, H, x0, P0


@entry_point(system=SYSTEM_ARG, y=Values(), N=Int())
def augmented_local_estimates(system: MultiSensorSystem, y: Tensor, N: int = 0):
    r"""Local N-step estimates of ``x`` from the augmented system (12)-(15), all sensors batched.

    Shapes:
        y: ``(T, *B, L, m)`` -> mean ``(T, *B, L, n)``, cov ``(T, L, n, n)``
    """
    present = check_measurements(system, y)
    if present is not None:
        y = torch.where(torch.isnan(y), torch.zeros_like(y), y)
    n = system.state_dim
    Phi, G, Q, S, Qv, H, x0, P0 = augmented_system(system, y.shape[0], present)
    res = _correlated_kf(Phi, G, Q, S, Qv, H, x0, P0, y)
    mean, cov = correlated_kf_estimates(res, Phi, G, Q, H, x0, P0, N)
    return mean[..., :n], cov[..., :n, :n]


def centralized_system(system: MultiSensorSystem, steps: int, present: Tensor | None = None):
    """Remark 10: matrices of the centralized augmented system ``[x; x^r_1; ..; x^r_L]``
    (``S``, ``Qv``, ``H`` per step, as :func:`correlated_kf` takes them)."""
    meas = measurement_sequence(system, steps, present)
    n, L, m, p = system.state_dim, system.num_sensors, system.meas_dim, system.noise_dim
    Xi, _, Qxi = system.second_moments(steps)
    kw = dict(dtype=Xi.dtype, device=Xi.device)
    Phi = torch.block_diag(system.A, *system.Phi.unbind(0))
    G = torch.block_diag(system.Gamma, torch.eye(n * L, **kw))
    Q = torch.stack([torch.block_diag(system.Qw, *Qxi[t].unbind(0)) for t in range(steps)])
    T = steps
    S = torch.cat([meas.R.permute(0, 2, 1, 3).reshape(T, p, L * m), torch.zeros(T, n * L, L * m, **kw)], 1)
    Qv = meas.Qv.permute(0, 1, 3, 2, 4).reshape(T, L * m, L * m)
    eye_L = torch.eye(L, **kw)
    Ct_blocks = (eye_L[:, None, :, None] * meas.Ct[:, :, :, None, :]).reshape(T, L * m, L * n)
    H = torch.cat([meas.C.reshape(T, L * m, n), Ct_blocks], dim=-1)
    x0 = torch.cat([system.mu0, torch.zeros(n * L, **kw)])
    P0 = torch.block_diag(system.P0, *(system.Qr0[:, None, None] * Xi[0]).unbind(0))
    return Phi, G, Q, S, Qv, H, x0, P0


@entry_point(system=SYSTEM_ARG, y=Values(), N=Int())
def centralized_estimates(system: MultiSensorSystem, y: Tensor, N: int = 0):
    r"""Centralized fusion (Remark 10): the LMMSE estimate of ``x(t)`` from all sensors' data.

    Shapes:
        y: ``(T, *B, L, m)`` -> mean ``(T, *B, n)``, cov ``(T, n, n)``
    """
    present = check_measurements(system, y)
    if present is not None:
        y = torch.where(torch.isnan(y), torch.zeros_like(y), y)
    n = system.state_dim
    Phi, G, Q, S, Qv, H, x0, P0 = centralized_system(system, y.shape[0], present)
    res = _correlated_kf(Phi, G, Q, S, Qv, H, x0, P0, y.flatten(-2))
    mean, cov = correlated_kf_estimates(res, Phi, G, Q, H, x0, P0, N)
    return mean[..., :n], cov[..., :n, :n]


@entry_point(system=SYSTEM_ARG, steps=Int(1))
def augmented_cross_predictor(system: MultiSensorSystem, steps: int) -> Tensor:
    r"""Cross-covariances of the augmented one-step errors from the error equation (49):

    ``x~^-_i(t+1|t) = Psi_i x~^-_i + G w^-_i - L^-_i v_i``, so
    ``P^-_ij <- Psi_i P^-_ij Psi_j^T + G E[w^-_i w^-_j^T] G^T - G S_j L^{-T}_j - L^-_i S_i^T G^T``
    ``+ L^-_i Q^v_ij L^{-T}_j``
    with ``E[w^-_i w^-_j^T] = diag(Q^w, delta_ij Q^xi_i)`` and ``E[w^-_i v_j^T] = [R_j; 0]``.
    An independent reference for Theorem 4 (gains from :func:`correlated_kf`).

    Shapes:
        -> ``(T, L, L, 2n, 2n)``
    """
    L, n, m = system.num_sensors, system.state_dim, system.meas_dim
    Phi, G, Q, S, Qv, H, x0, P0 = augmented_system(system, steps)
    dummy = torch.zeros(steps, L, m, dtype=Phi.dtype, device=Phi.device)
    res = _correlated_kf(Phi, G, Q, S, Qv, H, x0, P0, dummy)
    Psi = Phi - res.gain @ H  # (T, L, 2n, 2n)
    Gi, Gj = G[:, None], G[None]
    Xi0 = system.P0 + torch.outer(system.mu0, system.mu0)
    eye = torch.eye(L, dtype=Phi.dtype, device=Phi.device)[..., None, None]
    Pb = torch.zeros(L, L, 2 * n, 2 * n, dtype=Phi.dtype, device=Phi.device)
    Pb[..., :n, :n] = system.P0
    Pb[..., n:, n:] = eye * (system.Qr0[:, None, None] * Xi0)[:, None]
    out = []
    for t in range(steps):
        out.append(Pb)
        Lb = res.gain[t]
        Li, Lj = Lb[:, None], Lb[None]
        Qw_ij = Q[t][:, None].clone().expand(L, L, *Q.shape[-2:]).clone()
        Qw_ij[..., system.noise_dim:, system.noise_dim:] *= eye
        Si, Sj = S[t][:, None], S[t][None]
        Pb = (Psi[t][:, None] @ Pb @ Psi[t][None].mT + Gi @ Qw_ij @ Gj.mT - Gi @ Sj @ Lj.mT
              - Li @ Si.mT @ Gj.mT + Li @ system.Qv @ Lj.mT)
    return torch.stack(out)

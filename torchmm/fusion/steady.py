r"""Steady-state local and fused estimators (paper 002, Theorems 7-8, Remark 9).

* Theorem 7: for ``rho(A) < 1`` and ``|h_i| < 1`` the moments converge, ``Xi = A Xi A^T + GQG^T``
  (51) and ``Q^r_i = h_i^2 Q^r_i + Q^p_i`` (52), giving the constant ``Q^xi_i`` (53).
* Theorem 8: the augmented Riccati recursion (50) with the optimal gain
  ``L^-_i = (Phi^-_i P C^{-T}_i + G S_i)(Q^eps_i)^{-1}`` is iterated from ``P = 0`` to convergence;
  its limit gives the offline gains ``L_i = [I 0] L^-_i``, ``L^r_i = [0 I] L^-_i`` and ``Sigma_i``.
* Remark 9: with fixed gains the cross-covariance recursions (Theorem 4) are iterated to their
  limit from any initial value; the filter/smoother gains and cross-covariances follow with
  constant arrays, so the fusion weights are offline too.

The steady-state estimators are the same batched recursions of :mod:`.local` run with the
constant gains (``stationary=True`` statistics).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import Tensor

from torchmm.beliefs.ops import symmetrize
from torchmm.contract import Choice, Int, Of, Real, Values, entry_point
from torchmm.fusion.augmented import block_diagonal2
from torchmm.fusion.cross import CrossStats, cross_covariances, cross_innovation, cross_step
from torchmm.fusion.local import LocalStats, local_from_pred, local_gains, local_one_step, symmetrize_pairs
from torchmm.fusion.system import SYSTEM_ARG, MultiSensorSystem, measurement_sequence
from torchmm.fusion.weights import FUSION_METHODS, fusion_weights

log = logging.getLogger("torchmm")

__all__ = [
    "SteadyState",
    "steady_moments",
    "steady_state",
    "steady_local_estimates",
    "steady_fused_estimates",
]


def _spectral_radius(A: Tensor) -> float:
    return float(torch.linalg.eigvals(A.detach().to(torch.complex128)).abs().max())


@entry_point(system=SYSTEM_ARG, tol=Real(positive=True), max_iter=Int(1))
def steady_moments(system: MultiSensorSystem, tol: float = 1e-14, max_iter: int = 200):
    r"""Theorem 7: limits ``Xi`` (51), ``Q^r_i`` (52) and ``Q^xi_i`` (53).

    ``Xi`` by the doubling iteration ``X <- X + A_k X A_k^T``, ``A_k <- A_k^2`` (quadratic convergence).

    Shapes:
        -> Xi ``(n, n)``, Qr ``(L,)``, Qxi ``(L, n, n)``

    Raises:
        ValueError: if ``rho(A) >= 1`` or some ``|h_i| >= 1`` (no steady state).
    """
    rho = _spectral_radius(system.A)
    if rho >= 1:
        raise ValueError(f"A: steady state needs rho(A) < 1 (Theorem 7), got {rho:.6g}")
    if bool((system.h.abs() >= 1).any()):
        raise ValueError(f"h: steady state needs |h_i| < 1 (Theorem 7), got {system.h.tolist()}")
    tol = max(float(tol), 10 * torch.finfo(system.A.dtype).eps)
    X, Ak = system.GQG.clone(), system.A.clone()
    for _ in range(max_iter):
        X_new = symmetrize(X + Ak @ X @ Ak.T)
        Ak = Ak @ Ak
        done = float((X_new - X).abs().max()) <= tol * float(X_new.abs().max().clamp_min(1e-300))
        X = X_new
        if done:
            break
    Qr = system.Qp / (1 - system.h**2)
    return X, Qr, system.virtual_noise_cov(X, Qr)


@dataclass(frozen=True)
class SteadyState:
    """Offline steady-state quantities.

    Shapes:
        stats: :class:`LocalStats` with ``T = 1`` (stationary); cross: :class:`CrossStats` ``T = 1``;
        Pbar: ``(L, 2n, 2n)`` (limit of (50)); gain: ``(L, 2n, m)`` (``L^-_i``)
    """

    stats: LocalStats
    cross: CrossStats
    Pbar: Tensor
    gain: Tensor
    iterations: int
    cross_iterations: int

    def cross_covariances(self, system: MultiSensorSystem, N: int) -> Tensor:
        """Steady ``P_ij(N)``, ``(L, L, n, n)``."""
        return cross_covariances(system, self.stats, self.cross, N, steps=1)[0]

    def local_covariances(self, system: MultiSensorSystem, N: int) -> Tensor:
        """Steady ``P_i(N)``, ``(L, n, n)``."""
        return local_from_pred(system, self.stats, None, None, N, steps=1)[1][0]


@entry_point(system=SYSTEM_ARG, tol=Real(positive=True), max_iter=Int(1))
def steady_state(system: MultiSensorSystem, tol: float = 1e-12, max_iter: int = 100_000) -> SteadyState:
    r"""Theorems 7-8 and Remark 9: iterate (50) and then the cross recursions to convergence.

    Convergence: relative max-abs change below ``max(tol, 100 eps)`` (``eps`` of the dtype, so that
    float32 stops at its rounding level); a ``RuntimeWarning`` is logged if ``max_iter`` is reached.

    Example:
        >>> sys = MultiSensorSystem.from_correlation(
        ...     A=[[0.5]], Gamma=[[1.0]], Qw=[[1.0]], C=[[[1.0]], [[1.0]]], Ct=[[[0.5]], [[0.2]]],
        ...     h=[0.6, 0.7], Qp=[0.1, 0.1], d=[[[0.0]], [[0.3]]], Q_eta=[[[1.0]], [[2.0]]],
        ...     mu0=[0.0], P0=[[1.0]])
        >>> ss = steady_state(sys)
        >>> tuple(ss.cross_covariances(sys, 0).shape)
        (2, 2, 1, 1)
    """
    Xi, Qr, Qxi = steady_moments(system)
    tol = max(float(tol), 100 * torch.finfo(Xi.dtype).eps)
    n, L, m = system.state_dim, system.num_sensors, system.meas_dim
    eye_n = torch.eye(n, dtype=Xi.dtype, device=Xi.device)
    Phi = block_diagonal2(system.A.expand(L, n, n), system.Phi)
    G = block_diagonal2(system.Gamma.expand(L, *system.Gamma.shape), eye_n.expand(L, n, n))
    Q = block_diagonal2(system.Qw.expand(L, *system.Qw.shape), Qxi)
    S = torch.cat([system.R, system.R.new_zeros(L, n, m)], dim=-2)
    Qv = system.Qv.diagonal(dim1=0, dim2=1).permute(2, 0, 1)
    H = torch.cat([system.C, system.Ct], dim=-1)
    GQG, GS = G @ Q @ G.mT, G @ S
    P = torch.zeros(L, 2 * n, 2 * n, dtype=Xi.dtype, device=Xi.device)
    it = 0
    for it in range(1, max_iter + 1):
        Qe = symmetrize(H @ P @ H.mT + Qv)
        Lb = torch.linalg.solve(Qe, (Phi @ P @ H.mT + GS).mT).mT
        Psi = Phi - Lb @ H
        P_new = symmetrize(Psi @ P @ Psi.mT + GQG - GS @ Lb.mT - Lb @ GS.mT + Lb @ Qv @ Lb.mT)  # (50)
        change = float((P_new - P).abs().max()) / float(P_new.abs().max().clamp_min(1e-300))
        P = P_new
        if change <= tol:
            break
    else:
        log.warning("steady_state: the Riccati iteration (50) did not converge in %d steps", max_iter)
    Px, Pr, Pxr = P[:, :n, :n], P[:, n:, n:], P[:, :n, n:]
    meas = measurement_sequence(system, 1)
    Qeps, Lx, Lr = local_gains(system, meas.at(0), Px, Pr, Pxr)
    stats = LocalStats(Px[None], Pr[None], Pxr[None], Qeps[None], Lx[None], Lr[None], Qxi[None],
                       meas=meas, stationary=True)
    # Remark 9: cross-covariances with the fixed gains, from any initial value (here zero)
    Pij = torch.zeros(L, L, n, n, dtype=Xi.dtype, device=Xi.device)
    Prij = torch.zeros_like(Pij)
    Pxrij = torch.zeros_like(Pij)
    cit = 0
    for cit in range(1, max_iter + 1):
        P1, Pr1, Pxr1, Qe_ij = cross_step(system, meas.at(0), Pij, Prij, Pxrij, Lx, Lr, Qxi)
        P1, Pr1 = symmetrize_pairs(P1), symmetrize_pairs(Pr1)
        scale = max(float(P1.abs().max()), float(Pr1.abs().max()), 1e-300)
        change = max(float((P1 - Pij).abs().max()), float((Pr1 - Prij).abs().max()),
                     float((Pxr1 - Pxrij).abs().max())) / scale
        Pij, Prij, Pxrij = P1, Pr1, Pxr1
        if change <= tol:
            break
    else:
        log.warning("steady_state: the cross-covariance iteration did not converge in %d steps", max_iter)
    Qe_ij = cross_innovation(meas.at(0), Pij, Prij, Pxrij)[2]
    cross = CrossStats(Pij[None], Prij[None], Pxrij[None], Qe_ij[None], stationary=True)
    return SteadyState(stats, cross, P, torch.cat([Lx, Lr], dim=-2), it, cit)


_STEADY = Of(SteadyState, what="a SteadyState (steady_state)")


@entry_point(system=SYSTEM_ARG, ss=_STEADY, y=Values(), N=Int())
def steady_local_estimates(system: MultiSensorSystem, ss: SteadyState, y: Tensor, N: int = 0):
    r"""Local steady-state N-step estimators (55) with the offline gains.

    Shapes:
        y: ``(T, *B, L, m)`` -> mean ``(T, *B, L, n)``, cov ``(T, L, n, n)`` (the constant limit)
    """
    x_pred, _, eps = local_one_step(system, ss.stats, y)
    return local_from_pred(system, ss.stats, x_pred, eps, N)


@entry_point(system=SYSTEM_ARG, ss=_STEADY, y=Values(), N=Int(), method=Choice(*FUSION_METHODS))
def steady_fused_estimates(system: MultiSensorSystem, ss: SteadyState, y: Tensor, N: int = 0,
                           method: str = "matrix"):
    r"""Steady-state distributed fusion: offline weights from the steady ``P_ij(N)``.

    Shapes:
        y: ``(T, *B, L, m)`` -> mean ``(T, *B, n)``, cov ``(n, n)``, weights ``(L, n, n)``
    """
    mean, _ = steady_local_estimates(system, ss, y, N)
    weights, Po = fusion_weights(ss.cross_covariances(system, N), method)
    W = weights.reshape(*([1] * (mean.dim() - 2)), *weights.shape)
    out = (W @ mean.unsqueeze(-1)).squeeze(-1).sum(-2)
    return out, Po, weights


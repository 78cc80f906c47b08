r"""Cross-covariances between the sensors' local estimators (Theorems 4-6), paper 002; the local estimators
themselves (Theorems 1-3) and the readings of the printed equations are :mod:`torchmm.fusion.local`'s
(its docstring, and docs/reproduction-002.md)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchmm.contract import Flag, Int, Of, entry_point
from torchmm.linalg import solve_right
from torchmm.fusion.system import SYSTEM_ARG, MultiSensorSystem
from torchmm.fusion.local import (
    LOCAL_STATS,
    LocalStats,
    check_stats_steps,
    pair_transpose,
    pred_shift,
    shift_steps,
    symmetrize_pairs,
    valid_steps,
)

__all__ = ["CrossStats", "cross_predictor_stats", "cross_covariances", "theorem6_cross_covariances"]


# ------------------------------------------------------------------------------------------------
# Cross-covariances between sensors (Theorems 4-6)
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CrossStats:
    """Theorem 4 quantities for every sensor pair ``(i, j)`` at ``t|t-1``.

    Shapes:
        state_cov: ``(T, L, L, n, n)`` ``E[x~_i x~_j^T]``; aux_cov: ``E[x~^r_i x~^r_j^T]``;
        state_aux_cov: ``E[x~_i x~^r_j^T]``; innovation_cov: ``(T, L, L, m, m)`` ``E[eps_i eps_j^T]``
    """

    state_cov: Tensor
    aux_cov: Tensor
    state_aux_cov: Tensor
    innovation_cov: Tensor
    stationary: bool = False

    def joint(self) -> Tensor:
        """Augmented ``E[[x~_i; x~^r_i][x~_j; x~^r_j]^T]``, ``(T, L, L, 2n, 2n)``."""
        top = torch.cat([self.state_cov, self.state_aux_cov], dim=-1)
        bottom = torch.cat([self.state_aux_cov.transpose(1, 2).mT, self.aux_cov], dim=-1)
        return torch.cat([top, bottom], dim=-2)


_CROSS = Of(CrossStats, what="CrossStats (cross_predictor_stats)")


def cross_innovation(meas_t, P, Pr, Pxr):
    """(33), (34), (36) for all pairs; ``meas_t = (C, C~, R, Q^v)``. Shapes ``(..., L, L, n, n)``."""
    C, Ct, _, Qv = meas_t
    Ci, Cj = C[:, None], C[None]
    Cti, Ctj = Ct[:, None], Ct[None]
    Pxe = P @ Cj.mT + Pxr @ Ctj.mT  # E[x~_i eps_j^T]        (33)
    Pre = pair_transpose(Pxr) @ Cj.mT + Pr @ Ctj.mT  # E[x~^r_i eps_j^T]  (36)
    Qeps = Ci @ Pxe + Cti @ Pre + Qv  # (34)
    return Pxe, Pre, Qeps


def cross_step(system, meas_t, P, Pr, Pxr, Lx, Lr, Qxi):
    """(32), (35), (37): one step for all pairs; ``Lx, Lr (L, n, m)``, ``Qxi (L, n, n)``."""
    A, G = system.A, system.Gamma
    Phi_i, Phi_j = system.Phi[:, None], system.Phi[None]
    Li, Lj = Lx[:, None], Lx[None]
    Lri, Lrj = Lr[:, None], Lr[None]
    R = meas_t[2]
    Ri = R[:, None]  # (L, 1, p, m)
    Rj = R[None]
    Pxe, Pre, Qeps = cross_innovation(meas_t, P, Pr, Pxr)
    P1 = (A @ P @ A.T - A @ Pxe @ Lj.mT - Li @ pair_transpose(Pxe) @ A.T + Li @ Qeps @ Lj.mT
          - Li @ Ri.mT @ G.T - G @ Rj @ Lj.mT + system.GQG)
    eye = torch.eye(system.num_sensors, dtype=P.dtype, device=P.device)[..., None, None]
    Pr1 = (Phi_i @ Pr @ Phi_j.mT - Phi_i @ Pre @ Lrj.mT - Lri @ pair_transpose(Pre) @ Phi_j.mT
           + Lri @ Qeps @ Lrj.mT + eye * Qxi[:, None])
    Pxr1 = (A @ Pxr @ Phi_j.mT - A @ Pxe @ Lrj.mT - Li @ pair_transpose(Pre) @ Phi_j.mT
            + Li @ Qeps @ Lrj.mT - G @ Rj @ Lrj.mT)
    return P1, Pr1, Pxr1, Qeps


@entry_point(system=SYSTEM_ARG, stats=LOCAL_STATS, steps=Int(1, optional=True))
def cross_predictor_stats(system: MultiSensorSystem, stats: LocalStats,
                          steps: int | None = None) -> CrossStats:
    r"""Theorem 4: one-step prediction error cross-covariances of all sensor pairs.

    Initial values ``P_ij(0|-1) = P0``, ``P^{x^r}_ij(0|-1) = delta_ij Q^{r_0}_i Xi(0)``,
    ``P^{xx^r}_ij(0|-1) = 0``. The diagonal ``i = j`` reproduces Theorem 1.

    Shapes:
        -> :class:`CrossStats` with leading ``(T, L, L)``
    """
    if steps is not None and not stats.stationary and steps > stats.state_cov.shape[0]:
        raise ValueError(f"steps: {steps} steps, but `stats` were computed for {stats.state_cov.shape[0]}")
    T = stats.state_cov.shape[0] if steps is None else steps
    L, n = system.num_sensors, system.state_dim
    Xi0 = system.P0 + torch.outer(system.mu0, system.mu0)
    P = system.P0.expand(L, L, n, n)
    eye = torch.eye(L, dtype=P.dtype, device=P.device)[..., None, None]
    Pr = eye * (system.Qr0[:, None, None] * Xi0)[:, None]
    Pxr = torch.zeros_like(Pr)
    out = {k: [] for k in ("state_cov", "aux_cov", "state_aux_cov", "innovation_cov")}
    for t in range(T):
        st = stats.at(t)
        P1, Pr1, Pxr1, Qeps = cross_step(system, stats.meas.at(t), P, Pr, Pxr, st.state_gain, st.aux_gain, st.aux_noise_cov)
        for k, v in zip(out, (P, Pr, Pxr, Qeps)):
            out[k].append(v)
        P, Pr, Pxr = symmetrize_pairs(P1), symmetrize_pairs(Pr1), Pxr1
    return CrossStats(**{k: torch.stack(v) for k, v in out.items()})


def _augmented_blocks(system, stats: LocalStats):
    """``C^- = [C, C~]`` (T, L, m, 2n), ``L^- = [L; L^r]`` (T, L, 2n, m), ``Psi = Phi^- - L^- C^-``
    (T, L, 2n, 2n); ``T = 1`` for stationary statistics."""
    n, L = system.state_dim, system.num_sensors
    Cbar = torch.cat([stats.meas.C, stats.meas.Ct], dim=-1)
    Lbar = torch.cat([stats.state_gain, stats.aux_gain], dim=-2)
    Phibar = torch.zeros(L, 2 * n, 2 * n, dtype=Cbar.dtype, device=Cbar.device)
    Phibar[:, :n, :n] = system.A
    Phibar[:, n:, n:] = system.Phi
    return Cbar, Lbar, Phibar - Lbar @ Cbar


@entry_point(system=SYSTEM_ARG, stats=LOCAL_STATS, cross=_CROSS, N=Int(), steps=Int(1, optional=True))
def cross_covariances(system: MultiSensorSystem, stats: LocalStats, cross: CrossStats, N: int,
                      steps: int | None = None) -> Tensor:
    r"""Cross-covariances ``P_ij(t|t+N)`` of all sensor pairs' estimation errors (Thms 4-6).

    ``N = -1``: Theorem 4. ``N < -1``: (38). ``N >= 0``: Theorem 6, evaluated by the forward
    recursion over ``s = t..t+N`` of ``e_i(s) = x~_i(t|s-1)`` and ``z_i(s) = x~^-_i(s|s-1)``
    (augmented one-step error): ``e_i(s+1) = e_i - K_i(t|s)(C^-_i z_i + v_i)``,
    ``z_i(s+1) = Psi_i z_i + Gamma^- w^-_i - L^-_i v_i``, with ``X_ij = E[e_i z_j^T]``:

    .. math::
        E_{ij} \leftarrow E_{ij} - X_{ij} C^{-T}_j K_j^T - K_i C^-_i X_{ji}^T
            + K_i Q^\epsilon_{ij} K_j^T,\quad
        X_{ij} \leftarrow (X_{ij} - K_i C^-_i P^-_{ij}) \Psi_j^T - K_i [R_i^T \Gamma^T, 0]
            + K_i Q^v_{ij} L^{-T}_j

    starting from ``E_ij = P_ij(t|t-1)``, ``X_ij = [P_ij, P^{xx^r}_ij](t|t-1)``; ``K_i(t|s) = X_ii C^{-T}_i
    (Q^eps_i)^{-1}`` is Theorem 3's gain (28). Each lag is one batched update of all ``t`` and pairs.
    Time-varying ``stats`` and ``cross`` must cover the same steps (``steps``: their ``T``, the
    default); stationary ones (``T = 1``) any ``steps``; else ``ValueError`` naming the argument.

    Shapes:
        -> ``(T, L, L, n, n)``
    """
    if stats.stationary != cross.stationary:
        raise ValueError("cross: stationary and time-varying statistics mixed (`stats` stationary="
                         f"{stats.stationary}, `cross` stationary={cross.stationary})")
    if not cross.stationary:
        check_stats_steps("stats", stats, cross.state_cov.shape[0], "`cross` were computed for")
    if steps is not None:
        check_stats_steps("cross", cross, steps, "steps is")
    T = cross.state_cov.shape[0] if steps is None else steps
    stat = cross.stationary
    P_pred = cross.state_cov.expand(T, *cross.state_cov.shape[1:]) if stat else cross.state_cov
    if N < 0:
        k = -N - 1
        if stat:
            out = P_pred[:1]
            for _ in range(k):
                out = system.A @ out @ system.A.T + system.GQG
            return out.expand_as(P_pred)
        return pred_shift(None, P_pred, k, system, system.P0, pairs=True)[1]
    n, L, m = system.state_dim, system.num_sensors, system.meas_dim
    Cbar, Lbar, Psi = _augmented_blocks(system, stats)
    Pbar = cross.joint()
    Qe = cross.innovation_cov
    Qe_loc = stats.innovation_cov
    E = P_pred
    X = Pbar[..., :n, :] if not stat else Pbar[..., :n, :].expand(T, *Pbar.shape[1:-2], n, 2 * n)
    R, Qv = stats.meas.R, stats.meas.Qv  # (T, L, p, m), (T, L, L, m, m)
    RG = torch.cat([R.mT @ system.Gamma.T, R.new_zeros(*R.shape[:2], m, n)], -1)  # [R_i^T Gamma^T, 0]
    eye_m = torch.eye(m, dtype=E.dtype, device=E.device)
    idx = torch.arange(L, device=E.device)
    for k in range(N + 1):
        if stat:
            Pb, Qk, Psik, Lk, Qlk, valid = Pbar, Qe, Psi, Lbar, Qe_loc, None
            Cb, RGk, Qvk = Cbar, RG, Qv
        else:
            Pb, Qk = shift_steps(Pbar, k), shift_steps(Qe, k)
            Psik, Lk = shift_steps(Psi, k), shift_steps(Lbar, k)
            Qlk = shift_steps(Qe_loc, k, eye_m)
            Cb, RGk, Qvk = shift_steps(Cbar, k), shift_steps(RG, k), shift_steps(Qv, k)
            valid = valid_steps(T, k, E)
        Xii = X[:, idx, idx]  # (T, L, n, 2n)
        K = solve_right(Xii @ Cb.mT, Qlk)  # (T, L, n, m)
        if valid is not None:
            K = K * valid[:, None, None, None]
        Ki, Kj = K[:, :, None], K[:, None, :]
        Ci, Cj = Cb[:, :, None], Cb[:, None]
        XC = X @ Cj.mT  # E[e_i eps_j^T] minus the v term (e_i is orthogonal to v_j(s))
        E = symmetrize_pairs(E - XC @ Kj.mT - Ki @ pair_transpose(XC) + Ki @ Qk @ Kj.mT)
        X = ((X - Ki @ Ci @ Pb) @ Psik[:, None].mT - Ki @ RGk[:, :, None]
             + Ki @ Qvk @ Lk[:, None].mT)
    return E


@entry_point(system=SYSTEM_ARG, stats=LOCAL_STATS, cross=_CROSS, N=Int(0), xi_term=Flag())
def theorem6_cross_covariances(system: MultiSensorSystem, stats: LocalStats, cross: CrossStats, N: int,
                               xi_term: bool = True) -> Tensor:
    r"""Theorem 6: the closed sums (39)-(43) for the filter/smoother cross-covariances.

    An evaluation of the printed sums (loops over the lags ``k_i, k_j, m_j <= N``; every time step
    and sensor pair batched), a second implementation of :func:`cross_covariances` (``N >= 0``),
    with the readings ``P^{xx^r}`` for the cross terms printed ``P^{x^r}`` in (40)-(41) and
    ``(P^{x^r eps}_ji)^T`` for the printed ``(P^{x^r eps}_ij)^T`` in (42).

    ``xi_term=False`` is (42) as printed. Its proof (G12) drops ``E[eps_i(t+k_i) xi_j^T(t+k_j-m_j)]``
    by Remark 4, which holds for ``j != i`` but not for ``j = i`` when ``k_j - m_j < k_i`` (the
    future innovation contains the virtual noise through ``x^r_i``); the printed theorem is exact
    for ``N <= 1`` only. ``xi_term=True`` (default) adds, for ``i = j``,
    ``sum_{m_j > k_j - k_i} Omega^{eps xi}_i(t+k_i, t+k_j-m_j) (C~_i Phi_i^{m_j-1})^T`` with
    ``Omega^{eps xi}_i(t+a, t+s) = -sum_{m_i} M_i Omega^{eps xi}_i(t+a-m_i, t+s)
    + C~_i Phi_i^{a-s-1} Q^xi_i(t+s)`` (the analogue of (43); see ``docs/reproduction-002.md``).

    Shapes:
        -> ``(T, L, L, n, n)``
    """
    if N < 0:
        raise ValueError(f"N: Theorem 6 covers N >= 0, got {N}")
    if stats.stationary:
        raise ValueError("stats: Theorem 6's closed sums are evaluated for the time-varying statistics")
    if stats.meas.present is not None:
        raise ValueError("stats: Theorem 6's closed sums are implemented for complete data only")
    T = stats.state_cov.shape[0]
    A, G, C, Ct = system.A, system.Gamma, system.C, system.Ct
    h = system.h
    eye_m = torch.eye(system.meas_dim, dtype=A.dtype, device=A.device)
    Apow = [torch.linalg.matrix_power(A, k) for k in range(N + 1)]
    Phipow = [h[:, None, None] ** k * Apow[k] for k in range(N + 1)]  # (L, n, n)

    # local smoothing gains K_i(t|t+k), Theorem 3 (28)-(30)
    Ks, Om_x, Om_r = [], stats.state_cov, stats.state_aux_cov
    for k in range(N + 1):
        Qe = shift_steps(stats.innovation_cov, k, eye_m)
        K = solve_right(Om_x @ C.mT + Om_r @ Ct.mT, Qe) * valid_steps(T, k, Om_x)[:, None, None, None]
        Ks.append(K)
        KQ = K @ Qe
        Om_x = Om_x @ A.T - KQ @ shift_steps(stats.state_gain, k).mT
        Om_r = Om_r @ system.Phi.mT - KQ @ shift_steps(stats.aux_gain, k).mT

    def M(offset: int, mj: int) -> Tensor:
        """``C_j A^{m-1} L_j(t+offset) + C~_j Phi_j^{m-1} L^{x^r}_j(t+offset)``, ``(T, L, m, m)``."""
        return C @ Apow[mj - 1] @ shift_steps(stats.state_gain, offset) + Ct @ Phipow[mj - 1] @ shift_steps(stats.aux_gain, offset)

    P, Pxr, Pr = cross.state_cov, cross.state_aux_cov, cross.aux_cov
    Cj, Ctj = C[None], Ct[None]
    # (40), (41): E[x~_i(t|t-1) eps_j^T(t+k)] and E[x~^r_i(t|t-1) eps_j^T(t+k)]
    Pxe, Pre = [], []
    for kj in range(N + 1):
        a = P @ Apow[kj].T @ Cj.mT + Pxr @ Phipow[kj][None].mT @ Ctj.mT
        b = pair_transpose(Pxr) @ Apow[kj].T @ Cj.mT + Pr @ Phipow[kj][None].mT @ Ctj.mT
        for mj in range(1, kj + 1):
            Mt = M(kj - mj, mj)[:, None].mT
            a = a - Pxe[kj - mj] @ Mt
            b = b - Pre[kj - mj] @ Mt
        Pxe.append(a), Pre.append(b)
    # (43): Omega^{eps w}_i(t+a, t+s), 0 <= s <= a
    Om: dict[tuple[int, int], Tensor] = {}
    RT = system.R.mT  # (L, m, p)
    for a in range(N + 1):
        for s in range(a + 1):
            val = RT.expand(T, *RT.shape) if a == s else RT.new_zeros(T, *RT.shape)
            for mi in range(1, a + 1):
                if a - mi >= s:
                    val = val - M(a - mi, mi) @ Om[(a - mi, s)]
                if a - mi == s:
                    val = val + C @ Apow[mi - 1] @ G @ system.Qw
            Om[(a, s)] = val
    # E[eps_i(t+a) xi_i^T(t+s)], s < a (zero for s >= a); the term (42) omits
    Oxi: dict[tuple[int, int], Tensor] = {}
    if xi_term:
        for a in range(N + 1):
            for s in range(a):
                val = Ct @ Phipow[a - s - 1] @ shift_steps(stats.aux_noise_cov, s)
                for mi in range(1, a - s):
                    val = val - M(a - mi, mi) @ Oxi[(a - mi, s)]
                Oxi[(a, s)] = val
    pair_eye = torch.eye(system.num_sensors, dtype=A.dtype, device=A.device)[..., None, None]
    # (42): Q^eps_ij(t+ki, t+kj)
    Q: dict[tuple[int, int], Tensor] = {}
    for ki in range(N + 1):
        Q[(ki, ki)] = shift_steps(cross.innovation_cov, ki)
        for b in range(ki):
            Q[(ki, b)] = pair_transpose(Q[(b, ki)])
        for kj in range(ki + 1, N + 1):
            val = pair_transpose(Pxe[ki]) @ Apow[kj].T @ Cj.mT + pair_transpose(Pre[ki]) @ Phipow[kj][None].mT @ Ctj.mT
            for mj in range(1, kj + 1):
                val = val - Q[(ki, kj - mj)] @ M(kj - mj, mj)[:, None].mT
                if mj >= kj - ki:
                    val = val + Om[(ki, kj - mj)][:, :, None] @ (C @ Apow[mj - 1] @ G)[None].mT
                if xi_term and kj - mj < ki:
                    val = val + pair_eye * (Oxi[(ki, kj - mj)] @ (Ct @ Phipow[mj - 1]).mT)[:, :, None]
            Q[(ki, kj)] = val
    # (39)
    out = P
    for kj in range(N + 1):
        Kj = Ks[kj][:, None]
        out = out - Pxe[kj] @ Kj.mT - Ks[kj][:, :, None] @ pair_transpose(Pxe[kj])
    for ki in range(N + 1):
        for kj in range(N + 1):
            out = out + Ks[ki][:, :, None] @ Q[(ki, kj)] @ Ks[kj][:, None].mT
    return out

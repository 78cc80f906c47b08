r"""Non-augmented local estimators (Theorems 1-3) and cross-covariances (Theorems 4-6), paper 002.

All ``L`` sensors are one batch axis; gains and covariances do not depend on the data, so they are
computed once (shape ``(T, L, ...)`` or ``(T, L, L, ...)`` for sensor pairs) and shared by every
Monte Carlo run. The only Python loops are over time and, for the N-step smoothers, over the
``N + 1`` lags (each lag is one batched update of every time step at once).

Readings of the printed equations (see ``docs/reproduction-002.md``):

* (20) uses ``P^{xx^r}`` (the printed ``P^{x^r}`` is the cross term): ``L_i = [A (P^x C^T +
  P^{xx^r} C~^T) + Gamma R_i] (Q^eps)^{-1}``;
* (21) is ``L^{x^r}_i = Phi_i [(P^{xx^r})^T C^T + P^{x^r} C~^T] (Q^eps)^{-1}`` (the printed
  second term lacks ``Phi_i``; the projection ``E[x^r(t+1) eps^T] = Phi_i E[x~^r eps^T]`` needs it);
* initial ``P^{x^r}(0|-1) = Q^{r_0}_i Xi(0) = Q^{r_0}_i (P0 + mu0 mu0^T)`` (printed ``P0 Q^{r_0}``,
  equal only for ``mu0 = 0``);
* (35) gets ``+ delta_ij Q^xi_i(t)`` (the virtual process noise, as in (23));
* the filter/smoother cross-covariances (39)-(43) are evaluated by the forward recursion of the
  joint errors ``[x~_i(t|s-1); x~_i(s|s-1); x~^r_i(s|s-1)]`` over ``s = t..t+N`` that the proof
  (E4), (C3), (C4), (G1) starts from; :func:`theorem6_cross_covariances` evaluates the closed sums
  (the printed (42) lacks a term for ``i = j``, ``N >= 2``, and is offered with and without it).
* measurements start at ``t = 0`` (initial values ``x^(0|-1) = mu0``); the N-step predictor for
  ``t + N + 1 < 0`` is the prior; the smoother for ``t + N > T - 1`` uses the data up to ``T - 1``.

Missing measurements (NaN) are handled as a time-varying measurement model
(:class:`~torchmm.fusion.system.MeasurementSequence`): their gains are exactly zero. The pattern
must be the same for all runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchmm.beliefs.ops import symmetrize
from torchmm.contract import Flag, Int, Mask, Of, Values, entry_point
from torchmm.linalg import solve_right
from torchmm.fusion.system import (
    SYSTEM_ARG,
    MeasurementSequence,
    MultiSensorSystem,
    measurement_pattern,
    measurement_sequence,
)

__all__ = [
    "LocalStats",
    "CrossStats",
    "local_predictor_stats",
    "local_one_step",
    "local_estimates",
    "local_covariances",
    "cross_predictor_stats",
    "cross_covariances",
    "theorem6_cross_covariances",
    "check_measurements",
]


def check_measurements(system: MultiSensorSystem, y: Tensor, stats: "LocalStats | None" = None):
    """Validate ``y (T, *B, L, m)`` and return its missing pattern ``(T, L, m)`` (``None``: complete).

    With ``stats``, the pattern must be the one the statistics were computed for.
    """
    present = measurement_pattern(system, y)
    if stats is not None:
        want = stats.meas.present
        same = (present is None and want is None) or (
            present is not None and want is not None and present.shape == want.shape
            and bool((present == want).all()))
        if not same:
            raise ValueError("y: its missing (NaN) pattern differs from the one `stats` were computed for")
    return present


@dataclass(frozen=True)
class LocalStats:
    """Theorem 1 quantities per sensor at ``t|t-1`` (``T = 1`` and ``stationary`` for steady state).

    The auxiliary state ``x^r_i = r_i x`` is the state scaled by sensor ``i``'s multiplicative noise
    (the paper's ``x^r``); the fields name the theorem's symbols in words.

    Shapes:
        state_cov ``P^x``, aux_cov ``P^{x^r}``, state_aux_cov ``P^{xx^r}``: ``(T, L, n, n)``;
        innovation_cov ``Q^eps``: ``(T, L, m, m)``; state_gain ``L_i``, aux_gain ``L^{x^r}_i``:
        ``(T, L, n, m)``; aux_noise_cov ``Q^xi`` (the virtual process noise): ``(T, L, n, n)``;
        meas: the measurement model per step (:class:`MeasurementSequence`, ``T`` steps)
    """

    state_cov: Tensor
    aux_cov: Tensor
    state_aux_cov: Tensor
    innovation_cov: Tensor
    state_gain: Tensor
    aux_gain: Tensor
    aux_noise_cov: Tensor
    meas: MeasurementSequence
    stationary: bool = False

    def at(self, t: int) -> "LocalStats":
        k = 0 if self.stationary else t
        names = ("state_cov", "aux_cov", "state_aux_cov", "innovation_cov", "state_gain", "aux_gain", "aux_noise_cov")
        return LocalStats(*(getattr(self, f)[k] for f in names), meas=self.meas)


_STATS = Of(LocalStats, what="LocalStats (local_predictor_stats)")


def local_gains(system: MultiSensorSystem, meas_t, Px, Pr, Pxr):
    """Innovation covariance (17) and gains (20), (21) with ``meas_t = (C, C~, R, Q^v)`` of one step."""
    C, Ct, R, Qv = meas_t
    A, Phi = system.A, system.Phi
    PCt = Px @ C.mT + Pxr @ Ct.mT  # E[x~ eps^T]   (L, n, m)
    PrCt = Pxr.mT @ C.mT + Pr @ Ct.mT  # E[x~^r eps^T]
    Qeps = symmetrize(C @ PCt + Ct @ PrCt + Qv.diagonal(dim1=0, dim2=1).permute(2, 0, 1))
    Lx = solve_right(A @ PCt + system.Gamma @ R, Qeps)
    Lr = solve_right(Phi @ PrCt, Qeps)
    return Qeps, Lx, Lr


def _local_riccati(system: MultiSensorSystem, Px, Pr, Pxr, Qeps, Lx, Lr, Qxi):
    """(22)-(24): one step of the predictor covariances."""
    A, Phi = system.A, system.Phi
    Px1 = symmetrize(A @ Px @ A.T - Lx @ Qeps @ Lx.mT + system.GQG)
    Pr1 = symmetrize(Phi @ Pr @ Phi.mT - Lr @ Qeps @ Lr.mT + Qxi)
    Pxr1 = A @ Pxr @ Phi.mT - Lx @ Qeps @ Lr.mT
    return Px1, Pr1, Pxr1


@entry_point(system=SYSTEM_ARG, steps=Int(1), present=Mask(optional=True))
def local_predictor_stats(system: MultiSensorSystem, steps: int, present: Tensor | None = None) -> LocalStats:
    r"""Theorem 1: gains and one-step prediction covariances of every sensor, ``t = 0..T-1``.

    Initial values ``P^x(0|-1) = P0``, ``P^{x^r}(0|-1) = Q^{r_0}_i Xi(0)``, ``P^{xx^r}(0|-1) = 0``.
    ``present (T, L, m)``: which measurement components exist (``None``: all).

    Shapes:
        -> :class:`LocalStats` with leading ``(T, L)``
    """
    meas = measurement_sequence(system, steps, present)
    L, n = system.num_sensors, system.state_dim
    Xi, _, Qxi = system.second_moments(steps)
    Px = system.P0.expand(L, n, n)
    Pr = system.Qr0[:, None, None] * Xi[0]
    Pxr = torch.zeros_like(Pr)
    out = {k: [] for k in ("state_cov", "aux_cov", "state_aux_cov", "innovation_cov", "state_gain", "aux_gain")}
    for t in range(steps):
        Qeps, Lx, Lr = local_gains(system, meas.at(t), Px, Pr, Pxr)
        for k, v in zip(out, (Px, Pr, Pxr, Qeps, Lx, Lr)):
            out[k].append(v)
        Px, Pr, Pxr = _local_riccati(system, Px, Pr, Pxr, Qeps, Lx, Lr, Qxi[t])
    return LocalStats(**{k: torch.stack(v) for k, v in out.items()}, aux_noise_cov=Qxi, meas=meas)


@entry_point(system=SYSTEM_ARG, stats=_STATS, y=Values())
def local_one_step(system: MultiSensorSystem, stats: LocalStats, y: Tensor):
    r"""(16), (18), (19): one-step predictors of ``x`` and ``x^r_i`` and the innovations.

    Shapes:
        y: ``(T, *B, L, m)`` -> x_pred ``(T, *B, L, n)`` (``x^_i(t|t-1)``), xr_pred ``(T, *B, L, n)``,
        eps ``(T, *B, L, m)``
    """
    if stats.stationary:
        if check_measurements(system, y) is not None:
            raise ValueError("y: the steady-state estimators need complete data (no NaN measurements)")
    else:
        if check_measurements(system, y, stats) is not None:
            y = torch.where(torch.isnan(y), torch.zeros_like(y), y)  # masked rows: C = C~ = 0, eps = 0
    T = y.shape[0]
    B = y.shape[1:-2]
    L, n = system.num_sensors, system.state_dim
    x = system.mu0.expand(*B, L, n)
    xr = torch.zeros(*B, L, n, dtype=y.dtype, device=y.device)
    A, Phi = system.A, system.Phi
    xs, xrs, es = [], [], []
    for t in range(T):
        st = stats.at(t)
        C, Ct = stats.meas.at(t)[:2]
        eps = y[t] - (C @ x.unsqueeze(-1) + Ct @ xr.unsqueeze(-1)).squeeze(-1)
        xs.append(x), xrs.append(xr), es.append(eps)
        x = x @ A.T + (st.state_gain @ eps.unsqueeze(-1)).squeeze(-1)
        xr = (Phi @ xr.unsqueeze(-1) + st.aux_gain @ eps.unsqueeze(-1)).squeeze(-1)
    return torch.stack(xs), torch.stack(xrs), torch.stack(es)


def _shift(arr: Tensor, k: int, fill: Tensor | None = None) -> Tensor:
    """``out[t] = arr[t + k]`` (``fill`` or zeros past the end). ``arr (T, ...)``."""
    if k == 0:
        return arr
    pad = torch.zeros_like(arr[:k]) if fill is None else fill.expand_as(arr[:k])
    return torch.cat([arr[k:], pad], dim=0)


def _valid(T: int, k: int, like: Tensor) -> Tensor:
    return (torch.arange(T, device=like.device) + k < T).to(like.dtype)


def _pred_shift(mean: Tensor | None, cov: Tensor, k: int, system: MultiSensorSystem, prior_cov: Tensor,
                pairs: bool = False):
    r"""N-step predictor (25)/(26)/(38) with ``k = -N-1`` applications of ``A`` to ``x^(t-k|t-k-1)``.

    ``mean (T, *B, L, n)``; ``cov (T, *S, n, n)``; for ``t < k`` the prior (``A^t mu0``).
    ``pairs``: ``cov`` holds cross-covariances ``(T, L, L, n, n)`` (blocks are not symmetric).
    """
    A, GQG = system.A, system.GQG
    sym = symmetrize_pairs if pairs else symmetrize
    for _ in range(k):
        if mean is not None:
            head = system.mu0.expand_as(mean[:1])
            mean = torch.cat([head, mean[:-1] @ A.T], dim=0)
        head = prior_cov.expand_as(cov[:1])
        cov = torch.cat([head, sym(A @ cov[:-1] @ A.T + GQG)], dim=0)
    return mean, cov


@entry_point(system=SYSTEM_ARG, y=Values(), N=Int(),
             stats=Of(LocalStats, optional=True, what="LocalStats or None"))
def local_estimates(system: MultiSensorSystem, y: Tensor, N: int = 0, stats: LocalStats | None = None):
    r"""Local N-step estimates of every sensor: predictor (N < 0, Thm 2), filter (N = 0) and
    smoother (N > 0, Thm 3), with their error covariances.

    Smoother/filter (27)-(31): ``x^(t|t+k) = x^(t|t+k-1) + K(t|t+k) eps(t+k)``,
    ``K = [Omega^x C^T + Omega^{xx^r} C~^T] (Q^eps)^{-1}``,
    ``Omega^x <- Omega^x A^T - K Q^eps L^T``, ``Omega^{xx^r} <- Omega^{xx^r} Phi^T - K Q^eps (L^{x^r})^T``,
    ``P(t|t+k) = P(t|t+k-1) - K Q^eps K^T``, one batched update of all ``t`` per lag ``k = 0..N``.

    Shapes:
        y: ``(T, *B, L, m)`` -> mean ``(T, *B, L, n)``, cov ``(T, L, n, n)``

    Example:
        >>> import torch
        >>> from torchmm.fusion import MultiSensorSystem, simulate_fusion
        >>> sys = MultiSensorSystem.from_correlation(
        ...     A=[[0.5]], Gamma=[[1.0]], Qw=[[1.0]], C=[[[1.0]], [[1.0]]], Ct=[[[0.5]], [[0.2]]],
        ...     h=[0.6, 0.7], Qp=[0.1, 0.1], d=[[[0.0]], [[0.3]]], Q_eta=[[[1.0]], [[2.0]]],
        ...     mu0=[0.0], P0=[[1.0]])
        >>> sim = simulate_fusion(sys, 20, (8,), torch.Generator().manual_seed(0))
        >>> mean, cov = local_estimates(sys, sim.y, N=1)
        >>> tuple(mean.shape), tuple(cov.shape)
        ((20, 8, 2, 1), (20, 2, 1, 1))
    """
    T = y.shape[0]
    if stats is None:
        stats = local_predictor_stats(system, T, check_measurements(system, y))
    x_pred, _, eps = local_one_step(system, stats, y)
    return local_from_pred(system, stats, x_pred, eps, N)


@entry_point(system=SYSTEM_ARG, stats=_STATS, N=Int(), steps=Int(1, optional=True))
def local_covariances(system: MultiSensorSystem, stats: LocalStats, N: int,
                      steps: int | None = None) -> Tensor:
    """Error covariances ``P_i(t|t+N)`` only (no data). Shapes: -> ``(T, L, n, n)``."""
    return local_from_pred(system, stats, None, None, N, steps)[1]


def local_from_pred(system, stats: LocalStats, x_pred, eps, N: int, steps: int | None = None):
    if steps is None:
        steps = x_pred.shape[0] if x_pred is not None else stats.state_cov.shape[0]
    T = steps
    Px = stats.state_cov.expand(T, *stats.state_cov.shape[1:]) if stats.stationary else stats.state_cov
    if N < 0:
        mean, cov = _pred_shift(x_pred, Px, -N - 1, system, system.P0)
        if stats.stationary:  # steady state: the limit, no prior transient
            cov = _steady_pred_cov(system, stats.state_cov[0], -N - 1).expand_as(Px)
        return mean, cov
    A, Phi = system.A, system.Phi
    mean, cov = x_pred, Px
    Om_x = Px
    Om_r = stats.state_aux_cov.expand_as(Px) if stats.stationary else stats.state_aux_cov
    eye = torch.eye(system.meas_dim, dtype=Px.dtype, device=Px.device)
    for k in range(N + 1):
        if stats.stationary:
            Qe, Lx, Lr = stats.innovation_cov, stats.state_gain, stats.aux_gain
            C, Ct = stats.meas.C, stats.meas.Ct
        else:
            Qe = _shift(stats.innovation_cov, k, eye)
            Lx, Lr = _shift(stats.state_gain, k), _shift(stats.aux_gain, k)
            C, Ct = _shift(stats.meas.C, k), _shift(stats.meas.Ct, k)
        valid = _valid(T, k, Px)[:, None, None, None]
        K = solve_right(Om_x @ C.mT + Om_r @ Ct.mT, Qe)  # (T, L, n, m)
        if not stats.stationary:
            K = K * valid
        if mean is not None:
            Km = K.expand(T, *K.shape[1:]) * valid
            Kb = Km.reshape(T, *([1] * (mean.dim() - 3)), *K.shape[1:])
            mean = mean + (Kb @ _shift(eps, k).unsqueeze(-1)).squeeze(-1)
        KQ = K @ Qe
        cov = symmetrize(cov - KQ @ K.mT)
        Om_x = Om_x @ A.T - KQ @ Lx.mT
        Om_r = Om_r @ Phi.mT - KQ @ Lr.mT
    return mean, cov


def _steady_pred_cov(system, P1, k):
    P = P1
    for _ in range(k):
        P = symmetrize(system.A @ P @ system.A.T + system.GQG)
    return P


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


def _tr(x: Tensor) -> Tensor:
    """Swap the pair axes ``(.., i, j, a, b) -> (.., j, i, b, a)``: ``X_ji^T``."""
    return x.transpose(-4, -3).mT


def cross_innovation(meas_t, P, Pr, Pxr):
    """(33), (34), (36) for all pairs; ``meas_t = (C, C~, R, Q^v)``. Shapes ``(..., L, L, n, n)``."""
    C, Ct, _, Qv = meas_t
    Ci, Cj = C[:, None], C[None]
    Cti, Ctj = Ct[:, None], Ct[None]
    Pxe = P @ Cj.mT + Pxr @ Ctj.mT  # E[x~_i eps_j^T]        (33)
    Pre = _tr(Pxr) @ Cj.mT + Pr @ Ctj.mT  # E[x~^r_i eps_j^T]  (36)
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
    P1 = (A @ P @ A.T - A @ Pxe @ Lj.mT - Li @ _tr(Pxe) @ A.T + Li @ Qeps @ Lj.mT
          - Li @ Ri.mT @ G.T - G @ Rj @ Lj.mT + system.GQG)
    eye = torch.eye(system.num_sensors, dtype=P.dtype, device=P.device)[..., None, None]
    Pr1 = (Phi_i @ Pr @ Phi_j.mT - Phi_i @ Pre @ Lrj.mT - Lri @ _tr(Pre) @ Phi_j.mT
           + Lri @ Qeps @ Lrj.mT + eye * Qxi[:, None])
    Pxr1 = (A @ Pxr @ Phi_j.mT - A @ Pxe @ Lrj.mT - Li @ _tr(Pre) @ Phi_j.mT
            + Li @ Qeps @ Lrj.mT - G @ Rj @ Lrj.mT)
    return P1, Pr1, Pxr1, Qeps


@entry_point(system=SYSTEM_ARG, stats=_STATS, steps=Int(1, optional=True))
def cross_predictor_stats(system: MultiSensorSystem, stats: LocalStats,
                          steps: int | None = None) -> CrossStats:
    r"""Theorem 4: one-step prediction error cross-covariances of all sensor pairs.

    Initial values ``P_ij(0|-1) = P0``, ``P^{x^r}_ij(0|-1) = delta_ij Q^{r_0}_i Xi(0)``,
    ``P^{xx^r}_ij(0|-1) = 0``. The diagonal ``i = j`` reproduces Theorem 1.

    Shapes:
        -> :class:`CrossStats` with leading ``(T, L, L)``
    """
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


@entry_point(system=SYSTEM_ARG, stats=_STATS, cross=_CROSS, N=Int(), steps=Int(1, optional=True))
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

    Shapes:
        -> ``(T, L, L, n, n)``
    """
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
        return _pred_shift(None, P_pred, k, system, system.P0, pairs=True)[1]
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
            Pb, Qk = _shift(Pbar, k), _shift(Qe, k)
            Psik, Lk = _shift(Psi, k), _shift(Lbar, k)
            Qlk = _shift(Qe_loc, k, eye_m)
            Cb, RGk, Qvk = _shift(Cbar, k), _shift(RG, k), _shift(Qv, k)
            valid = _valid(T, k, E)
        Xii = X[:, idx, idx]  # (T, L, n, 2n)
        K = solve_right(Xii @ Cb.mT, Qlk)  # (T, L, n, m)
        if valid is not None:
            K = K * valid[:, None, None, None]
        Ki, Kj = K[:, :, None], K[:, None, :]
        Ci, Cj = Cb[:, :, None], Cb[:, None]
        XC = X @ Cj.mT  # E[e_i eps_j^T] minus the v term (e_i is orthogonal to v_j(s))
        E = symmetrize_pairs(E - XC @ Kj.mT - Ki @ _tr(XC) + Ki @ Qk @ Kj.mT)
        X = ((X - Ki @ Ci @ Pb) @ Psik[:, None].mT - Ki @ RGk[:, :, None]
             + Ki @ Qvk @ Lk[:, None].mT)
    return E


def symmetrize_pairs(P: Tensor) -> Tensor:
    """``(P_ij + P_ji^T) / 2`` over the pair axes ``(..., L, L, n, n)``."""
    return 0.5 * (P + _tr(P))


@entry_point(system=SYSTEM_ARG, stats=_STATS, cross=_CROSS, N=Int(0), xi_term=Flag())
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
        Qe = _shift(stats.innovation_cov, k, eye_m)
        K = solve_right(Om_x @ C.mT + Om_r @ Ct.mT, Qe) * _valid(T, k, Om_x)[:, None, None, None]
        Ks.append(K)
        KQ = K @ Qe
        Om_x = Om_x @ A.T - KQ @ _shift(stats.state_gain, k).mT
        Om_r = Om_r @ system.Phi.mT - KQ @ _shift(stats.aux_gain, k).mT

    def M(offset: int, mj: int) -> Tensor:
        """``C_j A^{m-1} L_j(t+offset) + C~_j Phi_j^{m-1} L^{x^r}_j(t+offset)``, ``(T, L, m, m)``."""
        return C @ Apow[mj - 1] @ _shift(stats.state_gain, offset) + Ct @ Phipow[mj - 1] @ _shift(stats.aux_gain, offset)

    P, Pxr, Pr = cross.state_cov, cross.state_aux_cov, cross.aux_cov
    Cj, Ctj = C[None], Ct[None]
    # (40), (41): E[x~_i(t|t-1) eps_j^T(t+k)] and E[x~^r_i(t|t-1) eps_j^T(t+k)]
    Pxe, Pre = [], []
    for kj in range(N + 1):
        a = P @ Apow[kj].T @ Cj.mT + Pxr @ Phipow[kj][None].mT @ Ctj.mT
        b = _tr(Pxr) @ Apow[kj].T @ Cj.mT + Pr @ Phipow[kj][None].mT @ Ctj.mT
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
                val = Ct @ Phipow[a - s - 1] @ _shift(stats.aux_noise_cov, s)
                for mi in range(1, a - s):
                    val = val - M(a - mi, mi) @ Oxi[(a - mi, s)]
                Oxi[(a, s)] = val
    pair_eye = torch.eye(system.num_sensors, dtype=A.dtype, device=A.device)[..., None, None]
    # (42): Q^eps_ij(t+ki, t+kj)
    Q: dict[tuple[int, int], Tensor] = {}
    for ki in range(N + 1):
        Q[(ki, ki)] = _shift(cross.innovation_cov, ki)
        for b in range(ki):
            Q[(ki, b)] = _tr(Q[(b, ki)])
        for kj in range(ki + 1, N + 1):
            val = _tr(Pxe[ki]) @ Apow[kj].T @ Cj.mT + _tr(Pre[ki]) @ Phipow[kj][None].mT @ Ctj.mT
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
        out = out - Pxe[kj] @ Kj.mT - Ks[kj][:, :, None] @ _tr(Pxe[kj])
    for ki in range(N + 1):
        for kj in range(N + 1):
            out = out + Ks[ki][:, :, None] @ Q[(ki, kj)] @ Ks[kj][:, None].mT
    return out

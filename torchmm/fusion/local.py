r"""Non-augmented local estimators (Theorems 1-3), paper 002; their cross-covariances (Theorems 4-6) are
:mod:`torchmm.fusion.cross`'s.

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
from torchmm.contract import Int, Mask, Of, Values, entry_point
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
    "local_predictor_stats",
    "local_one_step",
    "local_estimates",
    "local_covariances",
    "check_measurements",
    "check_stats_steps",
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


def check_stats_steps(name: str, stats, steps: int, what: str) -> None:
    """Raise ``ValueError`` naming ``name`` when time-varying statistics (:class:`LocalStats` or
    :class:`~torchmm.fusion.cross.CrossStats`, ``stationary=False``) cover a different number of
    steps than ``what`` (e.g. ``"y has"``) ``steps``; stationary statistics fit any length.
    """
    if stats.stationary:
        return
    have = stats.state_cov.shape[0]
    if have != steps:
        raise ValueError(f"{name}: computed for {have} steps, but {what} {steps} (compute the statistics "
                         "for the same number of steps)")


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


LOCAL_STATS = Of(LocalStats, what="LocalStats (local_predictor_stats)")


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


@entry_point(system=SYSTEM_ARG, stats=LOCAL_STATS, y=Values())
def local_one_step(system: MultiSensorSystem, stats: LocalStats, y: Tensor):
    r"""(16), (18), (19): one-step predictors of ``x`` and ``x^r_i`` and the innovations.

    Shapes:
        y: ``(T, *B, L, m)`` -> x_pred ``(T, *B, L, n)`` (``x^_i(t|t-1)``), xr_pred ``(T, *B, L, n)``,
        eps ``(T, *B, L, m)``
    """
    check_stats_steps("stats", stats, y.shape[0], "y has")
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


def shift_steps(arr: Tensor, k: int, fill: Tensor | None = None) -> Tensor:
    """``out[t] = arr[t + k]`` (``fill`` or zeros past the end). ``arr (T, ...)``."""
    if k == 0:
        return arr
    pad = torch.zeros_like(arr[:k]) if fill is None else fill.expand_as(arr[:k])
    return torch.cat([arr[k:], pad], dim=0)


def valid_steps(T: int, k: int, like: Tensor) -> Tensor:
    return (torch.arange(T, device=like.device) + k < T).to(like.dtype)


def pred_shift(mean: Tensor | None, cov: Tensor, k: int, system: MultiSensorSystem, prior_cov: Tensor,
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


@entry_point(system=SYSTEM_ARG, stats=LOCAL_STATS, N=Int(), steps=Int(1, optional=True))
def local_covariances(system: MultiSensorSystem, stats: LocalStats, N: int,
                      steps: int | None = None) -> Tensor:
    """Error covariances ``P_i(t|t+N)`` only (no data); ``steps`` (time-varying ``stats``: their
    ``T``, the default; stationary: any). Shapes: -> ``(T, L, n, n)``."""
    if steps is not None:
        check_stats_steps("stats", stats, steps, "steps is")
    return local_from_pred(system, stats, None, None, N, steps)[1]


def local_from_pred(system, stats: LocalStats, x_pred, eps, N: int, steps: int | None = None):
    if steps is None:
        steps = x_pred.shape[0] if x_pred is not None else stats.state_cov.shape[0]
    T = steps
    Px = stats.state_cov.expand(T, *stats.state_cov.shape[1:]) if stats.stationary else stats.state_cov
    if N < 0:
        mean, cov = pred_shift(x_pred, Px, -N - 1, system, system.P0)
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
            Qe = shift_steps(stats.innovation_cov, k, eye)
            Lx, Lr = shift_steps(stats.state_gain, k), shift_steps(stats.aux_gain, k)
            C, Ct = shift_steps(stats.meas.C, k), shift_steps(stats.meas.Ct, k)
        valid = valid_steps(T, k, Px)[:, None, None, None]
        K = solve_right(Om_x @ C.mT + Om_r @ Ct.mT, Qe)  # (T, L, n, m)
        if not stats.stationary:
            K = K * valid
        if mean is not None:
            Km = K.expand(T, *K.shape[1:]) * valid
            Kb = Km.reshape(T, *([1] * (mean.dim() - 3)), *K.shape[1:])
            mean = mean + (Kb @ shift_steps(eps, k).unsqueeze(-1)).squeeze(-1)
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


def pair_transpose(x: Tensor) -> Tensor:
    """Swap the pair axes ``(.., i, j, a, b) -> (.., j, i, b, a)``: ``X_ji^T``."""
    return x.transpose(-4, -3).mT


def symmetrize_pairs(P: Tensor) -> Tensor:
    """``(P_ij + P_ji^T) / 2`` over the pair axes ``(..., L, L, n, n)``."""
    return 0.5 * (P + pair_transpose(P))

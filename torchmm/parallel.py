r"""Parallel-in-time Kalman filtering and RTS smoothing through an associative scan (O(log T) depth).

Särkkä & García-Fernández, "Temporal parallelization of Bayesian smoothers", IEEE TAC 66(1), 2021,
(docs/smoothing.md). Each step ``k`` of a linear-Gaussian model
``x_k = F x_{k-1} + c + w`` (``Q``), ``z_k = H x_k + d + v`` (``R``) is an element
``(A_k, b_k, C_k, eta_k, J_k)``: with ``S = H Q H^T + R``, ``K = Q H^T S^{-1}``,

.. math::
    A_k = (I - K H) F,\ b_k = c + K (z_k - H c - d),\ C_k = Q - K S K^T,\
    \eta_k = F^T H^T S^{-1} (z_k - H c - d),\ J_k = F^T H^T S^{-1} H F

(step 1 uses ``F = 0``, ``c = F m_0 + c``, ``Q = F P_0 F^T + Q``: its element is the first filtered
belief). The associative operator of their filtering elements combines two of them; the prefix "sums" are the
filtered means ``b`` and covariances ``C``. The smoother's elements ``(E_k, g_k, L_k)``,
``E_k = P_k F^T (P^-_{k+1})^{-1}``, ``g_k = m_k - E_k m^-_{k+1}``, ``L_k = P_k - E_k P^-_{k+1} E_k^T``
(``(0, m_T, P_T)`` last), combine backwards as ``(E_i E_j, E_i g_j + g_i, E_i L_j E_i^T + L_i)``.

The scan (:func:`associative_scan`) is the odd-even recursion: ``log2 T`` levels of batched tensor
operations, each over every run at once, no Python loop over time or runs, no host synchronisation
(the entry checks of :func:`filter`, those of :func:`~torchmm.run_filter`, read values once, before
the scans).
Missing data (NaN components of ``z``) are skipped exactly: a missing component gets a zero row of
``H`` and a decoupled unit noise, which gives it a zero gain. Priors, innovations and the
log-likelihood come from one batched prediction and update over all steps, so the returned
:class:`~torchmm.run.Trajectory` has the fields of :func:`~torchmm.run_filter`'s.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief, symmetrize
from torchmm.contract import BeliefArg, Data, Of, Tensors, entry_point
from torchmm.filters.kalman import KalmanFilter
from torchmm.provenance import Provenance, fingerprints, note_infinite, tensor_versions
from torchmm.run import Trajectory, attach_provenance
from torchmm.validation import broadcast_shape, check_filter_dtype, check_measurement, gaussian_batch

__all__ = ["associative_scan", "filter", "smooth"]

Elements = tuple[Tensor, ...]

log = logging.getLogger("torchmm")


@entry_point(op=Of(callable_ok=True, what="a callable op(a, b) -> elements"), elems=Tensors(leading=True))
def associative_scan(op: Callable[[Elements, Elements], Elements], elems: Elements) -> Elements:
    """Inclusive scan of ``elems`` (tensors with a shared leading axis) under the associative ``op``.

    ``op(a, b)`` combines ``a`` (earlier) with ``b`` (later), elementwise over the leading axis.
    The odd-even recursion (as ``jax.lax.associative_scan``): pairs are combined, the half-length
    sequence scanned, and the even positions filled in, ``ceil(log2 T)`` levels deep; each level is
    a few batched calls of ``op``. Differentiable.

    Shapes:
        every element ``(T, ...)`` -> ``(T, ...)``

    Raises:
        TypeError: ``op`` is not callable, ``elems`` not a non-empty sequence of tensors;
        ValueError: naming ``elems``, where they do not share a leading axis.
    """
    return _scan(op, tuple(elems))  # op and elems: checked by kind at entry


def _scan(op: Callable[[Elements, Elements], Elements], elems: Elements) -> Elements:
    n = elems[0].shape[0]
    if n < 2:
        return elems
    reduced = op(tuple(e[0:-1:2] for e in elems), tuple(e[1::2] for e in elems))
    odd = _scan(op, reduced)  # the prefixes at positions 1, 3, 5, ...
    if n % 2 == 0:
        even = op(tuple(o[:-1] for o in odd), tuple(e[2::2] for e in elems))
    else:
        even = op(odd, tuple(e[2::2] for e in elems))
    out = []
    for e, ev, od in zip(elems, even, odd):
        ev = torch.cat([e[:1], ev])  # the prefixes at positions 0, 2, 4, ...
        pairs = torch.stack([ev[: od.shape[0]], od], 1).flatten(0, 1)
        out.append(pairs if ev.shape[0] == od.shape[0] else torch.cat([pairs, ev[-1:]]))
    return tuple(out)


def _filter_op(a: Elements, b: Elements) -> Elements:
    """Särkkä & García-Fernández (2021), the filtering operator: element ``a`` (earlier) then ``b`` (later)."""
    A1, b1, C1, e1, J1 = a
    A2, b2, C2, e2, J2 = b
    eye = torch.eye(A1.shape[-1], dtype=A1.dtype, device=A1.device)
    M = eye + C1 @ J2  # (I + C_i J_j)
    rhs = torch.cat([A1, (b1 + (C1 @ e2.unsqueeze(-1)).squeeze(-1)).unsqueeze(-1), C1], -1)
    X = torch.linalg.solve(M, rhs)  # (I + C_i J_j)^{-1} [A_i, b_i + C_i eta_j, C_i]
    n = A1.shape[-1]
    A = A2 @ X[..., :n]
    bb = (A2 @ X[..., n:n + 1]).squeeze(-1) + b2
    C = symmetrize(A2 @ X[..., n + 1:] @ A2.mT + C2)
    N = eye + J2 @ C1  # (I + J_j C_i)
    Y = torch.linalg.solve(N, torch.cat([(e2 - (J2 @ b1.unsqueeze(-1)).squeeze(-1)).unsqueeze(-1), J2 @ A1], -1))
    e = (A1.mT @ Y[..., :1]).squeeze(-1) + e1
    J = symmetrize(A1.mT @ Y[..., 1:] + J1)
    return A, bb, C, e, J


def _smoother_op(a: Elements, b: Elements) -> Elements:
    """Backward composition: ``a`` is the later part already combined, ``b`` the earlier element."""
    E1, g1, L1 = a
    E2, g2, L2 = b
    return E2 @ E1, (E2 @ g1.unsqueeze(-1)).squeeze(-1) + g2, symmetrize(E2 @ L1 @ E2.mT + L2)


def _check(kf, belief0, z) -> Tensor:
    """The entry checks of :func:`~torchmm.run_filter`, for the scans: ``kf``'s type, ``belief0``'s values
    (:meth:`~torchmm.beliefs.Belief.validate`) and dtype, ``z``'s shape against the prior's batch (a
    batch it would enlarge is refused, as in every filter step). Returns ``z`` in ``belief0``'s dtype."""
    if not isinstance(kf, KalmanFilter):
        raise TypeError(f"kf: the parallel filter needs a KalmanFilter (linear-Gaussian models), got "
                        f"{type(kf).__name__}")
    if not isinstance(belief0, GaussianBelief):
        raise TypeError(f"belief0: expected a GaussianBelief, got {type(belief0).__name__}")
    gaussian_batch(belief0, kf.state_dim, "belief0")
    belief0.validate_once("belief0")
    check_filter_dtype(kf, belief0, "belief0")
    if not isinstance(z, Tensor):
        raise TypeError(f"z: expected a tensor of shape (T, *B, {kf.meas_dim}), got {type(z).__name__}")
    if z.dim() < 2 or z.shape[-1] != kf.meas_dim:
        raise ValueError(f"z: expected shape (T, *B, {kf.meas_dim}), got {tuple(z.shape)}")
    if z.shape[0] < 1:
        raise ValueError("z: needs at least one step (T = 0)")
    batch = gaussian_batch(kf.predict(belief0), kf.state_dim)  # the prior's batch: belief0's and the models'
    return check_measurement(z, kf.meas_dim, torch.Size((z.shape[0], *batch)), belief0.mean, "z")


def _elements(kf: KalmanFilter, belief0: GaussianBelief, z: Tensor, *, update_first: bool = False,
              offsets: Tensor | None = None) -> Elements:
    """The filtering elements ``(A, b, C, eta, J)``, each ``(T, *B, ...)``. ``update_first``: ``belief0`` is
    the first step's prior (no prediction into it); ``offsets`` ``(T, *B, n)``: each prediction's extra
    offset (a motion model's inputs, ``B u_k``)."""
    n, m = kf.state_dim, kf.meas_dim
    dtype, device = belief0.mean.dtype, belief0.mean.device
    zero = torch.zeros(n, dtype=dtype, device=device)
    F = kf.motion.jacobian(zero)  # linear: the matrices themselves; c, d the affine offsets
    c = kf.motion(zero)
    Q = kf.motion.noise_cov(zero)
    H = kf.measurement.jacobian(zero)
    d = kf.measurement(zero)
    R = kf.measurement.noise_cov(zero)
    steps = z.shape[0]
    batch = broadcast_shape(belief0.batch_shape, z.shape[1:-1], F.shape[:-2], Q.shape[:-2], H.shape[:-2],
                            R.shape[:-2], c.shape[:-1], d.shape[:-1],
                            () if offsets is None else offsets.shape[1:-1])
    full = (steps, *batch)
    # step 1: its element is the filtered belief (F = 0, c = m1-, Q = P1-); later steps the model's
    if update_first:
        m1, P1 = belief0.mean, belief0.cov
    else:
        m1 = (F @ belief0.mean.unsqueeze(-1)).squeeze(-1) + c + (0 if offsets is None else offsets[0])
        P1 = F @ belief0.cov @ F.mT + Q
    Fk = torch.cat([torch.zeros_like(F.expand(*batch, n, n)).unsqueeze(0), F.expand(steps - 1, *batch, n, n)])
    later = c.expand(steps - 1, *batch, n) if offsets is None else c + offsets[1:].expand(steps - 1, *batch, n)
    ck = torch.cat([m1.expand(*batch, n).unsqueeze(0), later])
    Qk = torch.cat([P1.expand(*batch, n, n).unsqueeze(0), Q.expand(steps - 1, *batch, n, n)])
    # missing components: a zero row of H and a decoupled unit noise (zero gain, exactly)
    observed = torch.isfinite(z).expand(*full, m)
    zz = torch.where(observed, z, 0.0).expand(*full, m)
    Hk = H.expand(*full, m, n) * observed.unsqueeze(-1)
    pair = observed.unsqueeze(-1) & observed.unsqueeze(-2)
    Rk = torch.where(pair, R.expand(*full, m, m), torch.eye(m, dtype=dtype, device=device))
    S = symmetrize(Hk @ Qk @ Hk.mT + Rk)
    L = torch.linalg.cholesky(S)
    QHt = Qk @ Hk.mT
    K = torch.cholesky_solve(QHt.mT, L).mT  # Q H^T S^{-1}
    resid = zz - (Hk @ ck.unsqueeze(-1)).squeeze(-1) - torch.where(observed, d.expand(*full, m), 0.0)
    A = Fk - K @ Hk @ Fk
    b = ck + (K @ resid.unsqueeze(-1)).squeeze(-1)
    C = symmetrize(Qk - K @ S @ K.mT)
    HF = Hk @ Fk
    Sinv_HF = torch.cholesky_solve(HF, L)
    eta = (HF.mT @ torch.cholesky_solve(resid.unsqueeze(-1), L)).squeeze(-1)
    J = symmetrize(HF.mT @ Sinv_HF)
    return A, b, C, eta, J


def filter_smooth(kf: KalmanFilter, belief0: GaussianBelief, z: Tensor, *, update_first: bool = False,
                  offsets: Tensor | None = None) -> tuple[GaussianBelief, GaussianBelief, GaussianBelief, Tensor]:
    """``(filtered, prior, smoothed, log_likelihood)`` of every step by the two scans, for callers inside
    torchmm that checked their arguments (EM's E-step, :func:`torchmm.learn.em`): ``update_first`` and
    each prediction's extra ``offsets`` ``(T, *B, n)`` (inputs ``B u_k``) as for :func:`_elements`.

    Shapes:
        belief0 batch ``(*B,)``, z ``(T, *B, m)`` -> beliefs batch ``(T, *B)``, log_likelihood ``(T, *B)``
    """
    A, b, C, _, _ = _scan(_filter_op, _elements(kf, belief0, z, update_first=update_first, offsets=offsets))
    filtered = GaussianBelief(b, C)
    previous = GaussianBelief(torch.cat([belief0.mean.expand(b.shape[1:]).unsqueeze(0), b[:-1]]),
                              torch.cat([belief0.cov.expand(C.shape[1:]).unsqueeze(0), C[:-1]]))
    prior = kf.predict(previous)
    mean, cov = prior.mean, prior.cov
    if offsets is not None:
        mean = mean + offsets
    if update_first:  # the first step's prior is belief0 itself
        mean = torch.cat([belief0.mean.expand(mean.shape[1:]).unsqueeze(0), mean[1:]])
        cov = torch.cat([belief0.cov.expand(cov.shape[1:]).unsqueeze(0), cov[1:]])
    prior = GaussianBelief(mean, cov)
    ll = kf.update(prior, z).log_likelihood
    return filtered, prior, smooth_scan(kf, filtered, prior), ll


def smooth_scan(kf: KalmanFilter, filtered: GaussianBelief, prior: GaussianBelief) -> GaussianBelief:
    """The RTS smoother of a Kalman filter's run by the backward scan, from its filtered beliefs and the
    priors of every step (each step's prediction, ``prior[t]`` predicting ``t`` from ``filtered[t - 1]``),
    batch ``(T, *B)``: EM's E-step after a filter run by either the scans or the Numba kernel."""
    b, C, mean, cov = filtered.mean, filtered.cov, prior.mean, prior.cov
    F = kf.motion.jacobian(torch.zeros(kf.state_dim, dtype=b.dtype, device=b.device))
    if b.shape[0] == 1:
        return filtered
    E = torch.linalg.solve(cov[1:], (C[:-1] @ F.mT).mT).mT  # P_k F^T (P^-_{k+1})^{-1}
    g = b[:-1] - (E @ mean[1:].unsqueeze(-1)).squeeze(-1)
    L = symmetrize(C[:-1] - E @ cov[1:] @ E.mT)
    E = torch.cat([E, torch.zeros_like(E[:1])])
    g = torch.cat([g, b[-1:]])
    L = torch.cat([L, C[-1:]])
    _, gs, Ls = _scan(_smoother_op, (E.flip(0), g.flip(0), L.flip(0)))
    return GaussianBelief(gs.flip(0), Ls.flip(0))


# declared: _check refuses other filters and beliefs ("kf: the parallel filter needs a KalmanFilter")
_KF = Of(KalmanFilter, check=False, what="a KalmanFilter")
_BELIEF0 = BeliefArg(check=False)


@entry_point(kf=_KF, belief0=_BELIEF0, z=Data())
def filter(kf: KalmanFilter, belief0: GaussianBelief, z: Tensor) -> Trajectory:
    r"""Kalman filtering of all steps through a parallel scan: the :func:`~torchmm.run_filter` result.

    Args:
        kf: a :class:`~torchmm.KalmanFilter` (time-invariant linear-Gaussian models; model
            parameters may carry a batch that broadcasts against the runs').
        belief0: the prior of ``x_0``, batch ``(*B,)``.
        z: measurements ``(T, *B, m)``; NaN components are missing.

    Returns:
        a :class:`~torchmm.run.Trajectory` as ``run_filter(kf, belief0, z)``'s: filtered beliefs and
        priors with batch ``(T, *B)``, ``log_likelihood`` ``(T, *B)``, innovations and their
        covariances, ``extras["singular"]``, and the record of the run (``provenance``: ``kf``, ``z``'s
        fingerprint) that :func:`torchmm.smooth` checks.

    Raises:
        TypeError / ValueError: naming ``kf``, ``belief0`` or ``z``: the entry checks of
        :func:`~torchmm.run_filter` (``belief0``'s values and dtype; ``z`` time-major, ``T >= 1``, its
        batch broadcasting to the prior's - data of shape ``(T, 2, B, m)`` for ``B`` runs are refused).

    Shapes:
        belief0 batch ``(*B,)``, z ``(T, *B, m)`` -> beliefs batch ``(T, *B)``

    Examples:
        >>> import torch
        >>> from torchmm import GaussianBelief, KalmanFilter, run_filter, parallel
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> kf = KalmanFilter(ConstantVelocity(1, q=0.1, dtype=torch.float64),
        ...                   PositionMeasurement(2, [0], 1.0, dtype=torch.float64))
        >>> z = torch.randn(50, 4, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        >>> b0 = GaussianBelief(torch.zeros(4, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))
        >>> fast, slow = parallel.filter(kf, b0, z), run_filter(kf, b0, z)
        >>> bool(torch.allclose(fast.belief.mean, slow.belief.mean, atol=1e-10))
        True
    """
    given = z
    z = _check(kf, belief0, z)
    (data,), (infinite,) = fingerprints(given)  # one host read: the record smooth checks against
    note_infinite(infinite, "z")
    A, b, C, _, _ = _scan(_filter_op, _elements(kf, belief0, z))
    filtered = GaussianBelief(b, C)
    previous = GaussianBelief(torch.cat([belief0.mean.expand(b.shape[1:]).unsqueeze(0), b[:-1]]),
                              torch.cat([belief0.cov.expand(C.shape[1:]).unsqueeze(0), C[:-1]]))
    prior = kf.predict(previous)  # every step's prior at once (from the filtered belief before it)
    out = kf.update(prior, z)  # innovations, their covariances and the log-likelihood, all steps at once
    traj = Trajectory(belief=filtered, prior=prior, log_likelihood=out.log_likelihood,
                      innovation=out.innovation,
                      innovation_cov=out.innovation_cov, extras=out.extras)
    return attach_provenance(traj, Provenance("torchmm.parallel.filter", kf, z.shape[0], given, data,
                                              tensor_versions(given), kernel="parallel scans (torchmm.parallel)"))


@entry_point(kf=_KF, belief0=_BELIEF0, z=Data())
def smooth(kf: KalmanFilter, belief0: GaussianBelief, z: Tensor) -> Trajectory:
    r"""RTS smoothing through two parallel scans (filter, then backward): ``torchmm.smooth(kf,
    run_filter(kf, belief0, z))``'s result. The entry checks of :func:`filter` (errors naming ``kf``,
    ``belief0``, ``z``).

    Shapes:
        belief0 batch ``(*B,)``, z ``(T, *B, m)`` -> smoothed beliefs batch ``(T, *B)``
    """
    traj = filter(kf, belief0, z)
    m, P = traj.belief.mean, traj.belief.cov
    m_pred, P_pred = traj.prior.mean[1:], traj.prior.cov[1:]  # x^-_{k+1}
    F = kf.motion.jacobian(torch.zeros(kf.state_dim, dtype=m.dtype, device=m.device))
    PFt = P[:-1] @ F.mT
    E = torch.linalg.solve(P_pred, PFt.mT).mT  # P_k F^T (P^-_{k+1})^{-1}
    g = m[:-1] - (E @ m_pred.unsqueeze(-1)).squeeze(-1)
    L = symmetrize(P[:-1] - E @ P_pred @ E.mT)
    E = torch.cat([E, torch.zeros_like(E[:1])])
    g = torch.cat([g, m[-1:]])
    L = torch.cat([L, P[-1:]])
    # backwards: scan the reversed sequence; element k's result composes k, k+1, ..., T
    _, gs, Ls = _scan(_smoother_op, (E.flip(0), g.flip(0), L.flip(0)))
    belief = GaussianBelief(gs.flip(0), Ls.flip(0))
    return Trajectory(belief=belief, prior=None, log_likelihood=traj.log_likelihood, innovation=None,
                      innovation_cov=None, extras={})

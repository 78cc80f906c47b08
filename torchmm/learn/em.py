r"""Expectation-maximisation for linear-Gaussian state-space models, batched over series (issue 45).

:func:`em` fits a :class:`~torchmm.KalmanFilter` over :class:`~torchmm.LinearMotion` and
:class:`~torchmm.LinearMeasurement` models (Shumway & Stoffer, J. Time Ser. Anal. 3(4), 1982;
Ghahramani & Hinton, 1996): each iteration

* **E-step**: the Kalman filter - for at most ``torchmm.kernels.linear.MAX_RUNS`` series on the CPU the
  Numba kernel's serial loop, else the parallel scan (:mod:`torchmm.parallel`: ``log T`` batched
  levels, every series at once) - the RTS smoother by the backward scan, and the lag-one smoothed covariances
  ``P_{t,t-1|T} = P_{t|T} G_{t-1}^T`` (``G_t = P_{t|t} F^T P_{t+1|t}^{-1}``) give the expected
  sufficient statistics, summed over the steps (and over the series, for parameters they share);
* **M-step**, the exact conditional maximisers of the expected complete-data log-likelihood, in
  pykalman's order (each uses the ones updated before it: an ECM step, which never lowers the
  likelihood): ``H``, ``R``, ``F`` (given the offset ``b``), ``Q`` (given ``F`` and ``b``), the start's
  mean and covariance, then ``b`` (given ``F``):

  .. math::
      H = \Big(\sum_t y_t \hat x_t^\top\Big)\Big(\sum_t \hat x_t \hat x_t^\top + P_t\Big)^{-1},\quad
      R = \frac1{N_y} \sum_t (y_t - H\hat x_t)(y_t - H\hat x_t)^\top + H P_t H^\top,

      F = \Big(\sum_t P_{t,t-1} + \hat x_t \hat x_{t-1}^\top - b\,\hat x_{t-1}^\top\Big)
          \Big(\sum_t P_{t-1} + \hat x_{t-1}\hat x_{t-1}^\top\Big)^{-1},\quad
      b = \frac1{N_x}\sum_t \hat x_t - F\hat x_{t-1},

      Q = \frac1{N_x}\sum_t (\hat x_t - F\hat x_{t-1} - b)(\cdot)^\top + F P_{t-1} F^\top + P_t
          - P_{t,t-1} F^\top - F P_{t,t-1}^\top,

  ``x_0 = \hat x_{0|T}``, ``P_0 = P_{0|T}``; with shared parameters a start broadcast over the series
  (``belief0.expand(S)``: one start for all, as :func:`~torchmm.learn.estimate` holds it) pools them:
  ``x_0 = mean_s \hat x^s_{0|T}``, ``P_0 = mean_s P^s_{0|T} + (\hat x^s_{0|T} - x_0)(\cdot)^T``.

The log-likelihood of each iteration's parameters is that of its E-step's filter, so the history is
the likelihood *before* each M-step (pykalman's test convention), and EM never lowers it: a decrease
beyond rounding is reported (``EMResult.monotone``). Steps whose measurement is missing (NaN, the
whole vector) add nothing to the ``H``, ``R`` statistics; padding of shorter series (``present``)
adds nothing at all. ``per_series=True`` gives every series its own parameters (a batch of
independent fits in one batched EM); otherwise the series share them.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief
from torchmm.contract import BeliefArg, Data, Flag, Int, Mask, Of, Real, Unchecked, entry_point
from torchmm.filters.kalman import KalmanFilter
from torchmm.learn.em_checks import fixed_masks, pooled_axes, start_masks
from torchmm.models.linear import LinearMeasurement, LinearMotion, plain_linear
from torchmm.parallel import filter_smooth, smooth_scan
from torchmm.smooth_checks import after_last_datum
from torchmm.validation import check_filter_dtype, check_measurement, gaussian_batch
from torchmm.runtime import entries, one_thread_when_small

__all__ = ["EM_PARAMETERS", "EMResult", "em", "fixed_masks"]

#: what :func:`em` estimates, by name
EM_PARAMETERS = ("H", "R", "F", "offset", "Q", "initial_mean", "initial_cov")


@dataclass
class EMResult:
    """What :func:`em` found.

    Attributes:
        loglik: the log-likelihood at each iteration's parameters (before its M-step), then at the
            final ones: ``iterations + 1`` values, each ``(*B,)`` with ``per_series`` (else scalars, the
            sum over the series).
        belief0: the estimated start belief (the initial state's mean and covariance).
        iterations: the M-steps done; converged: the relative change of the log-likelihood fell below
            ``tol``; monotone: no iteration lowered it by more than rounding; seconds.
        unestimated: ``{name: mask}``, the parameters that some series had nothing to estimate from, the
            mask ``(*B,)`` of those series with ``per_series`` (else ``()``, or ``(*B,)`` for a start field
            per series): no measurement (every parameter), or no transition, i.e. a series of one step
            (``F``, ``Q``, the offset). Their values are NaN (held at the start values in the iterations:
            the other series' fits are those without them), never the 0 of an empty sum.
    """

    loglik: list
    belief0: GaussianBelief
    iterations: int
    converged: bool
    monotone: bool
    seconds: float
    decreases: list = field(default_factory=list)
    unestimated: dict = field(default_factory=dict)


def observed_steps(z: Tensor, present: Tensor | None) -> tuple[Tensor, Tensor]:
    """``(present, observed)`` ``(T, *B)``: the steps of each series (padding False) and those with a
    measurement; a vector with only some components missing is refused (the M-steps take whole vectors)."""
    seen = torch.isfinite(z)
    observed = seen.all(-1)
    if bool((seen.any(-1) & ~observed).any()):
        raise ValueError("measurements: a vector with some components missing (not all): EM's steps take whole "
                         "vectors only (not implemented yet)")
    if present is None:
        present = torch.ones(z.shape[:-1], dtype=torch.bool, device=z.device)
    elif tuple(present.shape) != tuple(z.shape[:-1]):
        raise ValueError(f"present: expected shape {tuple(z.shape[:-1])}, got {tuple(present.shape)}")
    return present, observed & present


def iteration_bar(iterations: int, progress, name: str):
    """The EM iterations' progress bar (``progress``: None shows it on a terminal, a bool, or its description)."""
    from tqdm.auto import tqdm

    return tqdm(total=iterations, desc=progress if isinstance(progress, str) else name,
                disable=None if progress is None else not progress, leave=False)


def _sum(x: Tensor, keep: int, shared: bool) -> Tensor:
    """``x`` summed over time (axis 0) and, for shared parameters, over the series axes (``keep``
    trailing axes are the event)."""
    x = x.sum(0)
    if shared:
        x = x.reshape(-1, *x.shape[x.dim() - keep:]).sum(0) if x.dim() > keep else x
    return x


def _constrained(X: Tensor, B: Tensor, C: Tensor, W: Tensor, free: Tensor) -> Tensor:
    r"""The exact conditional maximiser of ``-1/2 tr(W^{-1} (X C X^T - B X^T - X B^T))`` over the free
    entries of ``X`` ``(*, r, c)``, its fixed entries held (an M-step of a regression with fixed
    coefficients): on the free entries ``W^{-1} X C = W^{-1} B``, one linear system in ``vec(X)``
    (``(W^{-1} X C)_{ij} = \sum_{kl} W^{-1}_{ik} C_{lj} X_{kl}``). Batched over the leading axes."""
    r, c = X.shape[-2:]
    batch = torch.broadcast_shapes(X.shape[:-2], B.shape[:-2], C.shape[:-2], W.shape[:-2])
    Winv = torch.cholesky_inverse(torch.linalg.cholesky(W)).expand(*batch, r, r)  # (W positive definite: fixed_masks)
    K = torch.einsum("...ik,...lj->...ijkl", Winv, C.expand(*batch, c, c)).reshape(*batch, r * c, r * c)
    rhs = (Winv @ B.expand(*batch, r, c)).reshape(*batch, r * c)
    f = torch.nonzero(free.reshape(-1))[:, 0].to(X.device)
    h = torch.nonzero(~free.reshape(-1))[:, 0].to(X.device)
    x = X.expand(*batch, r, c).reshape(*batch, r * c).clone()
    Kf = K.index_select(-2, f)
    rhs_f = rhs.index_select(-1, f) - (Kf.index_select(-1, h) @ x.index_select(-1, h).unsqueeze(-1)).squeeze(-1)
    x[..., f] = torch.linalg.solve(Kf.index_select(-1, f), rhs_f)
    return x.reshape(*batch, r, c)


def _regression(X: Tensor, B: Tensor, C: Tensor, W: Tensor, mask: Tensor | None) -> Tensor:
    """The M-step of a regression matrix (``H`` or ``F``): ``B C^{-1}``, or with fixed entries ``mask``
    (True: held) :func:`_constrained`'s conditional maximiser weighted by ``W``."""
    if mask is not None:
        return _constrained(X, B, C, W, ~mask)
    return torch.linalg.solve(C.mT, B.mT).mT


@entry_point(filter=Of(KalmanFilter, what="a KalmanFilter over LinearMotion and LinearMeasurement"),
             belief0=BeliefArg(validate=True), measurements=Data(),
             parameters=Unchecked("names of EM_PARAMETERS, checked by em"),
             iterations=Int(1), tol=Real(minimum=0.0, optional=True), update_first=Flag(), per_series=Flag(),
             controls=Data(optional=True),
             present=Mask(optional=True), fixed=Unchecked("{name: boolean mask}, checked by em"),
             progress=Unchecked("None, True, False or a description"))
@one_thread_when_small(lambda filter, belief0, measurements, *args, **kwargs: entries(belief0) * measurements.shape[0])
def em(filter: KalmanFilter, belief0: GaussianBelief, measurements: Tensor,
       parameters: Sequence[str] = ("H", "R", "F", "offset", "Q", "initial_mean", "initial_cov"), *,
       iterations: int = 10, tol: float | None = None, update_first: bool = True, per_series: bool = False,
       controls: Tensor | None = None, present: Tensor | None = None,
       fixed: Mapping[str, Any] | None = None, progress: bool | str | None = None) -> EMResult:
    r"""Fit ``parameters`` of a linear-Gaussian Kalman filter by EM (module docstring), in place.

    Args:
        filter: a :class:`~torchmm.KalmanFilter` whose motion is a :class:`~torchmm.LinearMotion` and
            whose measurement is a :class:`~torchmm.LinearMeasurement` (its ``F``, ``offset``, ``Q``,
            ``H``, ``R`` are written with the estimates).
        belief0: the start, batch ``(*B,)``: the prior of the first measurement with ``update_first``
            (pykalman's and statsmodels' convention, the default), else the belief one step before it.
            With shared parameters a field it broadcasts over the series (an expanded view,
            ``belief0.expand(B)``) is estimated as one value for them (pooled), a materialised one a value
            per series (:func:`~torchmm.learn.estimate`'s convention); ``per_series``: one per series.
        measurements: ``(T, *B, m)``; a step whose vector is missing (NaN) informs the state only.
        parameters: which of :data:`EM_PARAMETERS` to estimate (the others stay).
        iterations: at most this many EM iterations; tol: stop once the log-likelihood's relative change
            is below it (None: run them all).
        controls: ``(T, *B, k)``, the inputs of a motion model with an ``input_matrix`` ``B`` (kept fixed):
            the prediction into step ``t`` adds ``B u_t`` (e.g. pykalman's time-varying
            ``transition_offsets`` as ``u_t`` with ``B = I``).
        per_series: each series its own parameters (a batch of fits; the models' tensors get the batch
            ``*B`` in front), else one set for all.
        present: ``(T, *B)`` bool, False at the padding after a shorter series' end (nothing there is
            counted: its values are not read). Default: each series up to its last step with a measurement
            (the steps after it never change the likelihood, but as latent steps they would enter the
            M-steps' statistics: NaN padding would change the iterates), as :func:`~torchmm.smooth` treats
            such a tail (torchmm.smooth_checks.after_last_datum).
        fixed: ``{name: mask}``, a boolean mask of a parameter's entries held at their current values
            (``H`` ``(m, n)``, ``F`` ``(n, n)``, ``offset`` and ``initial_mean`` ``(n,)``, ``Q``, ``R``,
            ``initial_cov`` square). ``H``, ``F``, ``offset`` and ``initial_mean`` take any mask: their
            M-step is then a weighted least squares over the free entries (weighted by the current ``R``,
            ``Q`` or start covariance: an exact conditional maximiser, so the likelihood still never
            falls). A covariance takes masks whose free entries are diagonal blocks with 0 between the
            blocks (e.g. a diagonal ``Q``: the estimate is the unrestricted one's blocks, exactly).
        progress: a bar over the iterations (None: on a terminal only).

    Returns:
        an :class:`EMResult`; the filter's models hold the estimates, ``result.belief0`` the start.

    Raises:
        TypeError / ValueError naming ``filter`` (not linear-Gaussian), ``parameters`` (an unknown name),
        ``measurements`` (a partly missing vector: not supported), ``present``, ``belief0`` (a start
        mean shared over series whose covariance is one per series).

    Examples:
        >>> from torchmm.models import LinearMotion, LinearMeasurement
        >>> one = torch.ones(1, 1, dtype=torch.float64)
        >>> kf = KalmanFilter(LinearMotion(one.clone(), one.clone()), LinearMeasurement(one.clone(), one.clone()))
        >>> z = torch.randn(100, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0)).cumsum(0)
        >>> out = em(kf, GaussianBelief(torch.zeros(1, dtype=torch.float64), one), z, ["Q", "R"], iterations=5)
        >>> out.monotone, len(out.loglik)
        (True, 6)
    """
    motion, sensor = filter.motion, filter.measurement
    if not (isinstance(motion, LinearMotion) and isinstance(sensor, LinearMeasurement)
            and plain_linear(motion) and plain_linear(sensor)):
        raise TypeError(f"filter: EM needs a LinearMotion and a LinearMeasurement (or subclasses that only build "
                        f"their matrices, such as ConstantVelocity), got {type(motion).__name__} and "
                        f"{type(sensor).__name__}")
    if (controls is None) != (motion.input_matrix is None):
        raise ValueError("controls: give controls exactly when the motion model has an input_matrix "
                         f"({'none' if motion.input_matrix is None else tuple(motion.input_matrix.shape)})")
    if controls is not None and (not isinstance(controls, Tensor) or controls.shape[0] != measurements.shape[0]):
        raise ValueError(f"controls: expected (T, *B, k) with the measurements' {measurements.shape[0]} steps")
    if isinstance(parameters, str) or not all(isinstance(p, str) for p in parameters):
        raise TypeError(f"parameters: expected names of {', '.join(EM_PARAMETERS)}, got {parameters!r}")
    unknown = [p for p in parameters if p not in EM_PARAMETERS]
    if unknown or not parameters:
        raise ValueError(f"parameters: {unknown or 'nothing'}: expected some of {', '.join(EM_PARAMETERS)}")
    wanted = set(parameters)
    if not isinstance(belief0, GaussianBelief):
        raise TypeError(f"belief0: expected a GaussianBelief, got {type(belief0).__name__}")
    masks = fixed_masks(filter, belief0, parameters, fixed)
    if not per_series:
        start_masks(belief0, parameters)
    check_filter_dtype(filter, belief0, "belief0")
    gaussian_batch(belief0, filter.state_dim, "belief0")
    z = measurements
    if not isinstance(z, Tensor) or z.dim() < 2:
        raise ValueError("measurements: expected a time-major tensor (T, *B, m)")
    batch = belief0.batch_shape
    if tuple(z.shape[1:-1]) != tuple(batch):
        raise ValueError(f"measurements: batch {tuple(z.shape[1:-1])} is not the start belief's {tuple(batch)}")
    z = check_measurement(z, filter.meas_dim, torch.Size((z.shape[0], *batch)), belief0.mean, "measurements")
    if present is None:  # up to each series' last datum: later steps never change the likelihood, but as
        # latent steps they would enter the M-steps' statistics (and change the iterates)
        present = ~after_last_datum(z, tuple(z.shape[:-1]))
    present, observed = observed_steps(z, present)
    z = torch.where(present.unsqueeze(-1), z, torch.nan)  # (the padding: missing for the smoother too)
    shared = not per_series
    dtype = z.dtype
    yz = torch.where(observed.unsqueeze(-1), z, 0.0)
    # the inputs' part of each prediction into step t (fixed): B u_t, for the pairs (t-1, t)
    Bu = None if controls is None else (motion.input_matrix @ controls.to(dtype).unsqueeze(-1)).squeeze(-1)
    w = observed.to(dtype)  # (T, *B)
    pairs = (present[1:] & present[:-1]).to(dtype)  # transitions inside a series
    n_obs = _sum(w, 0, shared)
    n_pairs = _sum(pairs, 0, shared)
    n_moves = n_pairs if update_first else _sum(torch.cat([present[:1].to(dtype), pairs]), 0, shared)
    # the series (or, shared, all of them) with nothing to estimate a parameter from: no datum (every
    # parameter), no transition (F, Q, the offset: a series of one step); their values are held in the
    # iterations and NaN at the end (EMResult.unestimated), never the 0 of an empty sum
    none_obs = n_obs == 0
    none_moves = none_obs | (n_moves == 0)
    unestimated = {name: mask for name in parameters for mask in [
        none_moves if name in ("F", "Q", "offset") else
        _start_none(w, belief0, name, shared) if name.startswith("initial") else none_obs]
        if bool(mask.any())}
    start = belief0
    history, decreases = [], []
    tic = time.perf_counter()
    bar = iteration_bar(iterations, progress, "em")
    # the filter of the E-step: for at most MAX_RUNS series on the CPU the Numba kernel's serial loop
    # (where it plans the run), else the parallel scans (log T batched levels); the smoother: the scan
    from torchmm.kernels import linear as linear_kernel

    sequential = math.prod(z.shape[1:-1]) <= linear_kernel.MAX_RUNS and z.device.type == "cpu"
    request = kernels.Request(update_first=update_first, keep=frozenset({"belief", "prior", "log_likelihood"}),
                              forced=True, controls=controls)
    converged, done = False, 0

    def e_step(start):
        """The log-likelihood and the smoothed moments ``(x_t, P_t, P_{t,t-1})`` by the parallel scans
        (torchmm.parallel: ``log T`` batched levels, no loop over the steps); without ``update_first`` the
        state one step before the first datum (the start's) is smoothed too, first in the sequence."""
        fields = None
        if sequential:  # a few series on the CPU: the Numba kernel's filter (serial, no scan levels)
            run, _ = kernels.plan(filter, start, z, request)
            fields = run() if run is not None else None
        if fields is not None:
            filt, prior, ll = fields[0], fields[1], fields[2]
            sm = smooth_scan(filter, filt, prior)
        else:
            filt, prior, sm, ll = filter_smooth(filter, start, z, update_first=update_first, offsets=Bu)
        ll = torch.where(present, ll, 0.0).sum(0)
        xs, Ps = sm.mean, sm.cov
        F = motion.F
        G = torch.linalg.solve(prior.cov[1:], (filt.cov[:-1] @ F.mT).mT).mT  # P_t F^T P_{t+1|t}^{-1}
        Pc = Ps[1:] @ G.mT
        if not update_first:
            mean0 = start.mean.expand(xs.shape[1:])
            cov0 = start.cov.expand(Ps.shape[1:])
            G0 = torch.linalg.solve(prior.cov[0], (cov0 @ F.mT).mT).mT
            x0 = mean0 + (G0 @ (xs[0] - prior.mean[0]).unsqueeze(-1)).squeeze(-1)
            P0 = cov0 + G0 @ (Ps[0] - prior.cov[0]) @ G0.mT
            xs = torch.cat([x0.unsqueeze(0), xs])
            Ps = torch.cat([(0.5 * (P0 + P0.mT)).unsqueeze(0), Ps])
            Pc = torch.cat([(Ps[1] @ G0.mT).unsqueeze(0), Pc])
        return (ll.sum() if shared else ll), (xs, Ps, Pc)

    with torch.no_grad():
        for it in range(iterations):
            ll, (xs, Ps, Pc) = e_step(start)
            history.append(ll)
            if it and bool((ll < history[-2] - 1e-9 * abs(history[-2]).clamp_min(1.0)).any()):
                decreases.append(it)
            if tol is not None and it and bool(((ll - history[-2]).abs() <= tol * ll.abs().clamp_min(1.0)).all()):
                converged = True
                break
            # the measurement steps: the smoothed state at each datum (without update_first, the first
            # smoothed state is the start's, one step before the first datum)
            xo, Po = (xs, Ps) if update_first else (xs[1:], Ps[1:])
            Exx = Po + xo.unsqueeze(-1) * xo.unsqueeze(-2)  # (T, *B, n, n)
            wx = w[..., None, None]
            if "H" in wanted:
                Syx = _sum(wx * (yz.unsqueeze(-1) * xo.unsqueeze(-2)), 2, shared)
                Sxx = _sum(wx * Exx, 2, shared)
                Sxx = Sxx + none_obs[..., None, None] * torch.eye(Sxx.shape[-1], dtype=dtype)  # (held below)
                H = torch.where(none_obs[..., None, None], sensor.H,
                                _regression(sensor.H, Syx, Sxx, sensor.R, masks.get("H")))
                sensor.H = H.reshape(_shape(sensor.H, H, shared))
            if "R" in wanted:
                H = sensor.H
                r = yz - (H @ xo.unsqueeze(-1)).squeeze(-1)
                term = r.unsqueeze(-1) * r.unsqueeze(-2) + H @ Po @ H.mT
                R = _sum(wx * term, 2, shared) / n_obs.clamp_min(1)[..., None, None]
                R = torch.where(none_obs[..., None, None], sensor.R, 0.5 * (R + R.mT))
                if "R" in masks:
                    R = torch.where(masks["R"], sensor.R, R)
                sensor.R = R.reshape(_shape(sensor.R, R, shared))
            # the transition steps: pairs (t-1, t) inside a series
            x1, x0 = xs[1:], xs[:-1]
            P1, P0, C = Ps[1:], Ps[:-1], Pc
            if Bu is not None:  # the pairs' targets less the inputs' part: x_t - B u_t
                x1 = x1 - (Bu[1:] if update_first else Bu)
            pw = (pairs if update_first else torch.cat([present[:1].to(dtype), pairs]))[..., None, None]
            npairs = n_moves
            E00 = P0 + x0.unsqueeze(-1) * x0.unsqueeze(-2)
            E10 = C + x1.unsqueeze(-1) * x0.unsqueeze(-2)
            if "F" in wanted:
                b = motion.offset
                num = _sum(pw * (E10 - b.unsqueeze(-1) * x0.unsqueeze(-2)), 2, shared)
                den = _sum(pw * E00, 2, shared)
                den = den + none_moves[..., None, None] * torch.eye(den.shape[-1], dtype=dtype)  # (held)
                F = torch.where(none_moves[..., None, None], motion.F,
                                _regression(motion.F, num, den, motion.Q, masks.get("F")))
                motion.F = F.reshape(_shape(motion.F, F, shared))
            F = motion.F
            if "Q" in wanted:
                b = motion.offset
                e = x1 - (F @ x0.unsqueeze(-1)).squeeze(-1) - b
                term = (e.unsqueeze(-1) * e.unsqueeze(-2) + F @ P0 @ F.mT + P1 - C @ F.mT - F @ C.mT)
                Q = _sum(pw * term, 2, shared) / npairs.clamp_min(1)[..., None, None]
                Q = torch.where(none_moves[..., None, None], motion.Q, 0.5 * (Q + Q.mT))
                if "Q" in masks:
                    Q = torch.where(masks["Q"], motion.Q, Q)
                motion.Q = Q.reshape(_shape(motion.Q, Q, shared))
            if "initial_mean" in wanted or "initial_cov" in wanted:
                start = _start_step(start, xs[0], Ps[0], present[0], wanted, masks, shared)
            if "offset" in wanted:  # last, as pykalman (Q above used the offset before this M-step)
                d = x1 - (F @ x0.unsqueeze(-1)).squeeze(-1)
                if "offset" in masks:  # weighted by Q: the free entries given the fixed ones
                    Sd = _sum(pw[..., 0] * d, 1, shared).unsqueeze(-1)
                    b = _constrained(motion.offset.unsqueeze(-1), Sd, npairs[..., None, None].to(dtype), motion.Q,
                                     ~masks["offset"].unsqueeze(-1)).squeeze(-1)
                else:
                    b = _sum(pw[..., 0] * d, 1, shared) / npairs.clamp_min(1)[..., None]
                b = torch.where(none_moves[..., None], motion.offset, b)
                motion.offset = b.reshape(_shape(motion.offset, b, shared))
            done += 1
            bar.update(1)
            bar.set_postfix(loglik=f"{float(ll.sum()):.6g}")
        else:
            ll, _ = e_step(start)
            history.append(ll)
            if bool((ll < history[-2] - 1e-9 * abs(history[-2]).clamp_min(1.0)).any()):
                decreases.append(len(history) - 1)
    bar.close()
    values = [float(h) if shared else h.clone() for h in history]
    start = _unestimated_nan(filter, start, unestimated)
    return EMResult(loglik=values, belief0=start, iterations=done, converged=converged, monotone=not decreases,
                    seconds=time.perf_counter() - tic, decreases=decreases, unestimated=unestimated)


def _start_none(w: Tensor, belief0: GaussianBelief, name: str, shared: bool) -> Tensor:
    """``(*B,)`` (or, for a field one value for the series, ``()``): the series whose start field ``name``
    no datum informs (a pooled field: none of the series it is pooled over has a datum)."""
    none = w.sum(0) == 0
    if not shared:
        return none
    event = 1 if name == "initial_mean" else 2
    axes = pooled_axes(belief0.mean if event == 1 else belief0.cov, none.shape, event)
    return none.all(axes, keepdim=True).expand(none.shape) if axes else none


def _unestimated_nan(filter: KalmanFilter, start: GaussianBelief, unestimated: dict) -> GaussianBelief:
    """NaN in the entries of ``unestimated`` (``{name: series mask}``): the models' tensors written, the
    start returned."""
    nan = math.nan
    for name, none in unestimated.items():
        if name.startswith("initial"):
            mean, cov = start.mean, start.cov
            if name == "initial_mean":
                mean = torch.where(none[..., None], nan, mean.expand(*none.shape, mean.shape[-1]))
            else:
                cov = torch.where(none[..., None, None], nan, cov.expand(*none.shape, *cov.shape[-2:]))
            start = GaussianBelief(mean, cov)
            continue
        model = filter.motion if name in ("F", "Q", "offset") else filter.measurement
        value = getattr(model, name)
        setattr(model, name, torch.where(none[(...,) + (None,) * (1 if name == "offset" else 2)], nan, value))
    return start


def _pool(x: Tensor, first: Tensor, axes: tuple[int, ...], event: int) -> Tensor:
    """``x`` ``(*B, *event)`` averaged over the batch ``axes`` (weights ``first`` ``(*B,)``: the series that
    have a first step) and expanded back along them (a view: one value)."""
    if not axes:
        return x
    w = first.to(x.dtype).reshape(*first.shape, *([1] * event))
    return ((w * x).sum(axes, keepdim=True) / w.sum(axes, keepdim=True).clamp_min(1)).expand(x.shape)


def _start_step(start: GaussianBelief, x0: Tensor, P0: Tensor, first: Tensor, wanted: set, masks: dict,
                shared: bool) -> GaussianBelief:
    r"""The M-step of the start's mean and covariance from the smoothed first state ``x0`` ``(*B, n)``,
    ``P0`` ``(*B, n, n)``: ``mu = x0``, ``V = P0 + (x0 - mu)(x0 - mu)^T`` for a start per series. With
    shared parameters a field the start broadcasts (an expanded view, ``belief0.expand(B)``) is one value
    for the series it is broadcast to, as :func:`~torchmm.learn.estimate` holds it: its statistics pooled
    over them (those with a first step, ``first`` ``(*B,)``, padding False): ``mu = mean_s x0_s``,
    ``V = mean_s P0_s + (x0_s - mu_s)(x0_s - mu_s)^T``, the exact maximiser of the expected complete-data
    log-likelihood, so EM's fixed point is the shared start's maximum-likelihood estimate. Fixed entries of
    ``mu``: the weighted least squares over the free ones (weight ``V``)."""
    batch, n = x0.shape[:-1], x0.shape[-1]
    mean0, cov0 = start.mean.expand(*batch, n), start.cov.expand(*batch, n, n)
    if "initial_mean" in wanted:
        axes = pooled_axes(start.mean, batch, 1) if shared else ()
        target = _pool(x0, first, axes, 1)
        mask = masks.get("initial_mean")
        if mask is not None:  # (the covariance is one value along the pooled axes: start_masks)
            target = _constrained(mean0.unsqueeze(-1), target.unsqueeze(-1),
                                  torch.ones_like(x0[..., :1, None]), cov0, ~mask.unsqueeze(-1)).squeeze(-1)
            target = target[tuple(slice(0, 1) if i in axes else slice(None) for i in range(len(batch)))]
        mean0 = target.expand(*batch, n)
    if "initial_cov" in wanted:
        d = x0 - mean0
        new0 = P0 + d.unsqueeze(-1) * d.unsqueeze(-2)
        new0 = _pool(0.5 * (new0 + new0.mT), first, pooled_axes(start.cov, batch, 2) if shared else (), 2)
        cov0 = torch.where(masks["initial_cov"], cov0, new0) if "initial_cov" in masks else new0
    return GaussianBelief(mean0, cov0)


def _shape(current: Tensor, new: Tensor, shared: bool) -> tuple:
    """The shape the estimate takes in the model: the model's own for shared parameters, the series'
    batch in front otherwise."""
    return tuple(current.shape[-new.dim():]) if shared and new.dim() <= current.dim() else tuple(new.shape)

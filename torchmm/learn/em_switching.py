r"""Expectation-maximisation for Markov-switching models run by an IMM (or GPB1) over linear Kalman filters,
batched over series (issue 45; split from :mod:`torchmm.learn.em` by concern, issue 47): :func:`em_switching`,
Kim's smoother as the E-step and the closed-form (or, for a time-varying transition, multinomial logistic)
M-steps - its docstring has the equations."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from torchmm.beliefs import ModeBelief
from torchmm.contract import Data, Flag, Int, Mask, Of, Real, Unchecked, entry_point
from torchmm.filters.kalman import KalmanFilter
from torchmm.learn.em import iteration_bar, observed_steps
from torchmm.models.linear import LinearMeasurement, plain_linear
from torchmm.multimodel.imm import MultipleModelFilter
from torchmm.run import run_filter
from torchmm.smooth_checks import after_last_datum
from torchmm.validation import check_measurement
from torchmm.runtime import entries, one_thread_when_small

__all__ = ["SWITCHING_PARAMETERS", "SwitchingEMResult", "em_switching"]


#: what :func:`em_switching` estimates, by name
SWITCHING_PARAMETERS = ("transition", "H", "R", "initial_mode_probs")


@dataclass
class SwitchingEMResult:
    """What :func:`em_switching` found (as :class:`EMResult`): ``loglik`` per iteration (before its M-step)
    and at the end, the start belief (its mode probabilities estimated with ``initial_mode_probs``)."""

    loglik: list
    belief0: Any
    iterations: int
    converged: bool
    monotone: bool
    seconds: float
    decreases: list = field(default_factory=list)


@entry_point(filter=Of(MultipleModelFilter, what="an IMM / GPB1 over a bank of linear Kalman filters"),
             belief0=Of(ModeBelief, what="the filter's start (a ModeBelief)"), measurements=Data(),
             parameters=Unchecked("names of SWITCHING_PARAMETERS, checked by em_switching"),
             iterations=Int(1), tol=Real(minimum=0.0, optional=True), update_first=Flag(),
             shared=Unchecked("names of the parameters every mode shares (or {name: mask}), checked by em_switching"),
             fixed=Unchecked("{name: bool mask} of entries held at their values, checked by em_switching"),
             ergodic=Flag(),
             controls=Data(optional=True), present=Mask(optional=True),
             progress=Unchecked("None, True, False or a description"))
@one_thread_when_small(lambda filter, belief0, measurements, *args, **kwargs: entries(belief0) * measurements.shape[0])
def em_switching(filter: MultipleModelFilter, belief0: ModeBelief, measurements: Tensor,
                 parameters: Sequence[str] = ("transition", "H", "R"), *, iterations: int = 50,
                 tol: float | None = None, update_first: bool = False, shared: Sequence[str] | dict = (),
                 fixed: dict | None = None, ergodic: bool = False,
                 controls: Tensor | None = None, present: Tensor | None = None,
                 progress: bool | str | None = None) -> SwitchingEMResult:
    r"""EM for a Markov-switching model run by an IMM over linear Kalman filters, the series sharing the
    parameters (Hamilton, J. Econometrics 45, 1990; Kim, J. Econometrics 60, 1994).

    **E-step**: the filter and Kim's smoother (:func:`torchmm.smooth`, ``method="kim"``) give the
    smoothed mode probabilities ``w_tj = P(s_t = j | z_{1:T})``, the pair probabilities
    ``P(s_{t-1} = i, s_t = j | z) = P(s_{t-1} = i | z_{1:t-1}) pi_ij w_tj / P(s_t = j | z_{1:t-1})`` and
    each mode's smoothed moments ``x_{t|T}^j``, ``P_{t|T}^j``. **M-step** (Baum-Welch for the chain):
    ``pi_ij = sum_t pairs_ij / sum_t sum_j pairs_ij``; the start's mode probabilities ``w_0j``; each
    mode's measurement by weighted least squares, ``H_j = (sum_t w_tj z_t x^{jT})(sum_t w_tj (P^j +
    x^j x^{jT}))^{-1}``, ``R_j = sum_t w_tj ((z_t - H_j x^j)(..)^T + H_j P^j H_j^T) / sum_t w_tj`` (``shared``:
    one ``H`` or ``R`` for all modes, the weights summed over the modes).

    **Shared and fixed entries** (``shared={"H": mask}``, ``fixed={"H": mask, "transition": mask}``): the
    entries of ``H`` the modes share, and those held at their current values, by the exact conditional
    maximiser over the free ones given the current ``R`` (a least squares over the regimes, each weighted by
    ``w_tj / R_j``: an expectation-conditional-maximisation step, which raises the likelihood as an EM step
    does; a shared ``H`` with switching variances takes the same weighted form); a fixed transition entry
    keeps its value and its row's free entries share the rest of the row's mass in proportion to their
    pair counts. As statsmodels' ``MarkovRegression`` with ``switching_trend``/``switching_exog`` False
    for some coefficients, or a constant held at 0 (``trend="n"``).

    **A time-varying transition** (:class:`~torchmm.models.transition.LogisticTransition`, needs ``controls``): each
    origin regime's coefficients maximise the pair probabilities' multinomial logistic likelihood on the
    step's inputs (Newton's method with step halving: a generalised EM step).

    **Exact or approximate.** Where the state is known exactly (covariance 0 and ``Q = 0``: a
    Markov-switching regression, ``experiments.scenarios.markov_switching``) the smoothed moments are the
    state itself and Kim's probabilities are exact, so this is the exact EM of the model (statsmodels'
    ``MarkovRegression`` EM). With an uncertain state, the IMM's likelihood and Kim's moments are
    approximations (each mode's smoothed belief is Kim's collapse), so the steps are an approximate EM:
    the likelihood is checked every iteration and a decrease is reported (``monotone``).

    Args:
        filter: an IMM (or GPB1) whose bank is one Kalman filter over a ``LinearMeasurement`` with a mode
            axis (a vectorised bank: ``filter.bank.filter.measurement.H`` ``(M, m, n)``), or one sensor
            shared by the modes (then ``H``, ``R`` are estimated as shared).
        belief0: the start (:meth:`~torchmm.multimodel.MultipleModelFilter.initial_belief`).
        measurements: ``(T, *B, m)``, NaN missing (a missing vector informs the chain only).
        parameters: of :data:`SWITCHING_PARAMETERS`; shared: those of ``"H"``, ``"R"`` the modes share, or a
            dict ``{"H": True or an (m, n) bool mask of the entries shared, "R": True}``.
        fixed: ``{"H": (m, n) or (M, m, n) bool mask, "transition": (M, M) bool mask}``: entries held at
            their current values (entry-wise masks of ``H`` need a diagonal ``R``: its rows are then
            separate least squares).
        iterations, tol: at most so many iterations; stop once the log-likelihood's relative change is below
            ``tol``.
        update_first: as for :func:`~torchmm.run_filter` (statsmodels' convention: False).
        ergodic: the start's mode probabilities are the stationary ones of the current transition matrix,
            re-derived every iteration (statsmodels' default; ``initial_mode_probs`` is then not estimated).
        controls: the motion models' inputs ``(T, *B, k)`` (a regression's regressors).
        present: ``(T, *B)`` bool, False at a shorter series' padding. Default: each series up to its last
            step with a finite datum (trailing NaN steps never change the likelihood, but as latent steps
            they would enter the chain's counts and change the iterates), as :func:`~torchmm.learn.em`.

    Returns:
        a :class:`SwitchingEMResult`; the filter holds the estimates.

    Examples:
        >>> import torch
        >>> from torchmm import GaussianBelief, IMM, KalmanFilter, LinearMeasurement, LinearMotion
        >>> dt = torch.float64
        >>> one = torch.ones(2, 1, 1, dtype=dt)
        >>> imm = IMM(KalmanFilter(LinearMotion(one, 0 * one), LinearMeasurement(torch.tensor([[[0.0]], [[3.0]]],
        ...           dtype=dt), one)), torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=dt))
        >>> b0 = imm.initial_belief(GaussianBelief(torch.ones(1, dtype=dt), torch.zeros(1, 1, dtype=dt)))
        >>> z = torch.cat([torch.zeros(50), 3 * torch.ones(50)]).to(dt).reshape(-1, 1)
        >>> out = em_switching(imm, b0, z + torch.randn(100, 1, dtype=dt, generator=torch.Generator().manual_seed(0)))
        >>> out.monotone, out.loglik[-1] > out.loglik[0]
        (True, True)
    """
    from torchmm.smooth import smooth

    bank = getattr(filter, "bank", None)
    inner = getattr(bank, "filter", None)
    M = filter.num_modes
    if not (isinstance(inner, KalmanFilter) and isinstance(inner.measurement, LinearMeasurement)
            and plain_linear(inner.measurement)):
        raise TypeError(f"filter: EM for switching models needs an IMM over one Kalman filter with a "
                        f"LinearMeasurement (a vectorised bank), got {type(bank).__name__}")
    if isinstance(parameters, str) or not all(isinstance(p, str) for p in parameters):
        raise TypeError(f"parameters: expected names of {', '.join(SWITCHING_PARAMETERS)}, got {parameters!r}")
    unknown = [p for p in parameters if p not in SWITCHING_PARAMETERS]
    if unknown or not parameters:
        raise ValueError(f"parameters: {unknown or 'nothing'}: expected some of {', '.join(SWITCHING_PARAMETERS)}")
    if isinstance(shared, str) or any(s not in ("H", "R") for s in shared):
        raise ValueError(f"shared: expected some of H, R, got {shared!r}")
    shared_masks = {k: v for k, v in shared.items() if not isinstance(v, bool)} if isinstance(shared, dict) else {}
    if isinstance(shared, dict):
        if not isinstance(shared.get("R", False), bool):
            raise ValueError("shared: R is shared whole or not at all (True or False)")
        shared = [k for k, v in shared.items() if v is True]
    fixed = dict(fixed or {})
    if any(k not in ("H", "transition") for k in fixed):
        raise ValueError(f"fixed: expected masks of H or transition, got {sorted(fixed)}")
    if "transition" in parameters and getattr(filter.transition, "learnable", False):
        raise ValueError("filter: its transition matrix is a learnable module (logits): EM writes a fixed one")
    varying = getattr(filter.transition, "takes_inputs", False)  # a LogisticTransition: its coefficients
    if varying and controls is None:
        raise ValueError("controls: a time-varying transition reads them (the step's inputs)")
    if varying and "transition" in (fixed or {}):
        raise ValueError("fixed: a time-varying transition's coefficients are estimated whole")
    sensor = inner.measurement
    h_masks = _h_masks(sensor, M, shared_masks.get("H"), fixed.get("H"), "H" in shared,
                       pooled="R" in shared and "R" in parameters)
    t_fixed = None
    if "transition" in fixed:
        t_fixed = torch.as_tensor(fixed["transition"], dtype=torch.bool)
        if t_fixed.shape != (M, M):
            raise ValueError(f"fixed: the transition's mask must be ({M}, {M}), got {tuple(t_fixed.shape)}")
        if bool(t_fixed.all(-1).any()):
            raise ValueError("fixed: a row of the transition with every entry fixed (leave it out of parameters)")
    z = measurements
    if not isinstance(z, Tensor) or z.dim() < 2:
        raise TypeError(f"measurements: expected a time-major tensor (T, *B, m), got "
                        f"{tuple(z.shape) if isinstance(z, Tensor) else type(z).__name__}")
    batch = belief0.batch_shape
    z = check_measurement(z, filter.meas_dim, torch.Size((z.shape[0], *batch)), belief0.mode_log_probs,
                          "measurements")
    if present is None:  # up to each series' last datum, as em: later steps never change the likelihood, but
        # as latent steps their expected transitions would enter the chain's counts (and change the iterates)
        present = ~after_last_datum(z, tuple(z.shape[:-1]))
    present, observed = observed_steps(z, present)
    yz = torch.where(observed.unsqueeze(-1), z, 0.0)
    wanted, share = set(parameters), set(shared)
    stacked = sensor.H.dim() == 3 and sensor.H.shape[0] == M
    if not stacked:
        share |= {"H", "R"}  # one sensor for every mode
    start = belief0
    history, decreases = [], []
    tic = time.perf_counter()
    bar = iteration_bar(iterations, progress, "em_switching")
    converged, done = False, 0

    def e_step(start):
        traj = run_filter(filter, start, z, controls=controls, update_first=update_first)
        ll = torch.where(present, traj.log_likelihood, 0.0).sum()
        sm = smooth(traj, method="kim", present=None if bool(present.all()) else present)
        return ll, traj, sm

    if ergodic and "initial_mode_probs" in wanted:
        raise ValueError("parameters: initial_mode_probs with ergodic=True (the stationary ones): give one")
    from torchmm.learn.entries import stationary

    def ergodic_start(start):  # (a time-varying transition: the ergodic ones of each series' first step)
        probs = stationary(filter.transition.at(controls[0]).matrix() if varying else filter.transition.matrix())
        return ModeBelief(probs.log().expand(start.mode_log_probs.shape).clone(), start.components)

    if ergodic:
        start = ergodic_start(start)
    with torch.no_grad():
        for it in range(iterations + 1):
            ll, traj, sm = e_step(start)
            history.append(float(ll))
            if it and history[-1] < history[-2] - 1e-9 * max(1.0, abs(history[-2])):
                decreases.append(it)
            if it == iterations:
                break
            if tol is not None and it and abs(history[-1] - history[-2]) <= tol * max(1.0, abs(history[-1])):
                converged = True
                break
            w = sm.belief.mode_probs  # (T, *B, M): P(s_t = j | z)
            filt = traj.belief.mode_probs  # P(s_t = j | z_{1:t})
            pred = traj.prior.mode_probs  # P(s_t = j | z_{1:t-1})
            P = filter.transition.at(controls).matrix() if varying else filter.transition.matrix()  # ((T, *B,) M, M)
            if "transition" in wanted:
                before = torch.cat([start.mode_probs.expand(filt[:1].shape), filt[:-1]]) if not update_first \
                    else filt[:-1]
                after_w, after_pred = (w, pred) if not update_first else (w[1:], pred[1:])
                ok = (present if not update_first else present[1:] & present[:-1]).to(z.dtype)
                ratio = torch.where(after_pred > 0, after_w / after_pred, 0.0)
                Pt = P[1:] if varying and update_first else P
                pairs = before.unsqueeze(-1) * Pt * ratio.unsqueeze(-2) * ok[..., None, None]  # (T', *B, M, M)
            if "transition" in wanted and varying:  # the weighted multinomial logistic M-step of each row
                x = controls[..., filter.transition.columns].to(z.dtype)
                x = (x[1:] if update_first else x).expand(*pairs.shape[:-2], x.shape[-1])
                coef = _logistic_m_step(filter.transition.coef, pairs.reshape(-1, M, M), x.reshape(-1, x.shape[-1]))
                filter.transition.coef.copy_(coef)
            elif "transition" in wanted:
                counts = pairs.reshape(-1, M, M).sum(0)  # over time and the series
                if t_fixed is not None:  # the free entries share what the fixed ones leave of each row
                    counts = torch.where(t_fixed, 0.0, counts)
                    left = 1.0 - torch.where(t_fixed, P, 0.0).sum(-1, keepdim=True)
                    rows = counts.sum(-1, keepdim=True)
                    newP = torch.where(t_fixed, P, torch.where(rows > 0, left * counts / rows.clamp_min(1e-300), P))
                else:
                    rows = counts.sum(-1, keepdim=True)
                    newP = torch.where(rows > 0, counts / rows.clamp_min(1e-300), P)
                filter.transition.value.copy_(newP)
            x = sm.belief.components.mean  # (T, *B, M, n): each mode's smoothed state
            Px = sm.belief.components.cov
            wy = (w * observed.unsqueeze(-1).to(z.dtype))[..., None, None]  # (T, *B, M, 1, 1)
            Exx = Px + x.unsqueeze(-1) * x.unsqueeze(-2)
            yx = yz.unsqueeze(-2).unsqueeze(-1) * x.unsqueeze(-2)  # (T, *B, M, m, n)

            def total(t):  # over time and series, keeping the mode axis (and the event)
                return t.reshape(-1, *t.shape[z.dim() - 1:]).sum(0)
            if "H" in wanted:
                Syx, Sxx = total(wy * yx), total(wy * Exx)  # (M, m, n), (M, n, n)
                if h_masks is not None:  # entries shared or fixed: the weighted least squares over the free ones
                    H = _masked_h(sensor, M, stacked, Syx, Sxx, *h_masks)
                else:
                    if "H" in share:
                        Syx, Sxx = Syx.sum(0, keepdim=True), Sxx.sum(0, keepdim=True)
                    H = torch.linalg.solve(Sxx.mT, Syx.mT).mT
                sensor.H = (H.expand(M, *H.shape[1:]) if stacked else H[0]).clone()
            if "R" in wanted:
                H = sensor.H if stacked else sensor.H.expand(M, *sensor.H.shape)
                r = yz.unsqueeze(-2) - (H @ x.unsqueeze(-1)).squeeze(-1)  # (T, *B, M, m)
                term = r.unsqueeze(-1) * r.unsqueeze(-2) + H @ Px @ H.mT
                num, den = total(wy * term), total(wy)  # (M, m, m), (M, 1, 1)
                if "R" in share:
                    num, den = num.sum(0, keepdim=True), den.sum(0, keepdim=True)
                R = num / den.clamp_min(1e-300)
                R = 0.5 * (R + R.mT)
                sensor.R = (R.expand(M, *R.shape[1:]) if stacked else R[0]).clone()
            if "initial_mode_probs" in wanted:
                first = w[0]  # P(s_0 = j | z): the start one step before the first datum, from the chain
                if not update_first:
                    first = (start.mode_probs * ((P[0] if varying else P)
                                                 * torch.where(pred[0] > 0, w[0] / pred[0], 0.0).unsqueeze(-2)).sum(-1))
                probs = first.reshape(-1, M).mean(0)
                start = ModeBelief(probs.log().expand(start.mode_log_probs.shape).clone(), start.components)
            if ergodic:
                start = ergodic_start(start)
            done += 1
            bar.update(1)
            bar.set_postfix(loglik=f"{history[-1]:.6g}")
    bar.close()
    return SwitchingEMResult(loglik=history, belief0=start, iterations=done, converged=converged,
                             monotone=not decreases, seconds=time.perf_counter() - tic, decreases=decreases)


def _h_masks(sensor, M: int, shared_mask, fixed_mask, shared_whole: bool, pooled: bool):
    """``(shared (m, n), fixed (M, m, n))`` bool masks of ``H``'s entries for the weighted M-step, or None
    where every entry is each mode's own and free (the plain M-step) or every entry shared with ``R``
    shared and estimated too (``pooled``: the plain shared M-step, pooled least squares, is then the joint
    maximiser of both)."""
    H = sensor.H
    m, n = H.shape[-2], H.shape[-1]
    stacked = H.dim() == 3 and H.shape[0] == M
    if shared_mask is None and fixed_mask is None and not (shared_whole and stacked):
        return None
    shared = torch.ones(m, n, dtype=torch.bool) if shared_whole or not stacked else torch.zeros(m, n, dtype=torch.bool)
    if shared_mask is not None:
        shared = torch.as_tensor(shared_mask, dtype=torch.bool)
        if shared.shape != (m, n):
            raise ValueError(f"shared: H's mask must be ({m}, {n}), got {tuple(shared.shape)}")
        if not stacked and not bool(shared.all()):
            raise ValueError("shared: one sensor for every mode shares every entry of H")
    fixed = torch.zeros(M, m, n, dtype=torch.bool)
    if fixed_mask is not None:
        given = torch.as_tensor(fixed_mask, dtype=torch.bool)
        try:
            fixed = given.expand(M, m, n).clone()
        except RuntimeError:
            raise ValueError(f"fixed: H's mask must be ({m}, {n}) or ({M}, {m}, {n}), got {tuple(given.shape)}") from None
        if bool((shared & ~(fixed.all(0) | ~fixed.any(0))).any()):
            raise ValueError("fixed: a shared entry of H is fixed in some modes only")
    if m > 1:
        R = sensor.R if sensor.R.dim() == 3 else sensor.R.unsqueeze(0)
        if bool((R - torch.diag_embed(torch.diagonal(R, dim1=-2, dim2=-1)) != 0).any()):
            raise ValueError("shared/fixed: entry-wise masks of H need a diagonal R (its rows are separate least "
                             "squares); estimate H whole")
    if shared_whole and shared_mask is None and fixed_mask is None and pooled:
        return None
    return shared, fixed


def _masked_h(sensor, M: int, stacked: bool, Syx: Tensor, Sxx: Tensor, shared: Tensor, fixed: Tensor) -> Tensor:
    """The conditional maximiser of ``H`` over its free entries given the current ``R``: for each row ``i``
    one least squares over the regimes, regime ``j`` weighted by ``1 / R_j[i, i]``; the shared entries one
    unknown for every regime, the fixed ones their current values. ``(M, m, n)``."""
    H = (sensor.H if stacked else sensor.H.expand(M, *sensor.H.shape)).clone()
    R = sensor.R if sensor.R.dim() == 3 else sensor.R.expand(M, *sensor.R.shape)
    m, n = H.shape[-2], H.shape[-1]
    for i in range(m):  # (the rows: a few; the M-step's own loop, not a filter step's)
        index = {}
        for k in range(n):
            for j in range(M):
                if fixed[j, i, k]:
                    continue
                key = ("shared", k) if shared[i, k] else (j, k)
                index.setdefault(key, len(index))
        d = len(index)
        if d == 0:
            continue
        N = Sxx.new_zeros(d, d)
        rhs = Sxx.new_zeros(d)
        for j in range(M):
            A = Sxx.new_zeros(n, d)
            for k in range(n):
                if not fixed[j, i, k]:
                    A[k, index[("shared", k) if shared[i, k] else (j, k)]] = 1.0
            held = torch.where(fixed[j, i], H[j, i], 0.0)
            a = 1.0 / R[j, i, i]
            N = N + a * A.T @ Sxx[j] @ A
            rhs = rhs + a * A.T @ (Syx[j, i] - Sxx[j] @ held)
        theta = torch.linalg.solve(N, rhs)
        for j in range(M):
            for k in range(n):
                if not fixed[j, i, k]:
                    H[j, i, k] = theta[index[("shared", k) if shared[i, k] else (j, k)]]
    return H


def _logistic_m_step(coef: Tensor, pairs: Tensor, x: Tensor, steps: int = 30) -> Tensor:
    """The M-step of a :class:`~torchmm.models.transition.LogisticTransition`'s coefficients ``(M, M - 1, q)``: for each
    origin regime ``i`` the maximiser of ``sum_n sum_j pairs[n, i, j] log p_ij(x_n)`` (a multinomial logistic
    regression with soft counts, the last regime the reference) by Newton's method with step halving (each
    step raises the objective: a generalised EM step, never a decrease). ``pairs (N, M, M)``, ``x (N, q)``."""
    M, q = coef.shape[0], coef.shape[-1]
    out = coef.detach().clone()
    for i in range(M):  # (the regimes: a few; the M-step's own loop)
        c = pairs[:, i, :]  # (N, M)
        total = c.sum(-1)  # (N,)

        def value(beta):  # (M - 1, q) -> the expected complete log-likelihood of row i
            logits = torch.cat([x @ beta.T, torch.zeros_like(x[:, :1])], dim=-1)
            return (c * torch.log_softmax(logits, dim=-1)).sum(), torch.softmax(logits, dim=-1)

        beta = out[i]
        current, p = value(beta)
        for _ in range(steps):
            pt = p[:, :-1]  # (N, M - 1)
            grad = ((c[:, :-1] - total[:, None] * pt).T @ x).reshape(-1)  # ((M - 1) q,)
            curv = torch.diag_embed(pt) - pt.unsqueeze(-1) * pt.unsqueeze(-2)  # (N, M-1, M-1)
            hess = torch.einsum("n,njk,na,nb->jakb", total, curv, x, x).reshape((M - 1) * q, (M - 1) * q)
            try:
                direction = torch.linalg.solve(hess + 1e-12 * torch.eye(len(grad), dtype=hess.dtype), grad)
            except RuntimeError:  # (a singular information: no row can move; keep it)
                break
            step, moved = 1.0, False
            while step > 1e-8:
                trial = beta + step * direction.reshape(M - 1, q)
                new, p_new = value(trial)
                if bool(new >= current):
                    moved = bool(new > current)
                    beta, current, p = trial, new, p_new
                    break
                step *= 0.5
            if not moved or float(direction.abs().max()) * step < 1e-12:
                break
        out[i] = beta
    return out

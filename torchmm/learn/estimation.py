r"""Maximum-likelihood estimation of any tensor of a filter, with standard errors (issue 45).

:func:`estimate` estimates named tensors of a filter - a bank's stacked ``H``, ``R``, ``F``, ``Q``, offsets,
the transition matrix, the start belief's fields (``belief0.mean``, ``belief0.mode_probs``, ...) -
by maximising the log-likelihood of the data, and reports each estimated entry with its standard
error from the observed information:

* **What is estimated** is declared per tensor by a :class:`Param`: its *kind* (``"free"`` entries on
  the real line or between bounds, ``"variance"`` (positive diagonal), ``"covariance"`` (a full
  positive-definite matrix through its Cholesky factor), ``"stochastic"`` (rows of a transition matrix:
  each row a softmax over its free entries, zeros kept), ``"probabilities"`` (the last axis sums to
  one)), the entries held *fixed*, and *groups* of entries that share one value (e.g. a regression
  coefficient shared by every regime).
* **The free vector** ``theta`` gathers every unconstrained value; each tensor is rebuilt from it at
  every evaluation and put in the filter's place for that evaluation
  (:func:`torch.func.functional_call`), so whatever reads the filter - its steps, the whole-run
  kernels of :class:`~torchmm.learn.Objective` - sees the estimated values. Nothing of the filter is
  changed in place until the end, when the estimates are written back (``write=True``).
* **The optimiser** is ``scipy.optimize.minimize`` (L-BFGS-B by default, statsmodels' choice), with
  the gradient from autograd; the objective is :class:`~torchmm.learn.Objective` (checked once, the
  kernels where they apply).
* **Standard errors**: the observed information ``I = -d^2 log L / d theta^2`` by autograd at the
  optimum (the eager steps: a second derivative through every step), ``Cov(theta) = I^{-1}``, and
  each reported entry ``g(theta)`` by the delta method, ``Cov(g) = J I^{-1} J^T``. At a maximum this
  equals the inverse information in the natural parameters, whatever the parametrisation (the
  Hessians differ by ``J^T H J`` only where the gradient is zero), so the errors are those of
  statsmodels' ``cov_type="approx"`` up to its finite differences. An entry at a bound of its
  parametrisation (a variance or probability at 0, :mod:`torchmm.learn.boundary`'s rule,
  docs/estimation.md) gets a NaN error and a note naming it, the others' errors with it held; an
  information that is not positive definite otherwise (a flat direction) gives NaN errors and says so
  (``Estimate.note``). A free value that no datum touches (the start mean of a series without a finite
  measurement: its gradient and its information row exactly 0, :func:`~torchmm.learn.search.untouched`) is
  held out of the information and of ``k``, its entries reported NaN and named in the note.
* **Failures** (:mod:`torchmm.learn.search`): a point where the objective is not finite is a failed step
  for scipy, not a number; a fit is never reported at a point worse than its start (the best point
  evaluated, not converged); a fit that did not converge has NaN errors unless one Newton step from it is
  below 1 % of each error (docs/estimation.md, "When the search fails").
* **Criteria**: the log-likelihood, ``k`` (the free values), ``nobs`` (the steps with a measurement),
  AIC ``= -2 log L + 2 k``, BIC ``= -2 log L + k log nobs``, and for a ``"stochastic"`` tensor the
  expected durations ``1 / (1 - p_ii)`` with their delta-method errors.

What is estimated and how a tensor maps to the free vector (:class:`~torchmm.learn.Param`, the blocks, the
start belief's fields) is :mod:`torchmm.learn.entries`; here the fit and its result.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from torchmm.beliefs import Belief
from torchmm.contract import Choice, Data, Flag, Int, Of, Real, Unchecked, entry_point
from torchmm.filters.base import Filter
from torchmm.learn.boundary import at_bounds, entry_directions, held_covariance
from torchmm.learn.entries import START, Param, StartFields, write_back
from torchmm.learn.entries import blocks as tensor_blocks  # (``blocks`` names the list in estimate)
from torchmm.learn.search import NEWTON_RATIO, Guarded, newton_ratio, untouched
from torchmm.runtime import one_thread_when_small

__all__ = ["Estimate", "estimate"]


@dataclass
class Estimate:
    """What :func:`estimate` found.

    Attributes:
        names: the reported entries, ``"<label>[i,j]"``; ``estimates``, ``se``: their values and
            standard errors (NaN at a bound, or where the information is not positive definite); an entry no
            datum touches (the start of a series without a finite measurement) is NaN in both, held out of
            the information and of ``k``, and named in ``note``;
            ``z = estimate / se``.
        cov: the covariance of the reported entries ``(K, K)`` (delta method).
        theta, theta_cov: the free values at the optimum and the inverse information (NaN rows for the free
            values no datum touches).
        loglik: the log-likelihood at the optimum (the sum over the runs); ``k``: the free values that some
            datum touches;
        nobs: the steps with a measurement; ``aic``, ``bic``.
        durations: ``[(name, 1 / (1 - p_ii), se)]`` for each ``"stochastic"`` tensor's diagonal.
        converged, iterations, evaluations, message, seconds: the optimiser's; converged is False also
            where the optimiser ended at a point whose log-likelihood is not finite or below the start's
            (the best point evaluated is reported then), and the message counts the evaluations that
            were not finite (failed steps).
        note: why the errors are NaN, if they are (a fit that did not converge: unless a Newton step from
            it is below 1 % of each error).
        belief0: the start belief with its estimated fields (``"belief0.<field>"`` parameters; the given
            belief where none is estimated; None for a start function).
    """

    names: list[str]
    estimates: list[float]
    se: list[float]
    cov: Tensor
    theta: Tensor
    theta_cov: Tensor
    loglik: float
    k: int
    nobs: int
    converged: bool
    iterations: int
    evaluations: int
    message: str
    seconds: float
    method: str
    durations: list[tuple[str, float, float]] = field(default_factory=list)
    note: str = ""
    belief0: Belief | None = None

    @property
    def z(self) -> list[float]:
        return [e / s if s and math.isfinite(s) and s > 0 else math.nan for e, s in zip(self.estimates, self.se)]

    @property
    def aic(self) -> float:
        return -2 * self.loglik + 2 * self.k

    @property
    def bic(self) -> float:
        return -2 * self.loglik + self.k * math.log(max(self.nobs, 1))

    def rows(self) -> list[list]:
        """``[name, estimate, se, z]`` per reported entry (the ``learned`` table)."""
        return [[n, e, s, z] for n, e, s, z in zip(self.names, self.estimates, self.se, self.z)]

    def __getitem__(self, name: str) -> tuple[float, float]:
        """``(estimate, se)`` of a reported entry by name."""
        try:
            i = self.names.index(name)
        except ValueError:
            raise KeyError(f"{name!r} is not a reported entry ({', '.join(self.names)})") from None
        return self.estimates[i], self.se[i]


class _Call(nn.Module):
    """The objective as a module's forward, so that :func:`torch.func.functional_call` puts the
    estimated tensors in the filter's place for one evaluation."""

    def __init__(self, filter: nn.Module, fn: Callable[[], Tensor], start: StartFields | None = None):
        super().__init__()
        self.filter = filter
        self.start = start
        self.fn = fn

    def forward(self) -> Tensor:
        return self.fn()


def _parametrisation_curvature(blocks, sizes, theta: Tensor, loss_of: Callable[[dict], Tensor]) -> Tensor:
    """``G = sum_e g_e d^2 v_e / d theta^2`` ``(P, P)``: the part of the Hessian in the free values that the
    parametrisation's curvature contributes, ``g_e`` the gradient of the loss (``loss_of({name: tensor})``)
    in the estimated tensors' entries ``v_e`` (torchmm/learn/boundary.py)."""
    with torch.no_grad():
        built = {b.name: b.build(u).detach().requires_grad_(True) for b, u in zip(blocks, theta.split(sizes))}
    grads = torch.autograd.grad(loss_of(built), list(built.values()), allow_unused=True)
    g = {name: (torch.zeros_like(v) if d is None else d).detach().to(torch.float64).cpu()
         for (name, v), d in zip(built.items(), grads)}

    def contracted(t: Tensor) -> Tensor:
        return sum((g[b.name] * b.build(u).to(torch.float64).cpu()).sum()
                   for b, u in zip(blocks, t.split(sizes)))
    return torch.autograd.functional.hessian(contracted, theta)


def _nobs(measurements: Tensor, burn: int, batch_dims: int) -> int:
    """The steps with a measurement after ``burn``, summed over the runs."""
    finite = torch.isfinite(measurements[burn:])
    return int(finite.reshape(*finite.shape[:1 + batch_dims], -1).any(-1).sum())


@entry_point(filter=Of(Filter), belief0=Of(Belief, callable_ok=True, what="a belief or a function filter -> belief"),
             measurements=Data(),
             parameters=Of(Mapping, what="a mapping {tensor name: Param or kind}"),
             controls=Data(optional=True),
             motions=Of((list, tuple), callable_ok=True, optional=True,
                        what="a sequence of T models, a callable k -> model, or None"),
             update_first=Flag(), burn=Int(0),
             method=Choice("L-BFGS-B", "BFGS", "CG", "TNC", "SLSQP", "trust-constr"),
             se=Flag(), hessian=Choice("differences", "autograd"), tol=Real(positive=True, optional=True),
             maxiter=Int(1, optional=True),
             write=Flag(), progress=Unchecked("None, True, False or a description"))
@one_thread_when_small(lambda filter, belief0, measurements, *args, **kwargs:
                       measurements[0].numel() * max(1, getattr(filter, "num_modes", 1) or 1) * 8)
def estimate(filter: Filter, belief0: Belief | Callable[[Filter], Belief], measurements: Tensor,
        parameters: Mapping[str, Param | str], *, controls: Tensor | None = None, motions: Any = None,
        update_first: bool = False,
        burn: int = 0, method: str = "L-BFGS-B", se: bool = True, hessian: str = "differences",
        tol: float | None = None,
        maxiter: int | None = None, write: bool = True, progress: bool | str | None = None) -> Estimate:
    r"""The maximum-likelihood estimates of ``parameters`` (tensors of ``filter`` by name), with standard
    errors from the observed information (module docstring).

    Args:
        filter: any filter whose log-likelihood :class:`~torchmm.learn.Objective` evaluates.
        belief0: the start belief, or a function ``filter -> belief`` (called at every evaluation, with
            the estimated tensors in place: e.g. the ergodic mode probabilities of the estimated transition
            matrix, :func:`stationary`).
        measurements: ``(T, *B, m)``, NaN missing; the runs ``*B`` share the parameters (their
            log-likelihoods add up).
        parameters: ``{name: Param or kind}``: the tensors of ``filter`` to estimate, by their names in
            ``filter.named_buffers()`` / ``named_parameters()`` (``"transition.value"``,
            ``"bank.filter.measurement.H"``, ...; a wrong name lists them), and the start belief's fields
            as ``"belief0.<field>"`` where ``belief0`` is a belief (``"belief0.mean"``, ``"belief0.cov"``;
            a mode belief's ``"belief0.mode_probs"`` (kind ``"probabilities"``) and
            ``"belief0.components.mean"``): a field the belief broadcasts (an ``expand``-ed view) is one
            value for every run or mode it is broadcast to, a materialised one a value each.
        controls: ``(T, *B, k)`` inputs ``u_k`` of the motion models (e.g. regressors).
        motions: per-step motion models (irregular time stamps: one model per step,
            :func:`~torchmm.run_filter`'s ``motions``), or None. The estimated tensors are the filter's:
            those of the per-step models are fixed (a motion's own tensors are not shared with them).
        update_first: ``belief0`` is the prior of the first measurement.
        burn: the first steps' log-likelihood terms left out.
        method: ``scipy.optimize.minimize``'s (a gradient method).
        se: compute the standard errors from the observed information.
        hessian: how the information is computed: ``"differences"`` (default): central differences of the
            exact (autograd) gradient, ``2 k`` evaluations through the kernels where they apply, step
            ``eps^(1/3) max(1, |theta_i|)``, ``eps`` the data's dtype's (in float64 it agrees with the exact
            Hessian to about 1e-7 relative, tests/learn/test_estimate.py; float32 errors within about 0.1 %
            of float64's, tests/learn/test_standard_errors.py); ``"autograd"``: the exact second
            derivative through the eager steps (no kernel has a second derivative: slower, seconds for a
            few hundred steps).
        tol, maxiter: the optimiser's tolerance and iteration limit (default for L-BFGS-B: ``ftol=1e-13``,
            ``gtol=1e-8`` in float64, tighter than scipy's, which stops short on a flat likelihood; ``1e-6``
            and ``1e-3`` in float32).
        write: leave the estimates in the filter's tensors (in place, without gradient).
        progress: a bar over the evaluations (None: on a terminal only).

    Returns:
        an :class:`Estimate` (``Estimate.belief0``: the start belief with its estimated fields).

    Raises:
        ValueError / TypeError naming ``parameters`` (an unknown name, a kind that does not fit the
        tensor, a start outside its constraints, every entry fixed) or the other arguments.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import LinearMotion, LinearMeasurement
        >>> one = torch.ones(1, 1, dtype=torch.float64)
        >>> kf = KalmanFilter(LinearMotion(one, one), LinearMeasurement(one, one))
        >>> z = torch.randn(200, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0)).cumsum(0)
        >>> est = estimate(kf, GaussianBelief(torch.zeros(1, dtype=torch.float64), one), z, {"motion.Q": "variance"})
        >>> est.names, est.converged, est.se[0] > 0
        (['motion.Q[0,0]'], True, True)
    """
    from scipy.optimize import minimize
    from tqdm.auto import tqdm

    import torchmm.kernels as kernels
    from torchmm.learn.objective import Objective

    held = StartFields(belief0) if isinstance(belief0, Belief) else None
    blocks = tensor_blocks(filter, parameters, held)
    given = belief0 if isinstance(belief0, Belief) else None
    if held is not None and any(b.name.startswith(START) for b in blocks):
        belief0 = lambda f: held.build()  # noqa: E731 (the start's estimated fields in place at each evaluation)
    sizes = [b.u0.numel() for b in blocks]
    theta0 = torch.cat([b.u0 for b in blocks]).to(torch.float64)
    objective = Objective(filter, belief0, measurements, reduction="sum", update_first=update_first,
                          controls=controls, motions=motions, burn=burn)
    call = _Call(filter, objective, held)

    def substitutes(theta: Tensor) -> dict[str, Tensor]:
        return {"start." + b.name.removeprefix(START) if b.name.startswith(START) else f"filter.{b.name}": b.build(u)
                for b, u in zip(blocks, theta.split(sizes))}

    def loss_at(theta: Tensor) -> Tensor:
        # tie_weights=False: a tensor object that the model holds under two names (LinearMotion(I, I): F
        # and Q the same tensor) is substituted under the estimated name only
        return torch.func.functional_call(call, substitutes(theta), (), tie_weights=False)

    estimate.objective = objective  # (the last call's: which kernel ran, objective.kernel / objective.why)
    evaluations = [0]
    bar = tqdm(desc=progress if isinstance(progress, str) else "estimate", disable=None if progress is None
               else not progress, leave=False)

    def loss_and_grad(x):
        theta = torch.from_numpy(x).requires_grad_(True)
        loss = loss_at(theta)
        (grad,) = torch.autograd.grad(loss, theta)
        evaluations[0] += 1
        bar.update(1)
        bar.set_postfix(nll=f"{float(loss.detach()):.6g}")
        return float(loss.detach()), grad.numpy()

    options = {} if maxiter is None else {"maxiter": int(maxiter)}
    if tol is None and method == "L-BFGS-B":  # to the optimum, not near it (likelihoods are cheap; scipy's
        # default ftol stops ~1e-4 short in flat directions); float32 likelihoods are only so precise
        single = measurements.dtype == torch.float32
        options.update(ftol=1e-6 if single else 1e-13, gtol=1e-3 if single else 1e-8)
    tic = time.perf_counter()
    guarded = Guarded(loss_and_grad)  # a non-finite loss: a failed step (torchmm/learn/search.py)
    try:
        result = minimize(guarded, theta0.numpy(), jac=True, method=method, tol=tol, options=options,
                          callback=guarded.callback)
    finally:
        bar.close()
    theta = torch.from_numpy(result.x).to(torch.float64)
    with torch.no_grad():
        loglik = -float(loss_at(theta))
    converged, message = bool(result.success), str(result.message)
    if not math.isfinite(loglik) or -loglik > guarded.start[1]:
        # never a point whose likelihood is not finite, or below the start's: the best point evaluated
        message += (f"; the optimiser ended where the log-likelihood is {loglik:.10g} (the start's "
                    f"{-guarded.start[1]:.10g}): the best point evaluated is reported, not converged")
        converged = False
        theta = torch.from_numpy(guarded.best[0]).to(torch.float64)
        with torch.no_grad():
            loglik = -float(loss_at(theta))
    if guarded.failed:
        message += (f"; {guarded.failed} evaluation(s) where the log-likelihood or its gradient was not "
                    "finite (answered as failed steps)")
    natural = torch.cat([b.natural(u) for b, u in zip(blocks, theta.split(sizes))])
    names = [n for b in blocks for n in b.names()]
    K = len(names)
    cov = torch.full((K, K), math.nan, dtype=torch.float64)
    theta_cov = torch.full((len(theta), len(theta)), math.nan, dtype=torch.float64)
    note, bound = "", []
    # the central differences' step (hessian="differences"): eps^(1/3) max(1, |theta_i|), eps the data's
    # dtype's (the step that balances the truncation error, O(h^2), with the gradient's rounding, O(eps / h))
    dtype = measurements.dtype if measurements.is_floating_point() else torch.float64
    step = torch.finfo(dtype).eps ** (1 / 3)
    stopped = ""  # (not converged, and not at a maximum: no errors)
    idle = untouched(guarded.touched)  # the free values no datum touches (torchmm/learn/search.py)
    if se:
        if hessian == "autograd":
            with kernels.switched_off(*kernels.names()):  # the eager steps: a second derivative through them
                eager = _Call(filter, Objective(filter, belief0, measurements, reduction="sum",
                                                update_first=update_first, controls=controls, motions=motions,
                                                burn=burn), held)
                H = torch.autograd.functional.hessian(
                    lambda t: torch.func.functional_call(eager, substitutes(t), (), tie_weights=False), theta)
        else:  # central differences of the exact gradient (2 k evaluations, the kernels where they apply)
            H = torch.empty(len(theta), len(theta), dtype=torch.float64)
            for i in range(len(theta)):
                h = step * max(1.0, abs(float(theta[i])))
                shift = torch.zeros_like(theta)
                shift[i] = h
                up = torch.from_numpy(loss_and_grad((theta + shift).numpy())[1])
                down = torch.from_numpy(loss_and_grad((theta - shift).numpy())[1])
                H[i] = (up - down) / (2 * h)
        hessian = 0.5 * (H + H.mT)
        idle = untouched(guarded.touched, hessian)
        keep = ~idle
        if not converged:  # the errors only where one Newton step from here is negligible against them
            # (torchmm/learn/search.py): else the observed information is not the estimates' covariance, and
            # the bound rule would read the gradient still there as a slope past a bound
            ratio = newton_ratio(hessian[keep][:, keep], torch.from_numpy(loss_and_grad(theta.numpy())[1])[keep])
            stopped = "" if ratio <= NEWTON_RATIO else (
                "not converged: no standard errors (" + (
                    f"a Newton step from here moves a free value by {ratio:.3g} of its standard error"
                    if math.isfinite(ratio) else "the observed information here is not positive definite")
                + ": not a maximum, where alone the observed information is the estimates' covariance)")
            note = stopped or (f"not converged, but a Newton step from here moves no free value by more than "
                               f"{ratio:.2g} of its standard error: the errors are the maximum's")
    unest = torch.zeros(K, dtype=torch.bool)  # the reported entries that depend on an untouched free value
    if bool(idle.any()):  # (their dependence at a point off the optimum: a derivative not 0 there by chance)
        probe = theta + 0.37 + 0.01 * torch.arange(len(theta), dtype=torch.float64)
        unest = (torch.autograd.functional.jacobian(lambda t: torch.cat(
            [b.natural(u) for b, u in zip(blocks, t.split(sizes))]), probe)[:, idle] != 0).any(-1)
        natural[unest] = math.nan
    if se and not stopped:
        # the entries at a bound of their parametrisation (torchmm/learn/boundary.py): NaN errors, the
        # others' with them held
        G = _parametrisation_curvature(blocks, sizes, theta, lambda built: torch.func.functional_call(
            call, {k: built[b.name] for k, b in zip(substitutes(theta), blocks)}, (), tie_weights=False))
        directions = [entry_directions(b) for b in blocks]
        kinds = [b.kind for b in blocks for _ in b.names()]
        D = torch.block_diag(*[d for d, _ in directions])
        bound = [k for k in at_bounds(hessian, G, D, torch.cat([b for _, b in directions]), step ** 3)
                 if not unest[k]]
        theta_cov, ok = held_covariance(hessian, torch.cat([D[bound].to(hessian.dtype),
                                                            torch.eye(len(theta), dtype=hessian.dtype)[idle]]))
        if ok:
            J = torch.autograd.functional.jacobian(
                lambda t: torch.cat([b.natural(u) for b, u in zip(blocks, t.split(sizes))]), theta)
            cov = J @ theta_cov @ J.mT
            # a covariance's diagonal direction (its Cholesky factor's log-diagonal) at 0: the matrix is
            # singular; the entry itself is at its bound (no error) only where that factor's term is most
            # of it
            singular = [k for k in bound if kinds[k] == "covariance"
                        and float(theta[int(D[k].nonzero()[0, 0])].mul(2).exp()) < 0.5 * float(natural[k])]
            nan = [k for k in bound if k not in singular]
            nan += [k for k in range(K) if unest[k]]
            cov[nan, :] = math.nan
            cov[:, nan] = math.nan
            theta_cov[idle, :] = math.nan
            theta_cov[:, idle] = math.nan
            nan = [k for k in nan if not unest[k]]
            notes = []
            if nan:
                where = ", ".join(f"{names[k]} = {float(natural[k]):.3g}" for k in nan)
                notes.append("at a bound of its parametrisation (the log-likelihood slopes past it, or its "
                             f"coordinate ran off: {where}): no standard error")
            if singular:
                notes.append("a covariance singular at the estimate (its Cholesky factor's diagonal at 0, in "
                             f"the direction of {', '.join(names[k] for k in singular)})")
            if bound:
                notes.append("the other errors with those directions held at the estimate (dropped from the "
                             "information)")
                note = "; ".join(([note] if note else []) + notes)
        else:
            note = "; ".join(([note] if note else []) + [
                "the observed information is not positive definite at the optimum (a parameter on a "
                "boundary, or one the data do not identify): no standard errors"])
    if bool(idle.any()):
        note = "; ".join(([note] if note else []) + [
            f"not estimated: {', '.join(n for n, u in zip(names, unest) if u)} (no datum touches them, e.g. "
            "the start of a series without a finite measurement: the log-likelihood's gradient in them is 0 "
            "at every point evaluated): reported NaN, left out of the information and of k (the filter and "
            "belief0 keep their start values there)"])
    errors = cov.diagonal().clamp_min(0).sqrt()
    durations = []
    for b, u in zip(blocks, theta.split(sizes)):
        if b.kind != "stochastic":
            continue
        M = b.shape[-1]

        def duration(t, b=b):
            P = b.build(t).to(torch.float64).cpu().reshape(-1, M, M)
            return (1 / (1 - P.diagonal(dim1=-2, dim2=-1))).reshape(-1)
        start = sum(sizes[:blocks.index(b)])
        d = duration(u)
        d[[i for i in range(M) if f"{b.label}[{i},{i}]" in names
           and unest[names.index(f"{b.label}[{i},{i}]")]]] = math.nan
        diagonal = [names.index(f"{b.label}[{i},{i}]") if f"{b.label}[{i},{i}]" in names else -1
                    for i in range(M)]
        if se and not math.isnan(float(theta_cov[start:start + u.numel()].sum())) \
                and not any(k in bound for k in diagonal):
            Jd = torch.autograd.functional.jacobian(duration, u)
            cov_u = theta_cov[start:start + u.numel(), start:start + u.numel()]
            d_se = (Jd @ cov_u @ Jd.mT).diagonal().clamp_min(0).sqrt()
        else:
            d_se = torch.full_like(d, math.nan)
        rows = d.numel() // M
        for i in range(d.numel()):
            where = f"[{i // M},{i % M}]" if rows > 1 else f"[{i}]"
            durations.append((f"duration of {b.label}{where}", float(d[i]), float(d_se[i])))
    with torch.no_grad():
        for b, u in zip(blocks, theta.split(sizes)):
            if b.name.startswith(START):
                write_back(held, b.name.removeprefix(START), b.build(u))
            elif write:
                write_back(filter, b.name, b.build(u))
        start_belief = held.build() if held is not None and given is not belief0 else given
    batch_dims = measurements.dim() - 2
    return Estimate(names=names, estimates=natural.tolist(), se=errors.tolist(), cov=cov, theta=theta,
                    theta_cov=theta_cov, loglik=loglik, k=len(theta) - int(idle.sum()), nobs=_nobs(measurements, burn, batch_dims),
                    converged=converged, iterations=int(getattr(result, "nit", 0)),
                    evaluations=evaluations[0], message=message, seconds=time.perf_counter() - tic,
                    method=method, durations=durations, note=note, belief0=start_belief)

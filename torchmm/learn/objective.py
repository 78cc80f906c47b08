r"""A likelihood evaluated many times: the objective of maximum likelihood, checked once.

:func:`~torchmm.learn.negative_log_likelihood` is an entry point: every call checks its arguments
(the start belief's values, the data's record) and asks which kernel runs, about 0.3-0.5 ms before any
filtering. An optimiser calls the same likelihood tens to thousands of times with only the parameters
changing; :class:`Objective` does the checks and the choice once, then each call reads the filter's
current parameters and runs.
"""

from __future__ import annotations

import inspect
import math
import re
import warnings
from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import Tensor
from torch.nn.utils import parametrize

import torchmm.kernels as kernels
from torchmm.beliefs import Belief, ModeBelief
from torchmm.contract import Choice, Data, Flag, Int, Of, Real, Tensors, entry_point
from torchmm.filters.base import Filter
from torchmm.learn.loss import REDUCTIONS, as_start_belief, negative_log_likelihood, reduce_total
from torchmm.learn.search import Guarded
from torchmm.provenance import note_infinite
from torchmm.run import Keep, check_controls, run_filter
from torchmm.validation import check_filter_dtype, check_measurement

__all__ = ["Objective"]

#: the methods of ``scipy.optimize.minimize`` that use the gradient and need no Hessian
GRADIENT_METHODS = ("L-BFGS-B", "BFGS", "CG", "Newton-CG", "TNC", "SLSQP", "trust-constr")


class Objective:
    r"""``-log p_theta(z_{1:T})`` of one filter and one data set, as a function of the filter's current
    parameters: what :func:`~torchmm.learn.negative_log_likelihood` returns, checked once.

    Args:
        filter: any filter (its parameters are read at every call).
        belief0: the belief at time 0 (as for :func:`~torchmm.learn.negative_log_likelihood`), or a
            function ``filter -> belief`` called at every evaluation, for a start that depends on the
            parameters (e.g. the exact diffuse start of the local level, ``N(y_1, R)``:
            ``lambda kf: local_level_start(kf, y[0])``, experiments/realdata.py).
        measurements: ``(T, *B, m)``, NaN = missing (checked once, here); at least one entry present
            (data that are all missing inform no parameter: a ``ValueError`` naming ``measurements``).
        reduction: ``"sum"`` (default: the log-likelihood's scale), ``"mean"`` or ``"none"``, as for
            :func:`~torchmm.learn.negative_log_likelihood`.
        update_first: ``belief0`` is the prior of the first measurement (statsmodels' convention).
        controls: ``(T, *B, k)``, the inputs ``u_k`` of the motion models (e.g. regressors).
        motions, sensors: per-step models, as for :func:`~torchmm.run_filter` (irregular time stamps:
            one motion model per step). With per-step models the eager steps run; controls reach the
            Numba kernel (a ``LinearMotion``'s ``input_matrix``).
        burn: the first steps' log-likelihood terms left out (e.g. 1 under a diffuse prior).

    Returns (a call):
        the loss, differentiable in the filter's parameters (and the start belief's).

    The first evaluation runs the full checks of :func:`~torchmm.learn.negative_log_likelihood`; the
    following ones check the start belief's shapes only. Where a kernel applies
    (:mod:`torchmm.kernels.linear`: Kalman filters, IMM, GPB1 over linear-Gaussian modes, small
    problems on the CPU) a call is that kernel's forward pass; elsewhere, or for an evaluation the
    kernel declines (a regularised update), it is :func:`~torchmm.learn.negative_log_likelihood`.
    ``objective.kernel`` says which ran last (``"eager"`` or the kernel's name), ``objective.why``
    why no kernel applies.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement, learnable_noise
        >>> kf = KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0))
        >>> _ = learnable_noise(kf.measurement, "R", "log_diagonal")
        >>> objective = Objective(kf, GaussianBelief(torch.zeros(2), torch.eye(2)), torch.randn(50, 1))
        >>> loss = objective()
        >>> loss.backward()
        >>> loss.shape, kf.measurement.parametrizations.R.original.grad is not None
        (torch.Size([]), True)
    """

    @entry_point(filter=Of(Filter), belief0=Of(Belief, callable_ok=True, what="a belief or a function filter -> belief"),
                 measurements=Data(), reduction=Choice(*REDUCTIONS), update_first=Flag(),
                 controls=Data(optional=True),
                 motions=Of((list, tuple, torch.nn.Module), callable_ok=True, optional=True,
                            what="a sequence of T models, a callable k -> model, or None"),
                 sensors=Of((list, tuple, torch.nn.Module), callable_ok=True, optional=True,
                            what="a sequence of T models, a callable k -> model, or None"),
                 burn=Int(0))
    def __init__(self, filter: Filter, belief0: Belief | Callable[[Filter], Belief], measurements: Tensor, *,
                 reduction: str = "sum", update_first: bool = False, controls: Tensor | None = None,
                 motions: Any = None, sensors: Any = None, burn: int = 0):
        if not isinstance(measurements, Tensor) or measurements.dim() < 2:
            raise ValueError("measurements: expected a time-major tensor (T, *B, m)")
        if measurements.shape[0] == 0:
            raise ValueError(f"measurements: no time steps (shape {tuple(measurements.shape)}): a likelihood "
                             "needs T >= 1")
        if burn >= measurements.shape[0]:
            raise ValueError(f"burn: leaves out all {measurements.shape[0]} steps ({burn}): no likelihood term is left")
        if controls is not None and (not isinstance(controls, Tensor) or controls.dim() < 1
                                     or controls.shape[0] != measurements.shape[0]):
            raise ValueError(f"controls: expected (T, *B, k) with the measurements' {measurements.shape[0]} steps, got "
                             f"{tuple(controls.shape) if isinstance(controls, Tensor) else type(controls).__name__}")
        self.filter, self.start, self.measurements = filter, belief0, measurements
        self.controls, self.motions, self.sensors, self.burn = controls, motions, sensors, int(burn)
        self._check_parameters()
        self.reduction, self.update_first = reduction, update_first
        self.kernel, self.why = "eager", ""
        with torch.no_grad(), parametrize.cached():
            # the checks of negative_log_likelihood's entry point, once: the start belief's values and
            # dtype, the measurements' shape against the filter (the contract checked their values)
            given = self._belief()
            if not isinstance(given, Belief):
                raise TypeError(f"belief0: the start function returned a {type(given).__name__}, not a belief")
            given.validate("belief0")
            check_filter_dtype(filter, given, "belief0")
            first = as_start_belief(filter, given)
            meas_dim = getattr(filter, "meas_dim", None)
            if meas_dim is not None:
                like = first.mode_log_probs if isinstance(first, ModeBelief) else getattr(first, "mean", None)
                if isinstance(like, Tensor):
                    batch = like.shape[:-1]
                    check_measurement(measurements[0], meas_dim, batch, like, "measurements")
            batch = getattr(first, "batch_shape", None)
            if batch is not None:  # (run_filter's entry checks of shapes, once: the calls skip them)
                if controls is not None:
                    check_controls(filter, controls, measurements.shape[0], batch)
                filter.check_parameter_batch(batch)
            note_infinite(int(torch.isinf(measurements).sum()), "measurements")  # (one host read, once)
            # one host read: data with no datum inform no parameter (the gradient is 0, not None, so
            # minimize would stop at once with success)
            if not bool(torch.isfinite(measurements[self.burn:]).any()):
                after = f" after the burn ({self.burn} steps)" if self.burn else ""
                raise ValueError(f"measurements: every entry{after} is missing (non-finite; shape "
                                 f"{tuple(measurements.shape)}): the likelihood does not depend on the "
                                 "parameters, nothing to learn from")
            if motions is not None or sensors is not None:
                self._prepared, self.why = None, "per-step models (the eager steps take them)"
            else:
                request = kernels.Request(update_first=update_first, keep=frozenset({"log_likelihood"}),
                                          repeated=True, controls=controls)
                self._prepared, self.why = kernels.plan(filter, first, measurements, request)

    def _belief(self) -> Any:
        return self.start(self.filter) if callable(self.start) else self.start

    def _check_parameters(self) -> None:
        """Every parameter of the filter finite (one host read for all of them), else a ``ValueError``
        naming it (``filter.measurement.parametrizations.R.original: ...``): at construction, and at an
        evaluation whose loss is not finite (each evaluation is an entry point: the parameters change
        between calls, by an optimiser's step or a user's assignment)."""
        named = list(self.filter.named_parameters())
        if not named:
            return
        with torch.no_grad():
            finite = torch.stack([torch.isfinite(p).all() for _, p in named])
            if bool(finite.all()):
                return
            name, value = named[int((~finite).nonzero()[0, 0])]
            bad = value[~torch.isfinite(value)].reshape(-1)[0].item()
        raise ValueError(f"filter.{name}: a parameter of the filter is not finite ({bad}); the loss would be "
                         "NaN (set it to a finite value, or start the optimiser from one)")

    def __call__(self) -> Tensor:
        """The loss at the filter's current parameters. A loss that is not finite (or an error of the
        evaluation) is checked against the parameters: a parameter that is not finite is a
        ``ValueError`` naming it (a finite loss reads nothing more: one scalar read per call)."""
        try:
            loss = self._loss()
        except ValueError:
            self._check_parameters()  # the cause (e.g. a start belief built from a NaN parameter): named
            raise
        finite = math.isfinite(loss.detach().item()) if loss.dim() == 0 else bool(torch.isfinite(loss.detach()).all())
        if not finite:
            self._check_parameters()
        return loss

    def _loss(self) -> Tensor:
        with parametrize.cached():
            belief = self._belief()
            if self._prepared is not None:
                if not (self._prepared.kalman or isinstance(belief, ModeBelief)):
                    belief = as_start_belief(self.filter, belief)  # (a multiple-model filter's start)
                total = self.reduction == "sum"
                ll = self._prepared(belief, self.update_first, total)
                if ll is not None:
                    self.kernel = self._prepared.name
                    if total:
                        return -ll[self.burn:].sum()
                    return reduce_total(-ll[self.burn:].sum(0), self.reduction, ll.shape[0] - self.burn)
            self.kernel = "eager"
            if self.burn == 0 and self.controls is None and self.motions is None and self.sensors is None:
                return negative_log_likelihood(self.filter, belief, self.measurements, reduction=self.reduction,
                                               update_first=self.update_first)
            traj = run_filter(self.filter, as_start_belief(self.filter, belief), self.measurements,
                              controls=self.controls, motions=self.motions, sensors=self.sensors,
                              record=Keep("log_likelihood"), update_first=self.update_first)
            steps = self.measurements.shape[0] - self.burn
            return reduce_total(-traj.log_likelihood[self.burn:].sum(0), self.reduction, steps)

    def smoothed(self) -> Any:
        """The smoothed beliefs ``(T, *B)`` at the filter's current parameters: Kim's smoother of an IMM or
        GPB1, the RTS smoother of a Kalman filter (what ``smooth(run_filter(...))`` returns, to rounding).
        Where the objective has the compiled loops (``self.kernel``'s plan) the run and the smoother are
        one prepared call, checked once - a repeated filter-and-smoother's cost (an E-step, a bootstrap;
        issue 47: Fed funds 2x statsmodels' raw ``smooth``); elsewhere ``run_filter`` then ``smooth``."""
        from torchmm.smooth import smooth

        with torch.no_grad(), parametrize.cached():
            belief = self._belief()
            if self._prepared is not None and hasattr(self._prepared, "smooth"):
                if not (self._prepared.kalman or isinstance(belief, ModeBelief)):
                    belief = as_start_belief(self.filter, belief)
                out = self._prepared.smooth(belief, self.update_first)
                if out is not None:
                    return out
            traj = run_filter(self.filter, as_start_belief(self.filter, belief), self.measurements,
                              controls=self.controls, motions=self.motions, sensors=self.sensors,
                              update_first=self.update_first)
            method = "kim" if isinstance(traj.belief, ModeBelief) else None
            return smooth(traj, method=method).belief

    @entry_point(parameters=Tensors(optional=True, check=False), method=Choice(*GRADIENT_METHODS),
                 tol=Real(positive=True, optional=True), options=Of(Mapping, optional=True, what="a dict"))
    def minimize(self, *, parameters: Any = None, method: str = "L-BFGS-B", tol: float | None = None,
                 options: dict | None = None) -> Any:
        """Minimise the loss over the filter's parameters with ``scipy.optimize.minimize`` (gradient from
        autograd, one evaluation giving both), leaving the parameters at the optimum found.

        Args:
            parameters: the tensors to optimise: leaf tensors that require grad, each once, that the
                loss depends on (the filter's, or those the start function reads); a list or any
                iterable such as ``module.parameters()``. Default: the filter's parameters that require
                grad.
            method: a gradient method of ``scipy.optimize.minimize`` (one of :data:`GRADIENT_METHODS`;
                default ``"L-BFGS-B"``, as statsmodels' ``fit``).
            tol: a positive tolerance, passed to ``scipy.optimize.minimize``.
            options: a dict, passed to ``scipy.optimize.minimize``; a key the method does not take
                (``max_iter`` for ``maxiter``) is a ``ValueError`` naming ``options`` and listing the
                unknown keys (scipy only warns and runs on).

        Returns:
            scipy's ``OptimizeResult`` (``x``: the flat parameters at the optimum, ``fun``: the loss,
            ``nfev``, ``nit``, ``success``, ``message``).

        Raises:
            ValueError naming ``parameters`` (``parameters[i]``): none requires grad, an entry that does
            not require grad, is not a leaf, repeats another, or that the loss does not depend on (found
            at the first evaluation: before, such a tensor was "optimised" to success after 0
            iterations); TypeError naming it: not an iterable of tensors. ``method``, ``tol`` and
            ``options`` are checked at entry (ValueError/TypeError naming them); a filter parameter
            that is not finite at an evaluation is a ValueError naming it.
        """
        from scipy.optimize import OptimizeWarning, minimize

        explicit = parameters is not None
        params = _parameter_list(parameters) if explicit else \
            [p for p in self.filter.parameters() if p.requires_grad]
        if not params:
            raise ValueError("parameters: none requires grad (make some learnable, e.g. torchmm.models.learnable_noise)")
        sizes = [p.numel() for p in params]
        with torch.no_grad():
            start = torch.cat([p.detach().reshape(-1) for p in params]).to(torch.float64).cpu().numpy()
        checked = [not explicit]  # the loss's dependence on the given tensors, at the first evaluation

        def assign(x):
            with torch.no_grad():
                flat = torch.from_numpy(x)
                for p, chunk in zip(params, flat.split(sizes)):
                    p.copy_(chunk.view_as(p))

        def loss_and_grad(x):
            assign(x)
            for p in params:
                p.grad = None
            loss = self()
            if loss.dim():
                raise ValueError("reduction: minimize needs a scalar loss ('sum' or 'mean')")
            loss.backward()
            if not checked[0]:
                unused = next((i for i, p in enumerate(params) if p.grad is None), None)
                if unused is not None:
                    raise ValueError(f"parameters[{unused}]: the loss does not depend on it (not a parameter "
                                     "of the filter, nor read by the start belief): nothing to optimise")
                checked[0] = True
            grad = torch.cat([torch.zeros_like(p).reshape(-1) if p.grad is None else p.grad.reshape(-1)
                              for p in params])
            return float(loss.detach()), grad.to(torch.float64).cpu().numpy()

        try:
            with warnings.catch_warnings():  # a misspelt option (max_iter) is an error, not a warning
                warnings.filterwarnings("error", message="Unknown solver options", category=OptimizeWarning)
                try:
                    guarded = Guarded(loss_and_grad)  # a non-finite loss: a failed step (torchmm/learn/search.py)
                    result = minimize(guarded, start, jac=True, method=method, tol=tol,
                                      options=None if options is None else dict(options), callback=guarded.callback)
                    if guarded.failed:
                        result.message = (f"{result.message} ({guarded.failed} evaluation(s) where the loss or its "
                                          "gradient was not finite, answered as failed steps)")
                except (OptimizeWarning, TypeError) as err:  # (scipy refuses them before any evaluation)
                    unknown = _unknown_options(err, options)
                    if not unknown:
                        raise
                    raise ValueError(
                        f"options: unknown option{'s' if len(unknown) > 1 else ''} "
                        f"{', '.join(repr(k) for k in unknown)} of scipy's {method} (its options: "
                        f"scipy.optimize.show_options('minimize', {method!r}))") from None
            assign(result.x)
        except Exception:
            assign(start)  # an error leaves the parameters where they were
            raise
        finally:
            for p in params:
                p.grad = None
        return result

    def __repr__(self) -> str:
        return (f"Objective({type(self.filter).__name__}, T={self.measurements.shape[0]}, "
                f"reduction={self.reduction!r}, kernel={'none: ' + self.why if self._prepared is None else 'yes'})")


def _unknown_options(err: Exception, options: Mapping | None) -> list[str]:
    """The keys of ``options`` that scipy's solver refused, from its ``OptimizeWarning`` ("Unknown
    solver options: a, b", raised as an error before any evaluation) or from the ``TypeError`` of a
    solver without a catch-all (trust-constr: "unexpected keyword argument 'a'", the first only; the
    others from its signature). Empty: the error is not about the options."""
    from scipy.optimize import OptimizeWarning

    if not options:
        return []
    text = str(err)
    if isinstance(err, OptimizeWarning):
        if not text.startswith("Unknown solver options:"):
            return []
        named = {n.strip() for n in text.split(":", 1)[1].split(",")}
        return [str(k) for k in options if str(k) in named]
    match = re.search(r"unexpected keyword argument '([^']+)'", text)
    if match is None or match.group(1) not in options:
        return []
    import scipy.optimize._minimize as scipy_minimize  # trust-constr's solver: its other unknown keys

    solver = getattr(scipy_minimize, "_minimize_trustregion_constr", None)
    try:
        known = set(inspect.signature(solver).parameters) if solver is not None else None
    except (TypeError, ValueError):
        known = None
    if known is None:
        return [match.group(1)]
    return [str(k) for k in options if str(k) not in known]


def _parameter_list(parameters: Any) -> list[Tensor]:
    """``minimize``'s ``parameters`` as a list of distinct leaf tensors that require grad, or an error
    naming ``parameters`` / ``parameters[i]``."""
    if isinstance(parameters, (Tensor, str, bytes)) or not hasattr(parameters, "__iter__"):
        raise TypeError(f"parameters: expected an iterable of tensors (a list, module.parameters()), got "
                        f"{'a tensor' if isinstance(parameters, Tensor) else repr(parameters)}"
                        + (" (one tensor: [tensor])" if isinstance(parameters, Tensor) else ""))
    params = list(parameters)
    if not params:
        raise ValueError("parameters: empty (nothing to optimise; None: the filter's parameters)")
    seen: dict[int, int] = {}
    for i, p in enumerate(params):
        if not isinstance(p, Tensor):
            raise TypeError(f"parameters[{i}]: expected a tensor, got {type(p).__name__}")
        if not p.requires_grad:
            raise ValueError(f"parameters[{i}]: does not require grad (make it learnable, e.g. "
                             "torchmm.models.learnable_noise, or torch.nn.Parameter)")
        if not p.is_leaf:
            raise ValueError(f"parameters[{i}]: not a leaf tensor (a value computed from parameters: give the "
                             "parameter it is computed from)")
        if id(p) in seen:
            raise ValueError(f"parameters[{i}]: the same tensor as parameters[{seen[id(p)]}] (give each once)")
        seen[id(p)] = i
    return params

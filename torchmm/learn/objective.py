r"""A likelihood evaluated many times: the objective of maximum likelihood, checked once.

:func:`~torchmm.learn.negative_log_likelihood` is an entry point: every call checks its arguments
(the start belief's values, the data's record) and asks which kernel runs, about 0.3-0.5 ms before any
filtering. An optimiser calls the same likelihood tens to thousands of times with only the parameters
changing; :class:`Objective` does the checks and the choice once, then each call reads the filter's
current parameters and runs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor
from torch.nn.utils import parametrize

import torchmm.kernels as kernels
from torchmm.beliefs import Belief, ModeBelief
from torchmm.contract import Choice, Data, Flag, Of, entry_point
from torchmm.filters.base import Filter
from torchmm.learn.loss import REDUCTIONS, as_start_belief, negative_log_likelihood, reduce_total
from torchmm.validation import check_filter_dtype, check_measurement

__all__ = ["Objective"]



class Objective:
    r"""``-log p_theta(z_{1:T})`` of one filter and one data set, as a function of the filter's current
    parameters: what :func:`~torchmm.learn.negative_log_likelihood` returns, checked once.

    Args:
        filter: any filter (its parameters are read at every call).
        belief0: the belief at time 0 (as for :func:`~torchmm.learn.negative_log_likelihood`), or a
            function ``filter -> belief`` called at every evaluation, for a start that depends on the
            parameters (e.g. the exact diffuse start of the local level, ``N(y_1, R)``:
            ``lambda kf: local_level_start(kf, y[0])``, experiments/realdata.py).
        measurements: ``(T, *B, m)``, NaN = missing (checked once, here).
        reduction: ``"sum"`` (default: the log-likelihood's scale), ``"mean"`` or ``"none"``, as for
            :func:`~torchmm.learn.negative_log_likelihood`.
        update_first: ``belief0`` is the prior of the first measurement (statsmodels' convention).

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
                 measurements=Data(), reduction=Choice(*REDUCTIONS), update_first=Flag())
    def __init__(self, filter: Filter, belief0: Belief | Callable[[Filter], Belief], measurements: Tensor, *,
                 reduction: str = "sum", update_first: bool = False):
        if not isinstance(measurements, Tensor) or measurements.dim() < 2:
            raise ValueError("measurements: expected a time-major tensor (T, *B, m)")
        self.filter, self.start, self.measurements = filter, belief0, measurements
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
            request = kernels.Request(update_first=update_first, keep=frozenset({"log_likelihood"}),
                                      repeated=True)
            self._prepared, self.why = kernels.plan(filter, first, measurements, request)

    def _belief(self) -> Any:
        return self.start(self.filter) if callable(self.start) else self.start

    def __call__(self) -> Tensor:
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
                        return -ll.sum()
                    return reduce_total(-ll.sum(0), self.reduction, ll.shape[0])
            self.kernel = "eager"
            return negative_log_likelihood(self.filter, belief, self.measurements, reduction=self.reduction,
                                           update_first=self.update_first)

    def minimize(self, *, parameters: Any = None, method: str = "L-BFGS-B", tol: float | None = None,
                 options: dict | None = None) -> Any:
        """Minimise the loss over the filter's parameters with ``scipy.optimize.minimize`` (gradient from
        autograd, one evaluation giving both), leaving the parameters at the optimum found.

        Args:
            parameters: the tensors to optimise (default: the filter's parameters that require grad).
            method: a gradient method of ``scipy.optimize.minimize`` (default ``"L-BFGS-B"``, as
                statsmodels' ``fit``).
            tol, options: passed to ``scipy.optimize.minimize``.

        Returns:
            scipy's ``OptimizeResult`` (``x``: the flat parameters at the optimum, ``fun``: the loss,
            ``nfev``, ``nit``, ``success``, ``message``).

        Raises:
            ValueError naming ``parameters``: none requires grad.
        """
        from scipy.optimize import minimize

        params = [p for p in (self.filter.parameters() if parameters is None else parameters) if p.requires_grad]
        if not params:
            raise ValueError("parameters: none requires grad (make some learnable, e.g. torchmm.models.learnable_noise)")
        sizes = [p.numel() for p in params]
        with torch.no_grad():
            start = torch.cat([p.detach().reshape(-1) for p in params]).to(torch.float64).numpy()

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
            grad = torch.cat([torch.zeros_like(p).reshape(-1) if p.grad is None else p.grad.reshape(-1)
                              for p in params])
            return float(loss.detach()), grad.to(torch.float64).numpy()

        result = minimize(loss_and_grad, start, jac=True, method=method, tol=tol, options=options)
        assign(result.x)
        for p in params:
            p.grad = None
        return result

    def __repr__(self) -> str:
        return (f"Objective({type(self.filter).__name__}, T={self.measurements.shape[0]}, "
                f"reduction={self.reduction!r}, kernel={'none: ' + self.why if self._prepared is None else 'yes'})")

r"""The small linear-Gaussian kernel: a whole run of a Kalman filter, an IMM, a GPB1 or a static bank
over linear-Gaussian modes in one compiled loop (Numba), with autograd through a hand-written reverse
pass.

**What it computes.** The eager steps' equations, operation by operation (torchmm/kernels/linear_loops.py,
linear_reverse.py, linear_kim.py): the interaction of torchmm/multimodel/imm.py, the prediction
``F x + b``, ``F P F^T + Q``, the update of :func:`torchmm.linalg.condition` (missing components
skipped, the posterior covariance symmetrised, the log-likelihood over the observed components) and
the mode update of :func:`~torchmm.multimodel.imm.mode_posterior`. Results equal the eager steps' to
rounding (tests/kernels/test_linear_kernel.py: 1e-12 relative in float64).

**The gradient** is the adjoint of that loop (the reverse pass, stored forward values): one backward
pass over the run whatever the number of parameters, about the cost of the forward. It covers the
model matrices (``F``, ``b``, ``Q``, ``H``, ``R``), the transition matrix and the start belief, and the
run's outputs ``log_likelihood`` and the filtered beliefs. The adjoints of the symmetric matrices
``Q``, ``R`` and the start covariance are symmetric (the part of a gradient that any symmetric
parametrisation sees).

**When it runs** (:func:`~torchmm.kernels.plan` asks, :func:`~torchmm.run_filter` uses it; no option
to set): the filter joined the ``"linear_gaussian"`` family (:class:`~torchmm.KalmanFilter`,
:class:`~torchmm.IMM`, :class:`~torchmm.GPB1`, :class:`~torchmm.StaticMM` over Kalman modes) and
describes itself through ``linear_gaussian()``; CPU tensors of one floating dtype; measurements one
tensor ``(T, *B, m)``; no per-step models (controls are taken: a ``LinearMotion``'s input matrix ``G``,
``F x + b + G u_t``, the terms ``G u_t`` computed by torch, so that their gradients are autograd's); a small problem (at most :data:`MAX_RUNS` runs:
the loop is serial, and beyond that the batched tensor kernels win); Numba importable. Every such run
takes it, short or long (:data:`LONG_RUN`): the one-shot call is then as fast as the repeated one. The
choice depends on the call only, never on what the process ran before.
With autograd the run keeps only its log-likelihood and filtered beliefs (their gradients are the
reverse pass's); a run that asks for more runs eagerly. A run with a regularised innovation covariance
or a non-finite result is run again eagerly, which flags it as it always does (docs/robustness.md).

Here the plan, the prepared (repeated) evaluation and the trajectory's fields; the run on NumPy arrays and its
autograd node: :mod:`torchmm.kernels.linear_run`.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.kernels.linear_run import (
    NoGrad,
    Run,
    all_broadcast,
    as_array,
    broadcasts,
    finfo,
    input_terms,
    kernel_arrays,
    layout_of,
    load,
    model_tensors,
)
from torchmm.runtime import host_reads_ok
from torchmm.unchanged import Unchanged

__all__ = ["MAX_RUNS", "LinearGaussian", "load"]

#: the most runs (batch elements) the kernel takes: its loop is serial over runs (measured crossover
#: with the batched tensor kernels, docs/performance.md)
MAX_RUNS = 128
#: the smallest run (steps x runs) the kernel takes by default: every run (issue 47). The choice depends on
#: the run only, never on the process's history, so the same call gives the same numbers everywhere. The
#: kernel's first call in a process costs ~0.3 s of loading Numba and its cached machine code, once; every
#: call after it costs ~0.3 ms besides its steps (0.1-0.4 us a step), where 100 eager steps cost ~16 ms (it
#: was 200 until then: short runs stepped eagerly, 0.003x statsmodels' loglike at 100 steps)
LONG_RUN = 1
_RULES = {"kalman": 2, "static": 2, "mix": 0, "collapse": 1}


class LinearGaussian(NamedTuple):
    """A filter's description of itself for the linear-Gaussian kernel (``filter.linear_gaussian()``).

    Shapes (``*P``: the model parameters' batch, ``()`` or the modes ``(M,)``):
        F ``(*P, n, n)``, b ``(*P, n)``, Q ``(*P, n, n)``, H ``(*P, m, n)``, R ``(*P, m, m)``;
        transition ``(M, M)``, or per run ``(*B, M, M)`` (only the Numba kernel's forward and reverse
        passes take it: the batch-last kernels decline), None for a single filter;
        rule: ``"kalman"`` (one filter),
        ``"mix"`` (IMM), ``"collapse"`` (GPB1), ``"static"`` (no interaction) or ``"pairs"`` (GPB2: the
        batch-last kernel only, :mod:`torchmm.kernels.batch_last.pairs`); post_update: None, or the
        filter's own work after each step's update, ``post_update(out, generator) -> StepOutput`` on the
        step's output (batch-first; the run continues from its belief's mode probabilities): a
        variable-structure IMM's model-set policy (the batch-last kernel only); G ``(*P, n, k)``: the
        motion's input matrix (``F x + b + G u_t`` with the run's controls ``u_t``), None without one
        (only the kernels that take controls are given a description with one:
        :func:`torchmm.kernels.describe`); time_varying: a transition whose matrices are the step's
        controls' (:class:`~torchmm.models.transition.LogisticTransition`: ``time_varying.at(u_t).log_matrix()``,
        ``(*B, M, M)``), ``transition`` then None; likewise only for the kernels that take controls.
    """

    F: Tensor
    b: Tensor
    Q: Tensor
    H: Tensor
    R: Tensor
    transition: Tensor | None = None
    rule: str = "kalman"
    post_update: Any = None
    G: Tensor | None = None
    time_varying: Any = None


def last_steps(z: Tensor, runs: int) -> np.ndarray:
    """Each run's last step with a finite measurement (0 for a run without one), ``(runs,)`` int64, from the
    measurements ``z (T, runs, m)``: where Kim's smoother ends it (``smooth``'s padding,
    docs/smoothing.md)."""
    seen = torch.isfinite(z).reshape(z.shape[0], runs, -1).any(-1)  # (T, runs)
    index = torch.arange(z.shape[0], device=z.device).unsqueeze(-1)
    return torch.where(seen, index, 0).amax(0).cpu().numpy().astype(np.int64)


class Prepared:
    """A run planned once and evaluated many times (:class:`~torchmm.learn.Objective`): the data, shapes and
    kernel choice fixed, the models read from the filter at every call (their current parameters).

    ``prepared(belief0)`` returns the log-likelihoods ``(T, *B)`` (differentiable through the reverse
    pass; ``total=True``: as ``(T, runs)``, for a caller that sums them all), or None where the run
    needs the eager steps (a regularised update, a non-finite result).
    """

    name = "linear_gaussian"

    def __init__(self, filter: Any, belief0: Any, z: Tensor, batch: tuple, M: int, n: int, m: int, rule: str,
                 controls: Tensor | None = None):
        self.filter, self.z, self.batch, self.controls = filter, z, batch, controls
        self.M, self.n = M, n
        self.rule = _RULES[rule]
        self.kalman = rule == "kalman"
        self.runs = math.prod(batch)
        model = kernels.describe(filter, self.name, inputs=True)
        steps = z.shape[0]
        self.per_run = per_run_transition(model)
        self.layout = layout_of(M, n, m, tuple(batch), self.kalman,
                              None if controls is None or model.G is None else steps,
                              None if model.time_varying is None else steps, self.per_run)
        self.zeros = z.new_zeros(self.runs, 1)
        self.zero_inputs = z.new_zeros(1, 1, M, n)  # (no controls: the input terms, made once)
        self._smooth_inputs = Unchanged(size=1)  # (the kernel's arrays of the last call's tensors)
        # each run's last step for Kim's smoother: its last with a datum (torchmm.smooth's padding);
        # RTS: T - 1
        self.last = np.full(self.runs, steps - 1, np.int64) if self.kalman else last_steps(z, self.runs)
        self.shape = (belief0.mean.shape, belief0.cov.shape) if self.kalman else (
            belief0.mode_log_probs.shape, belief0.components.mean.shape, belief0.components.cov.shape)

    def __call__(self, belief0: Any, update_first: bool = False, total: bool = False) -> Tensor | None:
        model = kernels.describe(self.filter, self.name, inputs=True)
        if isinstance(model, str):
            raise RuntimeError(f"filter: no longer linear-Gaussian since the objective was built ({model})")
        if self.kalman:
            if (belief0.mean.shape, belief0.cov.shape) != self.shape:
                raise ValueError(f"belief0: shapes {(tuple(belief0.mean.shape), tuple(belief0.cov.shape))} differ "
                                 f"from the objective's {tuple(tuple(s) for s in self.shape)}")
            start = (self.zeros, belief0.mean, belief0.cov)
        else:
            comps = belief0.components
            if (belief0.mode_log_probs.shape, comps.mean.shape, comps.cov.shape) != self.shape:
                raise ValueError("belief0: shapes differ from the objective's")
            start = (belief0.mode_log_probs, comps.mean, comps.cov)
        status = [0]
        bu = input_terms(model, self.controls, self.M, self.n, self.batch)
        outs = Run.apply(self.z, self.rule, bool(update_first), False, self.layout, status,
                          *model_tensors(model, self.controls, self.batch), *start, bu)
        if status[0]:
            return None
        return outs[0] if total else outs[0].reshape(self.z.shape[0], *self.batch)

    def smooth(self, belief0: Any, update_first: bool = False) -> Any:
        """The run and its smoother at the filter's current parameters, both compiled loops, no autograd:
        Kim's smoother of an IMM or GPB1 (the RTS smoother of one Kalman filter) - what ``run_filter`` then
        ``smooth`` return, without their entry checks (checked once, when the plan was made). The
        smoothed beliefs, batch ``(T, *B)``, or None where the eager route must run (a regularised update,
        a static bank, a time-varying or per-run transition: the compiled smoother reads one matrix). Kim's
        smoother ends each run at its last step with a
        datum, as ``smooth`` does (docs/smoothing.md)."""
        model = kernels.describe(self.filter, self.name, inputs=True)
        if isinstance(model, str) or model.time_varying is not None or self.per_run or self.rule == 2 \
                and not self.kalman:
            return None
        start = (self.zeros, belief0.mean, belief0.cov) if self.kalman else (
            belief0.mode_log_probs, belief0.components.mean, belief0.components.cov)
        with torch.no_grad():  # (NumPy throughout, one compiled call: the forward pass's arrays stay inside)
            bu = self.zero_inputs if self.controls is None else input_terms(model, self.controls, self.M, self.n,
                                                                               self.batch)
            tensors = (*model_tensors(model, self.controls, self.batch), *start, bu)
            # the kernel's arrays of unchanged tensors (the same objects at the same versions: torch's own test of
            # an in-place change) are the last call's: a repeated smoother at fixed parameters converts nothing
            inputs = self._smooth_inputs.remember(tensors, lambda: kernel_arrays(self.z, tensors, self.layout))
            T, runs = self.z.shape[0], self.runs
            dt = inputs[0].dtype
            out = [np.empty((T, runs, self.M), dt), np.empty((T, runs, self.M, self.n), dt),
                   np.empty((T, runs, self.M, self.n, self.n), dt)]
            bad, regularised = load().filter_and_kim(*inputs[:7], self.rule, bool(update_first), *inputs[7:],
                                                     *finfo(dt), self.last, *out)
            if bad + regularised:
                return None
            return _smoothed(out, tuple(self.batch), self.kalman)


def _with_parameter_batch(model, batch: tuple) -> tuple | None:
    """The batch of a Kalman filter's run: ``batch`` (the belief's) broadcast with the batch axes of the
    description's ``F, b, Q, H, R`` (their shapes less the event axes), or None where that adds runs (more
    than unit axes: the eager steps)."""
    shapes = [t.shape[:t.dim() - event] for t, event in zip((model.F, model.b, model.Q, model.H, model.R),
                                                            (2, 1, 2, 2, 2))]
    try:
        wide = tuple(torch.broadcast_shapes(batch, *shapes))
    except RuntimeError:
        return None
    return wide if math.prod(wide) == math.prod(batch) else None


def per_run_transition(model: LinearGaussian) -> bool:
    """Whether the description's transition is per run, ``(*B, M, M)`` (the forward and reverse loops read a
    run's own matrix, ``Pi (1, runs, M, M)``; the compiled Kim smoother reads one)."""
    return model.transition is not None and model.transition.dim() > 2


class LinearKernel:
    """The registered kernel (see the module docstring)."""

    name = "linear_gaussian"
    smooths_padding = True  # plan_smooth takes padding= (runs that end early)
    by_size = True  # taken by the number of runs (kernels.by_size)
    takes_controls = True  # the motion's input terms G u_t (LinearMotion's input_matrix)

    def plan(self, filter: Any, belief0: Any, measurements: Any, request: kernels.Request):
        if not isinstance(measurements, Tensor) or not measurements.is_floating_point():
            return "the measurements are not one floating-point tensor"
        if request.compile_required:
            return "compile=True (the kernel is compiled by Numba, not torch.compile)"
        model = kernels.describe(filter, self.name, inputs=True)
        if isinstance(model, str):
            return model
        controls = request.controls
        if controls is not None and model.G is None:
            if model.time_varying is None:
                return "controls, but the motion has no input matrix (the eager steps say so)"
        if model.time_varying is not None and controls is None:
            return "a time-varying transition reads the controls, and none were given (the eager steps say so)"
        if model.rule not in _RULES:
            return f"the {model.rule!r} rule (GPB2's pairs: the batch-last kernel)"
        if model.post_update is not None:
            return "a post-update (a model-set policy: the batch-last kernel)"
        if model.rule == "kalman":
            if type(belief0) is not GaussianBelief:
                return "belief0 is not a GaussianBelief"
            batch = belief0.batch_shape
            M = 1
            x0, P0 = belief0.mean, belief0.cov
            logmu0 = torch.zeros((math.prod(batch), 1), dtype=belief0.dtype)
        else:
            if type(belief0) is not ModeBelief or type(belief0.components) is not GaussianBelief:
                return "belief0 is not a ModeBelief of Gaussians"
            logmu0 = belief0.mode_log_probs
            batch = logmu0.shape[:-1]
            M = logmu0.shape[-1]
            x0, P0 = belief0.components.mean, belief0.components.cov
        dtype = logmu0.dtype
        n, m = x0.shape[-1], model.H.shape[-2]
        batch = tuple(batch)
        if model.rule == "kalman":
            # the eager steps' batch is the belief's broadcast with the parameters' (a Kalman filter's have
            # no mode axis): unit axes the belief lacks are the run's too
            # (tests/filters/test_broadcast_batches.py)
            wide = _with_parameter_batch(model, batch)
            if wide is None:
                return "the model's parameters are batched over more than the belief"
            if wide != batch:
                if measurements.shape != (measurements.shape[0], *batch, m):
                    return "the measurements are not (T, *B, m) of the belief's batch"
                measurements = measurements.reshape(measurements.shape[0], *wide, m)
                x0, P0, batch = x0.expand(*wide, n), P0.expand(*wide, n, n), wide
        try:
            models = model_tensors(model, controls, batch)  # (a time-varying transition's matrices at the controls)
        except (RuntimeError, ValueError) as err:
            return f"the time-varying transition at the controls: {err}"
        tensors = (measurements, x0, P0, logmu0, *(t for t in model if isinstance(t, Tensor)), models[5],
                   *((controls,) if controls is not None else ()))
        if not all(t.is_cpu for t in tensors) or not host_reads_ok(tensors[0]):
            return "not on the CPU (or host reads are off: torchmm.runtime.no_host_sync)"
        if dtype not in (torch.float32, torch.float64) or any(t.dtype != dtype for t in tensors):
            return "not one float32 or float64 dtype"
        runs = math.prod(batch)
        if controls is not None and model.G is not None:
            k = model.G.shape[-1]
            if model.G.dim() not in (2, 3) or (model.G.dim() == 3 and model.G.shape[0] not in (1, M)):
                return "the input matrix is batched over more than the modes"
            if controls.dim() < 2 or controls.shape[0] != measurements.shape[0] or controls.shape[-1] != k \
                    or not broadcasts(controls.shape[1:-1], tuple(batch)):
                return "the controls are not (T, *B, k) of the run's batch and the input matrix's k"
        if runs > MAX_RUNS and not request.forced:
            return f"{runs} runs: more than the serial loop's {MAX_RUNS} (the batched kernels win)"
        steps = measurements.shape[0]
        if measurements.dim() != len(batch) + 2 or measurements.shape[-1] != m:
            return "the measurements are not (T, *B, m) of the belief's batch"
        if measurements.requires_grad and torch.is_grad_enabled():
            return "the measurements require grad"
        grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
        if grad and (request.keep is None or request.keep - {"belief", "log_likelihood"}):
            return "with autograd the kernel keeps only the log-likelihood and the filtered beliefs"
        if not (request.forced or request.repeated or steps * runs >= LONG_RUN):
            return f"a short run ({steps} x {runs} < {LONG_RUN} steps x runs: the steps are as fast)"
        if not kernels.numba_available():
            return "Numba is not installed"
        try:
            z = measurements.expand(steps, *batch, m).reshape(steps, runs, m)
        except RuntimeError:
            return "the measurements' batch does not broadcast to the belief's"
        rule = _RULES[model.rule]
        per_run = per_run_transition(model)
        Pi = model.transition
        if model.rule != "kalman" and Pi is not None and (
                Pi.shape[-2:] != (M, M) or not broadcasts(Pi.shape, (*batch, M, M))):
            return "the transition matrix does not match the modes (or its batch the runs')"
        if model.time_varying is not None and models[5].shape != (steps, runs, M, M):
            return "the time-varying transition's matrices do not match the modes and the runs"
        kalman = model.rule == "kalman"
        layout = layout_of(M, n, m, batch, kalman, None if controls is None or model.G is None else steps,
                         None if model.time_varying is None else steps, per_run)
        if not all_broadcast([t.shape for t in (*models, logmu0, x0, P0)], layout):
            return "the models' parameters are batched over more than the modes (or the start belief's shapes)"
        start = (logmu0, x0, P0)
        mixed = model.rule in ("mix", "collapse")
        if request.repeated:
            return Prepared(filter, belief0, z, tuple(batch), M, n, m, model.rule, controls)

        def run():
            status = [0]
            bu = input_terms(model, controls, M, n, tuple(batch))
            args = (z, rule, bool(request.update_first), True, layout, status, *models, *start, bu)
            outs = Run.apply(*args) if grad else Run.forward(NoGrad(), *args)  # (no graph: no node)
            if status[0]:
                return None  # regularised or failed somewhere: the eager steps flag it as they do
            return _fields(outs, batch, steps, M, kalman, mixed, request)

        run.applies_record = False  # a record function: run_filter applies it to each step of the fields
        run.flags_clear = True  # (its fields come back only from a run without a regularised or failed update)
        return run


    def plan_smooth(self, filter: Any, trajectory: Any, method: str | None, padding: Tensor | None = None,
                    **inputs: Any):
        """Kim's smoother of an IMM or GPB1 run (``method="kim"``), or the RTS smoother of a Kalman
        filter run, without autograd (with it, the eager smoother runs: its gradient is autograd's).
        ``padding (T, *B)`` bool: True at the steps after a run's last one (``smooth``'s), which keep their
        filtered beliefs."""
        model = kernels.describe(filter, self.name)
        if isinstance(model, str):
            return model
        if model.post_update is not None:
            return "a post-update (a model-set policy): the eager smoother"
        if model.rule == "kalman":
            if method is not None or trajectory.prior is None:
                return "a smoother method for a single filter, or no priors recorded (the eager smoother says)"
        elif method != "kim" or model.rule not in ("mix", "collapse"):
            return "only Kim's smoother of IMM and GPB1 runs"
        if per_run_transition(model):
            return "a per-run transition (*B, M, M): the compiled Kim smoother reads one matrix"
        belief = trajectory.belief
        if model.rule == "kalman":
            if type(belief) is not GaussianBelief:
                return "the trajectory's beliefs are not Gaussian"
            logmu = torch.zeros((*belief.batch_shape, 1), dtype=belief.dtype)
            mean, cov = belief.mean.unsqueeze(-2), belief.cov.unsqueeze(-3)
        else:
            if type(belief) is not ModeBelief or type(belief.components) is not GaussianBelief:
                return "the trajectory's beliefs are not a ModeBelief of Gaussians"
            logmu, mean, cov = belief.mode_log_probs, belief.components.mean, belief.components.cov
        tensors = (logmu, mean, cov, *(t for t in model if isinstance(t, Tensor)))
        if not all(t.is_cpu for t in tensors) or not host_reads_ok(tensors[0]):
            return "not on the CPU (or host reads are off: torchmm.runtime.no_host_sync)"
        dtype = logmu.dtype
        if dtype not in (torch.float32, torch.float64) or any(t.dtype != dtype for t in tensors):
            return "not one float32 or float64 dtype"
        if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
            return "autograd (the eager smoother's gradient is autograd's)"
        steps, batch, M, n = logmu.shape[0], logmu.shape[1:-1], logmu.shape[-1], mean.shape[-1]
        runs = math.prod(batch)
        if runs > MAX_RUNS:
            return f"{runs} runs: more than the serial loop's {MAX_RUNS}"
        if steps * runs < LONG_RUN:
            return f"a short run ({steps} x {runs} < {LONG_RUN} steps x runs)"
        if not kernels.numba_available():
            return "Numba is not installed"
        models = model_tensors(model)
        wide = ((M, n, n), (M, n), (M, n, n))
        if not all(broadcasts(t.shape, w) for t, w in zip(models[:3], wide)):
            return "the models' parameters are batched over more than the modes"
        kalman = model.rule == "kalman"

        def run():
            flat = [t.detach().reshape(steps, runs, *t.shape[1 + len(batch):]).contiguous()
                    for t in (logmu, mean, cov)]
            last = np.full(runs, steps - 1, np.int64) if padding is None else \
                ((~padding).reshape(steps, runs).sum(0) - 1).clamp(min=0).numpy().astype(np.int64)
            return _kim(models, *flat, last, tuple(batch), kalman)

        return run


def _kim(models: tuple, logmu: Tensor, x: Tensor, P: Tensor, last: np.ndarray, batch: tuple,
         kalman: bool) -> Any:
    """Kim's smoother (one mode: RTS) of a filtered run in the compiled loop: the models ``_models``
    gives, the run's ``logmu (T, runs, M)``, ``x (T, runs, M, n)``, ``P (T, runs, M, n, n)`` (contiguous),
    each run's last step ``last (runs,)`` -> the smoothed beliefs, batch ``(T, *batch)`` (a GaussianBelief
    for one Kalman filter)."""
    M, n = logmu.shape[-1], x.shape[-1]
    F, b, Q, Pi = (np.ascontiguousarray(np.broadcast_to(as_array(t), w))
                   for t, w in zip((*models[:3], models[5]), ((M, n, n), (M, n), (M, n, n), (M, M))))
    return _kim_arrays(F, b, Q, Pi, logmu.numpy(), x.numpy(), P.numpy(), last, batch, kalman)


def _kim_arrays(F, b, Q, Pi, logmu, x, P, last, batch: tuple, kalman: bool) -> Any:
    """:func:`_kim` on NumPy arrays: ``F (M, n, n)``, ``b (M, n)``, ``Q (M, n, n)``, the transition ``Pi (M,
    M)``, the filtered ``logmu (T, runs, M)``, ``x``, ``P`` (contiguous) and each run's last step ``last``."""
    steps, runs, M = logmu.shape
    n = x.shape[-1]
    dt = logmu.dtype
    out = [np.empty((steps, runs, M), dt), np.empty((steps, runs, M, n), dt), np.empty((steps, runs, M, n, n), dt)]
    loops = load()
    loops.kim(F, b, Q, Pi, loops.log_matrix(Pi), logmu, x, P, *finfo(dt), last, *out)
    return _smoothed(out, batch, kalman)


def _smoothed(out: list, batch: tuple, kalman: bool) -> Any:
    """The smoothed beliefs, batch ``(T, *batch)``, over the Kim loop's ``(T, runs, ...)`` arrays."""
    steps, runs = out[0].shape[:2]
    if batch == (runs,):
        slogmu, sx, sP = (torch.from_numpy(o) for o in out)
    else:
        slogmu, sx, sP = (torch.from_numpy(o).reshape(steps, *batch, *o.shape[2:]) for o in out)
    if kalman:
        return GaussianBelief(sx.squeeze(-2), sP.squeeze(-3))
    return ModeBelief(slogmu, GaussianBelief(sx, sP))


def _as_bool(flags: Tensor) -> Tensor:
    """The kernel's int8 flags (0 or 1) as a bool tensor: a view of the same bytes on the CPU."""
    return flags.view(torch.bool) if flags.dtype == torch.int8 else flags.to(torch.bool)


def _fields(outs, batch, steps, M, kalman: bool, mixed: bool, request: kernels.Request) -> tuple:
    """The trajectory's fields, batch ``(T, *B)``, from the kernel's ``(T, runs, ...)`` outputs."""
    ll, logmu, x, P, xp, Pp, logc, xm, Pm, innov, S, mode_ll, flags = outs
    keep = request.keep

    def kept(name: str) -> bool:
        return keep is None or name in keep

    if kalman:
        def single(t):  # (T, runs, 1, ...) -> (T, *B, ...): one view of the kernel's contiguous output
            return t.view(steps, *batch, *t.shape[3:])

        belief = GaussianBelief(single(x), single(P))
        prior = GaussianBelief(single(xp), single(Pp)) if kept("prior") else None
        innovation = single(innov) if kept("innovation") else None
        innovation_cov = single(S) if kept("innovation_cov") else None
        extras = None
        if kept("extras"):
            singular = single(_as_bool(flags))
            extras = {"singular": singular, "failed": torch.zeros_like(singular)}
    else:
        def modes(t):
            return t.reshape(steps, *batch, M, *t.shape[3:])

        lp = ll.reshape(steps, *batch)
        belief = ModeBelief(modes(logmu), GaussianBelief(modes(x), modes(P)))
        prior = ModeBelief(modes(logc), GaussianBelief(modes(xp), modes(Pp))) if kept("prior") else None
        innovation = modes(innov) if kept("innovation") else None
        innovation_cov = modes(S) if kept("innovation_cov") else None
        extras = None
        if kept("extras"):
            singular = modes(_as_bool(flags))
            extras = {"mode_log_likelihood": modes(mode_ll),
                      "modes": {"singular": singular, "failed": torch.zeros_like(singular)},
                      "failed": torch.zeros(lp.shape, dtype=torch.bool)}
            if mixed and not request.update_first:
                extras["mixed"] = ModeBelief(modes(logc), GaussianBelief(modes(xm), modes(Pm)))
    log_likelihood = ll.reshape(steps, *batch) if kept("log_likelihood") else None
    if not kept("belief"):
        belief = None
    elif request.estimate:
        belief = belief.estimate()
    elif request.detach_belief:
        belief = belief.detach()
    return belief, prior, log_likelihood, innovation, innovation_cov, extras


#: the registered instance (torchmm.kernels.TABLE: first, before the batched kernels)
LINEAR = LinearKernel()

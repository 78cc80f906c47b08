"""What every batch-last kernel's plan shares (split from :mod:`torchmm.kernels.batch_last.imm` by concern, issue
47): whether a linear-Gaussian run fits the batch-last layout (:func:`why_not`), the filter's description where a batch-last kernel may plan the run (:func:`described`), the plan of a
prepared kernel (:func:`planned`: what it builds, from the request), and its whole run (:func:`run_steps`:
the steps, each output recorded, stacked batch-first in memory order). The IMM / GPB1 / GPB2 kernel
(:mod:`~torchmm.kernels.batch_last.imm`), the extended and unscented banks'
(:mod:`~torchmm.kernels.batch_last.nonlinear`) and IMM-TF's (:mod:`~torchmm.kernels.batch_last.transfer`) plan
through them."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.typing import StepOutput

__all__ = ["PER_RUN_TRANSITION", "described", "planned", "run_steps", "stack_batch_first", "why_not"]


def described(filter, request: kernels.Request, family: str, rules: tuple, which: str, belief0=None,
              measurements=None, why=None):
    """``filter``'s description for the kernel ``family`` where a batch-last kernel may plan the run (no
    ``update_first``, not a repeated evaluation, an interaction rule in ``rules``, the estimators named
    ``which``, and ``why(model, M, belief0, measurements)`` None where given), or the reason not."""
    if request.update_first:
        return "update_first"
    if request.repeated:
        return "no prepared (repeated) evaluation"
    model = kernels.describe(filter, family)
    if isinstance(model, str):
        return model
    if model.rule not in rules:
        return f"the {model.rule!r} rule ({which} only)"
    reason = None if why is None else why(model, model.transition.shape[-1], belief0, measurements)
    return model if reason is None else reason


def planned(kernel: Any, belief0, request: kernels.Request):
    """The plan of a prepared kernel: what it builds set from ``request`` (the kept fields, the
    estimate inside the step or after a post-update, the generator), and ``run()`` (:func:`run_steps`),
    with ``run.kernel``."""
    kernel.generator = request.generator
    kept = frozenset(StepOutput._fields) - {"belief", "log_likelihood"}
    if request.estimate and kernel.post_update is not None:  # the estimate from the post-update's belief
        kernel.estimate_after = True
        kernel.omit(kept)
    elif request.estimate:
        kernel.omit(kept, estimate=True)
    elif request.keep is not None:
        kernel.omit(frozenset(StepOutput._fields) - request.keep)

    def run():
        return run_steps(kernel, belief0, request)

    run.kernel = kernel  # (for tests and profiling)
    return run


def run_steps(kernel: Any, belief0, request: kernels.Request) -> tuple:
    """A planned kernel's whole run: its steps from ``belief0`` (a progress bar where asked), each
    output detached and recorded as ``request`` says, stacked (:func:`stack_batch_first`). After step 0
    the kernel stops building what a record function dropped."""
    state = kernel.initial_state(belief0)
    record, detach = request.record, request.detach_belief
    steps = range(len(kernel.data))
    if request.progress:
        from tqdm.auto import tqdm

        steps = tqdm(steps, desc=request.progress if isinstance(request.progress, str) else None, leave=False)
    kept = []
    for k in steps:
        state, out = kernel.step(state, None)
        if detach and out.belief is not None:
            out = out._replace(belief=out.belief.detach())
        kept.append(out if record is None else record(out))
        if k == 0 and record is not None and isinstance(kept[0], StepOutput):
            # what the record drops need not be built
            kernel.omit(kernel.omitted | frozenset(
                f for f in StepOutput._fields if getattr(kept[0], f) is None and getattr(out, f) is not None))
    return stack_batch_first(kept)


def stack_batch_first(outputs: list) -> tuple:
    """The steps' outputs (batch-first views of batch-last tensors) stacked on a new time axis, each
    field in its own memory order (a contiguous copy instead of a transposing gather): batch-first
    *views* of batch-last memory, full records as estimates. A further batch-first copy of the full
    record (2026-12-03 to 12-04) doubled a 40,000-run IMM's full-record run (14 -> 30 ms a step: 16
    transposing copies) to make the two-filter smoother that reads it 7 % faster
    (benchmarks/engine_throughput.py, docs/performance.md)."""
    return tuple(kernels.stack_steps(outputs, stack=_stack_in_memory_order))


def _stack_in_memory_order(tensors: list) -> Tensor:
    """``torch.stack(tensors)`` of equally permuted views, copied in their memory order (the same values
    and shape; a contiguous copy instead of a transposing gather), as a permuted view."""
    first = tensors[0]
    strides = first.stride()
    if first.is_contiguous() or first.dim() < 2 or any(t.stride() != strides for t in tensors[1:]):
        return torch.stack(tensors)
    order = sorted(range(first.dim()), key=lambda i: -strides[i])
    if not first.permute(order).is_contiguous():
        return torch.stack(tensors)
    stacked = torch.stack([t.permute(order) for t in tensors])
    inverse = [0] * first.dim()
    for position, axis in enumerate(order):
        inverse[axis] = position + 1
    return stacked.permute(0, *inverse)


#: why a batch-last kernel declines a per-run transition ``(*B, M, M)`` (its interaction reads one matrix)
PER_RUN_TRANSITION = "a per-run transition (*B, M, M): the kernel's interaction takes one (M, M)"


def why_not(model, M: int, belief0, measurements) -> str | None:
    """Why a run of the linear-Gaussian description ``model`` (:class:`~torchmm.kernels.linear.LinearGaussian`
    of an IMM or GPB1 over ``M`` Kalman modes) cannot run on this kernel (a short reason), or None if it can.

    Shapes and types only, plus one look at ``R``'s off-diagonal values (the entry point's value
    check, once per run). The reasons: a per-run transition ``(*B, M, M)``; model parameters batched beyond
    ``()`` or ``(M,)``; a
    non-diagonal ``R``, or one of ``m > 1`` components that requires grad (the kernel reads its diagonal
    only, so the off-diagonal entries' gradient would be 0) unless it is a ``torch.diag_embed`` output
    (whose backward drops that gradient anyway); a belief that is not the ``ModeBelief`` of Gaussians of
    ``initial_belief``;
    measurements that are not one tensor ``(T, *B, m)`` of the belief's dtype and device.
    """
    m, n = model.H.shape[-2], model.F.shape[-1]
    if model.transition.dim() != 2:
        return PER_RUN_TRANSITION
    events = (2, 1, 2, 2, 2)
    if any(tuple(t.shape[:t.dim() - e]) not in {(), (1,), (M,)} for t, e in zip(model[:5], events)):
        return "model parameters batched over more than the modes"
    if not isinstance(belief0, ModeBelief) or type(belief0.components) is not GaussianBelief:
        return "belief0 is not a ModeBelief of Gaussians"
    if not isinstance(measurements, Tensor) or not measurements.is_floating_point():
        return "the measurements are not one floating-point tensor"
    batch = belief0.mode_log_probs.shape[:-1]
    if measurements.dim() != len(batch) + 2 or measurements.shape[1:] != (*batch, m):
        return "the measurements' batch differs from belief0's"
    if measurements.dtype != belief0.mode_log_probs.dtype:
        return "the measurements' dtype differs from belief0's"
    if measurements.device != belief0.mode_log_probs.device:
        return "the measurements' device differs from belief0's"
    if belief0.components.mean.shape[-2:] != (M, n):
        return "belief0's components are not (*B, M, n)"
    if model.transition.dtype != belief0.mode_log_probs.dtype:
        return "the transition matrix's dtype differs from belief0's"
    R = model.R
    if m > 1 and bool((R - torch.diag_embed(R.diagonal(dim1=-2, dim2=-1))).abs().amax() > 0):  # once per run
        return "R is not diagonal"
    diag_embedded = type(R.grad_fn).__name__ == "DiagEmbedBackward0"
    if m > 1 and R.requires_grad and torch.is_grad_enabled() and not diag_embedded:
        # the update reads R's diagonal only: the gradient of its off-diagonal entries would be 0, not the
        # log-likelihood's (tests/multimodel/test_batch_last.py). A diag_embed output (the "log_diagonal"
        # parametrisation) drops that adjoint in its own backward, so it keeps the kernel.
        return "R requires grad (the diagonal update gives no gradient for its off-diagonal entries)"
    return None

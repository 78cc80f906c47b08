"""The small linear-Gaussian kernel's run on NumPy arrays (split from :mod:`torchmm.kernels.linear` by concern, issue
47): the compiled loops' namespace (:func:`load`), the inputs' layout and arrays, the forward call, and the run as
one autograd node (:class:`Run`, its gradient the hand-written reverse pass); :mod:`torchmm.kernels.linear` plans
runs and makes their trajectories."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["NoGrad", "Run", "all_broadcast", "as_array", "broadcasts", "by_run", "finfo", "forward_arrays",
           "input_terms",
           "kernel_arrays", "layout_of", "load", "model_tensors", "unbroadcast"]


def load():
    """The compiled loops (imports Numba; the first call on a machine compiles them, ~10 s, cached): the
    forward pass (:mod:`~torchmm.kernels.linear_loops`), its reverse pass (:mod:`~torchmm.kernels.linear_reverse`)
    and Kim's smoother (:mod:`~torchmm.kernels.linear_kim`), over the step functions they share
    (:mod:`~torchmm.kernels.loop_algebra`), as one namespace."""
    global _LOOPS
    if _LOOPS is None:
        from types import SimpleNamespace

        from torchmm.kernels import linear_kim, linear_loops, linear_reverse

        _LOOPS = SimpleNamespace(forward=linear_loops.forward, backward=linear_reverse.backward, kim=linear_kim.kim,
                                 filter_and_kim=linear_kim.filter_and_kim, log_matrix=linear_kim.log_matrix)
    return _LOOPS


_LOOPS = None


def as_array(t: Tensor):
    """A NumPy view of a CPU tensor (a contiguous copy where it is not contiguous)."""
    t = t.detach()
    return (t if t.is_contiguous() else t.contiguous()).numpy()


def unbroadcast(g, shape: tuple):
    """The adjoint of ``np.broadcast_to(a, g.shape)`` for ``a`` of ``shape``: ``g`` summed over the
    broadcast axes."""
    lead = g.ndim - len(shape)
    if lead:
        g = g.sum(axis=tuple(range(lead)))
    axes = tuple(i for i, (have, want) in enumerate(zip(g.shape, shape)) if want == 1 and have != 1)
    return g.sum(axis=axes, keepdims=True) if axes else g


class Run(torch.autograd.Function):
    """The whole run: inputs the models and the start belief as given (broadcast and reshaped to the
    kernel's layout in NumPy, so that autograd records one node); outputs ``ll``, ``logmu``, ``x``,
    ``P`` (differentiable) and, with ``full``, the
    intermediates ``xp, Pp, logc, xm, Pm, innov, S, mode_ll, flags`` (not differentiable).

    ``layout``: for each of the ten inputs ``F, b, Q, H, R, Pi, logmu0, x0, P0, bu``, the shape it is
    broadcast to and the kernel's shape of that (``(M, n, n)``, ..., ``(B, M, n, n)``; ``bu``: the
    input terms ``G u_t``, ``(T, runs, M, n)``, or ``(1, 1, M, n)`` zeros without controls). ``status``: a
    one-element list that receives the count of failed or regularised updates. The buffers are
    NumPy arrays (cheaper to make than tensors); the outputs are tensors over them."""

    @staticmethod
    def forward(ctx, z, rule, update_first, full, layout, status, *tensors):
        inputs = kernel_arrays(z, tensors, layout)
        outs, bad, regularised = forward_arrays(inputs, rule, update_first)
        ctx.arrays = (inputs, outs[1:9])
        ctx.rule, ctx.update_first, ctx.layout = rule, update_first, layout
        ctx.raw = [(t.shape, t.requires_grad) for t in tensors]
        status[0] = bad + regularised  # (the count of failed or regularised updates, for the caller)
        result = [torch.from_numpy(o) for o in outs[:4]]
        extra = [torch.from_numpy(o) for o in outs[4:]] if full else []
        if extra:
            ctx.mark_non_differentiable(*extra)
        return (*result, *extra)

    @staticmethod
    def backward(ctx, gll, glogmu, gx, gP, *unused):
        loops = load()
        inputs, saved = ctx.arrays
        z = inputs[0]
        T, B = z.shape[0], z.shape[1]
        grads = [np.zeros(a.shape, a.dtype) for a in inputs[1:]]
        adjoints = []
        for g, ref in zip((gll, glogmu, gx, gP), ((T, B), *(s.shape for s in saved[:3]))):
            adjoints.append(np.zeros(ref, z.dtype) if g is None else as_array(g))
        tiny = finfo(z.dtype)[1]
        loops.backward(*inputs[:7], ctx.rule, ctx.update_first, *inputs[7:], tiny, *saved, *adjoints, *grads)
        out = []
        for g, (shape, needed), (wide, target) in zip(grads, ctx.raw, ctx.layout):
            if not needed:
                out.append(None)
                continue
            if g.size == math.prod(shape):  # (only unit axes differ: a view)
                out.append(torch.from_numpy(g.reshape(tuple(shape))))
                continue
            g = unbroadcast(g.reshape(wide), tuple(shape))
            out.append(torch.from_numpy(np.ascontiguousarray(g)).reshape(shape))
        return (None, None, None, None, None, None, *out)


def kernel_arrays(z: Tensor, tensors, layout) -> list:
    """The kernel's NumPy inputs: the data ``z (T, runs, m)`` and each tensor broadcast and reshaped to its
    layout's kernel shape (views where only unit axes differ)."""
    inputs = [as_array(z)]
    for t, (wide, target) in zip(tensors, layout):
        a = (t.detach() if t.requires_grad else t).numpy()  # (strided where the tensor is: one copy below)
        if a.shape != target:
            if a.size == math.prod(target):  # (only unit axes differ)
                a = a.reshape(target)
            else:
                a = np.broadcast_to(a, wide).reshape(target)
        inputs.append(a if a.flags.c_contiguous else np.ascontiguousarray(a))
    return inputs


def forward_arrays(inputs: list, rule: int, update_first: bool) -> tuple[list, int, int]:
    """The compiled forward loop on :func:`_arrays`' inputs: its thirteen NumPy outputs (``ll, logmu, x,
    P``, then the intermediates) and the counts of failed and regularised updates."""
    zz = inputs[0]
    T, B, m = zz.shape
    M, n = inputs[1].shape[0], inputs[1].shape[1]
    dt = zz.dtype
    empty = np.empty
    outs = [empty((T, B), dt), empty((T, B, M), dt), empty((T, B, M, n), dt), empty((T, B, M, n, n), dt),
            empty((T, B, M, n), dt), empty((T, B, M, n, n), dt), empty((T, B, M), dt), empty((T, B, M, n), dt),
            empty((T, B, M, n, n), dt), empty((T, B, M, m), dt), empty((T, B, M, m, m), dt),
            empty((T, B, M), dt), empty((T, B, M), np.int8)]
    bad, regularised = load().forward(*inputs[:7], rule, update_first, *inputs[7:], *finfo(dt), *outs)
    return outs, bad, regularised


_FINFO: dict = {}


def finfo(dtype) -> tuple[float, float]:
    """``(eps, tiny)`` of a NumPy dtype (``np.finfo`` costs microseconds; read once a dtype)."""
    got = _FINFO.get(dtype)
    if got is None:
        finfo = np.finfo(dtype)
        got = _FINFO[dtype] = (float(finfo.eps), float(finfo.tiny))
    return got


class NoGrad:
    """The context of :meth:`Run.forward` called directly, where no input needs a gradient: the autograd
    node (about 20 microseconds of the one-shot call) is not made."""

    def mark_non_differentiable(self, *tensors):
        pass


def layout_of(M: int, n: int, m: int, batch: tuple, kalman: bool, steps: int | None = None,
            varying: int | None = None, per_run: bool = False) -> tuple:
    """``Run``'s layout (see there) of a run of ``M`` modes over the batch ``batch`` (``steps``: with
    an input matrix's controls, the run's steps; ``varying``: with a time-varying transition, the run's
    steps: a transition matrix for each step and run; ``per_run``: a transition ``(*B', M, M)`` whose batch
    broadcasts to ``batch``, one matrix a run, ``(1, runs, M, M)``)."""
    runs = math.prod(batch)
    inputs = ((((steps, runs, M, n),) * 2),) if steps is not None else ((((1, 1, M, n),) * 2),)
    if varying is not None:
        pi = ((varying, runs, M, M),) * 2
    elif per_run:
        pi = ((*batch, M, M), (1, runs, M, M))
    else:
        pi = ((1, 1, M, M),) * 2
    models = (((M, n, n),) * 2, ((M, n),) * 2, ((M, n, n),) * 2, ((M, m, n),) * 2, ((M, m, m),) * 2, pi)
    if kalman:
        start = (((runs, 1), (runs, 1)), ((*batch, n), (runs, 1, n)), ((*batch, n, n), (runs, 1, n, n)))
    else:
        start = (((*batch, M), (runs, M)), ((*batch, M, n), (runs, M, n)), ((*batch, M, n, n), (runs, M, n, n)))
    return (*models, *start, *inputs)


def input_terms(model: Any, controls: Tensor | None, M: int, n: int, batch: tuple) -> Tensor:
    """``bu``: each step's, run's and mode's input term ``G_j u_t`` ``(T, runs, M, n)`` (differentiable in
    ``G`` and the controls, by torch), or zeros ``(1, 1, M, n)`` without controls."""
    if controls is None or model.G is None:
        return model.F.new_zeros(1, 1, M, n)
    G = model.G.expand(M, n, model.G.shape[-1]) if model.G.dim() == 3 else model.G.expand(M, *model.G.shape)
    return torch.einsum("jnk,trk->trjn", G, by_run(controls, batch))


def by_run(controls: Tensor, batch: tuple) -> Tensor:
    """The controls ``(T, *B', k)``, whose batch ``B'`` broadcasts to ``batch`` (shared by the runs:
    ``(T, k)``, ``(T, 1, k)``, as the eager steps take them), as ``(T, runs, k)``."""
    T, k = controls.shape[0], controls.shape[-1]
    lead = len(batch) - (controls.dim() - 2)
    if lead:  # (the batch axes the controls lack, in front of theirs: NumPy's rule)
        controls = controls.reshape(T, *((1,) * lead), *controls.shape[1:])
    return controls.expand(T, *batch, k).reshape(T, math.prod(batch), k)


def broadcasts(shape: tuple, wide: tuple) -> bool:
    """Whether a tensor of ``shape`` broadcasts to ``wide`` (NumPy's rules)."""
    if len(shape) > len(wide):
        return False
    return all(have in (1, want) for have, want in zip(reversed(shape), reversed(wide)))


def all_broadcast(shapes: list, layout: tuple) -> bool:
    """Whether every shape broadcasts to its layout's wide shape (:func:`_broadcasts`, in one loop)."""
    for shape, (wide, _) in zip(shapes, layout):
        if len(shape) > len(wide):
            return False
        for have, want in zip(reversed(shape), reversed(wide)):
            if have != 1 and have != want:
                return False
    return True


def model_tensors(model: Any, controls: Tensor | None = None, batch: tuple = ()) -> tuple:
    """The model tensors as the filter gave them (``Run`` broadcasts them), and the transition matrix
    (``[[1]]`` for one filter; a time-varying transition's ``(T, runs, M, M)`` at the run's controls,
    computed by torch so that its gradient is autograd's)."""
    if model.time_varying is not None:
        u = by_run(controls, batch)
        return model.F, model.b, model.Q, model.H, model.R, model.time_varying.at(u).log_matrix().exp()
    Pi = model.transition
    if Pi is None:
        Pi = _ONE.get(model.F.dtype)
        if Pi is None:
            Pi = _ONE[model.F.dtype] = torch.ones(1, 1, dtype=model.F.dtype)
    return model.F, model.b, model.Q, model.H, model.R, Pi


_ONE: dict = {}  # the one-mode transition matrix [[1]] per dtype (never written: no grad, no in-place)

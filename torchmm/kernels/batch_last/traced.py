"""The batch-last IMM step as a ``torch.fx`` graph (split from :mod:`torchmm.kernels.batch_last.imm` by concern,
issue 47): once a structure of the kernel (sizes, layout, kept outputs, which model entries are 0, 1, shared or
per mode) has run ``_TRACE_AFTER`` = 1,000 steps in a process, its steps run as a graph of
:meth:`~torchmm.kernels.batch_last.imm.BatchLastIMM.core` - the same torch operations in the same order (the
same numbers, bit for bit) without the Python that builds them, 10-20 % faster a step; the graphs are cached by
structure with the model constants as their inputs (docs/performance.md)."""

from __future__ import annotations

import copy
import itertools
import threading
from collections import OrderedDict

import torch

from torchmm.kernels.batch_last.algebra import Coef

__all__ = ["bound", "constants", "select", "structure", "trace"]

#: the step as a ``torch.fx`` graph of :meth:`BatchLastIMM.core` (straight-line torch calls, no
#: Python logic; the same operations in the same order, so the same numbers), cached by the kernel's
#: structure (:func:`structure`) with every model constant an input of the graph
_TRACED: OrderedDict = OrderedDict()
#: how many structures the cache keeps (least recently used dropped)
_TRACED_MAX = 64
#: the steps each structure has run untraced in this process; tracing (13-44 ms) pays after about 1,000
#: (docs/performance.md: 10-20 % of a step, 45 us at 400 runs to 2.6 ms at 40,000)
_STEPS_SEEN: dict = {}
_TRACE_AFTER = 1000
_TRACE_LOCK = threading.Lock()
#: the linear bank's model coefficients (nested lists of Coef), the kernel's and the bank's tensor constants, in
#: the graph's input order
_COEFFICIENTS = ("F", "Q", "b", "H", "r")
_CONSTANTS = ("matrix", "tiny_t", "lowest", "zero")
_BANK_CONSTANTS = ("tiny_t", "log_2pi", "R_front")


def structure(kernel) -> tuple:
    """What the step's sequence of operations depends on: the kernel (IMM/GPB1 or GPB2), the sizes,
    the layout, the interaction, the omitted outputs, the dtype's smallest normal number and the
    kind of every model coefficient (zero, one, a shared scalar, a tensor). Two kernels of one
    structure run the same operations on their own constants (:func:`constants`)."""
    kinds = lambda c: tuple(map(kinds, c)) if isinstance(c, list) else c.kind  # noqa: E731
    return (kernel.kind, kernel.n, kernel.m, kernel.M, kernel.d, kernel.broadcast, kernel.collapse, kernel.omitted,
            kernel.estimate_only, kernel.tiny, *(kinds(getattr(kernel.bank, name)) for name in _COEFFICIENTS))


def constants(kernel) -> tuple:
    """Every tensor the kernel's ``core`` reads besides its arguments: its bank's coefficients that are not exactly
    0 or 1, then the transition matrix and the 0-dim constants (the traced step's first input)."""
    out = []

    def walk(c):
        if isinstance(c, list):
            for item in c:
                walk(item)
        elif c.kind in ("scalar", "tensor"):
            out.append(c.value)

    for name in _COEFFICIENTS:
        walk(getattr(kernel.bank, name))
    return (*out, *(getattr(kernel, name) for name in _CONSTANTS),
            *(getattr(kernel.bank, name) for name in _BANK_CONSTANTS))


def bound(kernel, values):
    """A shallow copy of the kernel (and of its bank) that reads its :func:`constants` from ``values`` (the
    graph's input while tracing)."""
    clone, index = copy.copy(kernel), itertools.count()
    clone.bank = bank = copy.copy(kernel.bank)

    def swap(c):
        if isinstance(c, list):
            return [swap(item) for item in c]
        return c if c.kind in ("zero", "one") else Coef(c.kind, values[next(index)])

    for name in _COEFFICIENTS:
        setattr(bank, name, swap(getattr(kernel.bank, name)))
    for name in _CONSTANTS:
        setattr(clone, name, values[next(index)])
    for name in _BANK_CONSTANTS:
        setattr(bank, name, values[next(index)])
    return clone


def trace(kernel) -> torch.fx.GraphModule:
    """The kernel's ``core`` as a ``torch.fx`` graph ``(constants, X, P, mu, zc, ob, nhob, anyob, zraw)`` (the
    arguments of ``core`` after :func:`constants`). It holds no tensor of the kernel: every constant is an
    input, so a graph serves every kernel of the same :func:`structure`."""
    def step(constants, X, P, mu, zc, ob, nhob, anyob, zraw):
        return bound(kernel, constants).core(X, P, mu, zc, ob, nhob, anyob, zraw)

    graph = torch.fx.symbolic_trace(step)
    held = [node.target for node in graph.graph.nodes if node.op == "get_attr"]
    if held:  # a constant read around constants(): a cached graph would use the kernel's values
        raise RuntimeError(f"the traced IMM step holds tensors {held}: add them to constants()")
    return graph


def select(kernel) -> None:
    """Run the steps to come on the traced graph of the kernel's structure where the cache holds
    one, or once the structure has run ``_TRACE_AFTER`` steps untraced in this process (what is
    left of this run counted); on its ``core`` otherwise."""
    if kernel._compiled or not hasattr(kernel, "data"):
        return
    remaining = len(kernel.data) - kernel._steps_done
    with _TRACE_LOCK:
        if kernel._key in _STEPS_SEEN:  # the steps counted for the previous structure run on this one
            _STEPS_SEEN[kernel._key] -= remaining
        key, kernel._key = structure(kernel), None
        graph = _TRACED.get(key)
        if graph is None:
            if len(_STEPS_SEEN) > 4 * _TRACED_MAX:  # bounded: counts of structures long unused go
                _STEPS_SEEN.clear()
            _STEPS_SEEN[key] = _STEPS_SEEN.get(key, 0) + remaining
            if _STEPS_SEEN[key] >= _TRACE_AFTER:
                graph = _TRACED[key] = trace(kernel)
                del _STEPS_SEEN[key]
                while len(_TRACED) > _TRACED_MAX:
                    _TRACED.popitem(last=False)
            else:
                kernel._key = key
        else:
            _TRACED.move_to_end(key)
    if graph is None:
        kernel._core = kernel.core
    else:
        forward, values = graph.forward, constants(kernel)
        kernel._core = lambda *args: forward(values, *args)

r"""Kernels: the one seam through which a filter gets speed (docs/architecture.md, "Kernels").

A *kernel* runs a whole filter run - every step - in a form faster than the filter's eager steps (one
compiled loop, a fused layout), and returns what the steps return, to rounding. :func:`~torchmm.run_filter`
(and so :func:`~torchmm.learn.negative_log_likelihood`, the :class:`~torchmm.learn.Trainer` and the
studies) asks :func:`plan` for one before it steps; where none applies the eager steps run, which are
correct everywhere.

Two halves meet here, and neither names the other's classes:

* a **filter joins** a kernel family with the class decorator :func:`joins` and describes itself
  through a capability method (the linear-Gaussian family: ``filter.linear_gaussian()``, the model
  matrices and the interaction rule, or the reason it has none). A subclass that overrides ``step``,
  ``predict`` or ``update`` has left the family (its steps are no longer the ones the kernel computes)
  until it joins again;
* a **kernel registers** with :func:`register`: ``kernel.plan(filter, belief0, measurements, request)``
  returns a callable that runs the whole trajectory, or a string saying why not.

Some kernels replace *stages inside a step* instead of the whole run: the multiple-model particle
filter's fused passes (:mod:`torchmm.kernels.particle`, name ``"particle_stages"``), asked for from the
particle step between its random draws. They meet the filter the same way (the filter joins the
``"linear_particles"`` family and describes its models), and are switched on and off by the same
:func:`set_enabled` and :func:`switched_off`.

The engine (``run.py``, ``multimodel/``) tests no concrete filter class to find speed
(tests/test_layering.py checks it).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import torch
import torch.utils._pytree as pytree

from torchmm.contract import Flag, Invalid, Kind, entry_point
from torchmm.validation import broadcast_shape

__all__ = ["EAGER", "TABLE", "Choice", "Request", "by_size", "choose", "counting", "describe", "enabled", "joined", "joins",
           "names", "count_run", "plan", "plan_smooth", "register", "registered", "set_enabled", "stack_steps",
           "switched_off", "switched_on", "table"]

_KERNELS: list = []
#: family -> {class: {method name: function}}: the steps each joining class computes
_JOINED: dict[str, dict[type, dict[str, Any]]] = {}
_METHODS = ("step", "predict", "update")


def joins(family: str, methods: tuple[str, ...] = _METHODS) -> Callable[[type], type]:
    """Class decorator: ``cls`` (and its subclasses that keep its ``methods``, by default ``step``,
    ``predict`` and ``update``: the computation the family's kernels replace) joins the kernel
    ``family`` (e.g. ``"linear_gaussian"``)."""

    def decorate(cls: type) -> type:
        _JOINED.setdefault(family, {})[cls] = {name: getattr(cls, name, None) for name in methods}
        _JOINED_BY_TYPE.clear()
        return cls

    return decorate


def joined(filter: Any, family: str) -> bool:
    """Whether ``filter`` belongs to the kernel ``family``: an instance of a joining class whose steps
    are that class's own."""
    kind = type(filter)
    known = _JOINED_BY_TYPE.get((kind, family))
    if known is None:
        known = _JOINED_BY_TYPE[(kind, family)] = any(
            issubclass(kind, cls) and all(getattr(kind, name, None) is fn for name, fn in methods.items())
            for cls, methods in _JOINED.get(family, {}).items())
    return known


#: joined()'s answers by (class, family): a class's methods are fixed once defined (cleared when a class joins)
_JOINED_BY_TYPE: dict = {}


def describe(filter: Any, family: str, *, inputs: bool = False) -> Any:
    """``filter``'s description of itself for the kernel ``family`` (its method of that name, e.g.
    ``filter.linear_gaussian()``), or the reason there is none: the filter has no such method, has not
    joined the family, or overrides the steps of the class that joined. A description with an input
    matrix (``G``: a motion with controls) or a time-varying transition (``time_varying``: matrices from
    the controls) is given only to a kernel that takes controls (``inputs=True``)."""
    method = getattr(filter, family, None)
    if method is None or not joined(filter, family):
        return f"{type(filter).__name__} has not joined the {family} kernels (or overrides their steps)"
    model = method()
    if not inputs and getattr(model, "G", None) is not None:
        return "the motion has a control input (input_matrix): this kernel takes none"
    if not inputs and getattr(model, "time_varying", None) is not None:
        return "a time-varying transition (it reads each step's controls): this kernel takes none"
    return model


@dataclass(frozen=True)
class Request:
    """What a run asks of a kernel.

    Attributes:
        update_first: step 0 is an update only (:func:`~torchmm.run_filter`).
        keep: the :class:`~torchmm.filters.StepOutput` fields kept (None: all of them).
        estimate: keep the point estimate (``belief.estimate()``) instead of the belief.
        detach_belief: the kept belief is detached from the autograd graph.
        compile: compile the kernel's step (``torch.compile``), where it has one.
        compile_required: the caller asked for the compiled step (``compile=True``): a kernel without
            one declines.
        forced: ``fast_path=True``: the caller wants a kernel even where it would not pay.
        progress: a progress bar over the steps (True or its description), for kernels that step.
        record: the caller's record function, applied to every step's output (None: ``keep`` says
            what is kept); a whole-run kernel that cannot apply it declines.
        generator: the run's random-number generator (``run_filter(generator=)``), for a filter's
            own per-step work that draws (a variable-structure policy's ``post_update``).
        controls: the run's inputs ``(T, *B, k)`` (``run_filter(controls=)``), or None; only kernels
            with ``takes_controls = True`` are asked (the others decline).
        repeated: the run is one of many evaluations of a likelihood (an optimiser's:
            :class:`~torchmm.learn.Objective`): the plan is a *prepared* evaluation,
            ``prepared(belief0, update_first) -> log_likelihood (T, *B)`` or None (the steps must run),
            checked once; one-off costs (loading Numba) pay back. Kernels without one decline.
    """

    update_first: bool = False
    keep: frozenset | None = None
    estimate: bool = False
    detach_belief: bool = False
    compile: bool = False
    compile_required: bool = False
    forced: bool = False
    repeated: bool = False
    progress: bool | str = False
    record: Callable | None = None
    generator: torch.Generator | None = None
    controls: torch.Tensor | None = None


_OFF: set = set()


#: kernels of stages inside a step (no plan; they ask enabled(name) themselves)
_STAGES = ("particle_stages", "assignment_loops")


def numba_available() -> bool:
    """Whether Numba can be imported (without importing it: it takes about 0.2 s), for the compiled
    kernels and stages."""
    import sys

    if "numba" in sys.modules:
        return True
    try:
        import importlib.util

        return importlib.util.find_spec("numba") is not None
    except (ImportError, ValueError):  # pragma: no cover
        return False


def names() -> list[str]:
    """The names :func:`set_enabled` knows: the registered kernels' and the stage kernels'."""
    return [kernel.name for kernel in registered()] + list(_STAGES)


class KernelName(Kind):
    """The kind of a kernel-name parameter (torchmm.contract): a string among :func:`names` (known
    when the call is made: a kernel registered later is one). Anything else is refused naming the
    parameter and listing the kernels: a ``TypeError`` for a non-string, a ``ValueError`` for an
    unknown name (before: ``enabled("bogus")`` said True)."""

    def describe(self):
        return "a kernel name"

    def check(self, value, name):
        known = names()
        if not isinstance(value, str):
            raise TypeError(f"{name}: expected a kernel name (a string), got {value!r}; the kernels are {known}")
        if value not in known:
            raise ValueError(f"{name}: no kernel named {value!r}; the kernels are {known}")
        return value

    def invalid(self, valid):
        return [Invalid("value", "no-such-kernel"), Invalid("value", ""), Invalid("type", 1)]


@entry_point(name=KernelName(), enabled=Flag())
def set_enabled(name: str, enabled: bool = True) -> None:
    """Switch the kernel ``name`` (one of :func:`names`) on or off for this process (off: :func:`plan`
    passes it over, ``fast_path=True`` included; a stage kernel's filter takes its eager passes). The
    study harness switches the small linear-Gaussian kernel off: its choice depends on the number of
    runs, and a study's numbers must not depend on how its runs are split into units
    (experiments/run.py, experiments/executors.py; :func:`by_size`).

    ``enabled`` is a bool (``"no"`` or ``0`` is a ``TypeError`` naming it); an unknown ``name`` is a
    ``ValueError`` naming it and listing the kernels."""
    if enabled:
        _OFF.discard(name)
    else:
        _OFF.add(name)


def switched_off(*names: str):
    """``with switched_off("linear_gaussian"): ...``: :func:`set_enabled` off inside for every kernel
    named, restored after. Every name is checked first (``names[i]: no kernel named ...``, nothing
    switched)."""
    return _switched(names, off=True)


def switched_on(*names: str):
    """``with switched_on(*by_size()): ...``: :func:`set_enabled` on inside for every kernel named, restored
    after (a study's one-off whole-data work, such as its maximum-likelihood fit, which no split into
    units can change). Every name is checked first (``names[i]: ...``, nothing switched)."""
    return _switched(names, off=False)


@contextlib.contextmanager
def _switched(names: tuple, off: bool):
    for i, name in enumerate(names):
        _NAME.check(name, f"names[{i}]")
    changed = {name for name in names if (name in _OFF) != off}  # (those this block switches: restored after)
    (_OFF.update if off else _OFF.difference_update)(changed)
    try:
        yield
    finally:
        (_OFF.difference_update if off else _OFF.update)(changed)


def by_size() -> list[str]:
    """The names of the registered kernels that a run takes or not by its number of runs (``by_size =
    True``: the small linear-Gaussian kernel, the nonlinear banks' batch-last kernel). The study
    harness switches them off (:func:`switched_off`): a study's numbers must not depend on how its runs
    are split into units (experiments/run.py, experiments/executors.py)."""
    _load()
    return [kernel.name for kernel in _KERNELS if getattr(kernel, "by_size", False)]


_NAME = KernelName()


@entry_point(name=KernelName())
def enabled(name: str) -> bool:
    """Whether the kernel ``name`` (one of :func:`names`; else a ``ValueError`` naming it) is switched
    on (:func:`set_enabled`). A stage kernel asks inside its filter's step through
    ``torchmm.contract.unchecked(enabled)``: its own name needs no check there."""
    return name not in _OFF


def register(kernel: Any, *, first: bool = False) -> Any:
    """Add ``kernel`` (an object with ``name`` and ``plan(filter, belief0, measurements, request)``) to
    the kernels :func:`plan` tries, after the others (``first=True``: before them); :data:`TABLE`'s
    own are registered by the table."""
    _load()
    if first:
        _KERNELS.insert(0, kernel)
    else:
        _KERNELS.append(kernel)
    return kernel


def registered() -> list:
    """The registered kernels, in the order :func:`plan` tries them."""
    _load()
    return list(_KERNELS)


#: the name a run's record gives the eager steps (no kernel ran)
EAGER = "eager steps"


class Choice(NamedTuple):
    """:func:`choose`'s answer: ``run`` (the plan, None where no kernel applies), the ``kernel``'s
    registered name (:data:`EAGER` where none applies) and why the kernels before it, or all of them,
    declined (``"name: reason; ..."``)."""

    run: Callable | None
    kernel: str
    declined: str


def choose(filter: Any, belief0: Any, measurements: Any, request: Request) -> Choice:
    """The first registered kernel that takes this run, in :func:`registered`'s order, with the reasons
    of those before it that declined (the record :func:`~torchmm.run_filter` keeps in the trajectory's
    provenance: ``trajectory.provenance.kernel`` and ``.declined``). A ``forced`` request (``fast_path=True``)
    takes the kernel the same run would take unforced, where one would; only where none would are the
    kernels asked again to run where they would not pay (the serial Numba loop past its ``MAX_RUNS``, a
    batch below ``MIN_BATCH``)."""
    if request.forced:
        unforced = choose(filter, belief0, measurements, replace(request, forced=False))
        if unforced.run is not None:
            return unforced
    _load()
    reasons = []
    for kernel in _KERNELS:
        if kernel.name in _OFF:
            reasons.append(f"{kernel.name}: switched off (torchmm.kernels.set_enabled)")
            continue
        if request.controls is not None and not getattr(kernel, "takes_controls", False):
            reasons.append(f"{kernel.name}: controls (the eager steps take them)")
            continue
        out = kernel.plan(filter, belief0, measurements, request)
        if not isinstance(out, str):
            return Choice(out, kernel.name, "; ".join(reasons))
        reasons.append(f"{kernel.name}: {out}")
    return Choice(None, EAGER, "; ".join(reasons) or "no kernel registered")


def plan(filter: Any, belief0: Any, measurements: Any, request: Request) -> tuple[Callable | None, str]:
    """The first registered kernel's plan for this run: ``(run, "")`` where ``run()`` returns the
    trajectory's fields ``(belief, prior, log_likelihood, innovation, innovation_cov, extras)``
    (stacked on a leading time axis, None where not kept), or ``(None, reasons)`` (:func:`choose` says
    which kernel it is)."""
    choice = choose(filter, belief0, measurements, request)
    return (choice.run, "") if choice.run is not None else (None, choice.declined)


_COUNTERS: list = []


@contextlib.contextmanager
def counting():
    """Count the runs of :func:`~torchmm.run_filter` by the kernel that computed them (``{name: runs}``,
    :data:`EAGER` for the eager steps) while the block runs, in this process: what a study's results
    record (results.json's ``provenance.kernels``). Nested blocks each count.

    Examples:
        >>> with counting() as runs:
        ...     pass  # run_filter(...) calls here
        >>> dict(runs)
        {}
    """
    counts: dict = {}
    _COUNTERS.append(counts)
    try:
        yield counts
    finally:
        _COUNTERS.remove(counts)


def count_run(kernel: str) -> None:
    """Add one run computed by ``kernel`` to every open :func:`counting` block (run_filter calls it)."""
    for counts in _COUNTERS:
        counts[kernel] = counts.get(kernel, 0) + 1


def plan_smooth(filter: Any, trajectory: Any, method: str | None, **inputs: Any) -> tuple[Callable | None, str]:
    """The first registered kernel's plan for smoothing ``trajectory`` (the run of ``filter``) with
    ``method`` (None: the filter's default smoother): ``(run, "")`` where ``run()`` returns the smoothed
    beliefs (batch ``(T, *B)``) or None (declined at run time), or ``(None, reasons)``. ``inputs``: what
    the method reads besides the run, checked by :func:`~torchmm.smooth` (the two-filter smoother's
    ``measurements (T, *B, m)`` and prior mode log-probabilities ``prior_log (T, [*B,] M)``), and
    ``padding (T, *B)`` bool where some run ends before ``T`` (True at the steps after its last one, which
    keep their filtered beliefs; ``ends``: the steps at which some run ends, a set): only kernels with
    ``smooths_padding = True`` are offered a padded run."""
    _load()
    reasons = []
    padded = inputs.get("padding") is not None
    for kernel in _KERNELS:
        if kernel.name in _OFF:
            continue
        if padded and not getattr(kernel, "smooths_padding", False):
            reasons.append(f"{kernel.name}: runs that end before the last step (padding)")
            continue
        planner = getattr(kernel, "plan_smooth", None)
        out = f"{kernel.name}: no smoother" if planner is None else planner(filter, trajectory, method, **inputs)
        if not isinstance(out, str):
            return out, ""
        reasons.append(out)
    return None, "; ".join(reasons) or "no kernel registered"


def stack_steps(outputs: list, stack: Callable | None = None) -> Any:
    """Stack a list of equally structured pytrees (e.g. StepOutputs) along a new leading axis
    (``torchmm.run.stack_outputs``; kernels that step use it too). ``stack``: how one leaf's column
    (a list of tensors of one shape) is stacked, default ``torch.stack``."""
    flat, structures = [], []
    for output in outputs:  # pytree.tree_flatten's leaves, without its per-node work at every step
        leaves, structure = [], []
        _flatten(output, leaves, structure)
        flat.append(leaves)
        structures.append(structure)
    if any(s != structures[0] for s in structures[1:]):
        raise ValueError("outputs: step outputs differ in structure between time steps")
    spec = pytree.tree_structure(outputs[0])
    if spec.num_leaves != len(flat[0]):  # a node type this flattening does not know as pytree does
        flat = [pytree.tree_leaves(o) for o in outputs]
    leaves = []
    for column in zip(*flat):
        if column[0] is None:
            leaves.append(None)
            continue
        shape = broadcast_shape(*(t.shape for t in column))
        leaves.append((stack or torch.stack)([t.expand(shape) for t in column]))
    return pytree.tree_unflatten(leaves, spec)


_NODES: dict = {}


def _node(cls: type) -> Any:
    """pytree's node (flatten function) for instances of ``cls``, or None for a leaf (cached)."""
    try:
        return _NODES[cls]
    except KeyError:
        key = pytree.namedtuple if cls not in pytree.SUPPORTED_NODES and pytree.is_namedtuple_class(cls) else cls
        node = _NODES[cls] = pytree.SUPPORTED_NODES.get(key)
        return node


def _flatten(tree: Any, leaves: list, structure: list) -> None:
    """Append ``tree``'s leaves to ``leaves`` in ``pytree.tree_flatten``'s order, and a description
    of its nodes (type, context, number of children; for a leaf, whether it is None) to ``structure``."""
    node = _node(type(tree))
    if node is None:
        leaves.append(tree)
        structure.append(tree is None)  # a field that is None at one step and not at another differs
        return
    children, context = node.flatten_fn(tree)
    structure.append((type(tree), context, len(children)))
    for child in children:
        _flatten(child, leaves, structure)


#: Every whole-run kernel, in the order :func:`plan` tries them (the first that takes a run computes it),
#: each with the module constants that decide which runs it takes (:func:`table` reads their values):
#: ``(name, module, instance, thresholds)``. No kernel registers itself when its module is imported:
#: this table registers them, on first use (:func:`registered`, :func:`plan`). A kernel of one's own
#: is added with :func:`register` (after these; ``first=True``: before them).
TABLE = (
    ("linear_gaussian", "torchmm.kernels.linear", "LINEAR", ("MAX_RUNS", "LONG_RUN")),
    ("batch_last", "torchmm.kernels.batch_last.imm", "BATCH_LAST", ("MAX_STATE",)),
    ("batch_last_transfer", "torchmm.kernels.batch_last.transfer", "TRANSFER", ("MAX_STATE",)),
    ("batch_last_transfer_large", "torchmm.kernels.batch_last.transfer", "TRANSFER_LARGE",
     ("MAX_STATE", "LARGE_STATE", "LARGE_BATCH")),
    ("batch_last_nonlinear", "torchmm.kernels.batch_last.nonlinear", "NONLINEAR", ("MIN_BATCH",)),
    ("batch_last_smooth_large", "torchmm.kernels.batch_last.smooth", "LARGE_SMOOTHER", ("LARGE_STATE", "LARGE_BATCH")),
)


def table() -> list[tuple[str, str, dict]]:
    """:data:`TABLE` as it stands: ``(name, module, {threshold: value})`` in the order tried (the
    thresholds as the kernel's module holds them now)."""
    import importlib

    out = []
    for name, module, _, thresholds in TABLE:
        mod = importlib.import_module(module)
        out.append((name, module, {key: getattr(mod, key) for key in thresholds}))
    return out


def _load() -> None:
    """Register :data:`TABLE`'s kernels (once, before any registered with :func:`register`)."""
    if _LOADED:
        return
    _LOADED.append(True)
    import importlib

    builtin = []
    for name, module, instance, _ in TABLE:
        kernel = getattr(importlib.import_module(module), instance)
        if kernel.name != name:  # (the table and the kernel agree on its name)
            raise RuntimeError(f"torchmm.kernels.TABLE: {module}.{instance} is named {kernel.name!r}, not {name!r}")
        builtin.append(kernel)
    _KERNELS[:0] = builtin  # (register() loads the table first: nothing is registered before it)


_LOADED: list = []

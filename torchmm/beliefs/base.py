"""Shared machinery of belief value objects: batch-shape bookkeeping and tensor mapping.

A belief is a frozen dataclass of tensors. Each tensor field has a number of *event* dimensions on
the right (``mean``: 1, ``cov``: 2, ...); everything to their left is the batch shape, shared by all
fields. Fields may also be beliefs themselves (the per-mode components of a :class:`ModeBelief`),
in which case their batch has one extra axis on the right (the mode axis).

Batch operations (``reshape``, ``expand``, indexing, ``stack``...) are written once here in terms of
:meth:`Belief.map_tensors`, so a new belief type only declares its event dimensions.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import ClassVar, TypeVar

import torch
import torch.utils._pytree as pytree
from torch import Tensor

from torchmm.unchanged import Unchanged
from torchmm.validation import all_finite, broadcast_shape

__all__ = ["Belief", "register_belief", "stack", "cat", "where"]

#: the beliefs that passed validate() and are unchanged since (Belief.validate_once)
_VALIDATED = Unchanged()

B = TypeVar("B", bound="Belief")


def register_belief(cls: type[B]) -> type[B]:
    """Register a belief dataclass as a pytree node (for ``tree_map``, ``vmap``, ``torch.compile``).

    ``torch.utils._pytree`` is semi-private; this is the one place torchmm touches it.
    """
    pytree.register_dataclass(cls)
    return cls



_FIELDS: dict[type, tuple[str, ...]] = {}


def _field_names(cls: type) -> tuple[str, ...]:
    """The dataclass fields of a belief class (cached: ``dataclasses.fields`` costs microseconds)."""
    try:
        return _FIELDS[cls]
    except KeyError:
        names = _FIELDS[cls] = tuple(f.name for f in dataclasses.fields(cls))
        return names

class Belief:
    """Mixin for belief dataclasses. Subclasses set ``event_dims = {field: n_event_dims}``.

    Fields not listed in ``event_dims`` must be beliefs whose batch is this belief's batch plus one
    trailing axis (see :class:`~torchmm.beliefs.ModeBelief`).
    """

    event_dims: ClassVar[dict[str, int]] = {}
    #: tensor fields whose finiteness a subclass's own ``validate`` checks (the same message): the base skips them
    finite_checked_by_subclass: ClassVar[tuple[str, ...]] = ()

    # -- the protocol combinators use (docs/architecture.md) --------------------------------------
    # estimate() -> GaussianBelief (*B,): the point estimate and its covariance (moments).
    # mix(weights (*B, K, J)) -> batch (*B, J): mixtures over batch axis -1 (IMM interaction).
    # collapse(weights (*B, K)) -> batch (*B,): the mixture over batch axis -1 as one belief.
    # Belief types that cannot mix (e.g. a belief with per-run adaptive noise) leave mix/collapse
    # out; the combinators that need them then fail with a TypeError naming the belief type.
    def estimate(self):
        """Point estimate and covariance as a :class:`~torchmm.beliefs.GaussianBelief`, batch ``(*B,)``."""
        raise TypeError(f"{type(self).__name__} does not define estimate()")

    def mix(self: B, weights: Tensor) -> B:
        """Mixtures over batch axis -1, one per column of ``weights`` ``(*B, K, J)`` -> batch ``(*B, J)``."""
        raise TypeError(f"{type(self).__name__} does not define mix(); it cannot be a mode filter's belief in an "
                        "interacting (mixing) combinator")

    def collapse(self: B, weights: Tensor) -> B:
        """The mixture over batch axis -1 with ``weights`` ``(*B, K)`` as one belief, batch ``(*B,)``."""
        return self.mix(weights.unsqueeze(-1)).select(-1, 0)

    # -- generic mapping ------------------------------------------------------------------------
    def map_tensors(self: B, fn: Callable[[Tensor, int], Tensor]) -> B:
        """Return a copy with ``fn(tensor, n_event_dims)`` applied to every tensor field."""
        values = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name in self.event_dims:
                values[field.name] = fn(value, self.event_dims[field.name])
            elif isinstance(value, Belief):
                values[field.name] = value.map_tensors(lambda t, e: fn(t, e + 1))
            else:
                values[field.name] = value
        return type(self)(**values)

    def _tensors(self) -> list[tuple[Tensor, int]]:
        """``(tensor, event dims)`` of every tensor field, nested beliefs' too, in :meth:`map_tensors`'
        order (without building a copy: this is read at every step)."""
        out: list[tuple[Tensor, int]] = []
        if type(self).map_tensors is not Belief.map_tensors:  # (its own map: its own event axes)
            self.map_tensors(lambda t, e: out.append((t, e)) or t)
            return out
        events = self.event_dims
        for name in _field_names(type(self)):
            value = getattr(self, name)
            if name in events:
                out.append((value, events[name]))
            elif isinstance(value, Belief):
                out.extend((t, e + 1) for t, e in value._tensors())
        return out

    # -- shape ------------------------------------------------------------------------------------
    @property
    def batch_shape(self) -> torch.Size:
        """Broadcast batch shape of all fields (``ValueError`` if they do not broadcast)."""
        shapes = [t.shape[: t.dim() - e] for t, e in self._tensors()]
        try:
            return broadcast_shape(*shapes)
        except RuntimeError:
            raise ValueError(f"{type(self).__name__}: batch shapes of the fields do not broadcast: "
                             f"{[tuple(s) for s in shapes]}") from None

    # -- values (entry points only) ---------------------------------------------------------------
    def validate(self: B, name: str = "belief") -> B:
        """Check the belief's values once, at an entry point; return it unchanged.

        The base check: every tensor field finite, the batch shapes broadcast; subclasses add what
        their fields mean (PSD covariances, normalised probabilities, ...). Reads tensor values
        (a device synchronisation), so filters call it in ``initial_belief`` and
        :func:`~torchmm.run_filter` calls it on ``belief0``, never inside a step.

        Raises:
            ValueError: naming ``name`` and the offending field, e.g. ``belief0.cov``.
        """
        try:
            self.batch_shape
        except ValueError as err:
            raise ValueError(f"{name}: {err}") from None
        for field in _field_names(type(self)):
            value = getattr(self, field)
            if isinstance(value, Belief):
                value.validate(f"{name}.{field}")
            elif isinstance(value, Tensor) and value.is_floating_point():
                if field not in self.finite_checked_by_subclass and not all_finite(value):
                    raise ValueError(f"{name}.{field}: contains NaN or infinite entries")
        return self

    def validate_once(self: B, name: str = "belief") -> B:
        """:meth:`validate`, skipped for this very belief when it passed before and none of its tensors has
        changed since (:class:`~torchmm.unchanged.Unchanged`; a change through ``.data`` or a NumPy view
        is not seen, as for autograd): an entry point called again with the same start (a loop of
        :func:`~torchmm.run_filter` calls, an objective) reads its values once. Returns the belief."""
        def checked() -> bool:
            self.validate(name)
            return True

        _VALIDATED.remember((self, *(t for t, _ in self._tensors())), checked)
        return self

    @property
    def batch_dim(self) -> int:
        return len(self.batch_shape)

    @property
    def dtype(self) -> torch.dtype:
        return self._tensors()[0][0].dtype

    @property
    def device(self) -> torch.device:
        return self._tensors()[0][0].device

    # -- batch operations ---------------------------------------------------------------------
    def reshape(self: B, *shape: int) -> B:
        """Reshape the batch dimensions: ``(*batch, ...) -> (*shape, ...)``."""
        shape = _shape_arg(shape)
        return self.map_tensors(lambda t, e: t.reshape(*shape, *t.shape[t.dim() - e :]))

    def expand(self: B, *shape: int) -> B:
        """Broadcast the batch dimensions to ``shape`` (views, no copy)."""
        shape = _shape_arg(shape)
        return self.map_tensors(lambda t, e: t.expand(*shape, *t.shape[t.dim() - e :]))

    def unsqueeze(self: B, dim: int) -> B:
        """Insert a batch axis of size 1 at batch position ``dim`` (negative counts from the right)."""
        return self.map_tensors(lambda t, e: t.unsqueeze(_batch_axis(dim, e)))

    def select(self: B, dim: int, index: int) -> B:
        """Index batch axis ``dim`` (negative counts from the right end of the batch shape)."""
        return self.map_tensors(lambda t, e: t.select(_batch_axis(dim, e), index))

    def transpose_batch(self: B, dim0: int, dim1: int) -> B:
        """Swap two batch axes (negative axes count from the right end of the batch shape)."""
        return self.map_tensors(lambda t, e: t.transpose(_batch_axis(dim0, e), _batch_axis(dim1, e)))

    def __getitem__(self: B, index) -> B:
        """Index the leading batch dimensions (ints, slices, tensors; no Ellipsis)."""
        if index is Ellipsis or (isinstance(index, tuple) and Ellipsis in index):
            raise IndexError("belief indexing applies to leading batch dims; Ellipsis is not supported")
        shape = self.batch_shape  # (a field broadcast over the batch is expanded first: a view)
        return self.map_tensors(lambda t, e: t.expand(*shape, *t.shape[t.dim() - e:])[index])

    def to(self: B, *args, **kwargs) -> B:
        """``Tensor.to`` on every field (device and/or dtype)."""
        return self.map_tensors(lambda t, e: t.to(*args, **kwargs))

    def detach(self: B) -> B:
        return self.map_tensors(lambda t, e: t.detach())

    def materialize(self: B) -> B:
        """Expand every field to the full batch shape (contiguous copies)."""
        shape = self.batch_shape
        return self.map_tensors(lambda t, e: t.expand(*shape, *t.shape[t.dim() - e :]).contiguous())


def _shape_arg(shape) -> tuple[int, ...]:
    if len(shape) == 1 and isinstance(shape[0], (tuple, list, torch.Size)):
        return tuple(shape[0])
    return tuple(shape)


def _batch_axis(dim: int, event_ndim: int) -> int:
    """Translate a batch-relative axis to a tensor axis (negative axes skip the event dims).

    Valid for indexing, ``select``, ``unsqueeze`` and ``stack``: batch axis ``-1`` of a field with
    ``e`` event dims is tensor axis ``-1 - e`` in each case.
    """
    return dim if dim >= 0 else dim - event_ndim


def _same_type(beliefs: list, what: str) -> None:
    kinds = sorted({type(b).__name__ for b in beliefs})
    if len(kinds) > 1:
        raise TypeError(f"beliefs: cannot {what} beliefs of different types {kinds} (e.g. the modes of one "
                        "bank: mode filters must share a belief type; use Gaussian or particle filters "
                        "throughout)")
    shapes = {tuple(t.shape[t.dim() - e:]) for b in beliefs for t, e in b._tensors()[:1]}
    if len(shapes) > 1:
        raise ValueError(f"beliefs: cannot {what} beliefs whose event shapes differ: {sorted(shapes)}")


def stack(beliefs: Sequence[B], dim: int = 0) -> B:
    """Stack beliefs of equal batch shape along a new batch axis ``dim``."""
    beliefs = list(beliefs)
    if not beliefs:
        raise ValueError("beliefs: cannot stack an empty sequence")
    _same_type(beliefs, "stack")
    shape = broadcast_shape(*(b.batch_shape for b in beliefs))
    flat = [pytree.tree_flatten(b.expand(shape))[0] for b in beliefs]
    spec = pytree.tree_flatten(beliefs[0])[1]
    events = [e for _, e in beliefs[0]._tensors()]
    leaves = [torch.stack(ts, _batch_axis(dim, e)) for ts, e in zip(zip(*flat), events)]
    return pytree.tree_unflatten(leaves, spec)


def cat(beliefs: Sequence[B], dim: int = 0) -> B:
    """Concatenate beliefs along an existing batch axis ``dim``."""
    beliefs = list(beliefs)
    if not beliefs:
        raise ValueError("beliefs: cannot concatenate an empty sequence")
    _same_type(beliefs, "concatenate")
    flat = [pytree.tree_flatten(b.materialize())[0] for b in beliefs]
    spec = pytree.tree_flatten(beliefs[0])[1]
    events = [e for _, e in beliefs[0]._tensors()]
    leaves = [torch.cat(ts, _batch_axis(dim, e)) for ts, e in zip(zip(*flat), events)]
    return pytree.tree_unflatten(leaves, spec)


def where(condition: Tensor, a: B, b: B) -> B:
    """Per batch element, ``a`` where ``condition`` holds and ``b`` elsewhere (same belief type).

    Shapes:
        condition: bool, broadcastable to the beliefs' batch ``(*B,)`` (right-aligned);
        a, b: beliefs of one type and broadcastable batches -> batch ``(*B,)``
    """
    if type(a) is not type(b):
        raise TypeError(f"where: beliefs of different types {type(a).__name__} and {type(b).__name__}")
    fields = getattr(type(a), "event_dims", {})
    if fields and len(fields) == len(dataclasses.fields(a)):  # flat beliefs (Gaussian, particle): direct
        values = {name: torch.where(condition.reshape(*condition.shape, *(1,) * e), getattr(a, name), getattr(b, name))
                  for name, e in fields.items()}
        return type(a)(**values)
    leaves_a, spec = pytree.tree_flatten(a)
    leaves_b, spec_b = pytree.tree_flatten(b)
    if spec != spec_b:
        raise ValueError("where: the two beliefs differ in structure")
    events = [e for _, e in a._tensors()]
    out = [torch.where(condition.reshape(*condition.shape, *(1,) * e), x, y)
           for x, y, e in zip(leaves_a, leaves_b, events)]
    return pytree.tree_unflatten(out, spec)

"""What made a trajectory: the record that :func:`~torchmm.run_filter` (and
:func:`torchmm.parallel.filter`) attach to their :class:`~torchmm.run.Trajectory`, so that the next
function (:func:`~torchmm.smooth`) checks its arguments against the run instead of trusting them.

A :class:`Provenance` holds the filter, the per-step models, the controls and a reference to the
measurements, with a *fingerprint* of the data streams (shape, dtype, device and checksums: the
float64 sums of the finite entries, of their magnitudes, and the same weighted by the flat index, so
that a permutation - ``z.flip(0)``, two runs swapped - changes it). The fingerprints of all streams
are taken in one pass and read by the host once, at the run's entry (the same read that counts the
infinite entries). Nothing is checked per step.

A record does not survive ``pickle`` or ``copy.deepcopy`` (an unpickled filter is another object),
nor a ``torch.utils._pytree`` map over it: a trajectory derived that way carries none, and is
smoothed as given.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np
import torch
import torch.utils._pytree as pytree
from torch import Tensor

from torchmm.unchanged import Unchanged
from torchmm.validation import host_array, module_tensors

__all__ = ["Fingerprint", "Provenance", "fingerprints", "module_state", "note_infinite", "tensor_versions"]

log = logging.getLogger("torchmm")

#: checksums of the same values summed again (another memory layout, another reduction order) agree
#: to this, relative to the sum of the magnitudes
CHECKSUM_RTOL = 1e-9


@dataclasses.dataclass(frozen=True)
class Fingerprint:
    """One data stream, cheaply: ``shape``, ``dtype``, ``device`` and checksums (float64):
    ``count`` finite entries, their ``total`` and ``magnitude`` (sum of ``|z|``), the same weighted by
    ``w_i = (i + 1) / N`` over the flat (row-major) index ``i`` (``weighted``, ``weighted_magnitude``),
    and ``where`` = the sum of ``i + 1`` over the finite entries (the pattern of missing data; exact)."""

    shape: tuple
    dtype: torch.dtype
    device: torch.device
    count: float = 0.0
    total: float = 0.0
    magnitude: float = 0.0
    weighted: float = 0.0
    weighted_magnitude: float = 0.0
    where: float = 0.0

    def differs(self, other: Fingerprint) -> str | None:
        """Why ``other`` (the same stream fingerprinted again?) is not this one, or None."""
        if other.shape != self.shape:
            return f"shape {other.shape} differs from {self.shape}"
        if other.dtype != self.dtype:
            return f"dtype {other.dtype} differs from {self.dtype}"
        if other.device != self.device:
            return f"device {other.device} differs from {self.device}"
        if other.count != self.count or other.where != self.where:
            return "the missing (non-finite) entries differ"
        for value, scale in (("total", "magnitude"), ("weighted", "weighted_magnitude")):
            tol = CHECKSUM_RTOL * max(getattr(self, scale), getattr(other, scale))
            if abs(getattr(other, value) - getattr(self, value)) > tol or \
                    abs(getattr(other, scale) - getattr(self, scale)) > tol:
                return "the values differ (checksum)"
        return None


#: entries per block of the fingerprint's pass: its temporaries stay in the cache (and bounded in
#: memory) however large the data (a pass over 8e7 entries took 3 GB and 5.3 s unblocked)
_BLOCK = 1 << 18


def _stats(t: Tensor) -> Tensor:
    """``(infinite, count, total, magnitude, weighted, weighted_magnitude, where)`` of ``t``, float64.

    One pass in blocks of :data:`_BLOCK` entries (a loop over memory at entry, never per step; no
    host read: the caller reads all streams' sums at once)."""
    x = t.detach().reshape(-1)
    if x.is_complex():
        x = torch.view_as_real(x).reshape(-1)
    n = x.numel()
    sums = torch.zeros(6, dtype=torch.float64, device=x.device)
    where = torch.zeros((), dtype=torch.int64, device=x.device)  # exact (integers)
    for start in range(0, n, _BLOCK):
        block = x[start:start + _BLOCK].to(torch.float64)
        finite = torch.isfinite(block)
        index = torch.arange(start + 1, start + block.numel() + 1, dtype=torch.float64, device=x.device)
        value = torch.where(finite, block, 0.0)
        size = value.abs()
        count = finite.sum()
        infinite = torch.isinf(block).sum() if t.is_floating_point() else torch.zeros_like(count)
        sums += torch.stack([infinite.to(torch.float64), count.to(torch.float64), value.sum(), size.sum(),
                             value @ index, size @ index])
        where += (finite.to(torch.int64) * torch.arange(start + 1, start + block.numel() + 1,
                                                         device=x.device)).sum()
    sums[4:6] /= max(n, 1)  # w_i = (i + 1) / N
    return torch.cat([sums, where.to(torch.float64).reshape(1)])


def _stats_numpy(t: Tensor) -> list | None:
    """:func:`_stats` of a small CPU floating tensor, in NumPy (a few microseconds where torch's small
    operations cost a hundred: the one-shot call's fixed cost, issue 47); None for any other tensor."""
    array = host_array(t)
    if array is None:
        return None
    x = array.reshape(-1).astype(np.float64)
    n = x.size
    finite = np.isfinite(x)
    count = int(np.count_nonzero(finite))
    if count == n:  # every entry finite (the usual case): the same numbers in fewer passes
        value, infinite, where = x, 0.0, float(n * (n + 1) // 2)
    else:
        value = np.where(finite, x, 0.0)
        infinite = float(np.isinf(x).sum())
        where = float(int(np.flatnonzero(finite).sum()) + count)  # sum of (i + 1) over finite i
    size = np.abs(value)
    index = np.arange(1, n + 1, dtype=np.float64)
    return [infinite, float(count), float(value.sum()), float(size.sum()), float(value @ index) / max(n, 1),
            float(size @ index) / max(n, 1), where]


#: each tensor's statistics while it is unchanged (a run called again on the same data reads it once)
_STATS = Unchanged()


def note_infinite(count: int, name: str) -> None:
    """Say (a warning of the ``torchmm`` logger) that ``count`` infinite entries of the data ``name`` are taken as
    missing (non-finite = missing, docs/robustness.md), where there are any: one line per entry point."""
    if count:
        log.warning("%s: %d infinite entries are treated as missing data (non-finite = missing, see "
                    "docs/robustness.md)", name, count)


def fingerprints(*streams: Any) -> tuple[list, list]:
    """The fingerprints of every tensor leaf of each of ``streams`` (pytrees of tensors, or None), and
    the number of infinite floating entries of each: one host read for all.

    Returns:
        ``([tuple of Fingerprint per stream, or None], [infinite entries per stream])``.
    """
    leaves = [None if s is None else [s] if isinstance(s, Tensor) else pytree.tree_leaves(s) for s in streams]
    flat = [t for ls in leaves if ls is not None for t in ls]
    values: list = [None] * len(flat)
    for i, t in enumerate(flat):  # the same data as before (the same tensor, unchanged): its statistics, else
        values[i] = _STATS.remember((t,), lambda t=t: _stats_numpy(t))  # (small CPU tensors: in NumPy)
    if None in values:  # the others in torch
        by_device: dict = {}
        for i, t in enumerate(flat):
            by_device.setdefault(t.device, []).append(i)
        for device, index in by_device.items():  # one read per device (one in practice)
            index = [i for i in index if values[i] is None]
            if not index:
                continue
            rows = torch.stack([_stats(flat[i]) for i in index]).tolist()
            for i, row in zip(index, rows):
                values[i] = _STATS.put((flat[i],), row)
    out, k, infinite = [], 0, []
    for ls in leaves:
        infinite.append(0)
        if ls is None:
            out.append(None)
            continue
        prints = []
        for t in ls:
            inf, *rest = values[k]
            k += 1
            infinite[-1] += int(inf)
            prints.append(Fingerprint(tuple(t.shape), t.dtype, t.device, *rest))
        out.append(tuple(prints))
    return out, infinite


def tensor_versions(tree: Any) -> tuple | None:
    """``(id, version)`` of every tensor leaf of ``tree`` (in-place changes bump a tensor's version);
    None where a tensor has no version counter (made under ``torch.inference_mode``)."""
    out = []
    for t in (tree,) if isinstance(tree, Tensor) else pytree.tree_leaves(tree):
        if isinstance(t, Tensor):
            try:
                out.append((id(t), t._version))
            except RuntimeError:  # inference tensors track no version
                return None
    return tuple(out)


def module_state(module: Any, tensors: list | None = None) -> tuple:
    """``(name, id, version)`` of a module's parameters and buffers: equal as long as none of them is
    replaced or changed in place (an optimiser step, ``copy_``, ``load_state_dict``). ``tensors``:
    :func:`~torchmm.validation.module_tensors`' list of them, where the caller has it (the versions are
    read now)."""
    if not isinstance(module, torch.nn.Module):
        return ()
    out = []
    for name, t in module_tensors(module) if tensors is None else tensors:
        try:
            version = t._version
        except RuntimeError:
            version = None
        out.append((name, id(t), version))
    return tuple(out)


def _dropped() -> None:
    return None


@dataclasses.dataclass(frozen=True, eq=False)
class Provenance:
    """What made a :class:`~torchmm.run.Trajectory` (``trajectory.provenance``).

    Attributes:
        made_by: ``"run_filter"`` or ``"torchmm.parallel.filter"``.
        filter: the filter that ran (the object itself).
        steps: the number of time steps ``T``.
        measurements: the measurements given (a reference; ``smooth(trajectory)`` uses them).
        data: their :class:`Fingerprint` per tensor leaf, taken at the run's entry.
        data_versions: the leaves' version counters then (an in-place change bumps them), or None.
        controls, control_data, control_versions: likewise for ``controls`` (None: no controls).
        motions, sensors: the per-step models given (a sequence, a callable or None), as given.
        update_first: as given.
        belief, prior: the trajectory's own fields as the run returned them (a trajectory whose
            fields are other objects - reversed, sliced, replaced - is refused by ``smooth``).
        state: :func:`module_state` of the filter at the end of the run.
        kernel: which computed the run: a registered kernel's name (:func:`torchmm.kernels.registered`)
            or ``"eager steps"``.
        declined: why the kernels tried before it (all of them, for the eager steps) declined,
            ``"name: reason; ..."`` (``""``: the first one took it).
    """

    made_by: str
    filter: Any
    steps: int
    measurements: Any
    data: tuple
    data_versions: tuple | None
    controls: Tensor | None = None
    control_data: tuple | None = None
    control_versions: tuple | None = None
    motions: Any = None
    sensors: Any = None
    update_first: bool = False
    belief: Any = None
    prior: Any = None
    state: tuple = ()
    kernel: str = "eager steps"
    declined: str = ""

    def __reduce__(self):
        return (_dropped, ())  # an unpickled (or deep-copied) trajectory carries no record

    def __repr__(self) -> str:
        return (f"Provenance(made_by={self.made_by!r}, filter={type(self.filter).__name__}, "
                f"steps={self.steps}, kernel={self.kernel!r})")


# a pytree map over a trajectory's fields gives data no run made: the record maps to None
pytree.register_pytree_node(Provenance, lambda p: ([], None), lambda children, context: None)

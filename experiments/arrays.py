"""Per-run arrays: a unit's per-run values (:func:`per_run`), joined or added across units in run order
(:func:`join_runs`, :func:`add_runs`), simulation outputs joined along the runs (:func:`cat_runs`), and
their place in the checkpoint - ``units/<key>.npz`` with its sha256, referenced from ``checkpoint.json``
(:func:`array_refs`, :func:`load_arrays`)."""

from __future__ import annotations

import hashlib
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from experiments.files import UnitFileError, error_reason, write_atomic

# -- per-run arrays in the checkpoint ---------------------------------------------------------------
#: a unit's value may hold numpy arrays (per-run values of its runs, e.g. squared errors ``(T, runs)``):
#: they are written to ``units/<key>.npz`` (exact, binary) and ``checkpoint.json`` holds a reference
ARRAY_REF = "__array__"


def per_run(tensor: torch.Tensor):
    """A unit's per-run values as a numpy array (exact: the same bits in any executor and on resume)."""
    return tensor.detach().cpu().numpy()


def _tensor(array: Any) -> torch.Tensor:
    """``torch.as_tensor``; a read-only numpy array (a Ray worker's result, shared zero-copy) is copied
    first, which torch would otherwise wrap with a warning that writing to it is undefined."""
    flags = getattr(array, "flags", None)
    if flags is not None and not flags.writeable:
        array = array.copy()
    return torch.as_tensor(array)


def join_runs(arrays: Sequence[Any], dim: int = 1) -> torch.Tensor:
    """Per-run values of consecutive units, in run order, as one tensor (runs on ``dim``)."""
    return torch.cat([_tensor(a) for a in arrays], dim)


def add_runs(arrays: Sequence[Any]) -> torch.Tensor:
    """Sums over the runs of consecutive units, added in run order (a single unit: its own sum)."""
    total = _tensor(arrays[0])
    for a in arrays[1:]:
        total = total + _tensor(a)
    return total


def _arrays_file(key: str) -> str:
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in key)[:80]
    return f"units/{safe}-{hashlib.sha256(key.encode()).hexdigest()[:8]}.npz"


def array_refs(key: str, value: Any, output_dir: Path) -> Any:
    """``value`` with its numpy arrays replaced by a reference to ``units/<key>.npz`` (written here)."""
    import numpy as np

    arrays: dict[str, Any] = {}

    def walk(v):
        if isinstance(v, np.ndarray):
            name = f"a{len(arrays)}"
            arrays[name] = v
            return {ARRAY_REF: name}
        if isinstance(v, dict):
            return {k: walk(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [walk(x) for x in v]
        return v

    refs = walk(value)
    if arrays:
        rel = _arrays_file(key)
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        data = buffer.getvalue()
        write_atomic(output_dir / rel, data)
        refs = {ARRAY_REF + "file": rel, "sha256": hashlib.sha256(data).hexdigest(), "value": refs}
    return refs



def load_arrays(value: Any, output_dir: Path) -> Any:
    """Inverse of :func:`array_refs`: a checkpointed value with its arrays read back. A file that
    is missing, unreadable or whose sha256 differs from the checkpoint's is a :class:`UnitFileError`."""
    import numpy as np

    if not (isinstance(value, dict) and ARRAY_REF + "file" in value):
        return value
    path = output_dir / value[ARRAY_REF + "file"]
    try:
        data = path.read_bytes()
    except OSError as err:
        raise UnitFileError(f"{path}: {error_reason(err)}") from None
    expected = value.get("sha256")
    if expected is not None and hashlib.sha256(data).hexdigest() != expected:
        raise UnitFileError(f"{path}: checksum mismatch ({len(data)} bytes; "
                            "not the file the checkpoint recorded)")
    try:
        with np.load(io.BytesIO(data)) as npz:
            # writable for torch
            arrays = {name: np.require(npz[name], requirements="W") for name in npz.files}
    except Exception as err:  # truncated or not an npz: BadZipFile, ValueError, EOFError, ...
        raise UnitFileError(f"{path}: unreadable ({type(err).__name__}: {err})") from None

    def walk(v):
        if isinstance(v, dict):
            if set(v) == {ARRAY_REF}:
                return arrays[v[ARRAY_REF]]
            return {k: walk(x) for k, x in v.items()}
        if isinstance(v, list):
            return [walk(x) for x in v]
        return v

    return walk(value["value"])



def cat_runs(parts: Sequence[Any], axes: Any = 1) -> Any:
    """Join per-block simulation outputs along the run axis.

    ``axes`` says where the runs are, with the structure of the outputs (or one value for all):
    an int (the run axis: 1 for time-major tensors ``(T, runs, ...)``, 0 for ``(runs, ...)``) or None
    (shared by all runs, e.g. per-step model matrices: the first block's value is kept).
    :class:`~torchmm.simulate.JumpSimulation` and :class:`~torchmm.fusion.FusionSimulation` know
    their own axes; named tuples, tuples and dicts are joined element-wise."""
    from torchmm.fusion import FusionSimulation
    from torchmm.simulate import JumpSimulation

    first = parts[0]
    if len(parts) == 1:
        return first
    if isinstance(axes, dict):
        return {k: cat_runs([p[k] for p in parts], axes.get(k, 1)) for k in first}
    if isinstance(first, tuple) and not isinstance(axes, (tuple, list)):
        axes = (axes,) * len(first)
    if isinstance(axes, (tuple, list)):
        joined = [cat_runs([p[i] for p in parts], axes[i]) for i in range(len(first))]
        return type(first)(*joined) if hasattr(first, "_fields") else type(first)(joined)
    if axes is None:
        return first
    if isinstance(first, torch.Tensor):
        return torch.cat(list(parts), int(axes))
    if isinstance(first, FusionSimulation):
        return FusionSimulation(*(torch.cat([getattr(p, f) for p in parts], 1) for f in ("x", "r", "y")))
    if isinstance(first, JumpSimulation):
        return JumpSimulation(torch.cat([p.states for p in parts], 1), torch.cat([p.modes for p in parts], 1),
                              torch.cat([p.initial_state for p in parts], 0),
                              torch.cat([p.initial_mode for p in parts], 0))
    raise TypeError(f"cat_runs: cannot join {type(first).__name__} along the runs (give axes=)")

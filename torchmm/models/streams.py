"""Measurement streams of several sensors at different rates (a pytree :func:`~torchmm.run_filter` indexes)."""

from __future__ import annotations

from typing import Any, NamedTuple

from torch import Tensor

__all__ = ["MultiRate", "split_streams"]


class MultiRate(NamedTuple):
    """Target and source measurement streams (a pytree: ``run_filter`` indexes both at ``k``).

    Shapes:
        target: ``(*B, m)`` per step (``(T, *B, m)`` as a sequence), NaN = missing
        source: ``(*B, m_S)`` per step, NaN where no source datum (``gamma_k = 0``)
    """

    target: Tensor
    source: Tensor


def split_streams(z: Any) -> tuple[Tensor, Tensor]:
    """``(target, source)`` of a multi-rate measurement: a :class:`MultiRate`, a pair or a dict."""
    if isinstance(z, MultiRate):
        return z.target, z.source
    if isinstance(z, dict) and {"target", "source"} <= set(z):
        return z["target"], z["source"]
    if isinstance(z, (tuple, list)) and len(z) == 2:
        return z[0], z[1]
    raise TypeError(
        "z: expected MultiRate(target, source), a (target, source) pair or a dict with keys "
        f"'target' and 'source', got {type(z).__name__}"
    )

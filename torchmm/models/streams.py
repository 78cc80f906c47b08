"""Measurement streams of several sensors at different rates (a pytree :func:`~torchmm.run_filter` indexes)."""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

__all__ = ["MultiRate"]


class MultiRate(NamedTuple):
    """Target and source measurement streams (a pytree: ``run_filter`` indexes both at ``k``).

    Shapes:
        target: ``(*B, m)`` per step (``(T, *B, m)`` as a sequence), NaN = missing
        source: ``(*B, m_S)`` per step, NaN where no source datum (``gamma_k = 0``)
    """

    target: Tensor
    source: Tensor

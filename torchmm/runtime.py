"""Process-level settings that matter for large CPU tensors.

torch's CPU allocator hands every tensor above glibc's mmap threshold (at most 32 MiB) to
``mmap`` and unmaps it when freed, so each new large temporary (a particle array of 2 million x 4
doubles is 64 MiB) costs fresh page faults: on the development machine this doubled the time of
simple elementwise ops on such arrays (``x * 2`` on 64 MiB: 32 ms vs 15 ms with reuse).
:func:`retain_freed_memory` keeps freed memory in the process heap for reuse instead. It changes
``malloc`` for the whole process (NumPy included) and cannot be undone, so torchmm never calls it
on import: the particle-filter studies (config key ``retain_freed_memory``) and
``benchmarks/pf_throughput.py`` do.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

__all__ = ["compile_fast_paths", "fast_paths_compiled", "retain_freed_memory"]

log = logging.getLogger("torchmm")

_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_DONE: list[bool] = []
_COMPILE: list[bool] = [False]


def compile_fast_paths(enabled: bool = True) -> bool:
    """Make ``compile=True`` the default of :func:`~torchmm.run_filter`'s fast paths in this
    process (the study key ``compile``); returns the previous setting.

    Compiling costs seconds per new shape (cached on disk by inductor) and then runs the fused
    step: docs/performance.md says when that pays. Runs without a fast path are not affected.
    """
    if not isinstance(enabled, bool):
        raise TypeError(f"enabled: expected True or False, got {enabled!r}")
    previous = _COMPILE[0]
    _COMPILE[0] = enabled
    return previous


def fast_paths_compiled() -> bool:
    """The process default set by :func:`compile_fast_paths` (False unless set)."""
    return _COMPILE[0]


def retain_freed_memory(trim_threshold: int = 1 << 30) -> bool:
    """Serve large allocations from the heap and keep up to ``trim_threshold`` bytes of freed
    memory for reuse (glibc ``mallopt(M_MMAP_MAX, 0)`` and ``mallopt(M_TRIM_THRESHOLD, ...)``).

    Returns True if the settings were applied, False where the C library is not glibc (nothing
    changes there). Idempotent.
    """
    if _DONE:
        return _DONE[0]
    ok = False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
        mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
        ok = bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, int(min(trim_threshold, 2**31 - 1))))
    except (OSError, AttributeError):
        ok = False
    if not ok:
        log.info("retain_freed_memory: mallopt is not available here; allocator left as it is")
    _DONE.append(ok)
    return ok

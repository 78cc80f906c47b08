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

import contextlib
import ctypes
import ctypes.util
import logging

__all__ = ["SMALL_PROBLEM", "HostSyncError", "compile_fast_paths", "fast_paths_compiled", "host_reads_ok",
           "no_host_sync", "retain_freed_memory", "thread_policy"]

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


_DEVICE_PATHS: list[bool] = [False]


def host_reads_ok(tensor) -> bool:
    """True where a step may read ``tensor``'s values on the host: a CPU tensor, whose values the
    host already holds (a branch that pays there, e.g. a faster path when no datum is missing).
    Elsewhere (CUDA) a step takes the form without the read, with the same numbers. Inside
    :func:`no_host_sync` it is False on the CPU too, so that the device form is what is checked."""
    return tensor.is_cpu and not _DEVICE_PATHS[0]


class HostSyncError(RuntimeError):
    """Raised inside :func:`no_host_sync` where the host reads tensor values."""


#: aten ops whose result the host must wait for: a value read back (item, bool, int, float), or an
#: output whose size depends on the values (nonzero, masked_select, unique, ...)
_SYNC_OPS = ("_local_scalar_dense", "nonzero", "masked_select", "unique", "_unique", "_unique2",
             "unique_consecutive", "unique_dim", "equal", "is_nonzero", "repeat_interleave", "bincount")


@contextlib.contextmanager
def no_host_sync(where: str = "this block"):
    """Raise :class:`HostSyncError` wherever the code inside reads tensor values on the host.

    The check of torchmm's rule that a filter step runs asynchronously on a GPU (no ``.item()``,
    ``bool(tensor)``, ``.tolist()``, ``.numpy()``, boolean-mask indexing or data-sized outputs), on
    any device, the CPU included: a ``TorchDispatchMode`` that refuses the aten ops above, and
    ``Tensor.tolist`` / ``numpy`` / ``__array__`` patched for the block. Inside it
    :func:`host_reads_ok` is False, so CPU tensors take the device form of every step. For tests
    and for checking one's own filter (``tests/test_host_sync.py``); it slows every op down.
    """
    import torch
    from torch.utils._python_dispatch import TorchDispatchMode

    class _Refuse(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            name = func.name().split("::")[-1].split(".")[0]
            bool_index = name == "index" and any(
                isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] if len(args) > 1 else ()))
            if name in _SYNC_OPS or bool_index:
                raise HostSyncError(f"host synchronisation in {where}: {func.name()}"
                                    + (" with a boolean mask" if bool_index else ""))
            if name == "lift_fresh":  # torch.tensor(...) of Python data, or t[i] = <Python number>
                raise HostSyncError(f"host synchronisation in {where}: a tensor made from Python data "
                                    "(torch.tensor, or a Python number assigned into a tensor) is a "
                                    "host-to-device copy on a GPU")
            return func(*args, **(kwargs or {}))

    def refuse(method):
        def raiser(self, *args, **kwargs):
            raise HostSyncError(f"host synchronisation in {where}: Tensor.{method}()")
        return raiser

    saved = {m: getattr(torch.Tensor, m) for m in ("tolist", "numpy", "__array__")}
    previous = _DEVICE_PATHS[0]
    try:
        _DEVICE_PATHS[0] = True  # host_reads_ok is False: the code takes its device (GPU) form
        for m in saved:
            setattr(torch.Tensor, m, refuse(m))
        with _Refuse():
            yield
    finally:
        _DEVICE_PATHS[0] = previous
        for m, f in saved.items():
            setattr(torch.Tensor, m, f)


# -- threads by problem size -------------------------------------------------------------------------
#: a call whose start belief holds fewer tensor entries than this runs on one thread (``thread_policy``)
SMALL_PROBLEM = 1 << 15
_THREADS: list[str] = ["auto"]


def thread_policy(policy: str | None = None) -> str:
    """The thread rule of :func:`~torchmm.run_filter`, :func:`~torchmm.smooth` and
    :meth:`~torchmm.learn.Trainer.fit`; with ``policy``, set it first. Returns the rule in force.

    * ``"auto"`` (default): a call on a small problem - a start belief (or smoothed trajectory step) of
      fewer than :data:`SMALL_PROBLEM` tensor entries, e.g. an IMM of 3 two-state modes below about
      1,800 runs, a Kalman filter below about 5,000 - runs on one thread, then torch's setting is
      restored. Such steps are dispatch-bound: a second thread never helps them, and on a busy machine
      its spinning made them 2 to 4.5 times slower (docs/performance.md, "Threads by problem size").
      Larger problems run at torch's setting (``torch.set_num_threads``).
    * ``"torch"``: always torch's setting.
    """
    if policy is not None:
        if policy not in ("auto", "torch"):
            raise ValueError(f"policy: expected 'auto' or 'torch', got {policy!r}")
        _THREADS[0] = policy
    return _THREADS[0]


def entries(tree) -> int:
    """The tensor entries of a pytree (a belief, a trajectory): the size of a step's state."""
    import torch.utils._pytree as pytree
    from torch import Tensor

    return sum(leaf.numel() for leaf in pytree.tree_leaves(tree) if isinstance(leaf, Tensor))


def one_thread_when_small(size):
    """Decorator: the call runs on one thread when ``size(*args, **kwargs)`` (tensor entries of one step's
    state) is below :data:`SMALL_PROBLEM` and the rule is ``"auto"`` (:func:`thread_policy`)."""
    import functools

    def decorate(fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            import torch

            threads = torch.get_num_threads()
            if _THREADS[0] != "auto" or threads <= 1:
                return fn(*args, **kwargs)
            try:
                small = size(*args, **kwargs) < SMALL_PROBLEM
            except Exception:  # noqa: BLE001 - a malformed argument: the call itself reports it
                small = False
            if not small:
                return fn(*args, **kwargs)
            torch.set_num_threads(1)
            try:
                return fn(*args, **kwargs)
            finally:
                torch.set_num_threads(threads)
        return wrapper
    return decorate

r"""The particle stages: fused CPU loops (Numba) for the multiple-model particle filter's passes over
its particles, behind the kernels seam (:mod:`torchmm.kernels`, name ``"particle_stages"``).

Unlike the whole-run kernels :func:`torchmm.kernels.plan` chooses, these replace *stages inside a
step* (the random numbers are drawn between them). The step asks for them the seam's way: the filter
joins the ``"linear_particles"`` family (:func:`torchmm.kernels.joins`) and describes its models with
``filter.linear_particles()`` (or says why not); the data-dependent conditions are :func:`applies`.

The eager step of :class:`~torchmm.multimodel.MultipleModelParticleFilter` makes about a dozen
memory-bound passes over its ``runs x M x Np`` particles. On CPU tensors, three of its stages run
here instead as one loop each, compiled by `Numba <https://numba.pydata.org>`_ and parallel over
the particle sets:

* :func:`two_stage_indices`: the interaction's indices for ``mixing="two_stage"`` (the systematic
  ancestor model by counting, the per-model systematic resample, the slot inside it);
* :func:`propagate_log_likelihood`: the ancestors' gather, ``F x + L eps + offset`` and the whitened
  linear-Gaussian log-likelihood of every particle;
* :func:`challenge_pass`: one pass of the challenge-match tournament.

**The same numbers.** The random numbers are drawn by torch, in the same order, before a kernel
runs; the kernels add and multiply in the order torch's kernels do (measured: ``c + x A^T`` of a
batched GEMM with ``beta = 1`` sums its products first and adds ``c`` last, an unbatched ``addmm_``
starts from ``c``; ``addcmul`` is a fused multiply-add), so on the machines we measured the
particles, weights and model sets equal the eager path's bit for bit and every particle study's
regression record is unchanged. Elsewhere (another BLAS, another vector width) they may differ in
the last bit, like the eager path itself between machines. Integer work (counting, gathers, the
tournament's comparisons) is exact everywhere.

**When they run.** CPU tensors, no autograd graph, Numba importable (a dependency of torchmm; without
it the eager path runs), and not switched off: ``torchmm.kernels.set_enabled("particle_stages",
False)``, ``with torchmm.kernels.switched_off("particle_stages")``, a study's ``cpu_kernels=false``,
or the environment variable ``TORCHMM_CPU_KERNELS=0``. The filters decide per call; nothing else
changes. The first call of
each kernel in a process compiles it (seconds; Numba caches the machine code on disk next to this
file). Threads: as many as torch uses (``torch.get_num_threads()``).
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.contract import unchecked
from torchmm.kernels.linear_run import as_array
from torchmm.runtime import host_reads_ok

log = logging.getLogger("torchmm.kernels.particle")
_ANNOUNCED: list[bool] = []

__all__ = ["NAME", "LinearParticles", "applies", "available", "challenge_pass", "enabled", "propagate_log_likelihood", "two_stage_indices"]

#: the name of the particle stages at the seam (torchmm.kernels.set_enabled, switched_off)
NAME = "particle_stages"
_NUMBA: list = []  # [module or None], imported on first use


def _numba():
    if not _NUMBA:
        try:
            import numba
        except ImportError:  # pragma: no cover - numba is a dependency; the GPU image may lack it
            numba = None
        _NUMBA.append(numba)
    return _NUMBA[0]


def available() -> bool:
    """Whether Numba can be imported here."""
    return _numba() is not None


def enabled() -> bool:
    """Whether the particle stages are on in this process: Numba importable, not switched off at the
    seam (``torchmm.kernels.set_enabled("particle_stages", False)``) nor by ``TORCHMM_CPU_KERNELS=0``."""
    if not unchecked(kernels.enabled)(NAME):  # asked inside a step: our own name needs no check
        return False
    flag = os.environ.get("TORCHMM_CPU_KERNELS", "1").strip().lower() not in ("0", "false", "no", "off")
    return flag and available()


def applies(*tensors: Tensor) -> bool:
    """Whether a kernel may run on these tensors: enabled, all on the CPU (and not inside
    :func:`~torchmm.runtime.no_host_sync`, which checks the device form), no autograd graph."""
    if not enabled():
        return False
    grad = torch.is_grad_enabled()
    return all(host_reads_ok(t) and not (grad and t.requires_grad) for t in tensors)


@dataclass(frozen=True)
class LinearParticles:
    """A particle filter's description of itself for the ``"linear_particles"`` family
    (``filter.linear_particles()``): linear-Gaussian propagation ``x' = F x + offset_i + noise(Q)`` of
    model ``i``'s particles and a linear-Gaussian measurement ``z = H x + noise(R)``, the models'
    own matrices (:func:`torchmm.models.linear.plain_linear`).

    Shapes:
        F: ``(n, n)``; offset: ``(n,)`` or ``(M, n)``; Q: ``(n, n)``; H: ``(m, n)``; R: ``(m, m)``
    """

    F: Tensor
    offset: Tensor
    Q: Tensor
    H: Tensor
    R: Tensor

    def why_not(self, particles: Tensor, z: Tensor, num_modes: int) -> str:
        """Why :func:`propagate_log_likelihood` cannot run on these particles and data ("" where it
        can): shapes, float64, unbatched matrices, and :func:`applies` (enabled, CPU, no autograd).
        Missing data is the caller's to check (it needs a host read).

        Shapes:
            particles: ``(*B, M, Np, n)``; z: ``(*B, m)``
        """
        F, H, Q, R, offset = self.F, self.H, self.Q, self.R, self.offset
        n = particles.shape[-1]
        if F.dim() != 2 or H.dim() != 2 or Q.dim() != 2 or R.dim() != 2 or F.shape != (n, n) or H.shape[-1] != n:
            return "batched model matrices"
        if offset.dim() > 2 or offset.shape[-1] != n or offset.numel() not in (n, num_modes * n):
            return "an offset batched beyond the modes"
        if particles.dim() < 3 or particles.dtype != torch.float64 or z.dtype != torch.float64:
            return "not float64 particles and data"
        if z.dim() < 1 or z.shape[-1] != H.shape[0]:
            return "data of another size"
        if not applies(particles, z, F, H, Q, R, offset):
            return "switched off, not on the CPU, or inside an autograd graph"
        return ""


def _threads() -> None:
    numba = _numba()
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))


def _kernels():
    """The loops' module (:mod:`torchmm.kernels.particle_loops`), imported on first use."""
    if not _ANNOUNCED:
        _ANNOUNCED.append(True)
        if not compiled_before():  # the first run on a machine is otherwise a minute of silence
            log.info("compiling the particle filters' fused CPU kernels (Numba, once per machine: about a "
                     "minute, then a few seconds per new problem size; cached on disk)")
    from torchmm.kernels import particle_loops

    return particle_loops


def compiled_before() -> bool:
    """Whether Numba's on-disk cache holds compiled loops of :mod:`torchmm.kernels.particle_loops`
    (``NUMBA_CACHE_DIR`` or the ``__pycache__`` beside it)."""
    custom = os.environ.get("NUMBA_CACHE_DIR")
    root = Path(custom) if custom else Path(__file__).parent / "__pycache__"
    return root.is_dir() and any(root.rglob("particle_loops.*.nbi"))


# ------------------------------------------------------------------------------------------------
# the calls
# ------------------------------------------------------------------------------------------------
def two_stage_indices(cdf_models: Tensor, u0: Tensor, weights: Tensor, v0: Tensor, num: int, *,
                      background: bool = False):
    """The ``two_stage`` interaction's flat indices ``a * Np_prev + b``, as
    :func:`~torchmm.multimodel.particle_mixing.mixing_indices` computes them with torch ops (the
    within-model CDFs of ``weights`` included).

    ``background=True`` runs the kernel in a worker thread (on one thread fewer than torch's) and
    returns a :class:`concurrent.futures.Future` of the indices: the filter draws its process
    noise meanwhile (torch's CPU generator is serial, so a core would otherwise idle).

    Shapes:
        cdf_models: ``(R, M, A)`` float64 (target ``i``, ancestor ``a``; last entry 1); u0: ``(R, M)``;
        weights: ``(R, A, P)`` float64, unnormalised, non-negative; v0: ``(R, A)`` -> ``(R, M, num)`` int64
    """
    kernel = _kernels().two_stage
    args = (as_array(cdf_models), as_array(u0), as_array(weights), as_array(v0), int(num))
    if background:
        return _pool().submit(_in_background, kernel, args)
    _threads()
    return torch.from_numpy(kernel(*args))


def _in_background(kernel, args) -> Tensor:
    numba = _numba()
    numba.set_num_threads(max(1, min(torch.get_num_threads() - 1, numba.config.NUMBA_NUM_THREADS)))  # per thread
    return torch.from_numpy(kernel(*args))


_POOL: list = []  # [(pid, executor)]


def _pool() -> ThreadPoolExecutor:
    """One worker thread for background kernels (a new one in a forked child)."""
    if not _POOL or _POOL[0][0] != os.getpid():
        _POOL[:] = [(os.getpid(), ThreadPoolExecutor(1, thread_name_prefix="torchmm-cpu-kernels"))]
    return _POOL[0][1]


def propagate_log_likelihood(table: Tensor, flat: Tensor, eps: Tensor, factor: Tensor, offset: Tensor, F: Tensor,
                             W: Tensor, shift: Tensor, const: float, *, with_nan: bool = False):
    """Gather, propagate and weigh: ``x = F table[flat] + factor eps + offset`` and
    ``-0.5 (|shift + W x|^2 + const)`` (NaN -> ``-inf``), in one pass over the particles.

    ``with_nan``: also return ``(R, M)`` bool, True where a log-likelihood of the set was NaN before
    it was mapped to ``-inf`` (non-finite particles: the filter flags the run as failed).

    Shapes:
        table: ``(R, S, n)`` float64 (the previous particles of a run); flat: ``(R, M, Np)`` int64 into
        ``S``; eps: ``(R, M, Np, k)`` (float32 or float64); factor: ``(n, k)``; offset: ``(M, n)``;
        F: ``(n, n)``; W: ``(m, n)``; shift: ``(R, m)`` -> particles ``(R, M, Np, n)``, log-likelihoods
        ``(R, M, Np)`` [, NaN flags ``(R, M)``]
    """
    R, M, Np = flat.shape
    n, k, m = table.shape[-1], factor.shape[-1], W.shape[0]
    x = torch.empty((R, M, Np, n), dtype=torch.float64)
    loglik = torch.empty((R, M, Np), dtype=torch.float64)
    nan = torch.empty((R, M), dtype=torch.bool)
    _threads()
    _kernels().propagate(*(as_array(t) for t in (table, flat, eps, factor, offset, F, W, shift)),
                         float(const), x.numpy(), loglik.numpy(), nan.numpy(), (0,) * n, (0,) * k, (0,) * m)
    return (x, loglik, nan) if with_nan else (x, loglik)


def challenge_pass(scores: Tensor, a: Tensor, b: Tensor, shifts: Tensor, num_winners: int) -> Tensor:
    """One pass of :func:`~torchmm.multimodel.challenge.challenge_match` from its random numbers.

    Sequence 1 and the pool are the random affine order ``(a j + b) mod P`` split at ``N``; holder
    ``p`` meets pool slot ``(p - shift_t) mod N`` of window ``t`` and ends as the first strict
    maximum over itself and its challengers (no winner where a challenger's score is NaN, as
    torch's ``max``).

    Shapes:
        scores: ``(R, P)``; a, b: ``(R,)`` int64; shifts: ``(rounds, R)`` int64 -> winners ``(R, N)``
    """
    _threads()
    out = _kernels().challenge(as_array(scores), as_array(a), as_array(b), as_array(shifts), int(num_winners))
    return torch.from_numpy(out)


"""Where a study's units run: in this process, a local process pool, SLURM or local jobs through
submitit, or a Ray cluster - with identical numbers (docs/scaling.md).

A study hands its work to :meth:`experiments.context.StudyContext.map_units` as :class:`Unit`\\ s:
the dotted path of a module-level function ``fn(ctx, **args)`` and JSON arguments. A unit's value
depends on the study's config and its arguments only (its random numbers come from
``ctx.generator(*key)``, seeded from ``seed`` and the key), so where it runs does not change it.

What travels to a worker is a :class:`Job`: the resolved config (a dict), the run folder and the
unit - never tensors. The worker rebuilds a study context from the config
(:func:`experiments.context.worker_context`), runs the function and sends back its JSON value; the
study's process checkpoints each value as it arrives, so a lost worker costs its unit, not the
study, and a re-run (``resume=latest``) skips every unit that arrived.

Executors (``executor=<kind>``, ``conf/executor/``):

* ``local`` - one after another in the study's process (the default; no rebuild of the context);
* ``processes`` - a local pool of ``executor.workers`` spawned processes; a worker that dies (killed,
  out of memory) breaks the pool: a new pool re-runs the units that had not arrived, up to
  ``executor.retries`` times;
* ``submitit_local`` / ``slurm`` - one submitit job per unit (a SLURM job array), logs in
  ``executor.folder`` (default ``<run folder>/submitit``); a job that ends without a result (killed,
  preempted, timed out) is resubmitted up to ``executor.retries`` times;
* ``ray`` - Ray tasks on the cluster at ``executor.address`` (or a local Ray started for the study,
  ``executor.workers`` CPUs); Ray re-runs a task whose worker died (``max_retries``).

An exception raised by a unit's own code is never retried: it is the study's error, raised in the
study's process with the worker's traceback text.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger("torchmm.experiments")

__all__ = ["Executor", "Job", "LocalExecutor", "ProcessExecutor", "RayExecutor", "SubmititExecutor", "Unit",
           "UnitError", "execute", "make_executor"]

KINDS = ("local", "processes", "submitit_local", "slurm", "ray")


@dataclass(frozen=True)
class Unit:
    """A piece of a study: ``fn`` (``"package.module:function"``, called as ``fn(ctx, **args)``) with
    JSON ``args``; ``key`` names it in ``checkpoint.json``."""

    key: str
    fn: str
    args: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Job:
    """What travels to a worker: the study's resolved config, its run folder and one unit."""

    config: dict
    output_dir: str
    unit: Unit
    #: the function that rebuilds the study context in the worker, ``context(config, output_dir)``, as
    #: ``"package.module:function"`` (resolved there like a unit's ``fn``): the executors name the study
    #: context rather than import it, which imports them (no import cycle)
    context: str = "experiments.context:worker_context"


class UnitError(RuntimeError):
    """A unit's own code raised in a worker (not retried); the message holds the worker's traceback."""


def resolve(path: str):
    """``"package.module:function"`` -> the function."""
    module, sep, name = path.partition(":")
    if not sep:
        raise ValueError(f"unit fn: expected 'package.module:function', got {path!r}")
    return getattr(importlib.import_module(module), name)


def execute(job: Job) -> Any:
    """Run one unit in a worker: rebuild the study context from the config, call the unit, return
    its JSON value. A unit's exception comes back as :class:`UnitError` (with the traceback)."""
    import traceback

    import torchmm.kernels as kernels
    from experiments.results import jsonable

    ctx = resolve(job.context)(job.config, Path(job.output_dir))
    try:
        # as run_study does around a study: no kernel whose choice depends on the number of runs
        with kernels.switched_off(*kernels.by_size()):
            return jsonable(resolve(job.unit.fn)(ctx, **job.unit.args))
    except Exception as err:  # the unit's own error: travels back as text (picklable everywhere)
        raise UnitError(f"unit {job.unit.key}: {type(err).__name__}: {err}\n{traceback.format_exc()}") from None


class Executor:
    """Runs jobs; :meth:`run` yields ``(index, value)`` as each finishes (any order)."""

    kind = "local"

    def run(self, jobs: Sequence[Job], ctx=None) -> Iterator[tuple[int, Any]]:
        raise NotImplementedError

    def close(self) -> None:
        pass


class LocalExecutor(Executor):
    """In the study's process, one after another, with the study's own context."""

    kind = "local"

    def run(self, jobs, ctx=None):
        from experiments.results import jsonable

        for index, job in enumerate(jobs):
            context = ctx if ctx is not None else resolve(job.context)(job.config, Path(job.output_dir))
            yield index, jsonable(resolve(job.unit.fn)(context, **job.unit.args))


def _init_worker(threads: int | None) -> None:
    import torch

    if threads:
        torch.set_num_threads(int(threads))


class ProcessExecutor(Executor):
    """A pool of ``workers`` spawned local processes; a broken pool (a worker died) is replaced and
    the units that had not arrived are re-run, ``retries`` times at most."""

    kind = "processes"

    def __init__(self, workers: int = 2, retries: int = 2, threads: int | None = 1):
        self.workers, self.retries, self.threads = int(workers), int(retries), threads

    def run(self, jobs, ctx=None):
        import multiprocessing
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
        from concurrent.futures.process import BrokenProcessPool

        pending = dict(enumerate(jobs))
        attempt = 0
        while pending:
            pool = ProcessPoolExecutor(max_workers=min(self.workers, len(pending)),
                                       mp_context=multiprocessing.get_context("spawn"),
                                       initializer=_init_worker, initargs=(self.threads,))
            broken = False
            try:
                futures = {pool.submit(execute, job): index for index, job in pending.items()}
                while futures:
                    done, _ = wait(futures, return_when=FIRST_COMPLETED)
                    for future in done:
                        index = futures.pop(future)
                        try:
                            value = future.result()
                        except BrokenProcessPool:
                            broken = True
                            continue
                        del pending[index]
                        yield index, value
                    if broken:
                        break
            finally:
                pool.shutdown(wait=True, cancel_futures=True)
            if broken:
                attempt += 1
                if attempt > self.retries:
                    raise RuntimeError(f"executor=processes: a worker died {attempt} times; "
                                       f"{len(pending)} units did not finish (executor.retries={self.retries})")
                log.warning("executor=processes: a worker died; re-running %d unfinished units (retry %d of %d)",
                            len(pending), attempt, self.retries)


class SubmititExecutor(Executor):
    """One submitit job per unit (``cluster="local"`` or ``"slurm"``, a job array); jobs that end
    without a result are resubmitted, ``retries`` times at most."""

    def __init__(self, cluster: str, folder: Path, retries: int = 2, parameters: dict | None = None,
                 poll_seconds: float = 0.5):
        try:
            import submitit  # noqa: F401
        except ImportError:
            raise ImportError("executor=slurm / submitit_local: needs submitit (pip install -e \".[slurm]\")") from None
        self.kind = "slurm" if cluster == "slurm" else "submitit_local"
        self.cluster, self.folder, self.retries = cluster, Path(folder), int(retries)
        self.parameters = {k: v for k, v in (parameters or {}).items() if v is not None}
        self.poll_seconds = poll_seconds

    def _executor(self):
        import submitit

        executor = submitit.AutoExecutor(folder=str(self.folder / "%j"), cluster=self.cluster)
        executor.update_parameters(**self.parameters)
        return executor

    def run(self, jobs, ctx=None):
        from submitit.core.utils import FailedJobError, UncompletedJobError

        executor = self._executor()
        tries = {i: 0 for i in range(len(jobs))}
        submitted = dict(zip(range(len(jobs)), executor.map_array(execute, list(jobs))))
        while submitted:
            finished = [i for i, job in submitted.items() if job.done()]
            if not finished:
                time.sleep(self.poll_seconds)
                continue
            for index in finished:
                job = submitted.pop(index)
                try:
                    value = job.result()
                except FailedJobError as err:  # the unit's own error (its traceback in the message)
                    raise UnitError(str(err)) from None
                except UncompletedJobError as err:  # killed, preempted, timed out: resubmit
                    tries[index] += 1
                    if tries[index] > self.retries:
                        raise RuntimeError(f"executor={self.kind}: unit {jobs[index].unit.key} did not finish "
                                           f"after {tries[index]} tries ({err})") from None
                    log.warning("executor=%s: job %s ended without a result; resubmitting unit %s",
                                self.kind, job.job_id, jobs[index].unit.key)
                    submitted[index] = executor.submit(execute, jobs[index])
                    continue
                yield index, value


class RayExecutor(Executor):
    """Ray tasks: on the cluster at ``address``, or a local Ray with ``workers`` CPUs."""

    kind = "ray"

    def __init__(self, address: str | None = None, workers: int = 2, retries: int = 2):
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ImportError("executor=ray: needs Ray (pip install -e \".[ray]\")") from None
        self.address, self.workers, self.retries = address, int(workers), int(retries)
        self._started = False

    def run(self, jobs, ctx=None):
        import ray

        if not ray.is_initialized():
            kwargs = {"address": self.address} if self.address else {"num_cpus": self.workers}
            ray.init(include_dashboard=False, log_to_driver=False, ignore_reinit_error=True, **kwargs)
            self._started = not self.address
        remote = ray.remote(max_retries=self.retries, num_cpus=1)(execute)
        refs = {remote.remote(job): index for index, job in enumerate(jobs)}
        while refs:
            done, _ = ray.wait(list(refs), num_returns=1)
            for ref in done:
                index = refs.pop(ref)
                try:
                    value = ray.get(ref)
                except ray.exceptions.RayTaskError as err:
                    raise UnitError(str(err)) from None
                yield index, value

    def close(self):
        if self._started:
            import ray

            ray.shutdown()
            self._started = False


def make_executor(cfg: dict | None, output_dir: Path, threads: int | None = 1) -> Executor:
    """The executor a config's ``executor`` node asks for (``kind`` in :data:`KINDS`)."""
    cfg = dict(cfg or {})
    kind = cfg.get("kind", "local")
    retries = int(cfg.get("retries", 2))
    if kind == "local":
        return LocalExecutor()
    if kind == "processes":
        return ProcessExecutor(int(cfg.get("workers", 2)), retries, threads)
    if kind in ("submitit_local", "slurm"):
        folder = Path(cfg.get("folder") or output_dir / "submitit")
        parameters = {"timeout_min": cfg.get("timeout_min"), "cpus_per_task": cfg.get("cpus_per_task"),
                      "mem_gb": cfg.get("mem_gb")}
        if kind == "slurm":
            parameters.update({"slurm_partition": cfg.get("partition"),
                               "slurm_array_parallelism": cfg.get("array_parallelism"),
                               **dict(cfg.get("slurm_parameters") or {})})
        return SubmititExecutor("slurm" if kind == "slurm" else "local", folder, retries, parameters)
    if kind == "ray":
        return RayExecutor(cfg.get("address"), int(cfg.get("workers", 2)), retries)
    raise ValueError(f"executor.kind: expected one of {', '.join(KINDS)}, got {kind!r}")

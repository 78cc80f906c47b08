"""The study context: what a study's ``run(ctx)`` gets (:class:`StudyContext`) - its config, dtype and
device, seeded random streams, resumable units (checkpointed in ``checkpoint.json``), its executor, figures
and progress bars - made for a run (:func:`open_context`, which picks up a checkpoint of the same config)
or rebuilt in a worker process (:func:`worker_context`)."""

from __future__ import annotations

import hashlib
import json
import logging
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from experiments.arrays import array_refs, cat_runs, load_arrays
from experiments.files import RunFolderError, UnitFileError, error_reason, remove_temporaries, write_atomic
from experiments.folders import check_code, config_hash, differing_keys, result_config, saved_run, unique_dir
from experiments.loggers import CurveRecorder, Logger, NullLogger, make_logger
from experiments.provenance import code_version
from experiments.results import Results, jsonable
from torchmm.runtime import compile_fast_paths

log = logging.getLogger("torchmm.experiments")

DTYPES = {"float64": torch.float64, "float32": torch.float32, "double": torch.float64, "float": torch.float32}


def resolve_dtype(name: str) -> torch.dtype:
    try:
        return DTYPES[str(name)]
    except KeyError:
        raise ValueError(f"dtype: expected one of {sorted(DTYPES)}, got {name!r}") from None


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device: {name!r} requested but CUDA is not available")
    return device



@dataclass
class StudyContext:
    """What a study gets: its config, where to write, and the shared services."""

    cfg: Any
    output_dir: Path
    results: Results
    logger: Logger
    dtype: torch.dtype
    device: torch.device
    seed: int
    progress: bool = True
    #: ``figures=false``: :meth:`save_figure` draws nothing (sweeps of many jobs)
    figures: bool = True
    #: in a ``-m`` sweep: the job's label on its bars (``[job 3]``) and the terminal line they keep, so
    #: parallel jobs' bars do not interleave
    bar_label: str = ""
    bar_position: int | None = None
    _checkpoint: dict = field(default_factory=dict)
    #: the checkpoint's units the study asked for again (what a resumed run really kept; a resume with another
    #: ``unit_runs`` asks for other keys and keeps none)
    reused: set = field(default_factory=set)
    #: the checkpoint as written to checkpoint.json (arrays as references to units/*.npz)
    _checkpoint_refs: dict = field(default_factory=dict)
    _config_hash: str = ""
    #: the code version the units are computed with (experiments.provenance.code_version), in checkpoint.json
    _code: dict = field(default_factory=dict)
    _result_config: dict = field(default_factory=dict)
    #: the resolved config (JSON): what travels to workers
    _config: dict = field(default_factory=dict)
    _executor: Any = None
    #: per-process memo of a study's shared inputs (e.g. simulated data of a scenario), keyed by the
    #: study; workers fill their own
    cache: dict = field(default_factory=dict)

    # -- randomness ----------------------------------------------------------------------------
    #: the dtype every study simulates its data in, whatever ``dtype`` the filters run in: float32
    #: and float64 runs of a study see the same data (float64 draws, cast down) - common random numbers
    data_dtype: torch.dtype = torch.float64

    def scenarios(self, node, **kwargs) -> tuple[Any, Any]:
        """``(scenario for the filters in ctx.dtype, the same scenario in data_dtype for simulating)``;
        one object when the two dtypes agree."""
        from hydra.utils import instantiate

        scenario = instantiate(node, dtype=self.dtype, device=self.device, **kwargs)
        if self.dtype == self.data_dtype:
            return scenario, scenario
        return scenario, instantiate(node, dtype=self.data_dtype, device=self.device, **kwargs)

    @property
    def block_runs(self) -> int:
        """Monte Carlo runs per random-number block (``block_runs``): run ``i`` draws from block
        ``i // block_runs``'s own generator, so its data depend on (seed, key, i) only."""
        return int(self.cfg.get("block_runs") or 50)

    def blocks(self, runs: int) -> list[slice]:
        """The runs ``0..runs-1`` in blocks of :attr:`block_runs` (the last one may be shorter)."""
        size = self.block_runs
        return [slice(start, min(start + size, runs)) for start in range(0, int(runs), size)]

    @property
    def unit_runs(self) -> int | None:
        """Runs per unit (``unit_runs``, a multiple of :attr:`block_runs`); None: one unit per setting."""
        value = self.cfg.get("unit_runs")
        return None if value is None else int(value)

    def run_ranges(self, runs: int) -> list[tuple[int, int]]:
        """The runs ``0..runs-1`` split into units of :attr:`unit_runs` runs: ``[(start, stop), ...]``
        (one range of all runs by default). Every start is a multiple of :attr:`block_runs`, so a unit
        holds whole random-number blocks and simulates, filters and reduces them as the whole study would."""
        runs, size = int(runs), self.unit_runs or int(runs)
        if size % self.block_runs and size < runs:
            raise ValueError(f"unit_runs: {size} is not a multiple of block_runs ({self.block_runs})")
        return [(start, min(start + size, runs)) for start in range(0, runs, size)]

    def simulate_runs(self, simulate: Callable[[int, torch.Generator], Any], runs: int, *key: Any,
                      axes: Any = 1, start: int = 0) -> Any:
        """Run-indexed random streams: ``simulate(n, generator)`` once per block of runs, with the
        generator of ``(*key, "block", b)``, and the blocks joined along the run axis (time-major
        tensors ``(T, runs, ...)``; :class:`~torchmm.simulate.JumpSimulation`; tuples of them).

        The data of run ``i`` depend on the seed, ``key`` and ``i`` only - not on ``mc_runs``, the
        chunking or which worker or machine simulates it: any split of the runs gives the same data.
        ``axes``: where the outputs hold the runs (:func:`cat_runs`). ``start`` (a multiple of
        :attr:`block_runs`): simulate runs ``start..runs-1`` only (a unit's range, :meth:`run_ranges`).
        """
        if start % self.block_runs:
            raise ValueError(f"simulate_runs: start {start} is not a multiple of block_runs ({self.block_runs})")
        stream, first = self.block_generators(*key), start // self.block_runs
        pieces = self.blocks(int(runs) - start)
        return cat_runs([simulate(b.stop - b.start, stream(first + i)) for i, b in enumerate(pieces)], axes)

    def memo(self, key: Any, compute: Callable[[], Any]) -> Any:
        """``compute()`` once per process (its value kept in :attr:`cache` under ``key``): a study's
        shared inputs, e.g. a scenario's simulated data, which every unit of a worker reuses."""
        if key not in self.cache:
            self.cache[key] = compute()
        return self.cache[key]

    def block_generators(self, *key: Any) -> Callable[[int], torch.Generator]:
        """``b -> generator of (*key, "block", b)``: a filter's random stream for block ``b`` of runs."""
        return lambda b: self.generator(*key, "block", b)

    def generator(self, *key: Any) -> torch.Generator:
        """A generator seeded from ``seed`` and ``key``: independent of the order units run in."""
        token = zlib.crc32(repr(key).encode())
        gen = torch.Generator(device=self.device)
        gen.manual_seed((self.seed * 1_000_003 + token) % (2**63 - 1))
        return gen

    # -- resumable units -----------------------------------------------------------------------
    def unit(self, key: str, compute: Callable[[], Any]) -> Any:
        """Return the cached value of ``key`` or compute, checkpoint and return it.

        ``compute`` must return JSON-serialisable data (rows, numbers, lists).
        """
        if key in self._checkpoint:
            log.info("resuming: unit %s already done", key)
            self.reused.add(key)
            return self._checkpoint[key]
        value = jsonable(compute())
        self._store(key, value)
        return value

    def map_units(self, units: Sequence[Any], desc: str = "units") -> list[Any]:
        """The values of ``units`` (:class:`experiments.executors.Unit`), in order, computed by the
        study's executor (``executor=...``) - here, in a process pool, on SLURM or Ray - with the
        same numbers everywhere. Finished units come from the checkpoint; each value is
        checkpointed as it arrives; a bar counts the units across all workers."""
        from experiments.executors import Job

        units = list(units)
        keys = [u.key for u in units]
        if len(set(keys)) != len(keys):
            raise ValueError(f"map_units: duplicate unit keys {sorted({k for k in keys if keys.count(k) > 1})}")
        todo = [u for u in units if u.key not in self._checkpoint]
        self.reused.update(k for k in keys if k in self._checkpoint)
        if todo:
            executor = self.executor
            jobs = [Job(self._config, str(self.output_dir), u) for u in todo]
            with self.progress_bar(total=len(units), initial=len(units) - len(todo), desc=desc) as bar:
                for index, value in executor.run(jobs, ctx=self):
                    self._store(todo[index].key, value)
                    bar.update(1)
        return [self._checkpoint[k] for k in keys]

    def _store(self, key: str, value: Any) -> None:
        self._checkpoint[key] = value
        # arrays: units/<key>.npz, written (atomically) before the checkpoint that names them and their sha256
        self._checkpoint_refs[key] = array_refs(key, value, self.output_dir)
        write_atomic(self.output_dir / "checkpoint.json",
                     json.dumps({"config_hash": self._config_hash, "config": self._result_config,
                                 "code": self._code, "units": self._checkpoint_refs}, default=str) + "\n")

    @property
    def executor(self):
        """The executor of ``cfg.executor`` (made on first use; closed when the study ends)."""
        if self._executor is None:
            from experiments.executors import make_executor

            self._executor = make_executor(self._config.get("executor"), self.output_dir, self._config.get("threads", 1))
        return self._executor

    def close_executor(self) -> None:
        if self._executor is not None:
            self._executor.close()
            self._executor = None

    # -- outputs -------------------------------------------------------------------------------
    def save_figure(self, name: str, figure) -> Path | None:
        """Save ``figures/<name>.png`` (200 dpi) and ``figures/<name>.pdf`` (vector, for papers), and log
        the PNG to TensorBoard under ``figures/<name>``; closes ``figure``. With ``figures=false``
        nothing is drawn and None is returned."""
        import matplotlib.pyplot as plt

        from experiments.plot import save_tight

        if not self.figures:
            plt.close(figure)
            return None
        path = self.output_dir / "figures" / f"{name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        png = save_tight(figure, [(path, 200), (path.with_suffix(".pdf"), None)])
        self.logger.figure(f"figures/{name}", figure, png=png)
        plt.close(figure)
        return path

    def progress_bar(self, iterable=None, **kwargs):
        """A tqdm bar over ``iterable`` (or a manual one: ``total=``), off with ``progress=false``."""
        from tqdm.auto import tqdm

        if self.bar_label:
            kwargs["desc"] = f"{self.bar_label} {kwargs.get('desc') or ''}".rstrip()
        if self.bar_position is not None:
            kwargs.setdefault("position", self.bar_position)
            kwargs.setdefault("leave", False)
        return tqdm(iterable, disable=not self.progress, **kwargs)



def open_context(cfg: Any, output_dir: Path, config_dict: dict, experiment: str, description: str = "") -> StudyContext:
    """Create the context; pick up a checkpoint left in ``output_dir`` by the same config.

    The checkpoint is keyed on the keys that change results only (:func:`result_config`). If
    ``output_dir`` holds a checkpoint of a config that differs in such keys, the differing keys are
    named and the study runs in a fresh sibling folder (``<dir>_1``, ...): nothing is overwritten.
    Units of the same config computed by other code (checkpoint.json's ``code``:
    :func:`experiments.provenance.code_version`) are never mixed with this run's:
    :class:`~experiments.folders.CodeChanged` naming both versions (docs/studies.md, "Resuming").
    A ``checkpoint.json`` (or, without one, a ``results.json``) that cannot be read is a
    :class:`RunFolderError` naming it; a unit whose ``units/*.npz`` is missing, truncated or fails its
    checksum is one warning naming the file, and that unit is computed again.
    """
    try:
        output_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RunFolderError(f"{output_dir}: cannot create the run folder ({error_reason(err)})") from None
    kept = result_config(config_dict)
    digest = config_hash(config_dict)
    checkpoint: dict = {}
    refs: dict = {}
    saved = saved_run(output_dir)
    saved_hash, saved_config = (saved[0], saved[1]) if saved is not None else (None, None)
    code = code_version()
    if saved is not None and saved_hash == digest:
        check_code(output_dir, saved, code)  # units of other code: refused, never mixed
        if saved[3] and saved[4] is None:
            log.warning("%s records no code version (written before code versions were recorded): its units "
                        "are kept as if this code had computed them", saved[2])
        remove_temporaries(output_dir)
        for key, ref in saved[3].items():
            try:
                checkpoint[key] = load_arrays(ref, output_dir)
            except UnitFileError as err:
                log.warning("%s; unit %s is computed again", err, key)
                continue
            refs[key] = ref
        log.info("found %d finished units in %s", len(checkpoint), saved[2])
    if saved_hash is not None and saved_hash != digest:
        differ = differing_keys(saved_config or {}, json.loads(json.dumps(kept, default=str)))
        fresh = Path(unique_dir(str(output_dir)))
        log.warning("%s holds a run whose %s differ; this run goes to %s (the old one is kept)", output_dir,
                    ", ".join(differ[:8]) or "config", fresh)
        output_dir = fresh
    results = Results(output_dir, experiment, config_dict, description)
    return StudyContext(
        cfg=cfg,
        output_dir=output_dir,
        results=results,
        logger=CurveRecorder(make_logger(config_dict.get("logger"), output_dir)),
        dtype=resolve_dtype(cfg.dtype),
        device=resolve_device(cfg.device),
        seed=int(cfg.seed),
        progress=bool(cfg.get("progress", True)),
        figures=bool(cfg.get("figures", True)),
        _checkpoint=checkpoint,
        _checkpoint_refs=refs,
        _config_hash=digest,
        _code=code,
        _result_config=json.loads(json.dumps(kept, default=str)),
        _config=json.loads(json.dumps(config_dict, default=str)),
    )


#: worker contexts by (config, folder): one per process, so a worker's units share its cache
_WORKER_CONTEXTS: dict[str, StudyContext] = {}


def worker_context(config: dict, output_dir: Path) -> StudyContext:
    """A study context rebuilt from a resolved config in a worker process (no logger, no results
    files, no checkpoint): what :func:`experiments.executors.execute` runs a unit with."""
    from omegaconf import OmegaConf

    token = hashlib.sha256(json.dumps([config, str(output_dir)], sort_keys=True, default=str).encode()).hexdigest()
    ctx = _WORKER_CONTEXTS.get(token)
    if ctx is None:
        cfg = OmegaConf.create(config)
        ctx = StudyContext(cfg=cfg, output_dir=Path(output_dir),
                           results=Results(Path(output_dir), str(config.get("experiment_name", "study")), config),
                           logger=NullLogger(), dtype=resolve_dtype(cfg.dtype), device=resolve_device(cfg.device),
                           seed=int(cfg.seed), progress=False, _config=config)
        _WORKER_CONTEXTS.clear()  # one study per worker at a time
        _WORKER_CONTEXTS[token] = ctx
        compile_fast_paths(bool(config.get("compile", False)))
    return ctx

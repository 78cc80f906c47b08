"""Study harness: results files, TensorBoard, figures, seeding and resumable work units.

Everything Hydra- and TensorBoard-specific lives here and in ``run.py``; the library never
imports either. A study receives a :class:`StudyContext` and writes through it:

* ``results.json`` (docs/specification.md §3 schema) and ``results.md``, rewritten after every finished
  unit, so an interrupted study keeps what it finished;
* ``checkpoint.json``: finished units by key; re-running with the same config in the same run
  directory (``hydra.run.dir=<dir>``) skips them;
* PNG figures under ``figures/`` (also logged to TensorBoard);
* TensorBoard events under ``tb/`` (or nothing with ``logger=none``).

Run folders are safe from faults and from each other (docs/robustness.md, "Run folders and faults"):
every file is written atomically (:func:`write_atomic`); each ``units/*.npz`` has its sha256 in the
checkpoint, and a unit whose file is missing or corrupt is computed again; a run holds an exclusive
lock on its folder (:func:`lock_folder`) for as long as it runs; a file-level failure is a
:class:`RunFolderError`, one line naming the file.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import io
import json
import logging
import math
import os
import struct
import tempfile
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

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


def _jsonable(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu()
        return value.item() if value.dim() == 0 else value.tolist()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


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


def _array_refs(key: str, value: Any, output_dir: Path) -> Any:
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


class RunFolderError(Exception):
    """A file of a run folder cannot be read or written, or the folder is in use: the message is one
    line that names the file (the command line prints it and exits with status 2)."""


class FolderInUse(RunFolderError):
    """Another process holds the run folder's lock (:func:`lock_folder`)."""


class UnitFileError(RunFolderError):
    """A unit's ``units/*.npz`` is missing, truncated or not the file the checkpoint recorded."""


def _load_arrays(value: Any, output_dir: Path) -> Any:
    """Inverse of :func:`_array_refs`: a checkpointed value with its arrays read back. A file that
    is missing, unreadable or whose sha256 differs from the checkpoint's is a :class:`UnitFileError`."""
    import numpy as np

    if not (isinstance(value, dict) and ARRAY_REF + "file" in value):
        return value
    path = output_dir / value[ARRAY_REF + "file"]
    try:
        data = path.read_bytes()
    except OSError as err:
        raise UnitFileError(f"{path}: {_reason(err)}") from None
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


#: temporary files of :func:`write_atomic`: ``.<name>.<random>.tmp`` next to the file
TMP_SUFFIX = ".tmp"


def _reason(err: OSError) -> str:
    return err.strerror or type(err).__name__


def write_atomic(path: Path, content: str | bytes | Callable[[Any], None]) -> None:
    """Write ``path`` atomically: into a temporary file in the same folder, flushed and fsynced, then
    moved over ``path`` with ``os.replace`` - a reader (or a run killed at any moment) sees the old file or
    the new one, never a part. ``content``: text, bytes, or ``write(binary_file)`` (e.g. ``np.savez``,
    ``figure.savefig``). Every file a run writes goes through here; a failure is a
    :class:`RunFolderError` naming ``path``."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TMP_SUFFIX)
        with os.fdopen(fd, "wb") as f:
            if isinstance(content, str):
                f.write(content.encode())
            elif isinstance(content, (bytes, bytearray, memoryview)):
                f.write(content)
            else:
                content(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 -> what open() would have made
        os.replace(tmp, path)
        tmp = None
    except OSError as err:
        raise RunFolderError(f"{path}: cannot write ({_reason(err)})") from None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass


_write_atomic = write_atomic  # the former name


_UMASK: list[int] = []


def _umask() -> int:
    """The process's umask (read once: reading it means setting it, which is not thread-safe)."""
    if not _UMASK:
        mask = os.umask(0o022)
        os.umask(mask)
        _UMASK.append(mask)
    return _UMASK[0]


def remove_temporaries(folder: Path) -> None:
    """Remove what :func:`write_atomic` left behind in ``folder``, ``units/`` and ``figures/`` when a
    run was killed between writing and replacing (call it holding the folder's lock)."""
    for sub in (Path(folder), Path(folder) / "units", Path(folder) / "figures",
                Path(folder) / "figures" / "curves"):
        for tmp in sub.glob(f".*{TMP_SUFFIX}"):
            try:
                tmp.unlink()
            except OSError:
                pass


# -- the run folder's lock --------------------------------------------------------------------------
#: the lock file in a run (or sweep) folder: ``fcntl.flock``-ed by the process that runs there
LOCK_FILE = ".torchmm.lock"
#: the locks this process holds: real path of the folder -> the lock file's descriptor
_LOCKS: dict[str, int] = {}


def lock_folder(folder: Path) -> bool:
    """Take the exclusive lock of ``folder`` (created if needed) for this process: ``flock`` on
    ``folder/.torchmm.lock``, released when the process ends, however it ends (SIGKILL too). True if
    taken now, False if this process holds it already. Another process holding it: :class:`FolderInUse`,
    and nothing in the folder is changed; a folder that cannot be written: :class:`RunFolderError`."""
    folder = Path(folder)
    key = os.path.realpath(folder)
    if key in _LOCKS:
        return False
    lock = folder / LOCK_FILE
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as err:
        raise RunFolderError(f"{folder}: cannot write there ({_reason(err)})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(fd)
        if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise FolderInUse(f"{folder}: in use by another run (pid {holder}; lock {lock}); wait for it to "
                              "end or choose another folder") from None
        raise RunFolderError(f"{lock}: cannot lock ({_reason(err)})") from None
    try:  # the lock file opens in a read-only folder too: check that the folder takes new files
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        probe_fd, probe = tempfile.mkstemp(dir=folder, prefix=".write-check.", suffix=TMP_SUFFIX)
        os.close(probe_fd)
        os.unlink(probe)
    except OSError as err:
        os.close(fd)
        raise RunFolderError(f"{folder}: cannot write there ({_reason(err)})") from None
    _LOCKS[key] = fd
    return True


def unlock_folder(folder: Path) -> None:
    """Release this process's lock of ``folder`` (if it holds it)."""
    fd = _LOCKS.pop(os.path.realpath(folder), None)
    if fd is not None:
        os.close(fd)


def _format(value: Any) -> str:
    if isinstance(value, float):
        if value != value:
            return "nan"
        if value == 0 or 1e-3 <= abs(value) < 1e5:
            return f"{value:.4f}"
        return f"{value:.3e}"
    return "" if value is None else str(value)


@dataclass
class Table:
    columns: list[str]
    rows: list[list[Any]] = field(default_factory=list)
    note: str = ""
    #: optional published values: ``{"columns": [...], "rows": [...], "source": "..."}``
    published: dict | None = None

    def markdown(self) -> str:
        lines = ["| " + " | ".join(self.columns) + " |", "|" + "---|" * len(self.columns)]
        lines += ["| " + " | ".join(_format(v) for v in row) + " |" for row in self.rows]
        return "\n".join(lines)


class Results:
    """The machine- and human-readable results of one study run.

    ``results.json``: ``{"experiment", "config", "metrics": {estimator: {metric: value}},
    "tables": {name: {"columns", "rows"}}, "timing": {estimator: seconds_per_step},
    "provenance": {versions, git, host, platform, command, start, end, wall_seconds, device, dtype,
    threads}}`` (docs/studies.md).
    """

    def __init__(self, output_dir: Path, experiment: str, config: dict, description: str = ""):
        self.output_dir = output_dir
        self.experiment = experiment
        self.config = config
        self.description = description
        self.metrics: dict[str, dict[str, Any]] = {}
        self.tables: dict[str, Table] = {}
        self.timing: dict[str, float] = {}
        self.notes: list[str] = []
        self.provenance: dict[str, Any] = {}
        #: what the config changes from the study's defaults (:func:`experiments.api.config_changes`),
        #: set when the run starts; None: not known (results.md then lists no changes)
        self.changes: dict | None = None

    def table(self, name: str, columns: Sequence[str], *, note: str = "", published: dict | None = None) -> Table:
        """Create (or reset) a table; append rows to ``.rows``."""
        self.tables[name] = Table(list(columns), [], note, published)
        return self.tables[name]

    def metric(self, estimator: str, name: str, value: Any) -> None:
        self.metrics.setdefault(estimator, {})[name] = _jsonable(value)

    def to_json(self) -> dict:
        return {
            "experiment": self.experiment,
            "config": self.config,
            "metrics": _jsonable(self.metrics),
            "tables": {k: {"columns": t.columns, "rows": _jsonable(t.rows)} for k, t in self.tables.items()},
            "timing": _jsonable(self.timing),
            "provenance": _jsonable(self.provenance),
        }

    @staticmethod
    def _show_value(value: Any) -> str:
        """A config value as written on the command line (``null``, ``true``, lists as JSON)."""
        if value is None:
            return "null"
        if isinstance(value, bool):
            return "true" if value else "false"
        return str(value)

    def _setup_markdown(self) -> list[str]:
        """The command line (``provenance.command``) and every result value that differs from the
        study's defaults (:attr:`changes`), for the top of results.md."""
        out = []
        command = (self.provenance or {}).get("command")
        if command:
            out += ["Command:", "", "```bash", str(command), "```", ""]
        changes = self.changes
        if changes is not None:
            choices, keys = changes.get("choices") or {}, changes.get("keys") or {}
            name = changes.get("experiment", self.experiment)
            if not choices and not keys:
                out += [f"Ran with the defaults of `{name}` (conf/experiment/{name}.yaml).", ""]
            else:
                out += [f"Differs from the defaults of `{name}` (conf/experiment/{name}.yaml) in:", ""]
                out += [f"- `{group}={self._show_value(value)}` (default: {self._show_value(default)})"
                        for group, (default, value) in choices.items()]
                out += [f"- `{key}={self._show_value(value)}` (default: {self._show_value(default)})"
                        for key, (default, value) in keys.items()]
                out += [""]
        return out

    def to_markdown(self) -> str:
        out = [f"# {self.experiment}", "", *self._setup_markdown()]
        if self.description:
            out += [self.description, ""]
        for name, table in self.tables.items():
            out += [f"## {name}", ""]
            if table.note:
                out += [table.note, ""]
            out += [table.markdown(), ""]
            if table.published:
                pub = Table(table.published["columns"], table.published["rows"])
                out += [f"Published ({table.published.get('source', 'paper')}):", "", pub.markdown(), ""]
        if self.metrics:
            names = sorted({m for v in self.metrics.values() for m in v})
            metrics = Table(["estimator", *names], [[e, *[v.get(m) for m in names]] for e, v in self.metrics.items()])
            out += ["## metrics", "", metrics.markdown(), ""]
        if self.timing:
            timing = Table(["estimator", "seconds_per_step"], [[k, v] for k, v in self.timing.items()])
            out += ["## timing", "", "Wall time per time step for all Monte Carlo runs at once.", "",
                    timing.markdown(), ""]
        if self.notes:
            out += ["## notes", ""] + [f"- {n}" for n in self.notes] + [""]
        if self.provenance:
            p = self.provenance
            git = p.get("git") or {}
            commit = (git.get("commit") or "unknown")[:12] + (" (uncommitted changes)" if git.get("dirty") else "")
            v = p.get("versions") or {}
            out += ["## provenance", "",
                    f"torchmm {v.get('torchmm')}, torch {v.get('torch')}, numpy {v.get('numpy')}, "
                    f"Python {v.get('python')}; commit {commit}; {p.get('host')}; device {p.get('device')}, "
                    f"{p.get('dtype')}, {p.get('threads')} threads; {p.get('start')} to {p.get('end')} "
                    f"({p.get('wall_seconds')} s).", ""]
        return "\n".join(out)

    def save(self) -> None:
        write_atomic(self.output_dir / "results.json", json.dumps(self.to_json(), indent=2) + "\n")
        write_atomic(self.output_dir / "results.md", self.to_markdown())


class Logger:
    """Logging interface of studies (TensorBoard or nothing)."""

    def scalar(self, tag: str, value: float, step: int = 0) -> None: ...

    def series(self, tag: str, values: Iterable[float], start: int = 1) -> None:
        """One scalar per time step (TensorBoard x-axis = time step)."""
        for k, v in enumerate(values, start=start):
            self.scalar(tag, float(v), k)

    def sweep(self, tag: str, x: Sequence[float], values: Iterable[float], axis: str) -> None:
        """One value per point of an in-study parameter sweep (``axis``, e.g. ``alpha``): a curve
        over that parameter, not over time steps (TensorBoard: drawn as a figure, ``sweeps/``)."""

    def histogram(self, tag: str, values: torch.Tensor, step: int = 0) -> None: ...

    def figure(self, tag: str, figure, png: bytes | None = None) -> None:
        """A matplotlib figure; ``png``: the figure already rendered as PNG (logged as it is)."""

    def text(self, tag: str, text: str) -> None: ...

    def hparams(self, hparams: dict, metrics: dict) -> None:
        """The run's settings and headline numbers (TensorBoard's HPARAMS tab: a row per run)."""

    def close(self) -> None: ...


class NullLogger(Logger):
    """``logger=none``: discard everything."""


class TensorBoardLogger(Logger):
    """TensorBoard event files under ``<run dir>/tb``."""

    def __init__(self, log_dir: Path, flush_secs: int = 10):
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(log_dir=str(log_dir), flush_secs=flush_secs)

    def scalar(self, tag, value, step=0):
        self.writer.add_scalar(tag, value, step)

    def histogram(self, tag, values, step=0):
        self.writer.add_histogram(tag, values.detach().cpu(), step)

    def figure(self, tag, figure, png=None):
        if png is None:
            self.writer.add_figure(tag, figure, close=False)
            return
        # the PNG the study saved, as TensorBoard's encoded image: no second rendering
        from tensorboard.compat.proto.summary_pb2 import Summary

        width, height = struct.unpack(">II", png[16:24])  # the IHDR chunk
        channels = {0: 1, 2: 3, 4: 2, 6: 4}.get(png[25], 4)  # by the PNG colour type
        image = Summary.Image(height=height, width=width, colorspace=channels, encoded_image_string=png)
        self.writer._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]))

    def text(self, tag, text):
        self.writer.add_text(tag, text)

    def hparams(self, hparams, metrics):
        # into this run's own event file (SummaryWriter.add_hparams would open a second writer)
        from torch.utils.tensorboard.summary import hparams as hparams_summary

        writer = self.writer._get_file_writer()
        for summary in hparams_summary(hparams, metrics):
            writer.add_summary(summary)
        for key, value in metrics.items():
            self.writer.add_scalar(key, value)

    def close(self):
        self.writer.flush()
        self.writer.close()


class CurveRecorder(Logger):
    """Records every per-step series a study logs (``series(tag, values)``) as data, whatever the
    logger; forwards everything to ``inner``. :meth:`save` writes ``curves.npz`` and ``curves.csv``."""

    def __init__(self, inner: Logger):
        self.inner = inner
        #: tag -> (axis name, x values, values); axis "step" for per-step curves
        self.curves: dict[str, tuple[str, list, list[float]]] = {}

    def series(self, tag, values, start=1):
        values = _floats(values)
        self.curves[tag] = ("step", list(range(start, start + len(values))), values)
        self.inner.series(tag, values, start)

    def sweep(self, tag, x, values, axis):
        if not axis or "#" in axis or axis == "step":
            raise ValueError(f"axis: a parameter name without '#' other than 'step', got {axis!r}")
        x, values = _floats(x), _floats(values)
        if len(x) != len(values):
            raise ValueError(f"sweep {tag}: {len(x)} x values but {len(values)} values")
        self.curves[tag] = (axis, x, values)  # once per tag: a re-logged sweep replaces the old points
        self.inner.sweep(tag, x, values, axis)

    def hparams(self, hparams, metrics):
        self.inner.hparams(hparams, metrics)

    def scalar(self, tag, value, step=0):
        self.inner.scalar(tag, value, step)

    def histogram(self, tag, values, step=0):
        self.inner.histogram(tag, values, step)

    def figure(self, tag, figure, png=None):
        self.inner.figure(tag, figure, png=png)

    def text(self, tag, text):
        self.inner.text(tag, text)

    def close(self):
        self.inner.close()

    def save(self, output_dir: Path, figures: bool = True) -> None:
        """``curves.npz``: per curve ``<tag>`` the values and ``<tag>#<axis>`` its x values - the time
        steps (``#step``) or a swept parameter (e.g. ``#alpha``); and a tidy ``curves.csv``
        (``quantity, series, axis, x, value``; the tag is ``quantity/series``). ``figures``: also draw
        the sweeps' curves for TensorBoard."""
        if not self.curves:
            return
        import numpy as np

        arrays = {}
        for tag, (axis, x, values) in self.curves.items():
            arrays[tag] = np.asarray(values, dtype=np.float64)
            arrays[f"{tag}#{axis}"] = np.asarray(x, dtype=np.int64 if axis == "step" else np.float64)
        write_atomic(output_dir / "curves.npz", lambda f: np.savez(f, **arrays))
        lines = ["quantity,series,axis,x,value"]
        for tag, (axis, x, values) in self.curves.items():
            quantity, _, series = tag.partition("/")
            for k, v in zip(x, values):
                lines.append(f"{_csv(quantity)},{_csv(series)},{_csv(axis)},{k!r},{v!r}")
        write_atomic(output_dir / "curves.csv", "\n".join(lines) + "\n")
        sweeps = {tag: c for tag, c in self.curves.items() if c[0] != "step"}
        if figures and sweeps and not isinstance(self.inner, NullLogger):  # TensorBoard: sweeps on their own axis
            from experiments.plot import draw_groups

            for quantity, fig in draw_groups(sweeps):
                self.inner.figure(f"sweeps/{quantity}", fig)
                import matplotlib.pyplot as plt

                plt.close(fig)


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


def _floats(values) -> list[float]:
    return [float(v) for v in (values.tolist() if isinstance(values, torch.Tensor) else values)]


def _csv(text: str) -> str:
    return f'"{text}"' if any(c in text for c in ',"\n') else text


def make_logger(cfg: dict | None, output_dir: Path) -> Logger:
    kind = (cfg or {}).get("kind", "none")
    if kind == "tensorboard":
        return TensorBoardLogger(output_dir / cfg.get("subdir", "tb"), flush_secs=int(cfg.get("flush_secs", 10)))
    if kind == "none":
        return NullLogger()
    raise ValueError(f"logger.kind: expected 'tensorboard' or 'none', got {kind!r}")


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
    #: the checkpoint as written to checkpoint.json (arrays as references to units/*.npz)
    _checkpoint_refs: dict = field(default_factory=dict)
    _config_hash: str = ""
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
            return self._checkpoint[key]
        value = _jsonable(compute())
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
        self._checkpoint_refs[key] = _array_refs(key, value, self.output_dir)
        write_atomic(self.output_dir / "checkpoint.json",
                     json.dumps({"config_hash": self._config_hash, "config": self._result_config,
                                 "units": self._checkpoint_refs}, default=str) + "\n")

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


def unique_dir(base: str) -> str:
    """Create ``base`` (or the first free ``base_1``, ``base_2``, ...) atomically; return its path.

    Registered as the OmegaConf resolver ``torchmm.unique_dir`` with caching, so one Hydra run
    (and every job of a sweep, whose configs share the cache) resolves it to one folder.
    """
    path = Path(base)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        for attempt in range(10_000):
            candidate = path if attempt == 0 else path.with_name(f"{path.name}_{attempt}")
            try:
                os.mkdir(candidate)
            except FileExistsError:
                continue
            return str(candidate)
    except OSError as err:  # a read-only parent, a file where a folder should be, ...
        where = err.filename or path
        raise RunFolderError(f"{where}: cannot create the run folder {path} ({_reason(err)})") from None
    raise RunFolderError(f"{base}: no free folder name next to it")


#: keys that do not change a study's numbers: a checkpoint made with other values is reused
#: (``chunk_runs``: identical bit for bit - run-indexed streams, per-run reductions; docs/scaling.md)
#: (``unit_runs``: the same to rounding - a unit's runs are filtered in one batch - and its own unit keys)
#: (``compile``: the fast paths compiled, the same to rounding)
NON_RESULT_KEYS = ("progress", "figures", "logger", "threads", "chunk_runs", "unit_runs", "retain_freed_memory",
                   "compile", "cpu_kernels", "executor", "resume")


def result_config(config_dict: dict) -> dict:
    """The part of a resolved config that decides the numbers (without :data:`NON_RESULT_KEYS`)."""
    return {k: v for k, v in config_dict.items() if k not in NON_RESULT_KEYS and k != "hydra"}


def config_hash(config_dict: dict) -> str:
    """The hash finished units are keyed on: of :func:`result_config`."""
    kept = result_config(config_dict)
    return hashlib.sha256(json.dumps(kept, sort_keys=True, default=str).encode()).hexdigest()[:16]


def latest_run(base: Path, config_dict: dict, unreadable: list[str] | None = None) -> Path | None:
    """The newest run folder under ``base`` (``outputs/<study>``) holding work of this config
    (a ``checkpoint.json`` or ``results.json`` of the same :func:`config_hash`), or None.
    ``unreadable``: a list that gets one line per folder skipped because its files cannot be read."""
    wanted = config_hash(config_dict)
    found = []
    for folder in Path(base).glob("*/"):
        try:
            saved = saved_run(folder)
        except RunFolderError as err:
            if unreadable is not None:
                unreadable.append(str(err))
            continue
        if saved is not None and saved[0] == wanted:
            found.append((saved[2].stat().st_mtime, str(folder)))
    return Path(max(found)[1]).resolve() if found else None


def _read_json(path: Path, what: str) -> dict:
    try:
        data = json.loads(path.read_text())
    except OSError as err:
        raise RunFolderError(f"{path}: cannot read ({_reason(err)})") from None
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError: truncated or not JSON
        raise RunFolderError(f"{path}: not a valid {what} ({type(err).__name__}: {err})") from None
    if not isinstance(data, dict):
        raise RunFolderError(f"{path}: not a valid {what} (a JSON {type(data).__name__}, not an object)")
    return data


def saved_run(folder: Path) -> tuple[str, dict | None, Path, dict] | None:
    """What ``folder`` holds of an earlier run: ``(config_hash, result config, file, units)`` from its
    ``checkpoint.json`` (else from a finished ``results.json``, with no units), or None for no run. A
    file that cannot be read or is not what it should be: :class:`RunFolderError` naming it."""
    ckpt_path, results_path = Path(folder) / "checkpoint.json", Path(folder) / "results.json"
    if ckpt_path.exists():
        saved = _read_json(ckpt_path, "checkpoint")
        units = saved.get("units", {})
        if not isinstance(saved.get("config_hash"), str) or not isinstance(units, dict):
            raise RunFolderError(f"{ckpt_path}: not a valid checkpoint (no config_hash or units)")
        return saved["config_hash"], saved.get("config"), ckpt_path, units
    if results_path.exists():  # a finished study without units: compare the configs it recorded
        recorded = _read_json(results_path, "results file").get("config") or {}
        if not isinstance(recorded, dict):
            raise RunFolderError(f"{results_path}: not a valid results file (its config is not an object)")
        return config_hash(recorded), result_config(recorded), results_path, {}
    return None


def _differing_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b), key=str):
            name = f"{prefix}.{key}" if prefix else str(key)
            if key not in a or key not in b:
                out.append(name)
            else:
                out += _differing_keys(a[key], b[key], name)
        return out
    return [] if a == b else [prefix or "(config)"]


def open_context(cfg: Any, output_dir: Path, config_dict: dict, experiment: str, description: str = "") -> StudyContext:
    """Create the context; pick up a checkpoint left in ``output_dir`` by the same config.

    The checkpoint is keyed on the keys that change results only (:func:`result_config`). If
    ``output_dir`` holds a checkpoint of a config that differs in such keys, the differing keys are
    named and the study runs in a fresh sibling folder (``<dir>_1``, ...): nothing is overwritten.
    A ``checkpoint.json`` (or, without one, a ``results.json``) that cannot be read is a
    :class:`RunFolderError` naming it; a unit whose ``units/*.npz`` is missing, truncated or fails its
    checksum is one warning naming the file, and that unit is computed again.
    """
    try:
        output_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RunFolderError(f"{output_dir}: cannot create the run folder ({_reason(err)})") from None
    kept = result_config(config_dict)
    digest = config_hash(config_dict)
    checkpoint: dict = {}
    refs: dict = {}
    saved = saved_run(output_dir)
    saved_hash, saved_config = (saved[0], saved[1]) if saved is not None else (None, None)
    if saved is not None and saved_hash == digest:
        remove_temporaries(output_dir)
        for key, ref in saved[3].items():
            try:
                checkpoint[key] = _load_arrays(ref, output_dir)
            except UnitFileError as err:
                log.warning("%s; unit %s is computed again", err, key)
                continue
            refs[key] = ref
        log.info("found %d finished units in %s", len(checkpoint), saved[2])
    if saved_hash is not None and saved_hash != digest:
        differ = _differing_keys(saved_config or {}, json.loads(json.dumps(kept, default=str)))
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

"""Study harness: results files, TensorBoard, figures, seeding and resumable work units.

Everything Hydra- and TensorBoard-specific lives in ``experiments/`` (this harness and ``run.py``); the
library never imports either. A study receives a :class:`StudyContext` and writes through it:

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

This module gathers the harness's public names (studies import them from here); each lives in the
module of its concern:

* :mod:`experiments.files` - :func:`write_atomic`, leftover temporaries, the folder lock, :class:`RunFolderError`;
* :mod:`experiments.results` - :class:`Results`, :class:`Table`, value formatting, JSON conversion;
* :mod:`experiments.loggers` - :class:`Logger`, :class:`NullLogger`, :class:`TensorBoardLogger`,
  :class:`CurveRecorder`, :func:`make_logger`;
* :mod:`experiments.arrays` - :func:`per_run`, :func:`join_runs`, :func:`add_runs`, :func:`cat_runs` and
  the arrays of checkpointed units;
* :mod:`experiments.folders` - :func:`unique_dir`, :func:`result_config`, :func:`config_hash`,
  :func:`latest_run`, :func:`saved_run`, :data:`NON_RESULT_KEYS`;
* :mod:`experiments.context` - :class:`StudyContext`, :func:`open_context`, :func:`worker_context`.
"""

from __future__ import annotations

from experiments.arrays import ARRAY_REF, add_runs, array_refs, cat_runs, join_runs, load_arrays, per_run
from experiments.context import (
    DTYPES,
    StudyContext,
    log,
    open_context,
    resolve_device,
    resolve_dtype,
    worker_context,
)
from experiments.files import (
    LOCK_FILE,
    LOCKS,
    TMP_SUFFIX,
    FolderInUse,
    RunFolderError,
    UnitFileError,
    error_reason,
    lock_folder,
    remove_temporaries,
    unlock_folder,
    write_atomic,
)
from experiments.folders import (
    NON_RESULT_KEYS,
    config_hash,
    differing_keys,
    latest_run,
    result_config,
    saved_run,
    unique_dir,
)
from experiments.loggers import CurveRecorder, Logger, NullLogger, TensorBoardLogger, make_logger
from experiments.results import Results, Table, format_value, jsonable

__all__ = [
    "ARRAY_REF",
    "DTYPES",
    "LOCKS",
    "LOCK_FILE",
    "NON_RESULT_KEYS",
    "TMP_SUFFIX",
    "CurveRecorder",
    "FolderInUse",
    "Logger",
    "NullLogger",
    "Results",
    "RunFolderError",
    "StudyContext",
    "Table",
    "TensorBoardLogger",
    "UnitFileError",
    "add_runs",
    "array_refs",
    "cat_runs",
    "config_hash",
    "differing_keys",
    "error_reason",
    "format_value",
    "join_runs",
    "jsonable",
    "latest_run",
    "load_arrays",
    "lock_folder",
    "log",
    "make_logger",
    "open_context",
    "per_run",
    "remove_temporaries",
    "resolve_device",
    "resolve_dtype",
    "result_config",
    "saved_run",
    "unique_dir",
    "unlock_folder",
    "worker_context",
    "write_atomic",
]

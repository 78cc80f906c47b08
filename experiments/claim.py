"""Before Hydra writes anything: the folder a run or a sweep's job writes into.

* ``resume=latest`` / ``resume=<dir>`` (:func:`resolve_resume`) and ``hydra.run.dir=<dir>`` /
  ``hydra.sweep.dir=<dir>`` (:func:`claim_folder`): the folder locked, a folder of another result config
  left for a fresh sibling, units of other code refused (:class:`experiments.folders.CodeChanged`);
* a sweep job's folder (the resolver ``torchmm.sweep_subdir`` of ``hydra.sweep.subdir``, conf/config.yaml:
  :func:`sweep_job_dir`): ``<num>_<overrides>``, or a fresh sibling ``<num>_<overrides>_1`` when that folder
  holds a run of another result config (an earlier sweep into the same ``hydra.sweep.dir`` whose job had
  the same name), chosen before Hydra writes the job's ``.hydra/`` and log there.

Split from :mod:`experiments.run` (the entry point), which re-exports these names. Imports neither torch nor
Hydra at import time.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from experiments.paths import CONFIG_DIR

__all__ = ["claim_folder", "fail", "job_folder", "resolve_resume", "sweep_job_dir", "sweep_subdir"]


def fail(message: str) -> None:
    """One line on stderr, ``torchmm-run: error: <message>``, and exit status 2."""
    print(f"torchmm-run: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def sweep_subdir(num: Any, overrides: Any = "") -> str:
    """A sweep job's folder name: its number and its overrides, ``3_alpha=0.5,seed=1`` (``/`` and
    other characters unsafe in a file name become ``_``; long names are cut and end in a hash)."""
    name = f"{num}_{overrides}" if overrides else str(num)
    name = re.sub(r"[^A-Za-z0-9=,._+\-\[\]]", "_", name)
    if len(name) > 120:
        name = f"{name[:103]}_{hashlib.sha1(name.encode()).hexdigest()[:16]}"
    return name


def sweep_job_dir(num: Any, overrides: Any = "", *, _root_: Any = None) -> str:
    """The resolver ``torchmm.sweep_subdir`` (``hydra.sweep.subdir``): the job's folder name under
    ``hydra.sweep.dir`` - :func:`sweep_subdir`, or a fresh sibling where that folder holds a run of another
    result config (:func:`job_folder`). ``_root_``: the job's whole config (OmegaConf passes it)."""
    name = sweep_subdir(num, overrides)
    if _root_ is None or OmegaConf.select(_root_, "hydra.sweep.dir") is None:
        return name
    from experiments.files import RunFolderError
    from experiments.folders import with_data_files

    # the job's config as run_study sees it (Hydra's task config: the root without hydra), never hydra itself
    # (whose sweep.subdir is being resolved here)
    config = {}
    for key in _root_:
        if key != "hydra":
            value = _root_[key]
            config[key] = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
    try:
        sweep = Path(str(OmegaConf.select(_root_, "hydra.sweep.dir")))
        return job_folder(sweep, name, with_data_files(config))
    except RunFolderError as err:  # a corrupt checkpoint, units of other code: one line, exit status 2
        fail(str(err))
        raise  # (not reached)


def job_folder(sweep_dir: Path, name: str, config: dict) -> str:
    """``name``, or the first ``name_1``, ``name_2``, ... under ``sweep_dir`` that holds no run or a run of
    ``config``'s result config (made here, so that the choice holds whenever it is made again: a requeued
    job). A folder holding units of the same config computed by other code:
    :class:`~experiments.folders.CodeChanged`; one whose checkpoint cannot be read:
    :class:`~experiments.files.RunFolderError`."""
    from experiments.folders import check_code, config_hash, differing_keys, result_config, saved_run

    digest = config_hash(config)
    first = None
    for attempt in range(10_000):
        candidate = name if attempt == 0 else f"{name}_{attempt}"
        folder = sweep_dir / candidate
        saved = saved_run(folder)
        if saved is not None and saved[0] == digest and saved[3]:
            from experiments.provenance import code_version

            check_code(folder, saved, code_version())
        if saved is None or saved[0] == digest:
            if attempt:
                folder.mkdir(parents=True, exist_ok=True)
                kept = json.loads(json.dumps(result_config(config), default=str))
                differ = ", ".join(differing_keys(first[1] or {}, kept)[:8]) or "config"
                print(f"torchmm-run: {sweep_dir / name} holds a run whose {differ} differ; this job goes to "
                      f"{folder} (the old one is kept)", file=sys.stderr, flush=True)
            return candidate
        first = first or saved
    raise RuntimeError(f"{sweep_dir / name}: no free folder name next to it")  # pragma: no cover


if not OmegaConf.has_resolver("torchmm.sweep_subdir"):
    OmegaConf.register_new_resolver("torchmm.sweep_subdir", sweep_job_dir)


def _literal(args: list[str], key: str) -> str | None:
    """The value of the last ``key=value`` in ``args`` if it is a plain path (no interpolation)."""
    values = [a.split("=", 1)[1] for a in args if a.startswith(key + "=")]
    if not values or "${" in values[-1] or values[-1][:1] in ("'", '"'):
        return None
    return values[-1]


#: Hydra's options that print and run nothing (``--cfg job``, ``--info``, ...)
_NO_RUN_FLAGS = ("--cfg", "-c", "--info", "-i", "--hydra-help", "--shell-completion", "-sc",
                 "--experimental-rerun")


def claim_folder(args: list[str], config_dir: str = CONFIG_DIR) -> list[str]:
    """Before Hydra writes anything: lock the folder the command line names (``hydra.run.dir=<dir>``,
    or ``hydra.sweep.dir=<dir>`` with ``-m``) for this process's life, and return the command line.

    * the folder is in use by another run or sweep: :class:`~experiments.files.FolderInUse`;
      it cannot be made or written: :class:`~experiments.files.RunFolderError` (nothing written);
    * a run folder holding a run of another result config (or a corrupt checkpoint: an error naming
      it): the run goes to a fresh sibling (``<dir>_1``, ...) so that Hydra's ``.hydra/`` and log of the
      old run are kept too; the differing keys are named;
    * a sweep folder holding an earlier sweep's ``multirun.yaml``: that record is kept as
      ``multirun.1.yaml`` (``.2``, ...: oldest first) and the new sweep writes ``multirun.yaml``.

    Folders named through ``${...}`` interpolation (the default, ``${torchmm.unique_dir:...}``) are
    locked by their resolver or by :func:`run_study` instead.
    """
    from experiments.config import compose_config
    from experiments.files import RunFolderError, lock_folder, unlock_folder
    from experiments.folders import (
        check_code,
        config_hash,
        differing_keys,
        result_config,
        saved_run,
        unique_dir,
        with_data_files,
    )

    if any(a.split("=", 1)[0] in _NO_RUN_FLAGS for a in args):
        return args  # Hydra prints something and runs nothing: no folder
    if "-m" in args or "--multirun" in args:
        sweep = _literal(args, "hydra.sweep.dir")
        if sweep is not None:
            folder = Path(sweep)
            lock_folder(folder)
            record = folder / "multirun.yaml"
            if record.exists():
                n = 1
                while (folder / f"multirun.{n}.yaml").exists():
                    n += 1
                try:
                    os.replace(record, folder / f"multirun.{n}.yaml")
                except OSError as err:
                    raise RunFolderError(f"{record}: cannot keep the earlier sweep's record "
                                         f"({err.strerror})") from None
                print(f"torchmm-run: {folder} holds an earlier sweep: its record is kept as "
                      f"multirun.{n}.yaml", file=sys.stderr)
        return args
    run_dir = _literal(args, "hydra.run.dir")
    if run_dir is None:
        return args
    folder = Path(run_dir)
    lock_folder(folder)
    saved = saved_run(folder)
    if saved is None:
        return args
    cfg, _ = compose_config([a for a in args if not a.startswith("-")], config_dir, "config")
    config = with_data_files(OmegaConf.to_container(cfg, resolve=True))
    if saved[0] == config_hash(config):
        from experiments.provenance import code_version

        check_code(folder, saved, code_version())  # units of other code: refused (CodeChanged), never mixed
        return args  # the same result config and code: continue the folder
    differ = differing_keys(saved[1] or {}, json.loads(json.dumps(result_config(config), default=str)))
    fresh = Path(unique_dir(str(folder)))
    lock_folder(fresh)
    unlock_folder(folder)
    print(f"torchmm-run: {folder} holds a run whose {', '.join(differ[:8]) or 'config'} differ; "
          f"this run goes to {fresh} (the old one is kept)", file=sys.stderr)
    return [a for a in args if not a.startswith("hydra.run.dir=")] + [f"hydra.run.dir={fresh}"]


def resolve_resume(args: list[str], config_dir: str = CONFIG_DIR) -> list[str]:
    """``resume=latest`` / ``resume=<run folder>``: the command line with ``hydra.run.dir`` set to
    the folder to continue (the newest one of the same result config under ``outputs/<study>``).

    With no earlier run of the config, the run starts in a fresh folder (said on stderr). Not for
    ``-m`` sweeps: re-run a sweep with ``hydra.sweep.dir=<its folder>`` to continue its jobs.
    """
    values = [a.split("=", 1)[1] for a in args if a.startswith("resume=")]
    if not values or values[-1] in ("null", "None", ""):
        return args
    if "-m" in args or "--multirun" in args:
        fail("resume: not for -m sweeps; re-run the sweep with hydra.sweep.dir=<its folder> to continue it")
    if any(a.startswith("hydra.run.dir=") for a in args):
        fail("resume: give either resume= or hydra.run.dir=, not both")
    if values[-1] != "latest":
        return [*args, f"hydra.run.dir={values[-1]}"]
    from experiments.config import compose_config
    from experiments.folders import latest_run, with_data_files

    cfg, _ = compose_config([a for a in args if not a.startswith("-")], config_dir, "config")
    config = with_data_files(OmegaConf.to_container(cfg, resolve=True))
    base = Path("outputs") / str(config.get("experiment_name", "study"))
    unreadable: list[str] = []
    folder = latest_run(base, config, unreadable)
    for problem in unreadable:  # a corrupt checkpoint is never passed over silently
        print(f"torchmm-run: resume=latest: skipping {problem}", file=sys.stderr)
    if folder is None:
        print(f"torchmm-run: resume=latest: no {'readable ' if unreadable else ''}earlier run of this config "
              f"under {base}; starting a fresh one", file=sys.stderr)
        return args
    from experiments.files import RunFolderError
    from experiments.folders import check_code, saved_run
    from experiments.provenance import code_version

    try:  # units of other code: one line naming both versions, before anything is written
        check_code(folder, saved_run(folder), code_version())
    except RunFolderError as err:
        fail(f"resume=latest: {err}")
    print(f"torchmm-run: resume=latest: continuing {folder}", file=sys.stderr)
    return [*args, f"hydra.run.dir={folder}"]

"""Run folders: fresh names (:func:`unique_dir`), the part of a config that decides the numbers
(:func:`result_config`, :data:`NON_RESULT_KEYS`, :func:`config_hash`) and what a folder holds of an earlier
run (:func:`saved_run`, :func:`latest_run`, :func:`differing_keys`) and the code its units came from
(:func:`check_code`). Imports neither torch nor Hydra."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from experiments.files import RunFolderError, error_reason


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
        raise RunFolderError(f"{where}: cannot create the run folder {path} ({error_reason(err)})") from None
    raise RunFolderError(f"{base}: no free folder name next to it")


#: keys that do not change a study's numbers: a checkpoint made with other values is reused
#: (``chunk_runs``: identical bit for bit - run-indexed streams, per-run reductions; docs/scaling.md)
#: (``unit_runs``: the same to rounding - a unit's runs are filtered in one batch - and its own unit keys)
#: (``compile``: the fast paths compiled, the same to rounding)
NON_RESULT_KEYS = ("progress", "figures", "logger", "threads", "chunk_runs", "unit_runs", "retain_freed_memory",
                   "compile", "cpu_kernels", "executor", "resume")


#: the key under which a run's config records the contents of the data files it reads
#: (:func:`with_data_files`)
DATA_FILES = "data_files"


def with_data_files(config_dict: dict) -> dict:
    """``config_dict`` with :data:`DATA_FILES`: ``{dotted key: "sha256:<16 hex digits>"}`` of every data
    file the config names (each string ``path`` of a block, e.g. ``scenario.data.path``,
    ``tracking.detections.truth.path``), found as the readers find it (the working directory, then the
    shipped experiments/data). Recorded in results.json and hashed with the config (:func:`config_hash`), so
    a run on a file whose contents changed is a different run: ``resume`` never mixes units computed from
    the old contents with new ones, and the earlier results are kept. A file that does not exist is left
    out (the study's reader names it)."""
    from experiments.datafile_io import find

    found: dict[str, str] = {}

    def walk(node: Any, prefix: str) -> None:
        if not isinstance(node, dict):
            return
        for key, value in node.items():
            name = f"{prefix}{key}"
            if key == "path" and isinstance(value, str) and value:
                file = find(Path(value))
                if file.is_file():
                    digest = hashlib.sha256()
                    with open(file, "rb") as handle:
                        for block in iter(lambda: handle.read(1 << 20), b""):
                            digest.update(block)
                    found[name] = "sha256:" + digest.hexdigest()[:16]
            elif key not in ("hydra", DATA_FILES):
                walk(value, name + ".")

    walk(config_dict, "")
    return {**config_dict, DATA_FILES: found} if found else dict(config_dict)


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
        raise RunFolderError(f"{path}: cannot read ({error_reason(err)})") from None
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError: truncated or not JSON
        raise RunFolderError(f"{path}: not a valid {what} ({type(err).__name__}: {err})") from None
    if not isinstance(data, dict):
        raise RunFolderError(f"{path}: not a valid {what} (a JSON {type(data).__name__}, not an object)")
    return data


def saved_run(folder: Path) -> tuple[str, dict | None, Path, dict, dict | None] | None:
    """What ``folder`` holds of an earlier run: ``(config_hash, result config, file, units, code)`` from its
    ``checkpoint.json`` (``code``: the code version its units were computed with, None if not recorded;
    :func:`experiments.provenance.code_difference`), else from a finished ``results.json`` (no units, no
    code), or None for no run. A file that cannot be read or is not what it should be:
    :class:`RunFolderError` naming it."""
    ckpt_path, results_path = Path(folder) / "checkpoint.json", Path(folder) / "results.json"
    if ckpt_path.exists():
        saved = _read_json(ckpt_path, "checkpoint")
        units = saved.get("units", {})
        if not isinstance(saved.get("config_hash"), str) or not isinstance(units, dict):
            raise RunFolderError(f"{ckpt_path}: not a valid checkpoint (no config_hash or units)")
        code = saved.get("code")
        code = code if isinstance(code, dict) else None
        return saved["config_hash"], saved.get("config"), ckpt_path, units, code
    if results_path.exists():  # a finished study without units: compare the configs it recorded
        recorded = _read_json(results_path, "results file").get("config") or {}
        if not isinstance(recorded, dict):
            raise RunFolderError(f"{results_path}: not a valid results file (its config is not an object)")
        return config_hash(recorded), result_config(recorded), results_path, {}, None
    return None


class CodeChanged(RunFolderError):
    """A run folder whose finished units were computed by other code than this run's: continuing it would
    mix the two in one table; refused (one line naming both versions and what to do instead)."""


def check_code(folder: Path, saved: tuple | None, current: dict) -> None:
    """:class:`CodeChanged` if ``folder``'s checkpoint (``saved``: :func:`saved_run`'s) holds finished units
    of another code version than ``current``; nothing for a folder without units."""
    if saved is None or not saved[3] or saved[2].name != "checkpoint.json":
        return
    from experiments.provenance import code_difference

    differ = code_difference(saved[4], current)
    if differ is None:
        return
    old = saved[4].get("commit")
    raise CodeChanged(
        f"{saved[2]}: its {len(saved[3])} finished units come from other code ({differ}); continuing would "
        f"mix the two: start a fresh run (without resume=, or another hydra.run.dir / hydra.sweep.dir)"
        + (f", or finish this one with its own code (git checkout {old[:12]})" if old else ""))


def differing_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    """The dotted keys whose values differ between the configs ``a`` and ``b`` (sorted; one missing on either side counts)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b), key=str):
            name = f"{prefix}.{key}" if prefix else str(key)
            if key not in a or key not in b:
                out.append(name)
            else:
                out += differing_keys(a[key], b[key], name)
        return out
    return [] if a == b else [prefix or "(config)"]

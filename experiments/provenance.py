"""Provenance of a study run: versions, source revision, host, times, the resolved device and dtype.

Written to ``results.json`` under ``provenance`` (docs/studies.md, "results.json"), so a table can
be traced to the code and machine that produced it.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["CODE_PATHS", "Provenance", "code_difference", "code_version", "describe_code", "git_revision",
           "versions"]

ROOT = Path(__file__).resolve().parents[1]


def versions() -> dict[str, str]:
    """Versions of Python, torchmm and the libraries that decide the numbers."""
    import numpy
    import torch

    import torchmm

    out = {"python": platform.python_version(), "torchmm": torchmm.__version__, "torch": torch.__version__,
           "numpy": numpy.__version__}
    try:
        import hydra

        out["hydra"] = hydra.__version__
    except ImportError:  # pragma: no cover - Hydra is a dependency of the studies
        pass
    return out


def git_revision(root: Path = ROOT) -> dict[str, Any]:
    """``{"commit": sha, "dirty": bool}`` of the source tree the studies run from (None outside git)."""
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10)
        if commit.returncode != 0:
            return {"commit": None, "dirty": None}
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=10)
        return {"commit": commit.stdout.strip(), "dirty": bool(status.stdout.strip())}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}


#: the source trees a study's numbers depend on (the code version compares them, not docs or tests)
CODE_PATHS = ("torchmm", "experiments", "conf")


def code_version(root: Path = ROOT) -> dict[str, Any]:
    """The code a run's numbers come from, as recorded in ``checkpoint.json`` (``code``) and compared when a
    run is continued (:func:`code_difference`): ``{"torchmm": version, "commit": sha, "dirty": bool,
    "changed": bool, "source": fingerprint}`` - ``dirty``: uncommitted changes to tracked files anywhere;
    ``changed``: to those of :data:`CODE_PATHS`; ``source``: the first 16 hex digits of the sha256 of the
    list of the tracked files under :data:`CODE_PATHS` with their contents' blob ids as they are on disk
    (``git ls-tree -r HEAD``, with ``git hash-object`` of those ``git diff HEAD`` names), so that it follows
    the code alone: an edit or a commit of docs or tests keeps it, committing an edit keeps it, and any
    change to a code file changes it (``commit``, ``dirty``, ``changed`` and ``source`` None outside git)."""
    from torchmm import __version__

    git = git_revision(root)
    out = {"torchmm": __version__, "commit": git["commit"], "dirty": git["dirty"], "changed": None,
           "source": None}
    if git["commit"] is None:
        return out
    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=60)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout if done.returncode == 0 else None

    listing = git("ls-tree", "-r", "-z", "HEAD", "--", *CODE_PATHS)  # "<mode> blob <sha>\t<path>\0" per file
    changed = git("diff", "HEAD", "--name-only", "-z", "--no-renames", "--", *CODE_PATHS)
    if listing is None or changed is None:
        return out
    blobs = {entry.split("\t", 1)[1]: entry.split()[2] for entry in listing.split("\0") if "\t" in entry}
    edited = [path for path in changed.split("\0") if path]
    for path in edited:
        blobs.pop(path, None)  # deleted: gone; edited or added: its working-tree contents below
    present = [path for path in edited if (root / path).is_file()]
    if present:
        shas = git("hash-object", "--", *present)  # (computes the blob ids; writes nothing)
        if shas is None:
            return out
        blobs.update(zip(present, shas.split()))
    out["changed"] = bool(edited)
    text = "\n".join(f"{sha} {path}" for path, sha in sorted(blobs.items()))
    out["source"] = hashlib.sha256(text.encode()).hexdigest()[:16]
    return out


def code_difference(saved: dict | None, current: dict) -> str | None:
    """None if the code versions ``saved`` (a checkpoint's ``code``) and ``current`` (:func:`code_version`)
    are the same - or ``saved`` is None (a checkpoint written before code versions were recorded: nothing to
    compare) - else ``"<saved>; this run: <current>"`` naming both. Compared: the torchmm version and, where
    both have one, the ``source`` fingerprint (the code's trees and their uncommitted changes)."""
    if not isinstance(saved, dict):
        return None
    keys = ["torchmm"] + (["source"] if saved.get("source") and current.get("source") else [])
    if all(saved.get(k) == current.get(k) for k in keys):
        return None
    return f"{describe_code(saved)}; this run: {describe_code(current)}"


def describe_code(code: dict) -> str:
    """A code version in a few words: ``commit 0123456789ab with uncommitted code changes (code 1a2b...),
    torchmm 0.1.0``."""
    commit = code.get("commit")
    where = f"commit {commit[:12]}" if commit else "no git commit"
    if code.get("changed"):
        where += " with uncommitted code changes"
    if code.get("source"):
        where += f" (code {code['source']})"
    return f"{where}, torchmm {code.get('torchmm')}"


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


class Provenance:
    """Collects a run's provenance: :meth:`start` before the study, :meth:`finish` after it."""

    def __init__(self):
        self.data: dict[str, Any] = {}
        self._tic = 0.0

    def start(self, *, device, dtype, threads: int) -> None:
        self._tic = time.perf_counter()
        code = code_version()
        self.data = {
            "versions": versions(),
            "git": {k: code[k] for k in ("commit", "dirty", "changed", "source")},
            "host": platform.node(),
            "platform": platform.platform(),
            "command": " ".join(sys.argv) if sys.argv and sys.argv[0] else None,
            "start": _now(),
            "end": None,
            "wall_seconds": None,
            "device": str(device),  # resolved (device=auto is recorded as what it chose)
            "dtype": str(dtype).removeprefix("torch."),
            "threads": int(threads),
        }

    def finish(self) -> None:
        self.data["end"] = _now()
        self.data["wall_seconds"] = round(time.perf_counter() - self._tic, 3)

    def continue_from(self, previous: dict | None, units_kept: int) -> None:
        """After :meth:`finish`, for a run that continued a folder: ``previous`` is the provenance of the
        finished run the folder held (its results.json's; None if it held none: an interrupted run).

        * a finished run of the same code (:func:`code_difference` of ``versions.torchmm`` and ``git``) of
          which units were kept (``units_kept``: those the study read back from the checkpoint): its
          provenance is kept (start, end, wall_seconds, command, ...: when and how its numbers were made) and
          this process is appended to its ``resumes``: ``{start, end, wall_seconds, command, host, units_kept,
          kernels}``;
        * else this process's provenance, with ``resumed: {"units_kept"}`` where units came from the
          checkpoint (its start is this process's) and ``replaced``: the start, end, command and git of a
          finished run whose results this run recomputed (other code, or none of its units asked for again: a
          resume with another ``unit_runs``)."""
        if previous is not None and previous.get("end") and units_kept and _same_code(previous, self.data):
            record = {k: self.data.get(k) for k in ("start", "end", "wall_seconds", "command", "host")}
            record.update(units_kept=int(units_kept), kernels=self.data.get("kernels", {}))
            self.data = {**previous, "resumes": [*previous.get("resumes", []), record]}
            return
        if units_kept:
            self.data["resumed"] = {"units_kept": int(units_kept)}
        if previous is not None and previous.get("end"):
            self.data["replaced"] = {k: previous.get(k) for k in ("start", "end", "command", "git")}

    def record_kernels(self, runs: dict, *, executor: str, resumed: bool = False) -> None:
        """``kernels``: the study's ``run_filter`` calls by the kernel that computed them (``{name: calls}``;
        ``"eager steps"``: no kernel; torchmm.kernels.counting), counted in the study's process; with
        ``kernels_note`` where units ran elsewhere (another executor) or came from the checkpoint."""
        self.data["kernels"] = dict(sorted(runs.items()))
        if executor != "local":
            self.data["kernels_note"] = (f"executor {executor}: the units ran in other processes, whose runs are "
                                         "not counted here")
        elif resumed:
            self.data["kernels_note"] = "the units came from the checkpoint: no run was made"


def _same_code(a: dict, b: dict) -> bool:
    """Whether two provenances name the same code (:func:`code_difference` of their versions and git)."""
    def code(p: dict) -> dict:
        return {"torchmm": (p.get("versions") or {}).get("torchmm"), **(p.get("git") or {})}

    return code_difference(code(a), code(b)) is None

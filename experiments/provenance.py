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

__all__ = ["Provenance", "code_version", "git_revision", "versions"]

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


def code_version(root: Path = ROOT) -> dict[str, Any]:
    """The code a run's numbers come from, as recorded in ``checkpoint.json`` (``code``) and compared when a
    run is continued (:func:`experiments.folders.code_difference`): ``{"torchmm": version, "commit": sha or
    None, "dirty": bool or None, "diff": the first 16 hex digits of the sha256 of ``git diff HEAD`` (the
    uncommitted changes to tracked files) or None}`` (``commit``, ``dirty`` and ``diff`` None outside git)."""
    from torchmm import __version__

    git = git_revision(root)
    diff = None
    if git["dirty"]:
        try:
            out = subprocess.run(["git", "-C", str(root), "diff", "HEAD", "--no-ext-diff", "--binary"],
                                 capture_output=True, timeout=30)
            diff = hashlib.sha256(out.stdout).hexdigest()[:16] if out.returncode == 0 else None
        except (OSError, subprocess.SubprocessError):
            diff = None
    return {"torchmm": __version__, "commit": git["commit"], "dirty": git["dirty"], "diff": diff}


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
            "git": {k: code[k] for k in ("commit", "dirty", "diff")},
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

        * a finished run of the same code (the same ``versions.torchmm`` and ``git``): its provenance is
          kept (start, end, wall_seconds, command, ...: when and how its numbers were made) and this
          process is appended to its ``resumes``: ``{start, end, wall_seconds, command, host, units_kept,
          kernels}``;
        * else this process's provenance, with ``resumed: {"units_kept"}`` where units came from the
          checkpoint (its start is this process's) and ``replaced``: the start, end, command and git of a
          finished run of other code whose results this run recomputed."""
        if previous is not None and previous.get("end") and _same_code(previous, self.data):
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
    """Whether two provenances name the same code: torchmm version and git commit, dirty flag and diff."""
    return ((a.get("versions") or {}).get("torchmm") == (b.get("versions") or {}).get("torchmm")
            and all((a.get("git") or {}).get(k) == (b.get("git") or {}).get(k) for k in ("commit", "dirty", "diff")))

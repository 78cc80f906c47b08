"""Provenance of a study run: versions, source revision, host, times, the resolved device and dtype.

Written to ``results.json`` under ``provenance`` (docs/studies.md, "results.json"), so a table can
be traced to the code and machine that produced it.
"""

from __future__ import annotations

import datetime as _dt
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["Provenance", "git_revision", "versions"]

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


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


class Provenance:
    """Collects a run's provenance: :meth:`start` before the study, :meth:`finish` after it."""

    def __init__(self):
        self.data: dict[str, Any] = {}
        self._tic = 0.0

    def start(self, *, device, dtype, threads: int) -> None:
        self._tic = time.perf_counter()
        self.data = {
            "versions": versions(),
            "git": git_revision(),
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

"""torchmm's studies: ``torchmm-run`` (experiments/run.py), ``torchmm-report`` (experiments/report.py)
and, from Python, :func:`study` and :func:`load` (experiments/api.py; docs/tutorial-study.md).

``study``, ``load`` and ``StudyResults`` are imported on first use, so ``import experiments`` stays
cheap (no torch or Hydra until a study runs).
"""

from __future__ import annotations

from typing import Any

__all__ = ["StudyResults", "load", "study"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from experiments import api

        return getattr(api, name)
    raise AttributeError(f"module 'experiments' has no attribute {name!r}")

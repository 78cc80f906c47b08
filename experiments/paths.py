"""Where the harness finds its files (no imports beyond the standard library: every module may use it)."""

from __future__ import annotations

from pathlib import Path

#: conf/ next to this package (absolute, so the console script works from any directory)
CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "conf")

"""Real data shipped with torchmm (package data; sources and licences in ``experiments/data/README.md``).

* ``fedfunds.csv`` - quarterly effective federal funds rate 1954Q3-2010Q4 (``date,rate``).
* ``nile.csv`` - annual Nile flow at Aswan 1871-1970 (``year,flow``).
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["FILES", "path"]

#: the files shipped here
FILES = ("fedfunds.csv", "nile.csv", "README.md")


def path(name: str) -> Path:
    """The path of the shipped data file ``name`` (e.g. ``"fedfunds.csv"``).

    Raises:
        TypeError: ``name`` is not a string.
        ValueError: ``name`` is not one of :data:`FILES`.
    """
    if not isinstance(name, str):
        raise TypeError(f"name: expected a file name (str), got {type(name).__name__}")
    if name not in FILES:
        raise ValueError(f"name: no data file {name!r} in experiments/data; expected one of {FILES}")
    return Path(__file__).resolve().parent / name

"""Compatibility alias: the shared linear algebra lives in :mod:`torchmm.linalg` (below the filters)."""

from torchmm.linalg import *  # noqa: F401,F403
from torchmm.linalg import __all__  # noqa: F401

"""Mode transition models; they live in :mod:`torchmm.models.transition` (below filters and simulators)."""

from torchmm.models.transition import *  # noqa: F401,F403
from torchmm.models.transition import __all__  # noqa: F401

"""Data association: filters that take a *set* of detections per scan (clutter, missed detections).

docs/tracking.md. :class:`PDA` (probabilistic data association) wraps any Gaussian filter of the
contract (Kalman, extended, unscented); :class:`JPDA` associates a run's tracks jointly
(:func:`jpda_marginals`: exact, or loopy belief propagation).
"""

from torchmm.association.jpda import JPDA, jpda_marginals
from torchmm.association.pda import PDA, chi2_gate

__all__ = ["JPDA", "PDA", "chi2_gate", "jpda_marginals"]

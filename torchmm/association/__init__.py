"""Data association: filters that take a *set* of detections per scan (clutter, missed detections).

docs/tracking.md. :class:`PDA` (probabilistic data association) wraps any Gaussian filter of the
contract (Kalman, extended, unscented).
"""

from torchmm.association.pda import PDA, chi2_gate

__all__ = ["PDA", "chi2_gate"]

"""Single-model filters sharing one interface (predict / update / step -> StepOutput)."""

from torchmm.filters.base import Filter, StepOutput
from torchmm.filters.kalman import ExtendedKalmanFilter, KalmanFilter
from torchmm.filters.smoother import rts_smoother, rts_step
from torchmm.filters.unscented import (
    CubatureSigmaPoints,
    JulierSigmaPoints,
    MerweScaledSigmaPoints,
    SigmaPointStrategy,
    UnscentedKalmanFilter,
)

__all__ = [
    "CubatureSigmaPoints",
    "ExtendedKalmanFilter",
    "Filter",
    "JulierSigmaPoints",
    "KalmanFilter",
    "MerweScaledSigmaPoints",
    "SigmaPointStrategy",
    "StepOutput",
    "UnscentedKalmanFilter",
    "rts_smoother",
    "rts_step",
]

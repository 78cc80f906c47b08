"""Distributed fusion under time-correlated multiplicative noise (paper 002).

* :mod:`.system`: the multi-sensor system (1)-(3) and its batched simulator;
* :mod:`.local`: non-augmented local predictors / filters / smoothers (Theorems 1-3) and the
  cross-covariances between sensors (Theorems 4-6), sensors as a batch axis;
* :mod:`.augmented`: the augmented formulation (12)-(15) and centralized fusion (Remark 10);
* :mod:`.weights`: matrix / diagonal / scalar weighted fusion (44)-(47), also of any estimators' beliefs
  (:func:`fuse_tracks`: IMM, UKF or particle tracks);
* :mod:`.steady`: steady-state gains, cross-covariances and fused estimators (Theorems 7-8).

Missing measurements (NaN) are supported when the pattern is the same in every run (multi-rate
sensors, dropouts shared by a batch): they become a time-varying measurement model with zero gain.
"""

from torchmm.fusion.augmented import (
    augmented_cross_predictor,
    augmented_local_estimates,
    centralized_estimates,
    correlated_kf,
)
from torchmm.fusion.cross import CrossStats, cross_covariances, cross_predictor_stats, theorem6_cross_covariances
from torchmm.fusion.local import (
    LocalStats,
    local_covariances,
    local_estimates,
    local_one_step,
    local_predictor_stats,
)
from torchmm.fusion.steady import (
    SteadyState,
    steady_fused_estimates,
    steady_local_estimates,
    steady_moments,
    steady_state,
)
from torchmm.fusion.system import (
    FusionSimulation,
    MeasurementSequence,
    MultiSensorSystem,
    measurement_pattern,
    measurement_sequence,
    simulate_fusion,
)
from torchmm.fusion.weights import FUSION_METHODS, FusedEstimate, fuse, fuse_tracks, fusion_weights

__all__ = [
    "FUSION_METHODS",
    "CrossStats",
    "FusedEstimate",
    "FusionSimulation",
    "LocalStats",
    "MeasurementSequence",
    "MultiSensorSystem",
    "SteadyState",
    "augmented_cross_predictor",
    "augmented_local_estimates",
    "centralized_estimates",
    "correlated_kf",
    "cross_covariances",
    "cross_predictor_stats",
    "fuse",
    "fuse_tracks",
    "fusion_weights",
    "local_covariances",
    "local_estimates",
    "local_one_step",
    "local_predictor_stats",
    "measurement_pattern",
    "measurement_sequence",
    "simulate_fusion",
    "steady_fused_estimates",
    "steady_local_estimates",
    "steady_moments",
    "steady_state",
    "theorem6_cross_covariances",
]

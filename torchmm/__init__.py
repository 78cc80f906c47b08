"""torchmm: batched multiple-model state estimation in PyTorch.

The public API is importable from the top level; see ``README.md`` for a one-page tour and
:mod:`torchmm.typing` for the shape vocabulary.
"""

from torchmm.beliefs import Belief, GaussianBelief, ModeBelief, ParticleBelief
from torchmm.filters import (
    CubatureSigmaPoints,
    ExtendedKalmanFilter,
    Filter,
    JulierSigmaPoints,
    KalmanFilter,
    MerweScaledSigmaPoints,
    StepOutput,
    UnscentedKalmanFilter,
    rts_smoother,
)
from torchmm.models import (
    CholeskyCovariance,
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    LearnedMeasurement,
    LearnedMotion,
    LinearMeasurement,
    LinearMotion,
    LogDiagonalCovariance,
    LogScaleCovariance,
    MeasurementModel,
    MotionModel,
    NonlinearCoordinatedTurn,
    PositionMeasurement,
    RangeBearing,
    learnable_noise,
)
from torchmm.multimodel import (
    GPB1,
    GPB2,
    IMM,
    FilterBank,
    ListBank,
    ModeTransition,
    VectorizedBank,
    alpha_transition,
    make_bank,
    validate_transition,
)
from torchmm.run import Trajectory, run_filter
from torchmm.distributions import MultivariateStudentT, SkewT, truncated_normal_moments
from torchmm.filters.variational import (
    VBAKFPR,
    AdaptiveGaussianBelief,
    SkewTIWVBFilter,
    SkewTVBFilter,
    StudentTVBFilter,
)
from torchmm.multimodel import (
    FusionIMM,
    InfluenceGate,
    MultiRate,
    SourceModeVSIMM,
    SourceUpdateIMM,
    TransferIMM,
    influence_value,
)
from torchmm.multimodel.variational import VariationalIMM, gimmaf, imm_vbt
from torchmm.filters.particle import ParticleFilter
from torchmm.multimodel.particle import MultipleModelParticleFilter
from torchmm.multimodel.mevsmm import (
    ChallengeMatch,
    EqMAParticleFilter,
    ExactMinimumEntropy,
    MinimumEntropyVSMM,
    ModelSetBelief,
)
from torchmm import analysis, fusion, learn, metrics, simulate  # subpackages, reachable as attributes

__version__ = "0.1.0"

__all__ = [
    "AdaptiveGaussianBelief",
    "ChallengeMatch",
    "EqMAParticleFilter",
    "ExactMinimumEntropy",
    "MinimumEntropyVSMM",
    "ModelSetBelief",
    "MultipleModelParticleFilter",
    "ParticleFilter",
    "CholeskyCovariance",
    "LearnedMeasurement",
    "LearnedMotion",
    "LogDiagonalCovariance",
    "LogScaleCovariance",
    "learnable_noise",
    "FusionIMM",
    "InfluenceGate",
    "MultiRate",
    "MultivariateStudentT",
    "SkewT",
    "SkewTIWVBFilter",
    "SkewTVBFilter",
    "SourceModeVSIMM",
    "SourceUpdateIMM",
    "StudentTVBFilter",
    "TransferIMM",
    "VBAKFPR",
    "VariationalIMM",
    "gimmaf",
    "imm_vbt",
    "influence_value",
    "truncated_normal_moments",
    "analysis",
    "fusion",
    "learn",
    "metrics",
    "simulate",
    "GPB1",
    "GPB2",
    "IMM",
    "Belief",
    "ConstantAcceleration",
    "ConstantVelocity",
    "CoordinatedTurn",
    "CubatureSigmaPoints",
    "ExtendedKalmanFilter",
    "Filter",
    "FilterBank",
    "GaussianBelief",
    "JulierSigmaPoints",
    "KalmanFilter",
    "LinearMeasurement",
    "LinearMotion",
    "ListBank",
    "MeasurementModel",
    "MerweScaledSigmaPoints",
    "ModeBelief",
    "ModeTransition",
    "MotionModel",
    "NonlinearCoordinatedTurn",
    "ParticleBelief",
    "PositionMeasurement",
    "RangeBearing",
    "StepOutput",
    "Trajectory",
    "UnscentedKalmanFilter",
    "VectorizedBank",
    "alpha_transition",
    "make_bank",
    "rts_smoother",
    "run_filter",
    "validate_transition",
]

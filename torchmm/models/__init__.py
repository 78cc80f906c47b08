"""Motion and measurement models (stateless ``nn.Module`` s)."""

from torchmm.models.adapters import (
    CholeskyCovariance,
    LearnedMeasurement,
    LearnedMotion,
    LogDiagonalCovariance,
    LogScaleCovariance,
    learnable_noise,
)
from torchmm.models.base import MeasurementModel, MotionModel, forward_jacobian
from torchmm.models.linear import LinearMeasurement, LinearMotion
from torchmm.models.measurement import PositionMeasurement, RangeBearing
from torchmm.models.motion import (
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    NonlinearCoordinatedTurn,
    kinematic_matrices,
)

__all__ = [
    "CholeskyCovariance",
    "LearnedMeasurement",
    "LearnedMotion",
    "LogDiagonalCovariance",
    "LogScaleCovariance",
    "learnable_noise",
    "ConstantAcceleration",
    "ConstantVelocity",
    "CoordinatedTurn",
    "LinearMeasurement",
    "LinearMotion",
    "MeasurementModel",
    "MotionModel",
    "NonlinearCoordinatedTurn",
    "PositionMeasurement",
    "RangeBearing",
    "forward_jacobian",
    "kinematic_matrices",
]

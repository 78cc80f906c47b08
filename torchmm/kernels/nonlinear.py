"""The nonlinear-Gaussian kernel family's description (docs/architecture.md, "Kernels").

An :class:`~torchmm.ExtendedKalmanFilter` or :class:`~torchmm.UnscentedKalmanFilter` (and an IMM or GPB1
over one) describes itself through ``filter.nonlinear_gaussian()``; the batch-last kernel
(:mod:`torchmm.kernels.batch_last.nonlinear`) runs the whole run from it, calling the filter's own
models one state component at a time (:meth:`~torchmm.models.MotionModel.forward_entries`,
:meth:`~torchmm.models.MotionModel.jacobian_entries`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

from torch import Tensor

__all__ = ["NonlinearGaussian"]


class NonlinearGaussian(NamedTuple):
    """A filter's description of itself for the nonlinear-Gaussian kernel.

    Attributes:
        motion: the :class:`~torchmm.models.MotionModel` (parameters broadcasting against the
            belief's batch ``(*B, M)``, as in the filter's steps).
        measurement: the :class:`~torchmm.models.MeasurementModel`.
        kind: ``"extended"`` (Jacobians) or ``"unscented"`` (sigma points).
        sigma_points: the unscented filter's :class:`~torchmm.filters.SigmaPointStrategy` (None for the
            extended filter).
        joseph: the unscented filter's ``joseph`` option (the kernel takes the ``P - K S K^T`` form only).
        transition: ``(M, M)``, None for a single filter.
        rule: ``"kalman"`` (one filter), ``"mix"`` (IMM) or ``"collapse"`` (GPB1).
        post_update: None, or the filter's own work after each step's update, as
            :class:`~torchmm.kernels.linear.LinearGaussian`'s (a variable-structure IMM's model-set policy).
    """

    motion: Any
    measurement: Any
    kind: str
    sigma_points: Any = None
    joseph: bool | None = None
    transition: Tensor | None = None
    rule: str = "kalman"
    post_update: Any = None

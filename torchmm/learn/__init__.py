"""Learning by gradient through the filters: marginal log-likelihood losses and a trainer.

* :func:`negative_log_likelihood` - ``-log p(z_{1:T})`` of a batch of sequences through any
  filter (KF, EKF, UKF, IMM, GPB1/2, ...), differentiable w.r.t. every parameter of the filter's
  modules (transition logits, parametrised noise covariances, networks).
* :func:`truncated_segments` and :class:`Trainer` (``window=``) - truncated back-propagation
  through time for long sequences.
* :func:`estimate` - maximum likelihood of any tensors of a filter (:class:`Param`: free, bounded,
  variances, covariances, transition matrices, shared and fixed entries) with standard errors from the
  observed information, AIC, BIC and expected durations (:class:`Estimate`).
* :class:`Trainer` - a training loop with a logger/callback hook (no TensorBoard import: pass any
  object with ``scalar(tag, value, step)``), parameter tracking and checkpoints
  (:func:`save_checkpoint` / :func:`load_checkpoint`).
* :func:`soft_resample`, :class:`SoftResamplingParticleFilter` - differentiable (soft)
  resampling of particle beliefs and a particle filter that uses it.
"""

from torchmm.learn.em import EMResult, em
from torchmm.learn.em_switching import SwitchingEMResult, em_switching
from torchmm.learn.entries import Param, estimated_entries, stationary
from torchmm.learn.estimation import Estimate, estimate
from torchmm.learn.loss import negative_log_likelihood, truncated_segments
from torchmm.learn.objective import Objective
from torchmm.learn.resampling import (
    SoftResamplingParticleFilter,
    soft_resample,
    soft_resample_where_needed,
)
from torchmm.learn.trainer import NonFiniteLossError, Trainer, TrainRecord, load_checkpoint, save_checkpoint

__all__ = [
    "EMResult",
    "Estimate",
    "Objective",
    "Param",
    "SwitchingEMResult",
    "NonFiniteLossError",
    "SoftResamplingParticleFilter",
    "TrainRecord",
    "Trainer",
    "em",
    "em_switching",
    "estimate",
    "estimated_entries",
    "load_checkpoint",
    "negative_log_likelihood",
    "save_checkpoint",
    "soft_resample",
    "soft_resample_where_needed",
    "stationary",
    "truncated_segments",
]

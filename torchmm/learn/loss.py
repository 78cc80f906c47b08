r"""The training loss: negative marginal log-likelihood of measurement sequences.

Every torchmm filter returns ``log p(z_k | z_{1:k-1})`` from its update (Gaussian filters: the
innovation density; IMM/GPB: ``logsumexp_j(ell_j + log c_j)``), so by the chain rule

.. math::
    -\log p_\theta(z_{1:T}) = -\textstyle\sum_{k=1}^T \log p_\theta(z_k \mid z_{1:k-1})

is the prediction-error decomposition of the likelihood: exact for the Kalman filter, the
filter's own approximation for EKF/UKF/IMM/GPB. Missing measurements (NaN) contribute 0; a run
whose update failed (a present datum and a non-finite prediction, e.g. a network whose weights went
NaN: ``extras["failed"]``, docs/robustness.md) contributes NaN, so the loss is NaN, never a
silently finite value.
"""

from __future__ import annotations

from typing import Any

from torch import Tensor
from torch.nn.utils import parametrize

from torchmm.beliefs import ModeBelief
from torchmm.contract import BeliefArg, Choice, Data, Flag, Int, Of, entry_point
from torchmm.filters.base import Filter
from torchmm.run import Keep, run_filter
from torchmm.validation import check_filter_dtype

__all__ = ["negative_log_likelihood", "truncated_segments"]

REDUCTIONS = ("mean", "sum", "none")


_keep_likelihood = Keep("log_likelihood")
_keep_likelihood_and_detached_belief = Keep("log_likelihood", "belief", detach=True)




@entry_point(filter=Of(Filter), belief0=BeliefArg(validate=True), measurements=Data(),
             controls=Data(optional=True), reduction=Choice(*REDUCTIONS), return_final=Flag(),
             update_first=Flag())
def negative_log_likelihood(
    filter: Filter,
    belief0: Any,
    measurements: Tensor,
    *,
    controls: Tensor | None = None,
    reduction: str = "mean",
    return_final: bool = False,
    update_first: bool = False,
):
    r"""``-log p(z_{1:T})`` of a batch of measurement sequences through ``filter``.

    Args:
        filter: any filter (KF/EKF/UKF, IMM/GPB over any bank, ...).
        belief0: belief at time 0, batch ``(*B,)``. For a multiple-model filter a
            :class:`~torchmm.beliefs.GaussianBelief` is accepted and started with uniform mode
            probabilities (``filter.initial_belief``).
        measurements: ``(T, *B, m)``; NaN = missing.
        controls: optional ``(T, *B, k)``.
        reduction: ``"mean"`` - mean over runs and time steps (a per-step loss whose scale does
            not depend on ``T`` or the batch size); ``"sum"`` - total over runs and steps;
            ``"none"`` - ``(*B,)`` totals over time.
        return_final: also return the final posterior, detached from the graph (to continue
            filtering, e.g. the next segment of truncated back-propagation through time).
        update_first: ``belief0`` is the prior of the *first measurement* (step 0 is an update
            only, no prediction: :func:`~torchmm.run_filter`'s ``update_first``), the convention of
            statsmodels, pykalman and Durbin and Koopman's ``a_1, P_1``. Default False: ``belief0``
            is the belief at time 0 and every step predicts, then updates.

    Returns:
        the loss (scalar, or ``(*B,)`` for ``reduction="none"``), and the final belief if asked.

    Shapes:
        measurements ``(T, *B, m)`` -> ``()`` or ``(*B,)``

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> kf = KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0))
        >>> prior = GaussianBelief(torch.zeros(3, 2), torch.eye(2))
        >>> negative_log_likelihood(kf, prior, torch.randn(20, 3, 1), reduction="none").shape
        torch.Size([3])
    """
    if reduction not in REDUCTIONS:
        raise ValueError(f"reduction: expected one of {REDUCTIONS}, got {reduction!r}")
    if not isinstance(measurements, Tensor) or measurements.dim() < 2:
        raise ValueError("measurements: expected a time-major tensor (T, *B, m)")
    belief0 = as_start_belief(filter, belief0)
    record = _keep_likelihood_and_detached_belief if return_final else _keep_likelihood
    with parametrize.cached():  # parametrised covariances are computed once per pass
        traj = run_filter(filter, belief0, measurements, controls=controls, record=record,
                          update_first=update_first)
    loss = reduce_total(-traj.log_likelihood.sum(0), reduction, measurements.shape[0])
    return (loss, traj.final_belief) if return_final else loss


def reduce_total(total: Tensor, reduction: str, steps: int) -> Tensor:
    """The loss from the per-run totals ``-log p(z_{1:T})`` ``(*B,)``: ``"none"`` keeps them, ``"sum"``
    adds them, ``"mean"`` averages over runs and the ``steps`` time steps (shared by
    :func:`negative_log_likelihood` and :class:`~torchmm.learn.Objective`)."""
    if reduction == "none":
        return total
    if reduction == "sum":
        return total.sum()
    return total.mean() / steps


@entry_point(steps=Int(0), window=Int(1, optional=True))
def truncated_segments(steps: int, window: int | None) -> list[slice]:
    """Time slices of at most ``window`` steps covering ``0 .. steps - 1`` (all of it if ``None``).

    Truncated back-propagation through time filters segment after segment, starting each from
    the previous segment's final belief *detached* from the graph, so memory and the cost of a
    gradient step are bounded by ``window`` (the gradient ignores dependence across segments).

    Examples:
        >>> truncated_segments(10, 4)
        [slice(0, 4, None), slice(4, 8, None), slice(8, 10, None)]
    """
    if window is None:
        return [slice(0, steps)]
    window = int(window)
    if window < 1:
        raise ValueError(f"window: must be a positive number of steps, got {window}")
    return [slice(start, min(start + window, steps)) for start in range(0, steps, window)]


def as_start_belief(filter, belief0):
    """The filter's belief at time 0: ``belief0`` itself if it is already a mode belief (from
    ``initial_belief``), otherwise ``filter.initial_belief(belief0)`` (every filter has one; the
    base returns the prior validated)."""
    if isinstance(belief0, ModeBelief):
        return belief0
    # named as the caller passed it (initial_belief says "belief")
    check_filter_dtype(filter, belief0, "belief0")
    return filter.initial_belief(belief0)

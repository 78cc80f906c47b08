r"""Rauch-Tung-Striebel fixed-interval smoother (extended form for nonlinear motion models).

.. math::
    G_k = P_k F_{k+1}^\top (P^-_{k+1})^{-1},\quad
    x^s_k = x_k + G_k (x^s_{k+1} - x^-_{k+1}),\quad
    P^s_k = P_k + G_k (P^s_{k+1} - P^-_{k+1}) G_k^\top

with ``F_{k+1}`` the motion Jacobian at the filtered mean ``x_k`` (the matrix itself for linear
models). The only loop is over time.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief, symmetrize
from torchmm.linalg import cholesky, cholesky_solve
from torchmm.models.base import MotionModel
from torchmm.contract import BeliefArg, Finite, Of, entry_point
from torchmm.validation import as_tensor, check_filter_dtype, check_same_dtype

__all__ = ["rts_smoother", "rts_step"]


@entry_point(motion=Of(MotionModel), filtered=BeliefArg(validate=True), predicted=BeliefArg(validate=True),
             controls=Finite(optional=True, check=False))
def rts_smoother(
    motion: MotionModel,
    filtered: GaussianBelief,
    predicted: GaussianBelief,
    *,
    controls: Tensor | None = None,
) -> GaussianBelief:
    """Smooth a filtered trajectory backwards.

    Args:
        motion: the motion model the filter used.
        filtered: posteriors ``x_{k|k}`` for ``k = 1..T`` (e.g. ``trajectory.belief``).
        predicted: priors ``x_{k|k-1}`` for the same steps (e.g. ``trajectory.prior``).
        controls: inputs ``u_k`` used by the filter's predictions, ``(T, *B, k)``.

    Returns:
        smoothed beliefs ``x_{k|T}``.

    Shapes:
        filtered, predicted: batch ``(T, *B)`` -> batch ``(T, *B)``
    """
    check_filter_dtype(motion, filtered, "filtered")
    check_same_dtype(predicted.mean, "predicted", filtered.mean, "filtered")
    if controls is not None:
        controls = as_tensor(controls, "controls", dtype=filtered.dtype, device=filtered.device)
    if filtered.batch_shape != predicted.batch_shape:
        raise ValueError(
            f"predicted: batch shape {tuple(predicted.batch_shape)} differs from filtered "
            f"{tuple(filtered.batch_shape)}"
        )
    filtered = filtered.materialize()
    steps = filtered.batch_shape[0]
    smoothed = [filtered[steps - 1]]
    for k in range(steps - 2, -1, -1):
        u = None if controls is None else controls[k + 1]
        smoothed.append(rts_step(motion, filtered[k], predicted[k + 1], smoothed[-1], u=u))
    means = torch.stack([b.mean for b in smoothed[::-1]])
    covs = torch.stack([b.cov for b in smoothed[::-1]])
    return GaussianBelief(means, covs)


def rts_step(
    motion: MotionModel,
    filtered: GaussianBelief,
    predicted: GaussianBelief,
    smoothed_next: GaussianBelief,
    *,
    u: Tensor | None = None,
) -> GaussianBelief:
    r"""One backward RTS step: ``x_{k|T}`` from ``x_{k|k}``, ``x_{k+1|k}`` and ``x_{k+1|T}``.

    ``G = P_k F^T (P^-_{k+1})^{-1}``, ``x^s_k = x_k + G (x^s_{k+1} - x^-_{k+1})``,
    ``P^s_k = P_k + G (P^s_{k+1} - P^-_{k+1}) G^T``. Paper 000's transfer smoothing (13)-(14) is
    this step with the source filter's posterior in place of ``x_{k+1|T}``.

    Args:
        motion: the motion model of the prediction ``k -> k+1`` (Jacobian at the filtered mean).
        filtered: ``x_{k|k}``; predicted: ``x_{k+1|k}``; smoothed_next: ``x_{k+1|T}`` (or any
            later posterior of ``x_{k+1}`` that refines ``predicted``).
        u: the input of that prediction.

    Shapes:
        all beliefs with batch ``(*B,)`` (broadcasting) -> batch ``(*B,)``

    Examples:
        >>> from torchmm.models import ConstantVelocity
        >>> cv = ConstantVelocity(1, q=1.0)
        >>> x = GaussianBelief(torch.zeros(3, 2), torch.eye(2).expand(3, 2, 2))
        >>> pred = GaussianBelief(cv(x.mean), cv.F @ x.cov @ cv.F.mT + cv.Q)
        >>> rts_step(cv, x, pred, pred).cov.allclose(x.cov)  # nothing learnt: smoothed = filtered
        True
    """
    F = motion.jacobian(filtered.mean, u=u)
    P, P_pred = filtered.cov, predicted.cov
    gain_t = cholesky_solve(cholesky(P_pred), F @ P)  # G^T = (P-)^{-1} F P
    gain = gain_t.mT
    mean = filtered.mean + (gain @ (smoothed_next.mean - predicted.mean).unsqueeze(-1)).squeeze(-1)
    cov = P + gain @ (smoothed_next.cov - P_pred) @ gain_t
    return GaussianBelief(mean, symmetrize(cov))

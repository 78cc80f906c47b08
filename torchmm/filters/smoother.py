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
from torchmm.filters.linalg import cholesky, cholesky_solve
from torchmm.models.base import MotionModel

__all__ = ["rts_smoother"]


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
    if filtered.batch_shape != predicted.batch_shape:
        raise ValueError(
            f"predicted: batch shape {tuple(predicted.batch_shape)} differs from filtered "
            f"{tuple(filtered.batch_shape)}"
        )
    filtered = filtered.materialize()
    steps = filtered.batch_shape[0]
    means, covs = [filtered.mean[-1]], [filtered.cov[-1]]
    for k in range(steps - 2, -1, -1):
        u = None if controls is None else controls[k + 1]
        F = motion.jacobian(filtered.mean[k], u=u)
        P, P_pred = filtered.cov[k], predicted.cov[k + 1]
        gain_t = cholesky_solve(cholesky(P_pred), F @ P)  # G^T = (P-)^{-1} F P
        gain = gain_t.mT
        mean = filtered.mean[k] + (gain @ (means[-1] - predicted.mean[k + 1]).unsqueeze(-1)).squeeze(-1)
        cov = P + gain @ (covs[-1] - P_pred) @ gain_t
        means.append(mean)
        covs.append(symmetrize(cov))
    return GaussianBelief(torch.stack(means[::-1]), torch.stack(covs[::-1]))

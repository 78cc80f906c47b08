r"""Gaussian conditioning with Cholesky factors; closed forms for 1x1 and 2x2 innovations.

Batched ``torch.linalg`` on thousands of tiny matrices is dominated by per-call overhead, so the
innovation covariance ``S`` (``m x m``) is factorised in closed form when ``m <= 2`` (the common
position-only sensors) and by ``torch.linalg.cholesky_ex`` otherwise. Nothing is inverted: the
update uses one forward substitution on ``[C^T | nu]``:

.. math::
    S = L L^\top,\quad V = L^{-1} C^\top,\quad w = L^{-1}\nu,\quad
    x^+ = x + V^\top w,\quad P^+ = P - V^\top V,\quad
    \log p(z) = -\tfrac12\left(\|w\|^2 + 2\textstyle\sum_i \log L_{ii} + m \log 2\pi\right)

Missing components (NaN in ``nu``) are conditioned out exactly with static shapes: their rows and
columns of ``S`` are replaced by the identity, their columns of ``C`` and entries of ``nu`` by
zero, so the gain for them is zero and they add nothing to the log-likelihood.
"""

from __future__ import annotations

import logging
import math

import torch
from torch import Tensor

from torchmm.beliefs.ops import symmetrize

__all__ = ["cholesky", "cholesky_solve", "condition", "solve_lower", "solve_lower_transposed"]

log = logging.getLogger("torchmm")
_LOG_2PI = math.log(2 * math.pi)


def cholesky(S: Tensor) -> Tensor:
    """Lower Cholesky factor of symmetric PD ``S (..., m, m)``, robust to near-singularity.

    Closed form for ``m <= 2`` (pivots clamped at ``eps * scale`` so the factor stays finite);
    for larger ``m``, failed factorisations are retried with growing diagonal jitter and a
    warning is logged.
    """
    m = S.shape[-1]
    eps = torch.finfo(S.dtype).eps
    if m == 1:
        return S.clamp_min(torch.finfo(S.dtype).tiny).sqrt()
    if m == 2:
        a, b, c = S[..., 0, 0], S[..., 1, 0], S[..., 1, 1]
        scale = torch.maximum(a.abs(), c.abs()) * eps + torch.finfo(S.dtype).tiny
        l11 = a.clamp_min(0).maximum(scale).sqrt()
        l21 = b / l11
        l22 = (c - l21 * l21).maximum(scale).sqrt()
        zero = torch.zeros_like(a)
        return torch.stack([torch.stack([l11, zero], -1), torch.stack([l21, l22], -1)], -2)
    chol, info = torch.linalg.cholesky_ex(S)
    if bool((info != 0).any()):
        diag_scale = S.diagonal(dim1=-2, dim2=-1).abs().mean(-1, keepdim=True).clamp_min(1.0)
        eye = torch.eye(m, dtype=S.dtype, device=S.device)
        for power in range(-10, 1, 2):
            jitter = (diag_scale * 10.0**power).unsqueeze(-1) * eye
            chol_j, info_j = torch.linalg.cholesky_ex(S + jitter)
            chol = torch.where((info != 0)[..., None, None], chol_j, chol)
            info = torch.where(info != 0, info_j, info)
            if not bool((info != 0).any()):
                break
        log.warning("innovation covariance not positive definite; added diagonal jitter")
    return chol


def solve_lower(L: Tensor, rhs: Tensor) -> Tensor:
    """``L^{-1} rhs`` for lower-triangular ``L (..., m, m)``, ``rhs (..., m, k)``."""
    m = L.shape[-1]
    if m == 1:
        return rhs / L
    if m == 2:
        y0 = rhs[..., 0, :] / L[..., 0, 0, None]
        y1 = (rhs[..., 1, :] - L[..., 1, 0, None] * y0) / L[..., 1, 1, None]
        return torch.stack([y0, y1], -2)
    return torch.linalg.solve_triangular(L, rhs, upper=False)


def solve_lower_transposed(L: Tensor, rhs: Tensor) -> Tensor:
    """``L^{-T} rhs`` for lower-triangular ``L (..., m, m)``, ``rhs (..., m, k)``."""
    m = L.shape[-1]
    if m == 1:
        return rhs / L
    if m == 2:
        x1 = rhs[..., 1, :] / L[..., 1, 1, None]
        x0 = (rhs[..., 0, :] - L[..., 1, 0, None] * x1) / L[..., 0, 0, None]
        return torch.stack([x0, x1], -2)
    return torch.linalg.solve_triangular(L.mT, rhs, upper=True)


def condition(
    mean: Tensor,
    cov: Tensor,
    innovation: Tensor,
    innovation_cov: Tensor,
    cross_cov: Tensor,
    *,
    joseph: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    r"""Condition a Gaussian on an innovation (the shared core of KF, EKF and UKF updates).

    Args:
        mean: prior mean ``x``.
        cov: prior covariance ``P``.
        innovation: ``nu = z - z_pred``; NaN entries are missing components.
        innovation_cov: ``S = Cov[z]``.
        cross_cov: ``C = Cov[x, z]`` (``P H^T`` for linear models).
        joseph: ``(H, R)`` to update the covariance in Joseph form
            ``(I - K H) P (I - K H)^T + K R K^T`` instead of ``P - K S K^T``.

    Returns:
        posterior mean, posterior covariance (symmetrised) and ``log N(nu; 0, S)`` over the
        observed components (0 if none is observed).

    Shapes:
        mean ``(*B, n)``, cov ``(*B, n, n)``, innovation ``(*B, m)``, innovation_cov
        ``(*B, m, m)``, cross_cov ``(*B, n, m)`` -> ``(*B, n)``, ``(*B, n, n)``, ``(*B,)``
    """
    n, m = mean.shape[-1], innovation.shape[-1]
    if m == 1 and joseph is None:
        return _condition_scalar(mean, cov, innovation, innovation_cov, cross_cov)
    observed = ~torch.isnan(innovation)
    nu = torch.where(observed, innovation, 0.0)
    if m == 1:
        S = torch.where(observed.unsqueeze(-1), innovation_cov, 1.0)
    else:
        pair = observed.unsqueeze(-1) & observed.unsqueeze(-2)
        S = torch.where(pair, innovation_cov, torch.eye(m, dtype=nu.dtype, device=nu.device))
    C = cross_cov * observed.unsqueeze(-2)
    L = cholesky(S)
    rhs = torch.cat([C.mT, nu.unsqueeze(-1)], dim=-1)  # (*B, m, n + 1)
    solved = solve_lower(L, rhs)
    V, w = solved[..., :n], solved[..., n]
    post_mean = mean + (V.mT @ w.unsqueeze(-1)).squeeze(-1)
    if joseph is None:
        post_cov = cov - V.mT @ V
    else:
        H, R = joseph
        gain = solve_lower_transposed(L, V).mT  # K = C S^{-1}, zero columns where missing
        eye = torch.eye(n, dtype=cov.dtype, device=cov.device)
        A = eye - gain @ H
        post_cov = A @ cov @ A.mT + gain @ R @ gain.mT
    half_logdet = L.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    count = observed.sum(-1).to(nu.dtype)
    log_likelihood = -0.5 * (w.square().sum(-1) + count * math.log(2 * math.pi)) - half_logdet
    return post_mean, symmetrize(post_cov), log_likelihood


def _condition_scalar(mean, cov, innovation, innovation_cov, cross_cov):
    """``m = 1``: the same update in closed form (``K = c / s``, ``P+ = P - c c^T / s``)."""
    nu = innovation[..., 0]
    observed = nu == nu  # False where NaN (missing)
    nu = torch.where(observed, nu, 0.0)
    s = innovation_cov[..., 0, 0].clamp_min(torch.finfo(nu.dtype).tiny)
    c = cross_cov[..., 0]
    gain = c * (observed / s).unsqueeze(-1)  # K = c / s, zero where missing
    post_mean = mean + gain * nu.unsqueeze(-1)
    post_cov = cov - gain.unsqueeze(-1) * c.unsqueeze(-2)  # P - K c^T (symmetrised below)
    log_likelihood = torch.where(observed, -0.5 * (nu * nu / s + s.log() + _LOG_2PI), 0.0)
    return post_mean, symmetrize(post_cov), log_likelihood


def cholesky_solve(L: Tensor, rhs: Tensor) -> Tensor:
    """``(L L^T)^{-1} rhs`` from a lower Cholesky factor. Shapes: ``(..., m, m)``, ``(..., m, k)``."""
    return solve_lower_transposed(L, solve_lower(L, rhs))

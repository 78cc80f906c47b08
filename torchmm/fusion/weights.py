r"""Linear-minimum-variance fusion weights (paper 002, (44)-(47); Sun & Deng 2004).

Given the local estimates ``x^_i`` and the joint error covariance ``P = [P_ij]`` of ``L`` unbiased
estimators, the fused estimate is ``x^_o = sum_i A_i x^_i`` with ``sum_i A_i = I``:

* **matrix** weights (45): ``A = (F^T P^{-1} F)^{-1} F^T P^{-1}``, ``P_o = (F^T P^{-1} F)^{-1}``,
  ``F = [I_n, ..., I_n]^T``;
* **diagonal-matrix** weights (46): the same formula on ``P^-``, the matrix of the diagonal parts
  of the blocks — i.e. scalar weights per state component
  ``a_c = (P_c)^{-1} e / (e^T (P_c)^{-1} e)``, ``P_c = [P_ij]_{cc}`` — and ``P_o = A P A^T``;
* **scalar** weights (47): ``a = P_tr^{-1} e / (e^T P_tr^{-1} e)``, ``P_tr = [tr P_ij]``,
  ``P_o = sum_ij a_i a_j P_ij``.

Everything is batched over leading dims (time steps); linear systems are solved, not inverted.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchmm.beliefs import Belief, GaussianBelief, stack
from torchmm.beliefs.ops import symmetrize
from torchmm.linalg import cholesky, cholesky_solve

__all__ = ["FusedEstimate", "constrained_weights", "fusion_weights", "fuse", "fuse_tracks", "FUSION_METHODS"]

FUSION_METHODS = ("matrix", "diagonal", "scalar")


def _stack_blocks(P: Tensor) -> Tensor:
    """``(..., L, L, n, n) -> (..., L n, L n)``."""
    *b, L, _, n, _ = P.shape
    return P.transpose(-3, -2).reshape(*b, L * n, L * n)


def constrained_weights(P: Tensor, F: Tensor) -> Tensor:
    r"""``argmin_W tr(W^T P W)`` subject to ``F^T W = I``: the KKT system
    ``[[P, F], [F^T, 0]] [W; Lambda] = [0; I]``, solved with a symmetric pseudo-inverse.

    For positive definite ``P`` this is ``W = P^{-1} F (F^T P^{-1} F)^{-1}`` (the transpose of the
    weights in (45)-(47)); for singular ``P`` (e.g. identical prior errors before any data, when
    every admissible weight is optimal) it returns the minimum-norm optimal weights instead of
    failing. ``P`` is scaled to unit diagonal maximum first (the weights are scale-invariant).

    Shapes:
        P: ``(*B, K, K)``; F: ``(K, n)`` -> ``(*B, K, n)``
    """
    K, n = F.shape
    scale = P.diagonal(dim1=-2, dim2=-1).abs().amax(-1)[..., None, None].clamp_min(torch.finfo(P.dtype).tiny)
    Ps = P / scale
    b = Ps.shape[:-2]
    top = torch.cat([Ps, F.expand(*b, K, n)], -1)
    bottom = torch.cat([F.T.expand(*b, n, K), Ps.new_zeros(*b, n, n)], -1)
    kkt = torch.cat([top, bottom], -2)
    rhs = torch.cat([Ps.new_zeros(K, n), torch.eye(n, dtype=P.dtype, device=P.device)], 0)
    return (torch.linalg.pinv(kkt, hermitian=True) @ rhs)[..., :K, :]


def fusion_weights(P: Tensor, method: str = "matrix") -> tuple[Tensor, Tensor]:
    r"""Fusion weights and fused error covariance from the joint covariance of the local errors.

    The fused covariance is ``P_o = sum_ij A_i P_ij A_j^T``, which equals ``(F^T P^{-1} F)^{-1}``
    of (45) for the matrix weights.

    Shapes:
        P: ``(*B, L, L, n, n)`` -> weights ``(*B, L, n, n)`` (``A_i``; diagonal for ``diagonal``,
        ``a_i I`` for ``scalar``), cov ``(*B, n, n)``

    Example:
        >>> import torch
        >>> P = torch.zeros(2, 2, 1, 1); P[0, 0] = 1.0; P[1, 1] = 3.0
        >>> A, Po = fusion_weights(P, "matrix")
        >>> [round(a, 4) for a in A.flatten().tolist()], round(Po.item(), 4)
        ([0.75, 0.25], 0.75)
    """
    if P.dim() < 4 or P.shape[-4] != P.shape[-3] or P.shape[-1] != P.shape[-2]:
        raise ValueError(f"P: expected shape (*B, L, L, n, n), got {tuple(P.shape)}")
    *b, L, _, n, _ = P.shape
    kw = dict(dtype=P.dtype, device=P.device)
    e = torch.ones(L, 1, **kw)
    if method == "matrix":
        F = torch.eye(n, **kw).repeat(L, 1)  # (L n, n)
        W = constrained_weights(_stack_blocks(P), F)  # (*B, L n, n) = A^T
        weights = W.mT.unflatten(-1, (L, n)).transpose(-3, -2)  # (*B, L, n, n)
    elif method == "diagonal":
        Pc = P.diagonal(dim1=-2, dim2=-1).movedim(-1, -3)  # (*B, n, L, L): [P_ij]_cc
        a = constrained_weights(Pc, e).squeeze(-1)  # (*B, n, L)
        weights = torch.diag_embed(a.transpose(-1, -2))  # (*B, L, n, n)
    elif method == "scalar":
        Ptr = P.diagonal(dim1=-2, dim2=-1).sum(-1)  # (*B, L, L): [tr P_ij]
        a = constrained_weights(Ptr, e).squeeze(-1)  # (*B, L)
        weights = a[..., None, None] * torch.eye(n, **kw)
    else:
        raise ValueError(f"method: expected one of {FUSION_METHODS}, got {method!r}")
    Po = torch.einsum("...iab,...ijbc,...jdc->...ad", weights, P, weights)
    return weights, symmetrize(Po)


@dataclass(frozen=True)
class FusedEstimate:
    """Shapes: mean ``(T, *B, n)``; cov ``(T, n, n)``; weights ``(T, L, n, n)``."""

    mean: Tensor
    cov: Tensor
    weights: Tensor


def fuse(mean: Tensor, P: Tensor, method: str = "matrix", components=None) -> FusedEstimate:
    r"""Distributed fusion (44) of local estimates with the weights of :func:`fusion_weights`.

    ``components`` (indices) fuses only those state components (e.g. the position of Example 1,
    with ``P^s_ij`` the corresponding sub-blocks).

    Shapes:
        mean: ``(T, *B, L, n)``; P: ``(T, L, L, n, n)`` -> :class:`FusedEstimate`
    """
    if components is not None:
        idx = torch.as_tensor(list(components), device=mean.device)
        mean = mean[..., idx]
        P = P[..., idx, :][..., idx]
    weights, Po = fusion_weights(P, method)
    T = mean.shape[0]
    W = weights.reshape(T, *([1] * (mean.dim() - 3)), *weights.shape[1:])
    fused = (W @ mean.unsqueeze(-1)).squeeze(-1).sum(-2)
    return FusedEstimate(fused, Po, weights)


def fuse_tracks(tracks, cross_covs: Tensor | None = None, method: str = "matrix") -> GaussianBelief:
    r"""Track-to-track fusion of ``L`` local estimates of one state, on torchmm's belief types.

    Any estimator's output can be a track: a Kalman or unscented filter's posterior, an IMM's
    ``belief.estimate()``, a particle filter's moments (each ``track.estimate()`` is used). With the
    local errors' joint covariance ``P = [P_ij]`` (``P_ii`` the tracks' own covariances, ``P_ij``
    the cross-covariances; zero when ``cross_covs`` is None, i.e. independent tracks) the fused
    estimate is ``sum_i A_i x_i`` with the matrix, diagonal-matrix or scalar weights of (45)-(47)
    (:func:`fusion_weights`), per batch element.

    ``method="covariance_intersection"`` fuses tracks whose cross-covariances are unknown (e.g.
    local filters that share the process noise): ``P^{-1} = sum_i w_i P_i^{-1}``,
    ``x = P sum_i w_i P_i^{-1} x_i``, consistent for any correlation (Julier and Uhlmann 1997), with
    the fast weights ``w_i ∝ 1 / tr P_i`` (Niehsen 2002); ``cross_covs`` must then be None.

    Args:
        tracks: a sequence of ``L`` beliefs with batch ``(*B,)``, or one belief with batch
            ``(*B, L)`` (the track axis last).
        cross_covs: ``(*B, L, L, n, n)`` joint error covariance (its diagonal blocks are replaced by
            the tracks' own covariances), or None.
        method: ``"matrix"`` (default), ``"diagonal"``, ``"scalar"`` or ``"covariance_intersection"``.

    Returns:
        :class:`~torchmm.beliefs.GaussianBelief` with batch ``(*B,)``: the fused mean and ``P_o``.

    Examples:
        >>> a = GaussianBelief(torch.zeros(1), torch.eye(1))
        >>> b = GaussianBelief(torch.ones(1), 3 * torch.eye(1))
        >>> fused = fuse_tracks([a, b])
        >>> round(fused.mean.item(), 4), round(fused.cov.item(), 4)
        (0.25, 0.75)
    """
    if isinstance(tracks, Belief):
        moments = tracks.estimate()
    else:
        tracks = list(tracks)
        if not tracks or not all(isinstance(t, Belief) for t in tracks):
            raise TypeError("tracks: expected a non-empty sequence of beliefs or one belief with a track axis")
        moments = stack([t.estimate() for t in tracks], dim=-1)
    moments = moments.materialize()
    mean, cov = moments.mean, moments.cov  # (*B, L, n), (*B, L, n, n)
    *batch, L, n = mean.shape
    if method == "covariance_intersection":
        if cross_covs is not None:
            raise ValueError("cross_covs: covariance intersection is for unknown cross-covariances; pass None")
        inv_trace = 1.0 / cov.diagonal(dim1=-2, dim2=-1).sum(-1)  # (*B, L)
        w = inv_trace / inv_trace.sum(-1, keepdim=True)
        # information form by Cholesky factors (no general inverse): P_i^{-1}, P_i^{-1} x_i, then P
        chol = cholesky(cov)  # (*B, L, n, n), regularised if a track's P is not positive definite
        info = torch.cholesky_inverse(chol)
        fused_info = (w[..., None, None] * info).sum(-3)
        vec = (w[..., None] * cholesky_solve(chol, mean.unsqueeze(-1)).squeeze(-1)).sum(-2)
        fused_chol = cholesky(symmetrize(fused_info))
        fused_cov = symmetrize(torch.cholesky_inverse(fused_chol))
        return GaussianBelief(cholesky_solve(fused_chol, vec.unsqueeze(-1)).squeeze(-1), fused_cov)
    if cross_covs is None:
        P = torch.zeros(*batch, L, L, n, n, dtype=mean.dtype, device=mean.device)
    else:
        if cross_covs.shape[-4:] != (L, L, n, n):
            raise ValueError(f"cross_covs: expected shape (*B, {L}, {L}, {n}, {n}), got {tuple(cross_covs.shape)}")
        P = cross_covs.expand(*batch, L, L, n, n).clone()
    idx = torch.arange(L, device=mean.device)
    P[..., idx, idx, :, :] = cov
    weights, Po = fusion_weights(P, method)  # (*B, L, n, n)
    fused = (weights @ mean.unsqueeze(-1)).squeeze(-1).sum(-2)
    return GaussianBelief(fused, Po)


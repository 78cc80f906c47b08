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

The matrix weights scale each state component ``c`` by ``s_c = sqrt(max_i [P_ii]_cc)`` before the
solve and map the weights back (``A_i = S A'_i S^{-1}``, ``S = diag(s)``, which keeps ``sum A_i = I``),
so that components of very different scale (m^2 next to rad^2/s^2) are weighted as (45) weights them.

Everything is batched over leading dims (time steps); linear systems are solved, not inverted.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchmm.beliefs import Belief, GaussianBelief, stack
from torchmm.beliefs.ops import symmetrize
from torchmm.contract import Beliefs, Choice, Cov, Finite, Indices, entry_point
from torchmm.linalg import cholesky, cholesky_solve
from torchmm.validation import SYMMETRY_RTOL, as_choice, broadcast_shape, check_square

__all__ = ["FusedEstimate", "constrained_weights", "fusion_weights", "fuse", "fuse_tracks", "FUSION_METHODS"]

FUSION_METHODS = ("matrix", "diagonal", "scalar")


def _check_relative_psd(cov: Tensor, name: str) -> None:
    """``ValueError`` naming ``name`` unless ``cov (..., d, d)`` is finite, symmetric and positive
    semi-definite, every tolerance relative to each matrix's own scale (its largest entry): symmetric
    to ``1e-5``, eigenvalues above ``-max(1e-10, 100 eps)`` of it (``eps`` of ``cov``'s dtype), so that a
    covariance of ``1e-12`` m^2 is held to the standard of one of ``1e6``. One host read."""
    check_square(cov, name)
    value = cov.detach()
    if not value.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point covariance, got dtype {value.dtype}")
    tol = max(1e-10, 100 * torch.finfo(value.dtype).eps)
    value = value.to(torch.float64)
    if value.numel() == 0:
        return
    scale = value.abs().amax(dim=(-1, -2), keepdim=True)
    unit = value / torch.where(scale > 0, scale, torch.ones_like(scale))  # NaN/inf stay non-finite
    asym = (unit - unit.mT).abs().amax(dim=(-1, -2))
    eig = torch.linalg.eigvalsh(0.5 * (unit + unit.mT).nan_to_num(0.0, 0.0, 0.0))[..., 0]
    finite, asym, eig = torch.stack([torch.isfinite(unit).all().double(), asym.max(), eig.min()]).tolist()
    if not finite:
        raise ValueError(f"{name}: contains NaN or infinite entries")
    if asym > SYMMETRY_RTOL:
        raise ValueError(f"{name}: covariance is not symmetric (asymmetry {asym:.3g} of its largest entry)")
    if eig < -tol:
        raise ValueError(f"{name}: covariance is not positive semi-definite (smallest eigenvalue {eig:.3g} "
                         "times its largest entry)")


def _checked_tracks(tracks) -> GaussianBelief:
    """The tracks' moments stacked on a last batch axis ``(*B, L)``, each track checked at entry (its
    values, :meth:`~torchmm.beliefs.Belief.validate`; its covariance PSD relative to its scale; state
    dimension, dtype and device against the first track's; batches that broadcast)."""
    if isinstance(tracks, Belief):
        tracks.validate("tracks")
        moments = tracks.estimate()
        if len(moments.batch_shape) < 1:
            raise ValueError("tracks: one belief needs a track axis (batch (*B, L)); got batch ()")
        _check_relative_psd(moments.cov,
                            "tracks.cov" if isinstance(tracks, GaussianBelief) else "tracks.estimate().cov")
        return moments.materialize()
    if isinstance(tracks, (str, bytes, Tensor)) or not hasattr(tracks, "__iter__"):
        raise TypeError("tracks: expected a non-empty sequence of beliefs or one belief with a track axis, "
                        f"got {type(tracks).__name__}")
    tracks = list(tracks)
    if not tracks or not all(isinstance(t, Belief) for t in tracks):
        bad = "an empty sequence" if not tracks else next(type(t).__name__ for t in tracks
                                                          if not isinstance(t, Belief))
        raise TypeError("tracks: expected a non-empty sequence of beliefs or one belief with a track axis, "
                        f"got {bad}")
    moments = []
    for i, t in enumerate(tracks):
        name = f"tracks[{i}]"
        t.validate(name)
        m = t.estimate()
        first = moments[0] if moments else m
        if m.state_dim != first.state_dim:
            raise ValueError(f"{name}: state dimension {m.state_dim} differs from tracks[0]'s "
                             f"{first.state_dim}")
        if m.mean.dtype != first.mean.dtype:
            raise TypeError(f"{name}: dtype {m.mean.dtype} differs from tracks[0]'s {first.mean.dtype}")
        if m.mean.device != first.mean.device:
            raise ValueError(f"{name}: on device {m.mean.device}, tracks[0] on {first.mean.device}")
        _check_relative_psd(m.cov,
                            f"{name}.cov" if isinstance(t, GaussianBelief) else f"{name}.estimate().cov")
        moments.append(m)
    try:
        broadcast_shape(*(m.batch_shape for m in moments))
    except RuntimeError:
        raise ValueError(f"tracks: batch shapes {[tuple(m.batch_shape) for m in moments]} "
                         "do not broadcast") from None
    return stack(moments, dim=-1).materialize()


def _stack_blocks(P: Tensor) -> Tensor:
    """``(..., L, L, n, n) -> (..., L n, L n)``."""
    *b, L, _, n, _ = P.shape
    return P.transpose(-3, -2).reshape(*b, L * n, L * n)


def _component_scales(P: Tensor) -> Tensor:
    """``s_c = sqrt(max_i |[P_ii]_cc|)`` per state component (``1`` where every sensor's variance
    is ``0`` or below the dtype's smallest normal number): the symmetric scaling that gives each
    component unit largest local variance.

    Shapes:
        P: ``(*B, L, L, n, n)`` -> ``(*B, n)``
    """
    var = P.diagonal(dim1=-4, dim2=-3).diagonal(dim1=-3, dim2=-2).abs().amax(-2)  # (*B, n)
    return torch.where(var > torch.finfo(P.dtype).tiny, var, torch.ones_like(var)).sqrt()


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


@entry_point(P=Cov(check=False), method=Choice(*FUSION_METHODS))
def fusion_weights(P: Tensor, method: str = "matrix") -> tuple[Tensor, Tensor]:
    r"""Fusion weights and fused error covariance from the joint covariance of the local errors.

    The fused covariance is ``P_o = sum_ij A_i P_ij A_j^T``, which equals ``(F^T P^{-1} F)^{-1}``
    of (45) for the matrix weights. The matrix weights are computed on the state scaled to unit
    largest local variance per component and mapped back, so a badly scaled state (components
    whose variances differ by many orders) still gets the weights of (45); for singular ``P`` they
    are the minimum-norm optimal weights in those scaled coordinates (docs/reproduction-002.md,
    "fusion with singular P").

    Shapes:
        P: ``(*B, L, L, n, n)`` -> weights ``(*B, L, n, n)`` (``A_i``; diagonal for ``diagonal``,
        ``a_i I`` for ``scalar``), cov ``(*B, n, n)``

    Example:
        >>> import torch
        >>> P = torch.zeros(2, 2, 1, 1); P[0, 0] = 1.0; P[1, 1] = 3.0
        >>> A, Po = fusion_weights(P, "matrix")
        >>> [round(a, 4) for a in A.flatten().tolist()], round(Po.item(), 4)
        ([0.75, 0.25], 0.75)

    Raises:
        TypeError / ValueError: naming ``P`` (a floating tensor of that shape whose joint matrix
        ``[P_ij]`` is finite, symmetric and positive semi-definite, relative to its scale) or ``method``.
    """
    _check_joint(P, "P")
    method = as_choice(method, "method", FUSION_METHODS)
    return _fusion_weights(P, method)


def _check_joint(P, name: str) -> None:
    """Entry check of a joint error covariance ``(*B, L, L, n, n)`` (shape, dtype, values)."""
    if not isinstance(P, Tensor):
        raise TypeError(f"{name}: expected a tensor (*B, L, L, n, n), got {type(P).__name__}")
    if P.dim() < 4 or P.shape[-4] != P.shape[-3] or P.shape[-1] != P.shape[-2] or 0 in P.shape[-4:]:
        raise ValueError(f"{name}: expected shape (*B, L, L, n, n), got {tuple(P.shape)}")
    _check_relative_psd(_stack_blocks(P), name)


def _fusion_weights(P: Tensor, method: str) -> tuple[Tensor, Tensor]:
    *b, L, _, n, _ = P.shape
    kw = dict(dtype=P.dtype, device=P.device)
    e = torch.ones(L, 1, **kw)
    if method == "matrix":
        s = _component_scales(P)  # (*B, n)
        Ps = P / (s[..., None, None, :, None] * s[..., None, None, None, :])
        F = torch.eye(n, **kw).repeat(L, 1)  # (L n, n)
        W = constrained_weights(_stack_blocks(Ps), F)  # (*B, L n, n) = A'^T in the scaled coordinates
        scaled = W.mT.unflatten(-1, (L, n)).transpose(-3, -2)  # (*B, L, n, n): A'_i = S^-1 A_i S
        weights = s[..., None, :, None] * scaled / s[..., None, None, :]  # A_i = S A'_i S^-1
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


@entry_point(mean=Finite(check=False), P=Cov(check=False), method=Choice(*FUSION_METHODS),
             components=Indices(optional=True))
def fuse(mean: Tensor, P: Tensor, method: str = "matrix", components=None) -> FusedEstimate:
    r"""Distributed fusion (44) of local estimates with the weights of :func:`fusion_weights`.

    ``components`` (indices) fuses only those state components (e.g. the position of Example 1,
    with ``P^s_ij`` the corresponding sub-blocks).

    Shapes:
        mean: ``(T, *B, L, n)``; P: ``(T, L, L, n, n)`` -> :class:`FusedEstimate`

    Raises:
        TypeError / ValueError: naming ``mean`` (finite, its shape matching ``P``'s), ``P`` (as
        :func:`fusion_weights`), ``method`` or ``components`` (state indices in ``[0, n)``).
    """
    method = as_choice(method, "method", FUSION_METHODS)
    _check_joint(P, "P")
    if P.dim() != 5:
        raise ValueError(f"P: expected shape (T, L, L, n, n), got {tuple(P.shape)}")
    T, L, _, n, _ = P.shape
    if not isinstance(mean, Tensor):
        raise TypeError(f"mean: expected a tensor (T, *B, L, n), got {type(mean).__name__}")
    if mean.dim() < 3 or mean.shape[0] != T or tuple(mean.shape[-2:]) != (L, n):
        raise ValueError(f"mean: expected shape ({T}, *B, {L}, {n}) (P's steps, tracks and state), got "
                         f"{tuple(mean.shape)}")
    if mean.dtype != P.dtype:
        raise TypeError(f"mean: dtype {mean.dtype} differs from P's {P.dtype}")
    if not bool(torch.isfinite(mean.detach()).all()):
        raise ValueError("mean: contains NaN or infinite entries")
    if components is not None:
        if isinstance(components, (str, bytes)) or not hasattr(components, "__iter__"):
            raise TypeError("components: expected a sequence of state indices, "
                            f"got {type(components).__name__}")
        components = list(components)
        if not components or not all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c < n
                                     for c in components):
            raise ValueError(f"components: expected state indices in [0, {n}), got {components}")
        idx = torch.as_tensor(components, device=mean.device)
        mean = mean[..., idx]
        P = P[..., idx, :][..., idx]
    weights, Po = _fusion_weights(P, method)
    T = mean.shape[0]
    W = weights.reshape(T, *([1] * (mean.dim() - 3)), *weights.shape[1:])
    fused = (W @ mean.unsqueeze(-1)).squeeze(-1).sum(-2)
    return FusedEstimate(fused, Po, weights)


@entry_point(tracks=Beliefs(), cross_covs=Cov(optional=True, check=False),
             method=Choice(*FUSION_METHODS, "covariance_intersection"))
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

    Raises:
        TypeError / ValueError: naming the argument, checked once at entry: ``tracks`` (beliefs;
        each track's values, :meth:`~torchmm.beliefs.Belief.validate`, e.g. ``tracks[1].cov:``; its
        covariance finite, symmetric and positive semi-definite to a tolerance relative to its own
        scale; state dimension, dtype and device equal, batches that broadcast), ``cross_covs``
        (a finite tensor of the tracks' dtype, shape ``(*B, L, L, n, n)``, the joint covariance with the
        tracks' own on its diagonal symmetric PSD likewise) and ``method``.

    Examples:
        >>> a = GaussianBelief(torch.zeros(1), torch.eye(1))
        >>> b = GaussianBelief(torch.ones(1), 3 * torch.eye(1))
        >>> fused = fuse_tracks([a, b])
        >>> round(fused.mean.item(), 4), round(fused.cov.item(), 4)
        (0.25, 0.75)
    """
    method = as_choice(method, "method", (*FUSION_METHODS, "covariance_intersection"))
    moments = _checked_tracks(tracks)
    mean, cov = moments.mean, moments.cov  # (*B, L, n), (*B, L, n, n)
    *batch, L, n = mean.shape
    if cross_covs is not None:
        if not isinstance(cross_covs, Tensor):
            raise TypeError("cross_covs: expected a tensor (*B, L, L, n, n) or None, "
                            f"got {type(cross_covs).__name__}")
        if cross_covs.dtype != mean.dtype:
            raise TypeError(f"cross_covs: dtype {cross_covs.dtype} differs from the tracks' {mean.dtype}")
        if not bool(torch.isfinite(cross_covs.detach()).all()):  # its diagonal blocks too, though replaced
            raise ValueError("cross_covs: contains NaN or infinite entries")
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
        if cross_covs.dim() < 4 or cross_covs.shape[-4:] != (L, L, n, n):
            raise ValueError(f"cross_covs: expected shape (*B, {L}, {L}, {n}, {n}), got {tuple(cross_covs.shape)}")
        try:
            P = cross_covs.to(mean.device).expand(*batch, L, L, n, n).clone()
        except RuntimeError:
            raise ValueError(f"cross_covs: batch shape {tuple(cross_covs.shape[:-4])} does not broadcast "
                             f"to the tracks' {tuple(batch)}") from None
    idx = torch.arange(L, device=mean.device)
    P[..., idx, idx, :, :] = cov
    if cross_covs is not None:  # the joint error covariance, with the tracks' own on its diagonal
        _check_relative_psd(_stack_blocks(P), "cross_covs")
    weights, Po = _fusion_weights(P, method)  # (*B, L, n, n); P checked above
    fused = (weights @ mean.unsqueeze(-1)).squeeze(-1).sum(-2)
    return GaussianBelief(fused, Po)


r"""Estimates at a bound of their parametrisation, for :func:`~torchmm.learn.estimate`'s standard errors.

A variance (``exp(u)``), a bounded entry, a probability of a ``"stochastic"`` or ``"probabilities"``
tensor (a softmax) or a covariance's diagonal (its Cholesky factor's log-diagonal) reaches its bound only
as its free coordinate ``u`` runs off to infinity. There the observed information in ``u`` stays
positive, but the delta method's error of the natural value shrinks to 0 with it: a tiny, confident
standard error for a value the data push past the bound. The rule (docs/estimation.md): write the
Hessian of the negative log-likelihood in ``u`` as

.. math::
    H = J^\top H_{\text{nat}} J + G, \qquad G = \sum_e g_e \nabla^2_u v_e(u),

``g_e`` the gradient in the natural entries ``v_e`` (the tensor's entries) and ``G`` the part the
parametrisation's curvature contributes. At an interior maximum ``g`` is 0 and so is ``G``. An entry is
*at its bound* when, along the direction of ``u`` that moves it alone (its own coordinate; for a
softmax's reference entry, every other entry of its row at once), ``G`` is more than half of ``H``:
the curvature there comes mostly from the likelihood still sloping toward the bound, not from the
likelihood's own curvature. Its standard error is NaN (with a note); the others' are computed with it
held at its estimate (the information restricted to the directions orthogonal to the held ones).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["at_bounds", "curvature_share", "entry_directions", "held_covariance"]


def entry_directions(block) -> tuple[Tensor, Tensor]:
    """``(D, bounded)``: ``D`` ``(n_reported, n_u)``, for each reported entry of a
    :class:`~torchmm.learn.entries.Block`, the direction of its free values that moves that entry alone - its
    coordinate (a free, bounded or variance entry, a covariance's entry, a non-reference probability), or, for
    a softmax row's reference entry (logit 0), minus every coordinate of its row (all the others' logits up
    together); along it the entry's log-distance to its bound (its log, log-odds) changes by one per unit.
    ``bounded`` ``(n_reported,)``: the entry has a bound its coordinate reaches only at infinity (a
    variance, a covariance's diagonal, a probability, a free entry with ``lower`` or ``upper``)."""
    n_u, reported = block.u0.numel(), block.reported
    D = torch.zeros(len(reported), n_u, dtype=torch.float64)
    if block.kind == "covariance":
        d = block.shape[-1]
        D[torch.arange(len(reported)), torch.arange(len(reported))] = 1.0
        bounded = (reported % (d * d)) // d == (reported % d)
    elif block.kind in ("stochastic", "probabilities"):
        M = block.shape[-1]
        coordinate = {int(e): c for c, e in enumerate(block.entries.tolist())}
        for k, flat in enumerate(reported.tolist()):
            if flat in coordinate:
                D[k, coordinate[flat]] = 1.0
            else:  # the row's reference entry
                row = flat // M
                for e, c in coordinate.items():
                    if e // M == row:
                        D[k, c] = -1.0
        bounded = torch.ones(len(reported), dtype=torch.bool)
    else:
        D[torch.arange(len(reported)), block.slot[reported]] = 1.0
        limited = block.kind == "variance" or block.param.lower is not None or block.param.upper is not None
        bounded = torch.full((len(reported),), limited, dtype=torch.bool)
    return D, bounded


def curvature_share(H: Tensor, G: Tensor, D: Tensor) -> Tensor:
    """``(K,)``: along each direction ``d`` (a row of ``D`` ``(K, P)``), ``d^T G d / |d^T H d|``, the share of
    the curvature ``H`` that the parametrisation's term ``G`` makes (NaN where ``d`` is 0)."""
    qG = torch.einsum("kp,pq,kq->k", D, G, D)
    qH = torch.einsum("kp,pq,kq->k", D, H, D)
    return torch.where((D != 0).any(-1), qG / qH.abs(), torch.nan)


def held_covariance(H: Tensor, held: Tensor) -> tuple[Tensor, bool]:
    """The covariance of the free values ``(P, P)`` with the directions ``held`` ``(h, P)`` fixed: ``N (N^T H
    N)^{-1} N^T``, ``N`` an orthonormal basis of the directions orthogonal to them (for coordinate
    directions: the information with those coordinates dropped). Returns ``(cov, ok)``; ``ok`` False when
    the restricted information is not positive definite (``cov`` NaN)."""
    P = H.shape[-1]
    if held.shape[0] == 0:
        N = torch.eye(P, dtype=H.dtype)
    else:
        _, s, Vh = torch.linalg.svd(held, full_matrices=True)
        rank = int((s > s.max() * P * torch.finfo(H.dtype).eps).sum())
        N = Vh[rank:].mT
    if N.shape[-1] == 0:  # every direction held
        return torch.zeros(P, P, dtype=H.dtype), True
    L, info = torch.linalg.cholesky_ex(N.mT @ H @ N)
    if int(info) != 0:
        return torch.full((P, P), torch.nan, dtype=H.dtype), False
    cov = N @ torch.cholesky_inverse(L) @ N.mT
    if held.shape[0]:  # coordinate directions held: their rows and columns are exactly 0
        exact = (held != 0).sum(-1) == 1
        for d in held[exact]:
            i = int(torch.nonzero(d)[0, 0])
            cov[i, :] = 0.0
            cov[:, i] = 0.0
    return cov, True


def at_bounds(H: Tensor, G: Tensor, D: Tensor, bounded: Tensor, eps: float,
              threshold: float = 0.5) -> list[int]:
    """The reported entries at a bound (module docstring), by either rule, along each entry's direction
    (``D`` ``(K, P)``, ``bounded`` ``(K,)``: :func:`entry_directions`):

    * *the likelihood slopes past it*: :func:`curvature_share` above ``threshold`` (a half: the
      parametrisation's term larger than the likelihood's own curvature);
    * *its coordinate has run off*: a bounded entry whose log-distance to the bound has a (conditional)
      standard error ``1 / sqrt(d^T H d)`` above ``|ln eps|`` (36 in float64, 16 in float32): the data leave
      it undetermined across more orders of magnitude than the floating-point type holds, and the delta
      method's error, that standard error times the vanishing derivative, is meaningless."""
    share = curvature_share(H, G, D)
    qH = torch.einsum("kp,pq,kq->k", D, H, D)
    runoff = bounded & (qH > 0) & (qH * math.log(eps) ** 2 < 1)
    return [k for k in range(D.shape[0]) if bool(share[k] > threshold) or bool(runoff[k])]

r"""Shared linear algebra (below beliefs, filters and metrics): Gaussian conditioning with Cholesky factors; closed forms for 1x1 and 2x2 innovations.

Batched ``torch.linalg`` on thousands of tiny matrices is dominated by per-call overhead, so the
innovation covariance ``S`` (``m x m``) is factorised in closed form when ``m <= 2`` (the common
position-only sensors) and by ``torch.linalg.cholesky_ex`` otherwise. Nothing is inverted: the
update uses one forward substitution on ``[C^T | nu]``:

.. math::
    S = L L^\top,\quad V = L^{-1} C^\top,\quad w = L^{-1}\nu,\quad
    x^+ = x + V^\top w,\quad P^+ = P - V^\top V,\quad
    \log p(z) = -\tfrac12\left(\|w\|^2 + 2\textstyle\sum_i \log L_{ii} + m \log 2\pi\right)

Missing components (non-finite *data*: NaN or ``+-inf`` entries of ``z``, passed as ``observed``) are
conditioned out exactly with static shapes: their rows and columns of ``S`` are replaced by the
identity, their columns of ``C`` and entries of ``nu`` by zero, so the gain for them is zero and
they add nothing to the log-likelihood. A non-finite *prediction* of an observed component is not
missing data: it propagates (NaN log-likelihood) and :func:`flag_failed` flags the run.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from torchmm.runtime import host_reads_ok

__all__ = ["any_observed", "check_joseph", "cholesky", "cholesky_diagonal", "cholesky_solve", "condition",
           "half_log_det", "not_psd", "psd_sqrt", "solve_lower", "solve_right", "solve_lower_transposed",
           "sum_last", "symmetrize", "use_joseph"]

_LOG_2PI = math.log(2 * math.pi)


def sum_last(x: Tensor) -> Tensor:
    """``x.sum(-1)`` for a short last axis (a state, a measurement, a few modes), as a product with a
    vector of ones: torch's CPU sum over a contiguous axis of a few entries costs ~15 ns an output
    (5 ms for 360,000 sums of two), the matrix-vector product under 1 ns (docs/performance.md). The
    same value for two entries; for more, to rounding (the product's summation order).

    Shapes:
        x: ``(..., k)`` floating -> ``(...)``
    """
    return x @ x.new_ones(x.shape[-1])


def half_log_det(L: Tensor) -> Tensor:
    """``sum_i log L_ii`` of a triangular factor, ``(1/2) log det(L L^T)``: the diagonal copied out
    before the ``log`` (on the strided diagonal, torch's ``log`` runs 6x slower), summed by
    :func:`sum_last`.

    Shapes:
        L: ``(..., m, m)`` -> ``(...)``
    """
    return sum_last(L.diagonal(dim1=-2, dim2=-1).contiguous().log())


def symmetrize(matrix: Tensor) -> Tensor:
    """Return ``(A + A^T) / 2``.

    Shapes:
        matrix: ``(..., d, d)`` -> ``(..., d, d)``
    """
    return (matrix + matrix.mT).mul_(0.5)


def psd_sqrt(cov: Tensor) -> Tensor:
    """A square root ``L`` with ``L L^T = cov`` for symmetric PSD (possibly singular) matrices.

    Uses Cholesky where it succeeds, so that rank-deficient process noise such as ``G G^T`` can be
    sampled, and elsewhere:

    * on the CPU, a symmetric eigendecomposition (negative eigenvalues of a matrix indefinite by
      rounding clamped to 0), computed only when some Cholesky fails;
    * on other devices (and inside :func:`torchmm.runtime.no_host_sync`), a Cholesky whose
      non-positive pivots are set to 0 with their column (:func:`pivot_clamped_cholesky`), computed
      for every matrix so that the host never waits (:func:`torchmm.runtime.host_reads_ok`). torch's
      ``eigh`` checks its result on the host (a synchronisation on a GPU) and cuSOLVER's batched
      ``eigh`` fails on a million matrices; this factor is another square root of the same matrix
      (``L L^T`` equal to rounding), so only draws from a singular covariance differ between the two.

    Never raises: a matrix with NaN or infinite entries gets a NaN factor (that batch element only).

    Shapes:
        cov: ``(..., d, d)`` -> ``(..., d, d)``
    """
    chol, info = torch.linalg.cholesky_ex(cov)
    if not host_reads_ok(info):  # on a GPU: no read, the sync-free fallback for every matrix
        return torch.where((info != 0)[..., None, None], pivot_clamped_cholesky(cov), chol)
    if not bool((info != 0).any()):
        return chol
    finite = torch.isfinite(cov).all(-1).all(-1)
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    safe = torch.where(finite[..., None, None], symmetrize(cov), eye)  # eigh raises on NaN input
    eigvals, eigvecs = torch.linalg.eigh(safe)
    eig_sqrt = eigvecs * eigvals.clamp_min(0).sqrt().unsqueeze(-2)
    eig_sqrt = torch.where(finite[..., None, None], eig_sqrt, torch.full_like(eig_sqrt, math.nan))
    return torch.where((info != 0)[..., None, None], eig_sqrt, chol)


def pivot_clamped_cholesky(cov: Tensor) -> Tensor:
    """A lower-triangular ``L`` with ``L L^T = cov`` for symmetric PSD, possibly singular matrices: the
    Cholesky recursion, column by column, with a pivot below ``d eps max_i cov_ii`` (zero up to
    rounding) set to 0 with the rest of its column (a PSD matrix's column below a zero pivot is zero).
    Batched, without a host read or an eigendecomposition (the device form of :func:`psd_sqrt`). A
    matrix with a non-finite entry gets a NaN factor.

    Shapes:
        cov: ``(..., d, d)`` -> ``(..., d, d)``
    """
    d = cov.shape[-1]
    A = symmetrize(cov)
    finite = torch.isfinite(A).flatten(-2).all(-1)[..., None]
    A = torch.where(finite[..., None], A, torch.zeros((), dtype=A.dtype, device=A.device))
    diag = A.diagonal(dim1=-2, dim2=-1)
    tol = d * torch.finfo(A.dtype).eps * diag.amax(-1, keepdim=True).clamp_min(torch.finfo(A.dtype).tiny)
    rows = torch.arange(d, device=A.device)
    zero = torch.zeros((), dtype=A.dtype, device=A.device)
    cols: list[Tensor] = []
    for j in range(d):
        v = A[..., :, j]
        for c in cols:  # v -= L[:, k] L[j, k] over the columns done
            v = v - c * c[..., j:j + 1]
        pivot = v[..., j:j + 1]
        keep = (pivot > tol) & (rows >= j)
        cols.append(torch.where(keep, v / pivot.clamp_min(tol).sqrt(), zero))
    L = torch.stack(cols, -1)
    return torch.where(finite[..., None], L, torch.full((), math.nan, dtype=A.dtype, device=A.device))


def flag_failed(log_likelihood: Tensor) -> Tensor:
    """``failed (*B,)`` of an update whose missing mask came from the data (``condition(...,
    observed=)``): True where its log-likelihood is NaN. A present datum with a NaN prediction,
    innovation or innovation covariance gives a NaN log-likelihood there (a NaN gain or posterior
    reaches it at the latest when it reaches the predicted measurement); a step without a datum has
    log-likelihood exactly 0, so missing data never fail. One elementwise op, no host read
    (``extras["failed"]``, docs/robustness.md)."""
    return torch.isnan(log_likelihood)


def not_psd(S: Tensor) -> Tensor:
    """``(...)`` True where the symmetric ``S (..., n, n)`` is not numerically positive
    semi-definite: a non-finite entry, or an eigenvalue below about ``-sqrt(eps) s`` (``s =
    max|S_ij|``), i.e. the Cholesky factorisation of ``S / s + sqrt(eps) I`` fails. Singular PSD
    matrices (the zero matrix included) and negative eigenvalues of rounding size pass. One batched
    ``cholesky_ex``, no host read (a filter's failure flag, docs/robustness.md).
    """
    finite = torch.isfinite(S).all(-1).all(-1)
    S = torch.where(finite[..., None, None], S, torch.zeros((), dtype=S.dtype, device=S.device))
    scale = S.abs().amax((-2, -1)).clamp_min(torch.finfo(S.dtype).tiny)
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    info = torch.linalg.cholesky_ex(S / scale[..., None, None] + math.sqrt(torch.finfo(S.dtype).eps) * eye)[1]
    return ~finite | (info != 0)


def any_observed(z: Tensor) -> Tensor:
    """``(*B,)`` True where ``z (*B, m)`` has a finite (observed) component; False means no datum
    at all this step (every component NaN or ``+-inf``: missing)."""
    return torch.isfinite(z[..., 0]) if z.shape[-1] == 1 else torch.isfinite(z).any(-1)


def check_joseph(value) -> bool | None:
    """The ``joseph`` option of the UKF and the VB filters: True, False or None (automatic)."""
    if value is not None and not isinstance(value, bool):
        raise TypeError(f"joseph: expected True, False or None (automatic), got {value!r}")
    return value


def use_joseph(joseph: bool | None, dtype: torch.dtype) -> bool:
    """The covariance-update form of the UKF and the VB filters: ``joseph=None`` (the default) is
    the PSD-preserving Joseph form in float32 and below, where ``P - K S K^T`` cancels with
    accurate sensors, and the cheaper ``P - K S K^T`` in float64."""
    return joseph if joseph is not None else torch.finfo(dtype).eps > 1e-10


def cholesky(S: Tensor, *, with_flag: bool = False):
    r"""Lower Cholesky factor of symmetric PD ``S (..., m, m)``, finite for every matrix.

    A matrix that is not numerically positive definite gets a regularised factor instead of an
    error (one run's trouble never stops the others); no host synchronisation:

    * ``m <= 2``: closed form with the pivots clamped at ``eps * max|S_ii|`` (``tiny`` for
      ``m = 1``);
    * ``m > 2``: ``torch.linalg.cholesky_ex``; where it fails, again with ``S + sqrt(eps) s I``
      (``s = max|S_ii|``), and where that fails too, ``diag(sqrt(max(S_ii, eps s)))``.

    A NaN matrix gives a NaN factor (for that batch element only).

    Args:
        with_flag: also return ``singular (...)`` bool, True where ``S`` was regularised.
    """
    m = S.shape[-1]
    eps, tiny = torch.finfo(S.dtype).eps, torch.finfo(S.dtype).tiny
    if m == 1:
        L = S.clamp_min(tiny).sqrt()
        return (L, ~(S[..., 0, 0] > tiny)) if with_flag else L
    if m == 2:
        a, l11, l21, pivot, l22, scale = _cholesky2(S)
        zero = torch.zeros_like(a)
        L = torch.stack([l11, zero, l21, l22], -1).unflatten(-1, (2, 2))  # (one stack: 3x cheaper)
        return (L, ~((a > scale) & (pivot > scale))) if with_flag else L
    chol, info = torch.linalg.cholesky_ex(S)
    failed = info != 0
    diag = S.diagonal(dim1=-2, dim2=-1)
    scale = diag.abs().amax(-1).nan_to_num(nan=1.0).clamp_min(tiny)  # (...)
    eye = torch.eye(m, dtype=S.dtype, device=S.device)
    jitter = torch.where(failed, scale * math.sqrt(eps), torch.zeros_like(scale))
    chol2, info2 = torch.linalg.cholesky_ex(S + jitter[..., None, None] * eye)
    fallback = torch.diag_embed(diag.maximum(eps * scale.unsqueeze(-1)).sqrt())
    repaired = torch.where((info2 != 0)[..., None, None], fallback, chol2)
    L = torch.where(failed[..., None, None], repaired, chol)
    return (L, failed) if with_flag else L


def _cholesky2(S: Tensor) -> tuple:
    """The closed-form regularised factor of ``S (..., 2, 2)`` (:func:`cholesky`): ``S_00``, ``l11``,
    ``l21``, the second pivot, ``l22`` and the pivots' clamp, each ``(...)``."""
    eps, tiny = torch.finfo(S.dtype).eps, torch.finfo(S.dtype).tiny
    a, b, c = S[..., 0, 0], S[..., 1, 0], S[..., 1, 1]
    scale = torch.maximum(a.abs(), c.abs()) * eps + tiny
    l11 = a.clamp_min(0).maximum(scale).sqrt()
    l21 = b / l11
    pivot = c - l21 * l21
    l22 = pivot.maximum(scale).sqrt()
    return a, l11, l21, pivot, l22, scale


def cholesky_diagonal(S: Tensor) -> tuple[Tensor, ...]:
    """The diagonal entries of :func:`cholesky` ``(S)``, the same numbers, as ``m`` tensors ``(...)``;
    for ``m <= 2`` without forming the factor (a log-determinant's or an entropy's only need, at a third
    of the passes)."""
    m = S.shape[-1]
    if m == 1:
        return (S[..., 0, 0].clamp_min(torch.finfo(S.dtype).tiny).sqrt(),)
    if m == 2:
        _, l11, _, _, l22, _ = _cholesky2(S)
        return l11, l22
    return cholesky(S).diagonal(dim1=-2, dim2=-1).unbind(-1)


def solve_right(G: Tensor, S: Tensor) -> Tensor:
    """``G S^{-1}`` for a symmetric non-singular ``S`` (a gain ``C S^{-1}``), by one solve.

    Shapes:
        G: ``(..., k, m)``; S: ``(..., m, m)`` -> ``(..., k, m)``
    """
    return torch.linalg.solve(S, G.mT).mT


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
    posterior_cov: Callable[[Tensor], Tensor] | None = None,
    with_flag: bool = False,
    observed: Tensor | None = None,
):
    r"""Condition a Gaussian on an innovation (the shared core of KF, EKF, UKF and VB updates).

    Args:
        mean: prior mean ``x``.
        cov: prior covariance ``P``.
        innovation: ``nu = z - z_pred``; without ``observed``, non-finite entries (NaN, ``+-inf``) are
            missing components.
        innovation_cov: ``S = Cov[z]``.
        cross_cov: ``C = Cov[x, z]`` (``P H^T`` for linear models).
        joseph: ``(H, R)`` to update the covariance in Joseph form
            ``(I - K H) P (I - K H)^T + K R K^T`` instead of ``P - K S K^T``.
        posterior_cov: any other PSD-preserving form of the covariance update: a function of the
            gain ``K (*B, n, m)`` (zero columns for missing components) returning ``P+``.
        with_flag: also return ``singular (*B,)``: True where ``S`` restricted to the observed
            components was not numerically positive definite and was regularised
            (:func:`cholesky`); the update is then finite but not meaningful for that element.
        observed: ``(*B, m)`` bool (broadcasting), True where the *measurement* component is
            present (``torch.isfinite(z)``). The filters pass it, so that a non-finite prediction of
            an observed component gives a NaN update and log-likelihood (a failure,
            :func:`flag_failed`) instead of being skipped as missing data.

    Returns:
        posterior mean, posterior covariance (symmetrised) and ``log N(nu; 0, S)`` over the
        observed components (exactly 0 if none is observed) [, singular].

    Shapes:
        mean ``(*B, n)``, cov ``(*B, n, n)``, innovation ``(*B, m)``, innovation_cov
        ``(*B, m, m)``, cross_cov ``(*B, n, m)`` -> ``(*B, n)``, ``(*B, n, n)``, ``(*B,)`` [, ``(*B,)``]
    """
    n, m = mean.shape[-1], innovation.shape[-1]
    if observed is None:
        observed = torch.isfinite(innovation)
    elif observed.shape[-1] != m:
        # (a mask broadcasting against the innovation: full event axis, for the count)
        observed = observed.expand(*observed.shape[:-1], m)
    if m == 1 and joseph is None and posterior_cov is None:
        out = _condition_scalar(mean, cov, innovation, innovation_cov, cross_cov, observed[..., 0])
        return out if with_flag else out[:3]
    nu = torch.where(observed, innovation, 0.0)
    if m == 1:
        S = torch.where(observed.unsqueeze(-1), innovation_cov, 1.0)
    else:
        pair = observed.unsqueeze(-1) & observed.unsqueeze(-2)
        S = torch.where(pair, innovation_cov, torch.eye(m, dtype=nu.dtype, device=nu.device))
    C = cross_cov * observed.unsqueeze(-2)
    L, singular = cholesky(S, with_flag=True)
    batch = torch.broadcast_shapes(C.shape[:-2], nu.shape[:-1])  # (a datum shared by the runs, or the converse)
    rhs = torch.cat([C.mT.expand(*batch, m, n), nu.unsqueeze(-1).expand(*batch, m, 1)], dim=-1)  # (*B,m,n+1)
    solved = solve_lower(L, rhs)
    V, w = solved[..., :n], solved[..., n]
    post_mean = mean + (V.mT @ w.unsqueeze(-1)).squeeze(-1)
    if joseph is None and posterior_cov is None:
        post_cov = cov - V.mT @ V
    else:
        gain = solve_lower_transposed(L, V).mT  # K = C S^{-1}, zero columns where missing
        if posterior_cov is not None:
            post_cov = posterior_cov(gain)
        else:
            H, R = joseph
            eye = torch.eye(n, dtype=cov.dtype, device=cov.device)
            A = eye - gain @ H
            post_cov = A @ cov @ A.mT + gain @ R @ gain.mT
    count = sum_last(observed.to(nu.dtype))
    log_likelihood = -0.5 * (sum_last(w.square()) + count * math.log(2 * math.pi)) - half_log_det(L)
    out = post_mean, symmetrize(post_cov), log_likelihood
    return (*out, singular) if with_flag else out


def _condition_scalar(mean, cov, innovation, innovation_cov, cross_cov, observed):
    """``m = 1``: the same update in closed form (``K = c / s``, ``P+ = P - c c^T / s``)."""
    nu = innovation[..., 0]
    nu = torch.where(observed, nu, 0.0)
    tiny = torch.finfo(nu.dtype).tiny
    s_raw = innovation_cov[..., 0, 0]
    s = s_raw.clamp_min(tiny)
    c = cross_cov[..., 0]
    gain = c * (observed / s).unsqueeze(-1)  # K = c / s, zero where missing
    post_mean = torch.addcmul(mean, gain, nu.unsqueeze(-1))  # x + K nu
    post_cov = torch.addcmul(cov, gain.unsqueeze(-1), c.unsqueeze(-2), value=-1.0)  # P - K c^T (symmetrised below)
    quad_logdet = torch.addcdiv(s.log().add_(_LOG_2PI), nu * nu, s)  # nu^2 / s + log s + log 2 pi
    log_likelihood = torch.where(observed, quad_logdet.mul_(-0.5), 0.0)
    return post_mean, symmetrize(post_cov), log_likelihood, (s_raw <= tiny) & observed


def cholesky_solve(L: Tensor, rhs: Tensor) -> Tensor:
    """``(L L^T)^{-1} rhs`` from a lower Cholesky factor. Shapes: ``(..., m, m)``, ``(..., m, k)``."""
    return solve_lower_transposed(L, solve_lower(L, rhs))

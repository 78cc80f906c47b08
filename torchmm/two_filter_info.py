r"""The information-form two-filter smoother of IMM / GPB1 / GPB2 runs over linear-Gaussian (Kalman) mode
filters, ``smooth(filter, trajectory, z, method="two_filter_info")`` (docs/smoothing.md, "The
information-form backward filter"). An opt-in alternative to the default two-filter reading
(:mod:`torchmm.two_filter`), without its flat start.

The backward pass carries, for every mode ``i``, the likelihood of the future data
``beta_k^i(x) = p(z_{k:T} | x_k = x, s_k = i)`` in information form,
``beta(x) = exp(lambda - x^T Omega x / 2 + omega^T x)``: zero information after the last step, the
log-normalising constant ``lambda`` kept exactly (:func:`info_predict`, :func:`info_fuse`). Every pair
``(j, i)`` (mode ``j`` at ``k``, ``i`` at ``k + 1``) is fused exactly with the forward mode ``j``, giving
``Lambda_ji = p(z_{k+1:T} | s_k = j, s_{k+1} = i, z_{1:k})`` directly, and
``P(s_k = j, s_{k+1} = i | z_{1:T}) ∝ mu_j pi_ji Lambda_ji``. Only the mixture
``sum_i pi_ji beta~^i`` of the backward-predicted likelihoods is approximated: multiplied by a proper
reference density (the forward filter's collapsed filtered density at ``k``, the same for every mode;
Briers, Doucet & Maskell, Ann. Inst. Stat. Math. 62, 2010), moment-matched, and the reference divided
out again (:func:`info_mixture`). Batched over every run and mode axis; the backward pass is the only loop
(over time) and reads no tensor value into Python.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, ModeBelief, symmetrize, where
from torchmm.beliefs.ops import safe_log_normalize
from torchmm.linalg import cholesky, half_log_det
from torchmm.models.linear import matvec
from torchmm.run import Trajectory
from torchmm.two_filter import gaussian_modes, mode_trajectory, two_filter_measurements

if TYPE_CHECKING:
    from torchmm.multimodel.imm import MultipleModelFilter

__all__ = ["info_fuse", "info_measurements", "info_mixture", "info_predict",
           "proper_log_det", "reference_root", "smooth_two_filter_info"]

#: The reference's eigenvalues are floored at ``eps ** REFERENCE_FLOOR_POWER`` times its largest
#: (:func:`reference_root`)
REFERENCE_FLOOR_POWER = 0.25


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(-1)


def proper_log_det(LU: Tensor, pivots: Tensor) -> Tensor:
    """``log det A`` from ``torch.linalg.lu_factor_ex``'s ``(LU, pivots)`` where ``det A > 0``, NaN where
    not: the fusions' ``I + Omega Q`` and ``I + S Omega`` have real eigenvalues of at least 1 when ``Omega``
    is positive semi-definite (:func:`info_mixture` keeps it so); a determinant of the wrong sign means a
    divergent fusion, and its NaN reaches the run's smoothed belief (``extras["failed"]``) instead of a
    number.

    Shapes:
        LU ``(*B, n, n)``, pivots ``(*B, n)`` -> ``(*B,)``
    """
    diag = LU.diagonal(dim1=-2, dim2=-1)
    swaps = (pivots != torch.arange(1, pivots.shape[-1] + 1, device=pivots.device)).sum(-1)
    negative = ((diag < 0).sum(-1) + swaps) % 2 == 1
    log_det = diag.abs().log().sum(-1)
    return torch.where(negative | (diag == 0).any(-1), torch.nan, log_det)


def info_measurements(H: Tensor, R: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""The likelihood of ``z = H x + v``, ``v ~ N(0, R)``, in information form: ``H^T R^{-1} H``,
    ``H^T R^{-1} z`` and ``lambda = log N(z; 0, R)``, over the finite components of ``z`` only (missing ones,
    NaN, carry nothing: a step without data gives zero information and ``lambda = 0``).

    Shapes:
        H ``(*P, m, n)``, R ``(*P, m, m)``, z ``(*B, m)`` (broadcasting) -> ``(*B, n, n)``, ``(*B, n)``,
        ``(*B,)``
    """
    seen = torch.isfinite(z)
    both = seen.unsqueeze(-1) & seen.unsqueeze(-2)
    eye = torch.eye(z.shape[-1], dtype=z.dtype, device=z.device)
    Ro = torch.where(both, R, eye)  # the observed block, the identity elsewhere
    L = cholesky(Ro)
    Ri = torch.where(both, torch.cholesky_inverse(L), 0.0)
    y = torch.where(seen, z, 0.0)
    Hm = torch.where(seen.unsqueeze(-1), H, 0.0)
    HtRi = Hm.mT @ Ri
    log_det = 2 * half_log_det(L)  # log det R_oo (the identity block adds 0)
    lam = -0.5 * (_dot(y, matvec(Ri, y)) + log_det + seen.sum(-1).to(z.dtype) * math.log(2 * math.pi))
    return symmetrize(HtRi @ Hm), matvec(HtRi, y), lam


def info_predict(Omega: Tensor, omega: Tensor, lam: Tensor, F: Tensor, Q: Tensor,
                 offset: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""The backward prediction ``int N(x'; F x + o, Q) beta(x') dx'`` of ``beta = (Omega, omega, lambda)``:
    ``A = I + Omega Q``, ``Omega' = A^{-1} Omega``, ``omega' = A^{-1} omega``, then ``F^T Omega' F``,
    ``F^T (omega' - Omega' o)`` and ``lambda + omega^T Q omega' / 2 - log det A / 2 - o^T Omega' o / 2 +
    omega'^T o``. No inverse of ``F`` or ``Q`` (both may be singular).

    Shapes:
        Omega ``(*B, n, n)``, omega ``(*B, n)``, lam ``(*B,)``; F, Q ``(*B, n, n)``, offset ``(*B, n)``
        (broadcasting) -> as Omega, omega, lam
    """
    eye = torch.eye(Omega.shape[-1], dtype=Omega.dtype, device=Omega.device)
    LU, pivots, _ = torch.linalg.lu_factor_ex(eye + Omega @ Q)
    solved = torch.linalg.lu_solve(LU, pivots, torch.cat([Omega, omega.unsqueeze(-1)], dim=-1))
    Op, op = symmetrize(solved[..., :-1]), solved[..., -1]
    log_det = proper_log_det(LU, pivots)
    lam = (lam + 0.5 * _dot(omega, matvec(Q, op)) - 0.5 * log_det - 0.5 * _dot(offset, matvec(Op, offset))
           + _dot(op, offset))
    return symmetrize(F.mT @ Op @ F), matvec(F.mT, op - matvec(Op, offset)), lam


def info_fuse(mean: Tensor, cov: Tensor, Omega: Tensor, omega: Tensor,
              lam: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""``N(x; m, S) beta(x) = exp(l) N(x; m_f, S_f)``: ``l = log E_{N(m, S)}[beta]`` and the fused
    Gaussian, ``A = I + S Omega``, ``S_f = A^{-1} S``, ``r = omega - Omega m``, ``m_f = m + S_f r``,
    ``l = lambda - m^T Omega m / 2 + omega^T m + r^T S_f r / 2 - log det A / 2``.

    Shapes:
        mean ``(*B, n)``, cov ``(*B, n, n)``; Omega, omega, lam as :func:`info_predict`'s (broadcasting)
        -> l ``(*B,)``, m_f ``(*B, n)``, S_f ``(*B, n, n)``
    """
    eye = torch.eye(mean.shape[-1], dtype=mean.dtype, device=mean.device)
    A = eye + cov @ Omega
    LU, pivots, _ = torch.linalg.lu_factor_ex(A)
    Sf = symmetrize(torch.linalg.lu_solve(LU, pivots, cov.expand_as(A)))
    r = omega - matvec(Omega, mean)
    Sr = matvec(Sf, r)
    log_det = proper_log_det(LU, pivots)
    ll = lam - 0.5 * _dot(mean, matvec(Omega, mean)) + _dot(omega, mean) + 0.5 * _dot(r, Sr) - 0.5 * log_det
    return ll, mean + Sr, Sf


def reference_root(cov: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""The reference covariance used by :func:`info_mixture`, ``G' = W W^T``, with its symmetric root ``W``
    and ``W^{-1}``: ``G``'s eigenvalues below ``c * max eig(G)`` raised to it (``c = eps ** 0.25``: 1.2e-4 in
    float64, 0.019 in float32), the identity where ``G`` is zero.

    The forward filter's collapsed covariance ``G`` is singular wherever a state component is known exactly
    (a constant 1 in the state, a mode with a zero row of ``F`` and no noise there): such a reference
    cannot be divided out of the mixture. Any proper density serves (it cancels exactly for one mode and for
    identical modes and only decides where the mixture is moment-matched), so ``G`` is kept where it is
    well conditioned and raised only where it is not. The division is done relative to the reference
    (:func:`info_mixture`), where the whitened mixture ``W^{-1} C W^{-T}`` carries relative rounding of
    about ``eps / c = eps ** 0.75`` (3e-12 in float64, 6e-6 in float32); in float64 the floor leaves every
    case of docs/smoothing.md's table unchanged.

    Shapes:
        cov ``(*B, n, n)`` -> ``G'``, ``W``, ``W^{-1}``, each ``(*B, n, n)``
    """
    e, U = torch.linalg.eigh(symmetrize(cov))
    top = e.amax(-1, keepdim=True)
    floor = torch.where(top > 0, top * torch.finfo(cov.dtype).eps ** REFERENCE_FLOOR_POWER, 1.0)
    e = torch.where(top > 0, e.maximum(floor), 1.0)
    root = e.sqrt()
    W = U * root.unsqueeze(-2)
    return symmetrize(W @ W.mT), W, U.mT / root.unsqueeze(-1)


def info_mixture(log_weights: Tensor, reference: GaussianBelief, Omega: Tensor, omega: Tensor,
                 lam: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""``sum_i w_ji beta^i(x)`` for every ``j`` as one information form, through the reference
    ``N(g, G)`` (``G`` conditioned by :func:`reference_root`): each ``N(g, G) beta^i = exp(l_i) N(f_i, S_i)``
    (:func:`info_fuse`), the mixture ``sum_i w_ji exp(l_i) N(f_i, S_i) ~ exp(c_j) N(a_j, C_j)``
    moment-matched, divided by ``N(g, G)``: ``Omega_j = C_j^{-1} - G^{-1}`` and, about the reference's
    mean, ``omega_j = C_j^{-1} (a_j - g) + Omega_j g``; ``Omega_j``'s negative eigenvalues relative to
    ``G^{-1}`` (``eig(W^T Omega_j W)``, ``G = W W^T``; above -1 by construction) set to 0, which keeps every
    later fusion proper (:func:`proper_log_det`); ``lambda_j`` such that ``E_{N(g, G)}[beta_j] = exp(c_j)``.
    The difference of inverses is taken whitened, ``(W^{-1} C_j W^{-T})^{-1} - I``.

    Shapes:
        log_weights ``(j, i)`` (or ``(*B, j, i)``); reference batch ``(*B,)``; Omega ``(*B, i, n, n)``,
        omega ``(*B, i, n)``, lam ``(*B, i)`` -> ``(*B, j, n, n)``, ``(*B, j, n)``, ``(*B, j)``
    """
    g = reference.mean
    G, _, Winv = reference_root(reference.cov)
    ll, f, S = info_fuse(g.unsqueeze(-2), G.unsqueeze(-3), Omega, omega, lam)  # (*B, i)
    log_w = log_weights + ll.unsqueeze(-2)  # (*B, j, i)
    c = torch.logsumexp(log_w, dim=-1)
    w = safe_log_normalize(log_w, c.unsqueeze(-1)).exp()
    n = g.shape[-1]
    pairs = GaussianBelief(f.unsqueeze(-3).expand(*w.shape, n), S.unsqueeze(-4).expand(*w.shape, n, n))
    mixed = pairs.collapse(w)
    Winv = Winv.unsqueeze(-3)
    Cw = symmetrize(Winv @ mixed.cov @ Winv.mT)  # the mixture relative to the reference
    Cwi = torch.cholesky_inverse(cholesky(Cw))
    eye = torch.eye(n, dtype=g.dtype, device=g.device)
    ev, V = torch.linalg.eigh(symmetrize(Cwi - eye))  # W^T Omega W
    root = V.mT @ Winv  # Omega = root^T diag(ev) root
    Om = symmetrize(root.mT @ (ev.clamp_min(0.0).unsqueeze(-1) * root))
    gj = g.unsqueeze(-2)
    om = matvec(Winv.mT @ Cwi, matvec(Winv, mixed.mean - gj)) + matvec(Om, gj)
    zero = torch.zeros_like(c)
    lam = c - info_fuse(gj, G.unsqueeze(-3), Om, om, zero)[0]
    return Om, om, lam


def linear_bank(filter: MultipleModelFilter, motions: Any, sensors: Any, controls: Tensor | None):
    """The modes' ``F, b, Q, H, R`` (each ``(M, ...)``) and input matrix ``G`` (or None) from the
    filter's linear-Gaussian description; refused (naming ``method``) where it has none."""
    model = kernels.describe(filter, "linear_gaussian", inputs=True)
    why = model if isinstance(model, str) else None
    if why is None and model.rule not in ("mix", "collapse", "pairs"):
        why = f"the interaction's rule {model.rule!r} (IMM, GPB1 and GPB2 only)"
    if why is None and (model.time_varying is not None or model.transition is None):
        why = "a time-varying transition"
    if why is None and any(m is not None for m in (*(motions or ()), *(sensors or ()))):
        why = "per-step motions or sensors"
    if why is not None:
        raise ValueError(f"method: 'two_filter_info' smooths IMM, GPB1 and GPB2 runs over linear-Gaussian "
                         f"(Kalman) mode filters with one motion and sensor per mode; not this "
                         f"{type(filter).__name__}: {why}. Use method='two_filter' or 'kim'")
    M = filter.num_modes
    F, b, Q, H, R = (t.expand(M, *t.shape[-e:]) for t, e in zip(tuple(model)[:5], (2, 1, 2, 2, 2)))
    singular = cholesky(R, with_flag=True)[1]  # one host read, at entry
    if bool(singular.any()):
        raise ValueError(f"method: 'two_filter_info' needs a positive definite measurement covariance R (a "
                         f"noise-free component has infinite information, which its information form cannot "
                         f"carry); mode {int(singular.nonzero()[0, 0])}'s is singular. Use method='kim' or "
                         f"'two_filter'")
    G = None if model.G is None or controls is None else model.G.expand(M, *model.G.shape[-2:])
    return F, b, Q, H, R, G


def smooth_two_filter_info(filter: MultipleModelFilter, trajectory: Trajectory, measurements: Tensor,
                           controls, motions, sensors, padding: Tensor | None = None) -> Trajectory:
    """``smooth(..., method="two_filter_info")``: the backward pass of the module docstring.
    ``padding (T, *B)`` bool: True after a run's last step (its backward filter starts there, and its
    controls there are not read). The result's ``extras["failed"] (*B,)`` is True for a run whose smoothed
    belief has a NaN (a failed forward run, or a fusion that came out improper: :func:`proper_log_det`)."""
    filtered = gaussian_modes(trajectory)
    comps = filtered.components
    steps = filtered.batch_shape[0]
    z = two_filter_measurements(filter, measurements, comps)
    F, b, Q, H, R, G = linear_bank(filter, motions, sensors, controls)
    Omz, omz, lamz = info_measurements(H, R, z.unsqueeze(-2))  # (T, *B, M, ...): every step at once
    log_pi = filter.transition.log_matrix().to(comps.mean)  # [j, i]
    Om, om, lam = Omz[steps - 1], omz[steps - 1], lamz[steps - 1]  # beta_{T-1}
    smoothed = [filtered[steps - 1]]
    for k in range(steps - 2, -1, -1):  # the prediction k -> k+1 used controls[k+1]
        offset = b if G is None else b + matvec(G, controls[k + 1].unsqueeze(-2))
        if padding is not None:  # a run whose step k+1 is padding ends at k: nothing comes back from k+1
            end = padding[k + 1]  # (and its controls there, NaN padding perhaps, move nothing)
            Om, om, lam, offset = (torch.where(end.view(*end.shape, *[1] * (t.dim() - end.dim())), 0.0, t)
                                   for t in (Om, om, lam, offset.expand(*end.shape, *offset.shape[-2:])))
        Om, om, lam = info_predict(Om, om, lam - lam.amax(-1, keepdim=True), F, Q, offset)  # beta~_{k+1}
        ll, mean, cov = info_fuse(comps.mean[k].unsqueeze(-2), comps.cov[k].unsqueeze(-3),
                                  Om.unsqueeze(-4), om.unsqueeze(-3), lam.unsqueeze(-2))  # (*B, j, i)
        log_pair = filtered.mode_log_probs[k].unsqueeze(-1) + log_pi + ll
        norm = torch.logsumexp(log_pair.flatten(-2), dim=-1)[..., None, None]
        log_pair = safe_log_normalize(log_pair, norm)
        log_mode = torch.logsumexp(log_pair, dim=-1)  # log mu^s_k(j)
        weights = safe_log_normalize(log_pair, log_mode.unsqueeze(-1)).exp()
        step = ModeBelief(log_mode, GaussianBelief(mean, cov).collapse(weights))
        if padding is not None:
            step = where(padding[k + 1], filtered[k], step)
        smoothed.append(step)
        if k > 0:
            Om, om, lam = info_mixture(log_pi, filtered[k].estimate(), Om, om, lam)
            Om, om, lam = Om + Omz[k], om + omz[k], lam + lamz[k]
    out = mode_trajectory(smoothed[::-1], trajectory)
    belief = out.belief  # a divergent fusion (proper_log_det) or a failed forward run: NaN, flagged
    failed = (belief.mode_log_probs.isnan().any(-1) | belief.estimate().mean.isnan().any(-1)).any(0)
    return Trajectory(belief=belief, prior=None, log_likelihood=out.log_likelihood, innovation=None,
                      innovation_cov=None, extras={"failed": failed})

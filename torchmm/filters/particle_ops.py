"""The particle operations every particle filter shares (split from :mod:`torchmm.filters.particle` by concern,
issue 47; re-exported there): the noise factor (cached while the covariance is unchanged), Gaussian draws,
the propagation of particles through a motion model, the measurement log-likelihoods, and the checks and
diagnostics of a particle update."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief, ParticleBelief, psd_sqrt, symmetrize
from torchmm.filters.base import Filter
from torchmm.linalg import cholesky
from torchmm.models.base import MeasurementModel, MotionModel, check_output
from torchmm.models.linear import LinearMeasurement, LinearMotion, plain_linear
from torchmm.runtime import host_reads_ok
from torchmm.unchanged import Unchanged
from torchmm.validation import as_int, broadcast_shape, check_covariance, check_filter_dtype, gaussian_batch

__all__ = [
    "cached_noise_factor",
    "check_generator",
    "check_likelihood_noise",
    "check_noise_dtype",
    "check_particle_prior",
    "degenerate_guard",
    "particle_batch",
    "particle_innovation",
    "particle_failure",
    "particle_log_likelihood",
    "gaussian_log_likelihood",
    "noise_factor",
    "propagate_particles",
    "sample_gaussian",
    "standard_normal",
    "usable_loglik",
    "whitening",
]


def noise_factor(cov: Tensor, rtol: float = 1e-10) -> Tensor:
    """A factor ``L`` with ``L L^T = cov``, dropping null directions shared by every matrix.

    Full-rank matrices get their Cholesky factor; rank-deficient process noise such as
    ``q G G^T`` gets an eigen-factor with only the ``r < n`` significant directions (eigenvalues
    above ``rtol`` times the largest), so it is sampled from ``r`` normals.

    Shapes:
        cov: ``(..., n, n)`` -> ``(..., n, r)``
    """
    eigvals, eigvecs = torch.linalg.eigh(symmetrize(cov))
    scale = eigvals.amax(-1, keepdim=True).clamp_min(torch.finfo(cov.dtype).tiny)
    rank = max(int((eigvals > rtol * scale).sum(-1).max()), 1)
    if rank == cov.shape[-1]:
        chol, info = torch.linalg.cholesky_ex(cov)
        if not bool((info != 0).any()):
            return chol
    # keep the r significant directions *before* the square root: sqrt has an infinite derivative
    # at the (numerically) zero eigenvalues, which would turn gradients w.r.t. Q into NaN
    top = eigvals[..., -rank:].clamp_min(torch.finfo(cov.dtype).tiny)
    return eigvecs[..., -rank:] * top.sqrt().unsqueeze(-2)


#: each Q's factor while Q is unchanged (per-step models with fresh Q tensors: at most 64 kept)
_FACTORS = Unchanged(size=64)


def cached_noise_factor(cov: Tensor) -> Tensor:
    """:func:`noise_factor` of a model's ``Q``, computed once per tensor (and per in-place change):
    its rank decides the number of normals, a host read that a step must not repeat. Recomputed
    (with that read) where ``Q`` requires gradients, so that every call has its own graph.

    Shapes:
        cov: ``(*P, n, n)`` -> ``(*P, n, r)``"""
    if cov.requires_grad and torch.is_grad_enabled():
        return noise_factor(cov)
    hit = _FACTORS.get((cov,))
    return hit if hit is not None else _FACTORS.put((cov,), noise_factor(cov))


def sample_gaussian(belief: GaussianBelief, num_particles: int, *,
                    generator: torch.Generator | None = None) -> Tensor:
    """``num_particles`` draws from every Gaussian of a batch.

    Shapes:
        belief: mean ``(*B, n)``, cov ``(*B, n, n)`` -> ``(*B, Np, n)``
    """
    num_particles = as_int(num_particles, "num_particles", minimum=1)
    root = psd_sqrt(belief.cov)
    batch, n = belief.batch_shape, belief.state_dim
    eps = torch.randn(*batch, int(num_particles), n, dtype=belief.dtype, device=belief.device,
                      generator=generator)
    return belief.mean.unsqueeze(-2) + eps @ root.mT


def standard_normal(shape, like: Tensor, *, generator: torch.Generator | None = None,
                    noise_dtype: torch.dtype | None = None) -> Tensor:
    """Standard normals of ``shape`` in ``like``'s dtype, optionally drawn in ``noise_dtype``.

    ``noise_dtype=torch.float32`` draws float32 normals and casts them: on CPU about 4x faster
    than float64 draws (torch's vectorised float32 Box-Muller), at the cost of 24-bit normals
    whose tails end near 5.8 sigma (``sqrt(-2 ln 2^-24)``), which a particle filter's process
    noise does not notice. ``None`` draws in ``like``'s dtype.

    Shapes:
        -> ``shape``
    """
    dtype = like.dtype if noise_dtype is None else noise_dtype
    eps = torch.randn(shape, dtype=dtype, device=like.device, generator=generator)
    return eps if dtype == like.dtype else eps.to(like.dtype)


def _add(a: Tensor, b: Tensor) -> Tensor:
    """``a + b``, in place into the fresh temporary ``a`` when the shapes allow it."""
    if broadcast_shape(a.shape, b.shape) == a.shape and a.dtype == b.dtype:
        return a.add_(b)
    return a + b


def _affine_rows(x: Tensor, A: Tensor, c: Tensor, shape) -> Tensor:
    """``c + x A^T`` for particle sets ``x (*S, Np, k)``, an unbatched ``A (d, k)`` and a small ``c``
    that broadcasts to ``shape = (*S, Np, d)`` without varying along the particles (one row per
    set): one ``baddbmm`` over the sets, ``c`` read with stride 0 along the particles."""
    *sets, num, d = shape
    rows = torch.Size(sets).numel()
    out = _repeat_rows(c.expand(*sets, 1, d).reshape(rows, 1, d), num)
    # in place (beta = 1): the same numbers as an out-of-place baddbmm with the stride-0 c, whose
    # copy of c into its result runs d elements at a time
    return out.baddbmm_(x.reshape(rows, num, x.shape[-1]), A.mT.expand(rows, *A.mT.shape)).view(shape)


def _repeat_rows(c: Tensor, num: int) -> Tensor:
    """``c (rows, 1, d)`` repeated ``num`` times along axis 1, as a new contiguous ``(rows, num, d)``.

    A copy of the broadcast ``c`` runs its inner loop over the ``d`` elements of one row (for
    particles, ``d`` = 2-6: ~5x slower than a copy on CPU); here it runs over ``k`` rows at once
    (a ``(rows, 1, k d)`` tile of ``c``, repeated ``num // k`` times, then the rest). Exact: a copy."""
    rows, _, d = c.shape
    out = torch.empty((rows, num, d), dtype=c.dtype, device=c.device)
    k = max(1, min(num, 64 // max(d, 1)))
    whole = num // k * k
    if whole:
        tile = c.expand(rows, k, d).reshape(rows, 1, k * d)
        out[:, :whole].view(rows, whole // k, k * d).copy_(tile.expand(rows, whole // k, k * d))
    if whole < num:
        out[:, whole:].copy_(c.expand(rows, num - whole, d))
    return out


def propagate_particles(motion: MotionModel, particles: Tensor, *, u: Tensor | None = None,
                        generator: torch.Generator | None = None,
                        noise_dtype: torch.dtype | None = None) -> Tensor:
    """``x_k = f(x_{k-1}, u_k) + w_k``, ``w_k ~ N(0, Q)``, for particle sets.

    The model's parameter batch ``*P`` broadcasts against the particle sets' batch ``*B`` (a bank
    of ``M`` modes against ``(*B, M)``). Linear models are applied as one matmul on the particle
    layout (with an unbatched ``F``: one ``addmm`` that also adds the noise and offset) where they are
    :func:`~torchmm.models.linear.plain_linear` (a subclass with its own ``forward`` is called); any other
    model is called with the particle axis leftmost (the torchmm convention for sample axes). The
    process noise ``Q = motion.noise_cov()`` is taken as state-independent; its standard normals
    are drawn in ``noise_dtype`` (see :func:`standard_normal`).

    Shapes:
        particles: ``(*B, Np, n)``; u: ``(*B, k)`` -> ``(*B, Np, n)``
    """
    Q = check_output(motion, motion.noise_cov(), None, "motion", "noise_cov", dtype=particles.dtype)
    factor = cached_noise_factor(Q)  # (*P, n, r), shared by the particles of a set
    eps = standard_normal((*particles.shape[:-1], factor.shape[-1]), particles, generator=generator,
                          noise_dtype=noise_dtype)
    # the matrices only for a plain LinearMotion: a subclass with its own forward is called (plain_linear)
    plain = isinstance(motion, LinearMotion) and plain_linear(motion)
    offset = motion.offset.unsqueeze(-2) if plain else None
    if (offset is not None and factor.dim() == 2 and particles.dim() >= 3
            and broadcast_shape(offset.shape, particles.shape) == particles.shape):
        # the offset and the noise in one batched GEMM over the particle sets: C + eps L^T with the
        # (small) offset as a stride-0 C; the same numbers as `linear` then `add_`, 25 % faster
        noise = _affine_rows(eps, factor, offset, particles.shape)
    else:
        # x @ A^T with an unbatched A as `linear` (a contiguous operand: ~3x faster than a matmul with
        # the transposed view for millions of rows on CPU)
        noise = torch.nn.functional.linear(eps, factor.contiguous()) if factor.dim() == 2 else eps @ factor.mT
        if offset is not None:
            noise = _add(noise, offset)
    if offset is not None:
        if u is not None:
            if motion.input_matrix is None:
                raise ValueError("u: this LinearMotion has no input_matrix")
            noise = _add(noise, u.unsqueeze(-2) @ motion.input_matrix.mT)
        F = motion.F
        if F.dim() == 2 and noise.shape == particles.shape:
            n = particles.shape[-1]
            # in place into the fresh noise tensor: one GEMM with beta = 1, no copy of the input
            rows = particles.shape[:-1].numel()
            return noise.view(rows, n).addmm_(particles.reshape(rows, n), F.mT.contiguous()).view(particles.shape)
        return particles @ F.mT + noise
    states = particles.movedim(-2, 0)
    out = check_output(motion, motion(states, u=None if u is None else u.unsqueeze(0)), states, "motion")
    return out.movedim(0, -2) + noise


def _predicted_measurement(measurement: MeasurementModel, particles: Tensor) -> Tensor:
    """``h(x)`` for particle sets ``(*B, Np, n)`` -> ``(*B, Np, m)``."""
    if isinstance(measurement, LinearMeasurement) and plain_linear(measurement):  # (else its own forward)
        return particles @ measurement.H.mT
    states = particles.movedim(-2, 0)
    return check_output(measurement, measurement(states), states, "measurement").movedim(0, -2)


def _sum_squares(x: Tensor) -> Tensor:
    """``(x ** 2).sum(-1)``; for a short last axis as a chain of ``addcmul`` over its columns, which
    on CPU is several times faster than a reduction over a tiny innermost axis."""
    m = x.shape[-1]
    if m > 8:
        return x.square().sum(-1)
    out = x[..., 0] * x[..., 0]
    for j in range(1, m):  # over the measurement components (m <= 8), not over runs or particles
        out = torch.addcmul(out, x[..., j], x[..., j])
    return out


def whitening(cov: Tensor) -> tuple[Tensor, Tensor]:
    """``(L^{-1}, log det cov)`` with ``L L^T = cov``. Shapes: ``(..., m, m)`` -> same, ``(...)``.

    The factor is :func:`~torchmm.linalg.cholesky` (never raises; regularised where
    ``cov`` is not numerically positive definite)."""
    chol = cholesky(cov)
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    inv = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
    return inv, 2 * chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)


def gaussian_log_likelihood(resid: Tensor, cov: Tensor, observed: Tensor | None = None) -> Tensor:
    """Gaussian log-density of residuals of particle sets, with per-batch missing components.

    ``observed`` marks the measured components of each batch element (NaN = missing); missing
    components are marginalised out exactly (an all-missing element gives 0).

    Shapes:
        resid: ``(*B, Np, m)``; cov: ``(*P, m, m)`` broadcasting with ``*B``;
        observed: ``(*B, m)`` bool or None -> ``(*B, Np)``
    """
    m = resid.shape[-1]
    if observed is None:
        inv, logdet = whitening(cov)
        count = torch.full((), float(m), dtype=resid.dtype, device=resid.device)
    else:
        eye = torch.eye(m, dtype=resid.dtype, device=resid.device)
        resid = torch.where(observed.unsqueeze(-2), resid, torch.zeros((), dtype=resid.dtype, device=resid.device))
        pair = observed.unsqueeze(-1) & observed.unsqueeze(-2)
        inv, logdet = whitening(torch.where(pair, cov, eye))
        count = observed.sum(-1).to(resid.dtype).unsqueeze(-1)
    white = resid @ inv.mT
    return -0.5 * (_sum_squares(white) + logdet.unsqueeze(-1) + count * math.log(2 * math.pi))


def particle_log_likelihood(measurement: MeasurementModel, z: Tensor, particles: Tensor,
                             state_dependent_noise: bool, *,
                             need_predicted: bool = True) -> tuple[Tensor, Tensor | None]:
    """``log p(z | x)`` per particle and the predicted measurements (None unless ``need_predicted``
    or needed anyway).

    A linear measurement with unbatched ``H`` and ``R`` and no missing data is whitened before the
    particles are touched: ``L^{-1}(z - H x) = L^{-1} z - (L^{-1} H) x``, one matmul over them.

    Shapes:
        z: ``(*B, m)`` (NaN = missing); particles ``(*B, Np, n)`` -> ``(*B, Np)``, ``(*B, Np, m)``
    """
    missing = ~torch.isfinite(z)
    # the whitened path needs complete data: asked on the CPU only; elsewhere the general path (no host read)
    any_missing = bool(missing.any()) if host_reads_ok(z) else True
    if (not need_predicted and not state_dependent_noise and not any_missing
            and isinstance(measurement, LinearMeasurement) and plain_linear(measurement)
            and measurement.H.dim() == 2):
        cov = _noise(measurement, particles)
        if cov.dim() == 2:
            inv, logdet = whitening(cov)
            weights, shift = (inv @ measurement.H).contiguous(), -(z @ inv.mT).unsqueeze(-2)
            shape = (*particles.shape[:-1], z.shape[-1])
            if particles.dim() >= 3 and broadcast_shape(shift.shape, shape) == shape:
                white = _affine_rows(particles, weights, shift, shape)  # C + x W^T, one batched GEMM
            else:
                white = _add(torch.nn.functional.linear(particles, weights), shift)  # (*B, Np, m)
            m = z.shape[-1]
            const = logdet + m * math.log(2 * math.pi)
            return _sum_squares(white).add_(const).mul_(-0.5), None
    predicted = _predicted_measurement(measurement, particles)
    if state_dependent_noise:
        loglik = measurement.log_likelihood(z.unsqueeze(0), particles.movedim(-2, 0)).movedim(0, -1)
        return loglik, predicted
    observed = None if not any_missing else ~missing
    resid = z.unsqueeze(-2) - predicted
    return gaussian_log_likelihood(resid, _noise(measurement, particles), observed), predicted


def _noise(measurement: MeasurementModel, particles: Tensor) -> Tensor:
    """``measurement.noise_cov()`` checked against the particles' dtype (shapes only)."""
    return check_output(measurement, measurement.noise_cov(), None, "measurement", "noise_cov",
                        dtype=particles.dtype)


def check_noise_dtype(noise_dtype):
    if noise_dtype is None:
        return None
    if isinstance(noise_dtype, str):
        noise_dtype = getattr(torch, noise_dtype, None)
    if not isinstance(noise_dtype, torch.dtype) or not noise_dtype.is_floating_point:
        raise ValueError(f"noise_dtype: expected a floating-point torch dtype (e.g. torch.float32), got {noise_dtype!r}")
    return noise_dtype


def check_generator(generator):
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"generator: expected a torch.Generator or None, got {type(generator).__name__}")
    return generator


def check_likelihood_noise(measurement: MeasurementModel) -> None:
    """The particle weights need a positive definite measurement noise (a singular ``R`` makes the
    likelihood a point mass)."""
    try:
        cov = measurement.noise_cov()
    except (TypeError, ValueError, RuntimeError):
        return  # state-dependent by construction: checked when evaluated
    if isinstance(cov, Tensor):
        check_covariance(cov, "measurement.R", definite=True)


def check_particle_prior(filter: Filter, belief) -> None:
    """Entry-point checks of the Gaussian prior particles are drawn from."""
    if not isinstance(belief, GaussianBelief):
        raise TypeError(f"belief: expected a GaussianBelief prior to sample from, got {type(belief).__name__}")
    gaussian_batch(belief, filter.motion.state_dim)
    belief.validate("belief")
    check_filter_dtype(filter, belief, "belief")


def particle_batch(belief, state_dim: int, name: str = "belief") -> torch.Size:
    """Batch shape of a particle belief, checked against the state dimension (shapes only)."""
    if not isinstance(belief, ParticleBelief):
        raise TypeError(f"{name}: expected a ParticleBelief, got {type(belief).__name__}")
    if belief.particles.shape[-1] != state_dim:
        raise ValueError(f"{name}: particles have state dimension {belief.particles.shape[-1]}, the model "
                         f"{state_dim}")
    return belief.log_weights.shape[:-1]


def particle_failure(loglik: Tensor, present: Tensor) -> Tensor:
    """``(*B,)`` True where the datum is present but a particle's likelihood ``loglik (*B, Np)`` is
    NaN or ``+inf``: non-finite particles after propagation (a model that went NaN), a state-dependent
    ``R(x)`` that is not positive definite, or a user likelihood with a point mass - a model failure,
    not missing data and not an all-underflow. The update's log-likelihood is NaN there
    (``extras["failed"]``, docs/robustness.md); the weights drop those particles (:func:`usable_loglik`).
    No host read."""
    return (~(loglik < math.inf)).any(-1) & present  # (one comparison: False for NaN and +inf)


def usable_loglik(loglik: Tensor) -> Tensor:
    """``loglik (*B, Np)`` with its NaN and ``+inf`` entries (:func:`particle_failure`) set to ``-inf``:
    those particles get zero weight. Same shape."""
    return torch.where(loglik < math.inf, loglik, -math.inf)


def degenerate_guard(log_evidence: Tensor) -> Tensor:
    """``(*B,)`` True where every particle weight vanished (the evidence is not finite): the update
    keeps the prior weights there (``extras["degenerate"]``). No host read in the step:
    :func:`~torchmm.run_filter` warns once per run with the count."""
    return ~torch.isfinite(log_evidence)


def particle_innovation(z: Tensor, predicted: Tensor, log_w: Tensor, cov: Tensor | None) -> tuple[Tensor, Tensor | None]:
    """Innovation ``z - E[h(x)]`` and ``Cov[h(x)] + R`` under normalised log-weights ``(*B, Np)``."""
    w = log_w.exp().unsqueeze(-1)
    mean = (w * predicted).sum(-2)
    if cov is None:
        return z - mean, None
    diff = predicted - mean.unsqueeze(-2)
    spread = (diff * w).mT @ diff
    return z - mean, symmetrize(spread + cov)

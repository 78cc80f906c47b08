"""The two-filter IMM smoother (Helmick, Blair & Hoffman, IEEE Trans. Inf. Theory 41(6), 1995), the default of
:func:`torchmm.smooth` for multiple-model filters (split from torchmm/smooth.py by concern, issue 47): a
backward-time IMM over the same data (:func:`backward_predict` through the inverted motion,
:func:`backward_imm_update`) whose mode-conditioned beliefs are fused with the forward ones for every pair of
modes at ``k`` and ``k + 1`` (:func:`two_filter_step`). Batched over every run and mode axis; the backward
pass is the only loop (over time)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, ModeBelief, symmetrize, where
from torchmm.beliefs.ops import safe_log_normalize
from torchmm.linalg import cholesky, half_log_det, solve_lower, sum_last
from torchmm.models.base import MotionModel
from torchmm.multimodel.bank import ListBank, VectorizedBank
from torchmm.multimodel.imm import mode_posterior
from torchmm.run import Trajectory

if TYPE_CHECKING:
    from torchmm.multimodel.imm import MultipleModelFilter

__all__ = ["backward_imm_update", "backward_predict", "diffuse_factor", "gaussian_modes", "mode_trajectory", "prior_mode_log_probs", "smooth_two_filter",
           "two_filter_step"]


def member_motion(member: Any) -> MotionModel:
    if getattr(member, "smoother", None) in ("rts", "unscented"):
        return member.motion
    raise TypeError(f"filter: the two-filter smoother runs the mode filters' motion models backwards; no support "
                    f"for mode filters of type {type(member).__name__} (supported: KalmanFilter, "
                    "ExtendedKalmanFilter, UnscentedKalmanFilter)")


def linearized_motions(bank: Any, at: Tensor, u: Tensor | None, *,
                        expand: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    """Every mode's motion at ``at``: ``f_i(at)``, the Jacobian ``F_i(at)`` and ``Q_i``.

    Shapes:
        at: ``(*B, M, n)``; u: ``(*B, 1, k)`` -> ``(*B, M, n)``, ``(*B, M, n, n)``, ``(*B, M, n, n)``
        (with ``expand=False``, ``F`` and ``Q`` as the models give them, broadcastable to those)
    """
    n = at.shape[-1]
    if isinstance(bank, VectorizedBank):  # the models broadcast over the mode axis
        motion = member_motion(bank.filter)
        fx, F, Q = motion(at, u=u), motion.jacobian(at, u=u), motion.noise_cov(at)
        if not expand:
            return fx, F, Q
        return fx, F.expand(*at.shape, n), Q.expand(*at.shape, n)
    if isinstance(bank, ListBank):  # one call per mode filter
        parts = []
        for i, member in enumerate(bank.filters):
            motion, x = member_motion(member), at.select(-2, i)
            ui = None if u is None else u.select(-2, 0 if u.shape[-2] == 1 else i)
            parts.append((motion(x, u=ui), motion.jacobian(x, u=ui), motion.noise_cov(x).expand(*x.shape, n)))
        return tuple(torch.stack([p[k] for p in parts], dim=-2 - min(k, 1)) for k in range(3))
    raise TypeError(f"filter: no two-filter smoother for a bank of type {type(bank).__name__}")


def backward_predict(bank: Any, belief: GaussianBelief, at: Tensor, u: Tensor | None = None) -> GaussianBelief:
    r"""The backward time update of every mode: ``p(x_k | s_{k+1} = i, z_{k+1:T})`` from
    ``p(x_{k+1} | s_{k+1} = i, z_{k+1:T})``, through mode ``i``'s motion run backwards.

    With ``x_{k+1} = f_i(x_k) + w``, ``w ~ N(0, Q_i)``, ``f_i`` linearised at ``at``
    (``f_i(x) ~ f_i(at) + F_i (x - at)``, exact for linear models) and the backward belief
    ``N(m, P)``: ``x_k = at + F_i^{-1}(m - f_i(at))``, ``P_k = F_i^{-1} (P + Q_i) F_i^{-T}``,
    the likelihood of the future data carried back through the transition density.

    Shapes:
        belief: batch ``(*B, M)``; at: ``(*B, M, n)``; u: ``(*B, 1, k)`` -> batch ``(*B, M)``
    """
    fx, F, Q = linearized_motions(bank, at, u, expand=False)
    # the distinct matrices: a model's Jacobian that is the same for every run (a linear model's F,
    # returned as an expanded view) has stride 0 over those axes
    distinct = F[tuple(slice(0, 1) if stride == 0 else slice(None) for stride in F.stride()[:-2])]
    if distinct.shape[:-2].numel() * 8 <= at.shape[:-1].numel():
        # one Jacobian per mode, shared by the runs: invert the few (M, n, n) once and multiply, where a
        # batched solve would factorise the same matrix for every run
        inverse = torch.linalg.inv_ex(distinct)[0]
        mean = (inverse @ (belief.mean - fx).unsqueeze(-1)).squeeze(-1)
        cov = inverse @ (belief.cov + Q) @ inverse.mT
        return GaussianBelief(at + mean, symmetrize(cov))
    F = F.expand(*at.shape, at.shape[-1])
    rhs = torch.cat([(belief.mean - fx).unsqueeze(-1), belief.cov + Q], dim=-1)  # (*B, M, n, 1 + n)
    solved = torch.linalg.solve_ex(F, rhs)[0]  # F^{-1} [m - f, P + Q]
    cov = torch.linalg.solve_ex(F, solved[..., 1:].mT)[0]  # F^{-1} (P + Q) F^{-T}
    return GaussianBelief(at + solved[..., 0], symmetrize(cov))


def prior_mode_log_probs(filter: MultipleModelFilter, trajectory: Trajectory, steps: int, like: Tensor) -> Tensor:
    """``log P(s_k = j)`` before any datum, ``k = 0 .. T-1``, ``(T, *B, M)`` (or ``(T, M)``).

    Step 0's is read from the trajectory's first prior (the IMM's predicted ``log c_j``, GPB2's pair
    weights summed over the previous mode, or the initial belief with ``update_first``): the prior
    mode probabilities of ``initial_belief`` through the chain, before any datum. Without recorded
    priors, ``initial_belief``'s default (uniform) is assumed. Later steps follow the chain.
    """
    M = filter.num_modes
    matrix = filter.transition.matrix().to(like)
    prior = trajectory.prior
    first = prior.mode_log_probs[0] if type(prior) is ModeBelief else None
    if first is not None and first.shape[-1] == M * M:  # GPB2: log mu_i pi_ij over the pairs (i, j)
        first = torch.logsumexp(first.unflatten(-1, (M, M)), dim=-2)
    if first is None or first.shape[-1] != M:
        first = (torch.full((M,), 1.0 / M, dtype=like.dtype, device=like.device) @ matrix).log()
    p = first.exp()
    out = [p]
    for _ in range(steps - 1):  # the time loop; (*B, M) x (M, M) (per-run: (*B, 1, M) x (*B, M, M))
        p = p @ matrix if matrix.dim() == 2 else (p.unsqueeze(-2) @ matrix).squeeze(-2)
        out.append(p)
    return torch.stack(out).log()


def two_filter_step(filter: MultipleModelFilter, filtered: ModeBelief, backward_prior: ModeBelief,
                    prior_log_probs_next: Tensor) -> ModeBelief:
    r"""The smoothed ``p(x_k, s_k | z_{1:T})`` of the two-filter IMM smoother from the forward filter's
    ``p(x_k, s_k | z_{1:k})`` and the backward-predicted ``p(x_k | s_{k+1} = i, z_{k+1:T})``
    (:func:`backward_predict`, with the backward mode probabilities ``P(s_{k+1} = i | z_{k+1:T})``).

    For every pair ``(j, i)`` (mode ``j`` at ``k``, ``i`` at ``k + 1``), the forward ``N(x_j, P_j)`` and
    the backward ``N(b_i, B_i)`` are fused, ``D = P_j + B_i``:
    ``x_ji = x_j + P_j D^{-1} (b_i - x_j)``, ``P_ji = P_j - P_j D^{-1} P_j``, and
    ``Lambda_ji = N(b_i - x_j; 0, D) mu^b_i / p_{k+1}(i)`` approximates
    ``p(z_{k+1:T} | s_k = j, s_{k+1} = i, z_{1:k})`` (``p_{k+1}`` the prior mode probabilities, the
    backward filter's flat start). ``P(s_k = j, s_{k+1} = i | z_{1:T}) ∝ mu_j pi_ji Lambda_ji``;
    mode ``j``'s smoothed belief is the moment-matched collapse of ``x_ji`` over ``i``.

    Shapes:
        filtered, backward_prior: batch ``(*B,)``, components ``(*B, M)``; prior_log_probs_next
        ``log p_{k+1}``, ``(*B, M)`` or ``(M,)`` -> batch ``(*B,)``
    """
    fwd, bwd = filtered.components, backward_prior.components
    n = fwd.state_dim
    Pj = fwd.cov.unsqueeze(-3)  # (*B, j, 1, n, n)
    D = Pj + bwd.cov.unsqueeze(-4)  # (*B, j, i, n, n)
    delta = bwd.mean.unsqueeze(-3) - fwd.mean.unsqueeze(-2)  # (*B, j, i, n)
    L = cholesky(D)
    V = solve_lower(L, Pj)  # L^{-1} P_j (two solves: concatenating [P_j | delta] cost more than both)
    w = solve_lower(L, delta.unsqueeze(-1)).squeeze(-1)  # L^{-1} delta
    mean = fwd.mean.unsqueeze(-2) + (V.mT @ w.unsqueeze(-1)).squeeze(-1)  # x_ji
    log_overlap = -0.5 * (sum_last(w.square()) + n * math.log(2 * math.pi)) - half_log_det(L)
    evidence = backward_prior.mode_log_probs - prior_log_probs_next  # log mu^b_i / p_{k+1}(i), (*B, i)
    log_pair = (filtered.mode_log_probs.unsqueeze(-1) + filter.transition.log_matrix() + log_overlap
                + evidence.unsqueeze(-2))
    norm = torch.logsumexp(log_pair.flatten(-2), dim=-1)[..., None, None]
    log_pair = safe_log_normalize(log_pair, norm)
    log_mode = torch.logsumexp(log_pair, dim=-1)  # log mu^s_k(j)
    weights = safe_log_normalize(log_pair, log_mode.unsqueeze(-1)).exp()  # P(s_{k+1} = i | s_k = j, z_{1:T})
    # the collapse over i of N(x_ji, P_j - V_ji^T V_ji), weights w_ji summing to one:
    # P_j - sum_i w_ji V_ji^T V_ji + spread, the weighted sum as one product of the stacked sqrt(w_ji) V_ji
    # (never forming the M x M pair covariances)
    merged = (weights.unsqueeze(-2) @ mean).squeeze(-2)  # (*B, j, n)
    diff = mean - merged.unsqueeze(-2)  # (*B, j, i, n)
    spread = (diff * weights.unsqueeze(-1)).mT @ diff
    root = (V * weights.sqrt()[..., None, None]).flatten(-3, -2)  # (*B, j, i n, n)
    cov = symmetrize(fwd.cov - root.mT @ root + spread)
    return ModeBelief(log_mode, GaussianBelief(merged, cov))


def backward_imm_update(filter: MultipleModelFilter, predicted: ModeBelief, z: Tensor, prior_log_probs: Tensor, *,
                        sensor: Any = None) -> ModeBelief:
    r"""The backward IMM's interaction and update at step ``k``: ``p(x_k, s_k | z_{k:T})`` from the
    backward-predicted ``p(x_k | s_{k+1} = i, z_{k+1:T})`` with ``P(s_{k+1} = i | z_{k+1:T})``.

    Backward transition ``P(s_k = j | s_{k+1} = i) = pi_ji p_k(j) / sum_l pi_li p_k(l)`` (``p_k`` the
    prior mode probabilities); mixing weights ``P(s_{k+1} = i | s_k = j, z_{k+1:T}) ∝
    P(s_k = j | s_{k+1} = i) mu^b_{k+1}(i)``; mode ``j``'s mixed belief is updated with ``z_k`` by mode
    ``j``'s filter; ``mu^b_k(j) ∝ a_j Lambda_j``.

    Shapes:
        predicted: batch ``(*B,)``, components ``(*B, M)``; z ``(*B, m)``; prior_log_probs ``log p_k``,
        ``(*B, M)`` or ``(M,)`` -> batch ``(*B,)``
    """
    log_pi = filter.transition.log_matrix()  # [j, i]
    log_back = (log_pi + prior_log_probs.unsqueeze(-1)).mT  # [i, j]: log pi_ji p_k(j)
    log_back = log_back - torch.logsumexp(log_back, dim=-1, keepdim=True)  # P(s_k = j | s_{k+1} = i)
    log_joint = predicted.mode_log_probs.unsqueeze(-1) + log_back  # (*B, i, j)
    log_a = torch.logsumexp(log_joint, dim=-2)  # (*B, j)
    weights = safe_log_normalize(log_joint, log_a.unsqueeze(-2)).exp()
    mixed = predicted.components.mix(weights)  # (*B, j)
    out = filter.bank.update(mixed, z.unsqueeze(-2), sensor=sensor)
    log_mode, _ = mode_posterior(out.log_likelihood, log_a)
    return ModeBelief(log_mode, out.belief)


def diffuse_factor(dtype: torch.dtype) -> float:
    """The backward filter's start: the last collapsed estimate with its covariance times this factor,
    the same for every mode - a nearly flat prior, so that the backward filter carries the likelihood of
    the future data alone. ``eps^{-1/2}`` (6.7e7 in float64, 2.9e3 in float32) balances what the prior
    still weighs (``~1/factor``) against the rounding of the first update (``~eps factor``). With modes
    that share ``F`` the results are insensitive to it from about 1e3 up; with modes of different ``F`` they
    depend on it (docs/smoothing.md, "A nearly flat start")."""
    return torch.finfo(dtype).eps ** -0.5


def smooth_two_filter(filter: MultipleModelFilter, trajectory: Trajectory, measurements: Tensor, controls, motions,
                       sensors, padding: Tensor | None = None) -> Trajectory:
    gaussian_modes(trajectory, materialize=False)  # (the type check)
    steps = trajectory.belief.batch_shape[0]
    z = two_filter_measurements(filter, measurements, trajectory.belief.components)
    prior_log = prior_mode_log_probs(filter, trajectory, steps, trajectory.belief.mode_log_probs)
    if steps > 1:  # once, at the entry point: the backward filter runs every mode's motion backwards
        check_invertible(bank_at(filter, motions, steps - 1), trajectory.belief.components.mean[steps - 1],
                          None if controls is None else controls[steps - 1].unsqueeze(-2))
    # the steps at which some run ends before T (one host read at the entry point)
    ends = set() if padding is None else set(torch.nonzero(padding[1:] & ~padding[:-1])[:, 0].tolist())
    if controls is None and motions is None and sensors is None:  # a whole-run kernel
        run, _ = kernels.plan_smooth(filter, trajectory, "two_filter", measurements=z, prior_log=prior_log,
                                     **({} if padding is None else {"padding": padding, "ends": ends}))
        smoothed = None if run is None else run()
        if smoothed is not None:
            return Trajectory(belief=smoothed, prior=None, log_likelihood=trajectory.log_likelihood,
                              innovation=None, innovation_cov=None, extras={})
    filtered = gaussian_modes(trajectory)
    comps = filtered.components
    last = filtered[steps - 1]

    def start(k: int) -> ModeBelief:
        """The backward filter's start at step ``k`` (a run's last step): a nearly flat prior around the
        filter's collapsed estimate, updated with ``z_k``."""
        est = filtered[k].estimate()
        flat = GaussianBelief(est.mean.unsqueeze(-2).expand_as(comps.mean[k]),
                              (diffuse_factor(est.cov.dtype) * est.cov).unsqueeze(-3).expand_as(comps.cov[k]))
        out = filter.bank.update(flat, z[k].unsqueeze(-2), sensor=None if sensors is None else sensors[k])
        return ModeBelief(mode_posterior(out.log_likelihood, prior_log[k])[0], out.belief)

    backward = start(steps - 1)
    smoothed = [last]
    for k in range(steps - 2, -1, -1):  # the prediction k -> k+1 used motions[k+1] and controls[k+1]
        bank = bank_at(filter, motions, k + 1)
        u = None if controls is None else controls[k + 1].unsqueeze(-2)
        at = filtered[k].estimate().mean.unsqueeze(-2).expand(comps.mean[k].shape)  # the linearisation point
        predicted = ModeBelief(backward.mode_log_probs, backward_predict(bank, backward.components, at, u))
        step = two_filter_step(filter, filtered[k], predicted, prior_log[k + 1])
        if padding is not None:  # a run whose step k+1 is padding ends at k: its filtered belief
            step = where(padding[k + 1], filtered[k], step)
        smoothed.append(step)
        if k > 0:
            backward = backward_imm_update(filter, predicted, z[k], prior_log[k],
                                           sensor=None if sensors is None else sensors[k])
            if k in ends:  # the runs whose last step is k start their backward filter here
                backward = where(padding[k + 1], start(k), backward)
    return mode_trajectory(smoothed[::-1], trajectory)


def bank_at(filter: MultipleModelFilter, motions: list | None, k: int) -> Any:
    """The bank that predicted into step ``k``: the filter's, or with ``motions[k]`` (None: the filter's)."""
    motion = None if motions is None else motions[k]
    return filter.bank if motion is None else filter.bank.with_motion(motion)


def two_filter_measurements(filter: MultipleModelFilter, measurements: Any, comps: GaussianBelief) -> Tensor:
    steps, batch = comps.batch_shape[0], comps.batch_shape[1:-1]
    if measurements is None:
        raise ValueError("measurements: the two-filter smoother (the default for multiple-model filters) runs a "
                         "backward IMM over the data: pass the measurements given to run_filter, "
                         "smooth(filter, trajectory, z); method='kim' smooths without them (docs/smoothing.md)")
    if not isinstance(measurements, Tensor):
        raise TypeError(f"measurements: expected a tensor (T, *B, m), got {type(measurements).__name__}")
    m = filter.meas_dim
    expected = (steps, *batch) + ((m,) if m is not None else tuple(measurements.shape[len(batch) + 1:]))
    if tuple(measurements.shape) != expected:
        raise ValueError(f"measurements: expected shape {expected} (the trajectory's steps and runs), got "
                         f"{tuple(measurements.shape)}")
    if measurements.dtype != comps.mean.dtype:
        raise TypeError(f"measurements: dtype {measurements.dtype} differs from the trajectory's {comps.mean.dtype}")
    return measurements


def check_invertible(bank: Any, at: Tensor, u: Tensor | None) -> None:
    """Refuse a motion whose Jacobian is singular at ``at`` (the backward filter inverts it). One host
    read, at the entry point."""
    F = linearized_motions(bank, at, u)[1]
    sv = torch.linalg.svdvals(F)
    bad = (sv[..., -1] <= 1e3 * torch.finfo(F.dtype).eps * sv[..., 0]).reshape(-1, F.shape[-3]).any(0)
    if bool(bad.any()):
        modes = [i for i, b in enumerate(bad.tolist()) if b]
        raise ValueError(f"filter: the two-filter smoother runs the motion backwards and needs an invertible motion "
                         f"Jacobian; mode(s) {modes} have a singular one. Use method='kim'")


def gaussian_modes(trajectory: Trajectory, materialize: bool = True) -> ModeBelief:
    """The filtered mode beliefs of ``trajectory``, checked to be Gaussian modes, materialised (or as
    they are)."""
    filtered = trajectory.belief
    if type(filtered) is not ModeBelief or not isinstance(filtered.components, GaussianBelief):
        got = type(filtered).__name__ + ("" if type(filtered) is not ModeBelief else
                                         f" of {type(filtered.components).__name__}")
        why = ("; run_filter(..., record='estimate') keeps only the combined estimate: smooth a run that "
               "keeps its beliefs (record=None, the default)" if isinstance(filtered, GaussianBelief) else "")
        raise TypeError("trajectory.belief: the multiple-model smoothers need a ModeBelief of Gaussian "
                        f"modes, got {got}{why}")
    components = filtered.components
    return ModeBelief(filtered.mode_log_probs, components.materialize() if materialize else components)


def mode_trajectory(smoothed: list[ModeBelief], trajectory: Trajectory) -> Trajectory:
    belief = ModeBelief(torch.stack([b.mode_log_probs for b in smoothed]),
                        GaussianBelief(torch.stack([b.components.mean for b in smoothed]),
                                       torch.stack([b.components.cov for b in smoothed])))
    return Trajectory(belief=belief, prior=None, log_likelihood=trajectory.log_likelihood, innovation=None,
                      innovation_cov=None, extras={})

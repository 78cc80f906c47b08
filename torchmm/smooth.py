r"""Fixed-interval smoothing: ``smooth(filter, trajectory) -> Trajectory`` of ``p(x_k | z_{1:T})``.

One entry point, dispatching on the filter that produced ``trajectory`` (docs/smoothing.md):

* :class:`~torchmm.KalmanFilter` - the Rauch-Tung-Striebel smoother;
* :class:`~torchmm.ExtendedKalmanFilter` - the extended RTS smoother: the same backward step with
  the motion Jacobian ``F_{k+1}`` at the filtered mean (:func:`~torchmm.filters.rts_step`);
* :class:`~torchmm.UnscentedKalmanFilter` - the unscented RTS smoother of Särkkä (IEEE TAC 53(3),
  2008): sigma points of ``x_{k|k}`` through the motion model give the predicted
  moments and the cross-covariance ``C_{k+1}``, ``G_k = C_{k+1} (P^-_{k+1})^{-1}``,

  .. math::
      x^s_k = x_k + G_k (x^s_{k+1} - x^-_{k+1}),\qquad P^s_k = P_k + G_k (P^s_{k+1} - P^-_{k+1}) G_k^\top.

* :class:`~torchmm.ParticleFilter` - forward-filtering backward-smoothing (FFBSm) of the particle
  weights (Doucet, Godsill & Andrieu, Stat. Comput. 10, 2000; Godsill, Doucet & West,
  JASA 99, 2004): the filter's particles keep their places and get smoothed weights
  ``w_{k|T}^i = w_k^i sum_j w_{k+1|T}^j f(x_{k+1}^j | x_k^i) / sum_l w_k^l f(x_{k+1}^j | x_k^l)``,
  :func:`ffbsm_step`. Cost ``O(T B Np^2 n)`` time and ``O(B Np^2)`` memory per step (all pairs of
  particles): thousands of particles, not millions. Needs a positive-definite process noise ``Q``
  (the transition density);
* :class:`~torchmm.IMM`, :class:`~torchmm.GPB1`, :class:`~torchmm.GPB2` (and any
  :class:`~torchmm.multimodel.MultipleModelFilter` with Gaussian mode beliefs, over Kalman,
  extended or unscented mode filters) - by default the two-filter IMM smoother (Helmick, Blair &
  Hoffman, IEEE Trans. Inf. Theory 41(6), 1995; :func:`backward_predict`,
  :func:`backward_imm_update`, :func:`two_filter_step`): a backward-time IMM over the same data
  (``smooth(filter, trajectory, z)``) whose mode-conditioned beliefs are fused with the forward
  ones for every pair of modes at ``k`` and ``k + 1``; it needs invertible motion Jacobians.
  ``method="kim"``: Kim's smoother (Kim, J. Econometrics 60, 1994; :func:`kim_step`), RTS steps
  from the forward beliefs alone, which needs no data but loses accuracy backwards over long
  horizons on kinematic targets (docs/smoothing.md). Both return smoothed mode probabilities and
  mode-conditioned smoothed beliefs.

``smooth(..., lag=L)`` is fixed-lag smoothing, ``p(x_k | z_{1:k+L})``, for the Kalman, extended and
unscented filters: all windows go back together, ``L`` batched backward steps.

The backward pass is the only loop (over time), batched over every run (and mode) axis; it is
differentiable, and reads no tensor value into Python inside a step (FFBSm checks ``Q`` once, at the
entry point, before any step). Missing data (NaN measurements): the filter's posterior at a missing step
is its prior, and the RTS-type passes use beliefs only (the two-filter smoother's backward IMM skips them
as the forward one does). Missing steps at the end of a run carry nothing about its earlier steps: the
multiple-model smoothers and FFBSm end each run at its last step with a finite measurement, as
``present=`` does (docs/smoothing.md, "Runs of different lengths").
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, ModeBelief, ParticleBelief, symmetrize, where
from torchmm.beliefs.ops import safe_log_normalize
from torchmm.contract import Choice, Data, Finite, Int, Mask, Of, entry_point
from torchmm.filters.base import Filter
from torchmm.filters.smoother import rts_step
from torchmm.linalg import cholesky, cholesky_solve
from torchmm.models.base import MotionModel
from torchmm.multimodel.bank import ListBank, VectorizedBank
from torchmm.run import Trajectory
from torchmm.runtime import entries, host_reads_ok, one_thread_when_small
from torchmm.smooth_checks import (
    checked_against_run,
    padding_steps,
    singular_process_noise,
    unobserved_tail,
    why_not_smoothable,
)
from torchmm.two_filter import (
    backward_imm_update,
    backward_predict,
    diffuse_factor,
    gaussian_modes,
    mode_trajectory,
    smooth_two_filter,
    two_filter_step,
)
from torchmm.two_filter_info import smooth_two_filter_info

if TYPE_CHECKING:  # (annotations only: smooth dispatches on Filter.smoother, never on a filter class)
    from torchmm.filters.particle import ParticleFilter
    from torchmm.filters.unscented import SigmaPointStrategy
    from torchmm.multimodel.imm import MultipleModelFilter

__all__ = ["backward_imm_update", "backward_predict", "diffuse_factor", "ffbsm_step", "kim_step", "smooth",
           "two_filter_step", "unscented_rts_step"]


def _sigma_moments(motion: MotionModel, sigma_points: SigmaPointStrategy, belief: GaussianBelief,
                   u: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Sigma points of ``belief`` through ``motion``: predicted mean ``(*B, n)``, predicted covariance
    (with ``Q``) and cross-covariance ``C = E[(x - m)(f(x) - m^-)^T]``, ``(*B, n, n)`` each."""
    wm, wc = sigma_points.weights(belief.state_dim, belief.dtype, belief.device)
    points = sigma_points.points(belief.mean, belief.cov)  # (S, *B, n)
    propagated = motion(points, u=None if u is None else u.unsqueeze(0))
    shape = (-1,) + (1,) * (propagated.dim() - 1)
    mean = (wm.reshape(shape) * propagated).sum(0)
    weighted = wc.reshape(shape) * (propagated - mean)
    cov = symmetrize(torch.einsum("s...i,s...j->...ij", weighted, propagated - mean) + motion.noise_cov(belief.mean))
    cross = torch.einsum("s...i,s...j->...ij", points - belief.mean, weighted)
    return mean, cov, cross


def unscented_rts_step(motion: MotionModel, sigma_points: SigmaPointStrategy, filtered: GaussianBelief,
                       smoothed_next: GaussianBelief, *, u: Tensor | None = None) -> GaussianBelief:
    r"""One backward step of the unscented RTS smoother (Särkkä 2008): ``x_{k|T}`` from ``x_{k|k}``
    and ``x_{k+1|T}``.

    Sigma points ``X`` of ``x_{k|k}`` are propagated, ``x^- = sum W^m f(X)``,
    ``P^- = sum W^c (f(X) - x^-)(.)^T + Q``, ``C = sum W^c (X - x_k)(f(X) - x^-)^T``,
    ``G = C (P^-)^{-1}``; then ``x^s_k = x_k + G (x^s_{k+1} - x^-)`` and
    ``P^s_k = P_k + G (P^s_{k+1} - P^-) G^T``. On a linear model it is the RTS step.

    Shapes:
        beliefs with batch ``(*B,)`` (broadcasting) -> batch ``(*B,)``; ``u``: ``(*B, k)``.
    """
    mean_pred, cov_pred, cross = _sigma_moments(motion, sigma_points, filtered, u)
    gain_t = cholesky_solve(cholesky(cov_pred), cross.mT)  # G^T = (P^-)^{-1} C^T
    gain = gain_t.mT
    mean = filtered.mean + (gain @ (smoothed_next.mean - mean_pred).unsqueeze(-1)).squeeze(-1)
    cov = filtered.cov + gain @ (smoothed_next.cov - cov_pred) @ gain_t
    return GaussianBelief(mean, symmetrize(cov))


def _transition_log_density(motion: MotionModel, particles: Tensor, following: Tensor, u: Tensor | None,
                            chol_q: Tensor) -> Tensor:
    """``log N(following_j; f(particles_i), Q)`` up to a constant, ``(*B, i, j)``: whitened by
    ``chol(Q)`` and expanded as ``|a|^2 + |b|^2 - 2 a.b`` (one matmul, no ``(*B, Np, Np, n)`` tensor).

    Both sets are first taken relative to a per-run reference point (the mean of the finite
    ``following`` particles, detached): the density depends on differences only, so the shift is exact
    for values and gradients, and the expansion then cancels on the particles' spread instead of their
    absolute coordinates (at 6.4e6 with a process sd of 0.1 it lost the weights to 3e-2 in total
    variation in float64; tests/smoothing/test_smooth.py)."""
    mean = motion(particles.movedim(-2, 0), u=None if u is None else u.unsqueeze(0)).movedim(0, -2)  # f(x_i)
    reference = following.detach()
    finite = torch.isfinite(reference).all(-1, keepdim=True)  # (*B, j, 1)
    reference = (torch.where(finite, reference, 0.0).sum(-2, keepdim=True)
                 / finite.sum(-2, keepdim=True).clamp_min(1))  # (*B, 1, n)
    a = torch.linalg.solve_triangular(chol_q, (mean - reference).mT, upper=False).mT  # (*B, i, n)
    b = torch.linalg.solve_triangular(chol_q, (following - reference).mT, upper=False).mT  # (*B, j, n)
    sq = (a.square().sum(-1).unsqueeze(-1) + b.square().sum(-1).unsqueeze(-2) - 2 * a @ b.mT).clamp_min(0)
    return -0.5 * sq


def ffbsm_step(motion: MotionModel, filtered: ParticleBelief, following: ParticleBelief,
               smoothed_log_weights: Tensor, *, u: Tensor | None = None) -> Tensor:
    r"""One backward FFBSm step: the smoothed log-weights of ``filtered``'s particles at step ``k``.

    ``log w_{k|T}^i = log w_k^i + logsumexp_j(log w_{k+1|T}^j + log f_ij - logsumexp_l(log w_k^l + log f_lj))``
    with ``f_ij = N(x_{k+1}^j; f(x_k^i, u_{k+1}), Q)`` (Doucet, Godsill & Andrieu 2000).

    Args:
        motion: the model of the prediction ``k -> k+1`` (its ``noise_cov()`` positive definite).
        filtered: the filter's particles at ``k``; following: its particles at ``k+1``, whose
            smoothed log-weights are ``smoothed_log_weights``.

    Shapes:
        filtered, following: particles ``(*B, Np, n)``; smoothed_log_weights ``(*B, Np)`` -> ``(*B, Np)``
    """
    chol_q = torch.linalg.cholesky(motion.noise_cov())
    log_f = _transition_log_density(motion, filtered.particles, following.particles, u, chol_q)  # (*B, i, j)
    log_w = torch.log_softmax(filtered.log_weights, dim=-1)
    denom = torch.logsumexp(log_w.unsqueeze(-1) + log_f, dim=-2)  # (*B, j)
    back = (torch.log_softmax(smoothed_log_weights, dim=-1) - denom).nan_to_num(nan=-torch.inf)
    return torch.log_softmax(log_w + torch.logsumexp(log_f + back.unsqueeze(-2), dim=-1), dim=-1)


def _smooth_particles(filter: ParticleFilter, trajectory: Trajectory, controls, motions,
                      padding: Tensor | None = None) -> Trajectory:
    filtered = trajectory.belief
    if not isinstance(filtered, ParticleBelief):
        raise TypeError(f"trajectory.belief: expected particle beliefs, got {type(filtered).__name__}")
    steps = filtered.batch_shape[0]
    for k, motion in enumerate([filter.motion] if motions is None else motions):  # once, at the entry point
        if singular_process_noise(motion):
            where = "the filter's motion" if motions is None else f"motions[{k}]"
            raise ValueError(f"filter: FFBSm needs a positive-definite process noise Q (the transition "
                             f"density); {where} has a singular one")
    log_weights = [torch.log_softmax(filtered.log_weights[steps - 1], dim=-1)]
    for k in range(steps - 2, -1, -1):
        motion = filter.motion if motions is None else motions[k + 1]
        step = ffbsm_step(motion, filtered[k], filtered[k + 1], log_weights[-1],
                          u=None if controls is None else controls[k + 1])
        if padding is not None:  # a run whose step k+1 is padding ends at k: its filtered weights
            step = torch.where(padding[k + 1].unsqueeze(-1), torch.log_softmax(filtered.log_weights[k], dim=-1), step)
        log_weights.append(step)
    belief = ParticleBelief(filtered.particles, torch.stack(log_weights[::-1]))
    return Trajectory(belief=belief, prior=None, log_likelihood=trajectory.log_likelihood, innovation=None,
                      innovation_cov=None, extras={})


def _cross_covariance(member: Any, filtered: GaussianBelief, u: Tensor | None) -> Tensor:
    """``Cov(x_k, x_{k+1} | z_{1:k})`` through ``member``'s motion model: ``P F^T`` (Kalman, extended:
    ``F`` the Jacobian at the mean) or the sigma-point cross-covariance (unscented). ``(*B, n, n)``."""
    kind = getattr(member, "smoother", None)  # (the filter's own backward pass: Filter.smoother)
    if kind == "unscented":
        return _sigma_moments(member.motion, member.sigma_points, filtered, u)[2]
    if kind == "rts":
        return filtered.cov @ member.motion.jacobian(filtered.mean, u=u).mT
    raise TypeError(f"filter: no smoother for mode filters of type {type(member).__name__}; supported: "
                    "KalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter")


def _pair_cross_covariance(bank: Any, pairs: GaussianBelief, u: Tensor | None) -> Tensor:
    """Cross-covariances of every pair ``(j, i)``: mode ``j``'s posterior through mode ``i``'s motion.
    ``pairs``: batch ``(*B, M, M)`` (last axis: the motion's mode) -> ``(*B, M, M, n, n)``."""
    if isinstance(bank, VectorizedBank):  # the models broadcast over the last batch axis
        return _cross_covariance(bank.filter, pairs, u)
    if isinstance(bank, ListBank):  # one call per member filter, as the bank's own predict
        return torch.stack([_cross_covariance(f, pairs.select(-1, i), None if u is None else u[..., i, :])
                            for i, f in enumerate(bank.filters)], dim=-3)
    raise TypeError(f"filter: no smoother for a bank of type {type(bank).__name__}")


def kim_step(filter: MultipleModelFilter, filtered: ModeBelief, smoothed_next: ModeBelief, *,
             u: Tensor | None = None, motion: Any = None) -> ModeBelief:
    r"""One backward step of Kim's smoother (Kim 1994): ``p(x_k, s_k | z_{1:T})`` from the filter's
    ``p(x_k, s_k | z_{1:k})`` and ``p(x_{k+1}, s_{k+1} | z_{1:T})``.

    With ``mu_j`` the filtered mode probabilities, ``pi_ji`` the transition matrix and
    ``mu^-_i = sum_j pi_ji mu_j`` the predicted ones, the joint of ``(s_k, s_{k+1})`` is
    ``P(j, i | z_{1:T}) = mu^s_{k+1}(i) mu_j pi_ji / mu^-_i``, ``mu^s_k(j) = sum_i P(j, i)``.
    For every pair, the RTS step from mode ``j``'s posterior through mode ``i``'s model:
    ``G_ji = C_ji (P^-_ji)^{-1}``, ``x_ji = x_j + G_ji (x^s_{k+1, i} - x^-_ji)``,
    ``P_ji = P_j + G_ji (P^s_{k+1, i} - P^-_ji) G_ji^T``; mode ``j``'s smoothed belief is their
    moment-matched collapse over ``i`` with weights ``P(j, i) / mu^s_k(j)``.

    Shapes:
        filtered, smoothed_next: batch ``(*B,)``, components ``(*B, M)`` -> batch ``(*B,)``;
        ``u``: ``(*B, k)``.
    """
    M = filter.num_modes
    comps = filtered.components
    batch = comps.batch_shape[:-1]
    pairs = comps.unsqueeze(-1).expand(*batch, M, M)  # [..., j, i]: mode j's posterior, mode i's model
    u_pairs = None if u is None else u.unsqueeze(-2).unsqueeze(-2)
    bank = filter.bank if motion is None else filter.bank.with_motion(motion)
    predicted = bank.predict(pairs, u=u_pairs)  # x^-_ji, P^-_ji
    cross = _pair_cross_covariance(bank, pairs, u_pairs)  # C_ji
    gain_t = cholesky_solve(cholesky(predicted.cov), cross.mT)  # G_ji^T
    nxt = smoothed_next.components.unsqueeze(-2)  # (*B, 1, i)
    mean = pairs.mean + (gain_t.mT @ (nxt.mean - predicted.mean).unsqueeze(-1)).squeeze(-1)
    cov = symmetrize(pairs.cov + gain_t.mT @ (nxt.cov - predicted.cov) @ gain_t)
    # mode probabilities, in log space (a time-varying transition's at the step's controls)
    log_pi = filter.transition_at(u).log_matrix() if getattr(filter.transition, "takes_inputs", False) \
        else filter.transition.log_matrix()
    joint_pred = filtered.mode_log_probs.unsqueeze(-1) + log_pi  # log mu_j pi_ji, (*B, j, i)
    log_pred = torch.logsumexp(joint_pred, dim=-2, keepdim=True)  # log mu^-_i
    ratio = (smoothed_next.mode_log_probs.unsqueeze(-2) - log_pred).nan_to_num(nan=-torch.inf)  # 0/0: no mass
    log_pair = joint_pred + ratio
    log_pair = log_pair - torch.logsumexp(log_pair.flatten(-2), dim=-1)[..., None, None]  # sums to one
    log_mode = torch.logsumexp(log_pair, dim=-1)  # log mu^s_k(j)
    weights = safe_log_normalize(log_pair, log_mode.unsqueeze(-1)).exp()  # P(i | j, z_{1:T})
    merged = GaussianBelief(mean, cov).collapse(weights)  # (*B, j)
    return ModeBelief(log_mode, merged)


_PER_STEP = "a sequence of T models, a callable k -> model, or None"


def _step_entries(filter, trajectory=None, *args, **kwargs) -> int:
    """One step's tensor entries of the trajectory to smooth (the thread rule, torchmm.runtime)."""
    traj = filter if isinstance(filter, Trajectory) else trajectory
    return entries(traj.belief) // max(int(traj.log_likelihood.shape[0]), 1)


# declared only where smooth's own check says more (the filter types it smooths, the options a filter
# has) or where the argument's meaning depends on another: smooth(trajectory, measurements)
@entry_point(filter=Of((Filter, Trajectory), check=False, what="the filter that ran, or its Trajectory"),
             trajectory=Of(Trajectory, optional=True, check=False, what="the Trajectory of run_filter"),
             measurements=Data(optional=True), controls=Finite(optional=True, check=False),
             motions=Of((list, tuple, torch.nn.Module), callable_ok=True, optional=True, what=_PER_STEP),
             sensors=Of((list, tuple, torch.nn.Module), callable_ok=True, optional=True, what=_PER_STEP),
             lag=Int(0, optional=True, check=False),
             method=Choice("two_filter", "kim", "two_filter_info", optional=True, check=False),
             present=Mask(optional=True))
@one_thread_when_small(_step_entries)
def smooth(filter: Any, trajectory: Trajectory | None = None, measurements: Tensor | None = None, *,
           controls: Tensor | None = None, motions: Any = None, sensors: Any = None, lag: int | None = None,
           method: str | None = None, present: Tensor | None = None) -> Trajectory:
    r"""The fixed-interval smoothed beliefs ``p(x_k | z_{1:T})`` of a filtered ``trajectory``.

    ``smooth(trajectory)`` smooths with what the run recorded (``trajectory.provenance``): its filter,
    measurements, controls and per-step models. Whatever is passed is checked against that record
    (docs/robustness.md, "What a trajectory knows").

    Args:
        filter: the filter that made ``trajectory`` (:func:`~torchmm.run_filter`), the same object: a
            :class:`~torchmm.KalmanFilter` (RTS), :class:`~torchmm.ExtendedKalmanFilter`
            (extended RTS), :class:`~torchmm.UnscentedKalmanFilter` (unscented RTS), a
            :class:`~torchmm.ParticleFilter` (FFBSm) or a multiple-model filter over Gaussian modes
            (two-filter IMM smoother, or Kim's). Or the trajectory itself, ``smooth(trajectory)``
            (``smooth(trajectory, measurements)``), to use the run's filter.
        trajectory: its output, with the priors recorded (``trajectory.prior``; the default
            ``record`` keeps them).
        measurements: the measurements given to ``run_filter``, ``(T, *B, m)`` (NaN: missing). Needed
            by the two-filter smoother of multiple-model filters (its backward IMM filters them
            again); the other smoothers use the filtered beliefs, and the multiple-model smoothers and
            FFBSm end each run at its last step with a finite measurement (see ``present``). Default: the
            run's.
        controls: the inputs ``u_k`` given to ``run_filter``, ``(T, *B, k)``. Default: the run's.
        motions: the per-step motion models given to ``run_filter`` (a sequence of ``T``, a callable
            ``k -> model`` or one model). Default: the run's.
        sensors: the per-step sensors given to ``run_filter`` (likewise; the two-filter smoother's
            backward updates use them). Default: the run's.
        method: multiple-model filters only: ``"two_filter"`` (default), ``"kim"``, or
            ``"two_filter_info"`` (IMM / GPB1 / GPB2 over Kalman mode filters: the information-form backward
            filter, :mod:`torchmm.two_filter_info`; docs/smoothing.md).
        present: ``(T, *B)`` bool, for runs of different lengths padded at the end (a batch of recorded
            series): False at a run's padding steps, which must follow all its real steps. Each run is
            smoothed over its own steps only, as if it were alone: its last real step keeps the filtered
            belief and the padding never reaches back (the two-filter smoother starts each run's
            backward filter at its own last step). Padding steps keep the filtered beliefs (the
            predictions), which score nothing. One host read at entry. Default: every step present.
            Whether given or not, the multiple-model smoothers and FFBSm also end each run at its last
            step with a finite measurement (the steps after it carry nothing about the earlier ones),
            found from the measurements in one batched pass: a run ends at the earlier of the two. The
            RTS-type smoothers return the filtered beliefs through such steps anyway (to rounding).
        lag: fixed-lag smoothing (Kalman, extended and unscented filters): step ``k`` is smoothed with
            the data up to ``k + lag``, ``p(x_k | z_{1:min(k + lag, T)})``. All ``T`` windows go back
            together: ``lag`` batched backward steps (``O(T lag)`` work). ``None``: fixed interval.

    Returns:
        a :class:`~torchmm.run.Trajectory` whose ``belief`` is the smoothed beliefs, batch ``(T, *B)``
        (``x_{k|T}``; the last equals the filter's last posterior), with the filter's
        ``log_likelihood`` (that of the data, unchanged by smoothing) and no priors or innovations.

    Raises:
        ValueError / TypeError: naming ``filter`` (not the object that ran, another type, or its
        parameters changed in place since), ``measurements`` / ``controls`` (not the data the run
        filtered: shape, dtype, device or checksum; or changed in place since), ``motions`` /
        ``sensors`` (not the run's per-step models), ``trajectory`` (its beliefs are not the run's:
        reversed, sliced or replaced), ``method`` or ``lag``. A trajectory without a record (built
        by hand) is smoothed as given.

    Shapes:
        trajectory.belief, trajectory.prior: batch ``(T, *B)`` -> belief batch ``(T, *B)``.

    Examples:
        >>> import torch
        >>> from torchmm import GaussianBelief, KalmanFilter, run_filter, smooth
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> kf = KalmanFilter(ConstantVelocity(1, q=0.1), PositionMeasurement(2, [0], 1.0))
        >>> z = torch.randn(20, 3, 1, generator=torch.Generator().manual_seed(0))
        >>> traj = run_filter(kf, GaussianBelief(torch.zeros(3, 2), torch.eye(2)), z)
        >>> smoothed = smooth(kf, traj).belief
        >>> tuple(smoothed.mean.shape), bool((smoothed.cov[:-1].diagonal(dim1=-2, dim2=-1)
        ...                                   <= traj.belief.cov[:-1].diagonal(dim1=-2, dim2=-1)).all())
        ((20, 3, 2), True)

        A multiple-model filter is smoothed with the data (the two-filter smoother):

        >>> from torchmm import IMM
        >>> bank = ConstantVelocity(1, q=0.1, acceleration=[[0.0], [2.0]])
        >>> imm = IMM(KalmanFilter(bank, PositionMeasurement(2, [0], 1.0)), torch.tensor([[0.9, 0.1], [0.1, 0.9]]))
        >>> traj = run_filter(imm, imm.initial_belief(GaussianBelief(torch.zeros(3, 2), torch.eye(2))), z)
        >>> out = smooth(imm, traj, z).belief
        >>> out.mode_probs.shape, out.estimate().mean.shape
        (torch.Size([20, 3, 2]), torch.Size([20, 3, 2]))
    """
    if isinstance(filter, Trajectory):  # smooth(trajectory[, measurements]): the run's own filter
        if trajectory is not None and measurements is not None:
            raise TypeError("trajectory: smooth(trajectory, measurements) takes no filter; or pass "
                            "smooth(filter, trajectory, measurements)")
        filter, trajectory, measurements = (None, filter,
                                            trajectory if trajectory is not None else measurements)
    if not isinstance(trajectory, Trajectory):
        raise TypeError(f"trajectory: expected the Trajectory of run_filter, got {type(trajectory).__name__}")
    steps = trajectory.belief.batch_shape[0]
    if controls is not None and (not isinstance(controls, Tensor) or controls.dim() < 1
                                 or controls.shape[0] != steps):
        raise ValueError(
            f"controls: expected a tensor with {steps} steps on the leading axis, got "
            f"{tuple(controls.shape) if isinstance(controls, Tensor) else type(controls).__name__}")
    filter, measurements, controls, motions, sensors = checked_against_run(
        filter, trajectory, measurements, controls, motions, sensors, method, steps)
    # None entries: the filter's model
    kind = getattr(filter, "smoother", None)  # the filter's backward pass (Filter.smoother): no class is named
    why = why_not_smoothable(filter)  # (the rule a study asks before it filters)
    if why is not None:
        raise TypeError(f"filter: {why}")
    if motions is not None and kind != "modes":
        motions = ([filter.motion if m is None else m for m in motions] if hasattr(filter, "motion")
                   else motions)
    if motions is not None and all(m is None for m in motions):
        motions = None
    if lag is not None and kind in ("modes", "particles"):
        raise ValueError(f"lag: fixed-lag smoothing is implemented for Kalman, extended and unscented filters, "
                         f"not {type(filter).__name__}")
    padding = padding_steps(present, trajectory)
    data = measurements if measurements is not None else getattr(trajectory.provenance, "measurements", None)
    if padding is not None and isinstance(data, Tensor):  # padding holds no datum (one host read)
        data = torch.isfinite(data).reshape(*padding.shape, -1).any(-1) & padding
        if bool(data.any()):
            k, *run = torch.nonzero(data)[0].tolist()
            raise ValueError(f"present: run {tuple(run)} has a measurement at step {k}, marked as padding; padding "
                             "is the steps after a run's last one (a missing datum is a NaN measurement)")
    if kind in ("modes", "particles"):  # a run ends at its last step with a datum (the steps after it
        # carry nothing about the earlier ones; Kim's and FFBSm's backward steps through them would move
        # its estimates)
        tail = unobserved_tail(data, trajectory)
        if tail is not None:
            padding = tail if padding is None else padding | tail
            # whether some run ends early: read where it is free (the CPU) or where the entry reads anyway
            # (the two-filter smoother's checks); elsewhere the mask stays on the device (the steps' where)
            if padding is tail and (host_reads_ok(tail) or (kind == "modes" and method != "kim")):
                padding = tail if bool(tail.any()) else None
    if controls is None and motions is None and lag is None and method != "two_filter_info":
        run, _ = kernels.plan_smooth(filter, trajectory, method,
                                     **({} if padding is None else {"padding": padding}))
        smoothed = None if run is None else run()
        if smoothed is not None:  # a whole-run kernel (torchmm.kernels), to rounding the steps below
            return Trajectory(belief=smoothed, prior=None, log_likelihood=trajectory.log_likelihood,
                              innovation=None, innovation_cov=None, extras={})
    if kind == "modes":
        if method not in (None, "two_filter", "kim", "two_filter_info"):
            raise ValueError(f"method: expected 'two_filter', 'kim' or 'two_filter_info' for "
                             f"{type(filter).__name__}, got {method!r}")
        if method != "kim" and getattr(filter.transition, "takes_inputs", False):
            raise ValueError("method: a time-varying transition (LogisticTransition) is smoothed by Kim's smoother: "
                             "method='kim' (the two-filter smoother's backward chain needs one matrix)")
        if method == "kim":
            return _smooth_modes(filter, trajectory, controls, motions, padding)
        if method == "two_filter_info":
            return smooth_two_filter_info(filter, trajectory, measurements, controls, motions, sensors,
                                          padding)
        return smooth_two_filter(filter, trajectory, measurements, controls, motions, sensors, padding)
    if method is not None:
        raise ValueError("method: only multiple-model filters have a choice of smoother ('two_filter', 'kim', "
                         f"'two_filter_info'); "
                         f"got {method!r} for {type(filter).__name__}")
    if kind == "particles":
        return _smooth_particles(filter, trajectory, controls, motions, padding)
    filtered = trajectory.belief
    if not isinstance(filtered, GaussianBelief):
        raise TypeError(f"trajectory.belief: expected Gaussian beliefs, got {type(filtered).__name__}")
    if kind == "rts" and trajectory.prior is None:
        raise ValueError("trajectory.prior: the smoother needs the filter's priors; run run_filter without a "
                         "record that drops them")
    filtered = filtered.materialize()
    predicted = trajectory.prior.materialize() if kind == "rts" else None
    if lag is not None:  # (padding needs nothing here: a padded step's filtered belief is its prediction,
        # which the Gaussian backward steps return unchanged; tests/smoothing/test_padding.py)
        return _fixed_lag(filter, kind, filtered, predicted, controls, motions, lag, trajectory)
    smoothed = [filtered[steps - 1]]
    for k in range(steps - 2, -1, -1):  # the prediction k -> k+1 used motions[k+1] and controls[k+1]
        motion = filter.motion if motions is None else motions[k + 1]
        u = None if controls is None else controls[k + 1]
        if kind == "rts":
            step = rts_step(motion, filtered[k], predicted[k + 1], smoothed[-1], u=u)
        else:
            step = unscented_rts_step(motion, filter.sigma_points, filtered[k], smoothed[-1], u=u)
        # a run whose step k+1 is padding ends at k (the Gaussian smoothers give this to rounding anyway:
        # the filtered belief at a padded step is its prediction)
        smoothed.append(step if padding is None else where(padding[k + 1], filtered[k], step))
    belief = GaussianBelief(torch.stack([b.mean for b in smoothed[::-1]]),
                            torch.stack([b.cov for b in smoothed[::-1]]))
    return Trajectory(belief=belief, prior=None, log_likelihood=trajectory.log_likelihood, innovation=None,
                      innovation_cov=None, extras={})


def _smooth_modes(filter: MultipleModelFilter, trajectory: Trajectory, controls, motions,
                  padding: Tensor | None = None) -> Trajectory:
    filtered = gaussian_modes(trajectory)
    steps = filtered.batch_shape[0]
    smoothed = [filtered[steps - 1]]
    for k in range(steps - 2, -1, -1):  # the prediction k -> k+1 used motions[k+1] and controls[k+1]
        step = kim_step(filter, filtered[k], smoothed[-1], u=None if controls is None else controls[k + 1],
                        motion=None if motions is None else motions[k + 1])
        if padding is not None:  # a run whose step k+1 is padding ends at k: its filtered belief
            step = where(padding[k + 1], filtered[k], step)
        smoothed.append(step)
    return mode_trajectory(smoothed[::-1], trajectory)


def _fixed_lag(filter, kind: str, filtered: GaussianBelief, predicted: GaussianBelief | None, controls, motions,
               lag: Any, trajectory: Trajectory) -> Trajectory:
    """Every window ``k .. min(k + lag, T)`` smoothed back to ``k`` at once: ``lag`` backward steps,
    each over all ``T`` windows (window ``k`` at step ``k + d``); steps outside a window keep its value."""
    if isinstance(lag, bool) or not isinstance(lag, int) or lag < 0:
        raise ValueError(f"lag: expected a non-negative integer, got {lag!r}")
    if motions is not None:
        raise ValueError("lag: fixed-lag smoothing with per-step motions is not implemented; pass lag=None")
    steps = filtered.batch_shape[0]
    L = min(lag, steps - 1)
    index = torch.arange(steps, device=filtered.mean.device)
    end = (index + L).clamp(max=steps - 1)  # the last step of window k
    mean, cov = filtered.mean[end], filtered.cov[end]
    for d in range(L - 1, -1, -1):
        t = (index + d).clamp(max=steps - 1)
        t1 = (index + d + 1).clamp(max=steps - 1)
        active = (index + d < end).view(steps, *([1] * (mean.dim() - 1)))  # t inside window k, before its end
        nxt = GaussianBelief(mean, cov)
        u = None if controls is None else controls[t1]
        if kind == "rts":
            new = rts_step(filter.motion, filtered[t], predicted[t1], nxt, u=u)
        else:
            new = unscented_rts_step(filter.motion, filter.sigma_points, filtered[t], nxt, u=u)
        mean = torch.where(active, new.mean, mean)
        cov = torch.where(active.unsqueeze(-1), new.cov, cov)
    return Trajectory(belief=GaussianBelief(mean, cov), prior=None, log_likelihood=trajectory.log_likelihood,
                      innovation=None, innovation_cov=None, extras={})

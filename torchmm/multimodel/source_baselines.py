r"""Paper 000's baselines with a source sensor, over any bank (docs/baselines.md §3).

* :class:`SourceUpdateIMM` - **IMM-SU**: every mode updated sequentially with ``y_S`` (noise
  ``R_S``) when present, then with ``y`` (the Bayes-optimal use of an undelayed source datum).
* :class:`FusionIMM` - **IMM-FU**: a separate source-only IMM track, fused into every mode's
  posterior when a source datum arrives (docs/baselines.md §3.2).
* :class:`SourceModeVSIMM` - **VSIMM**: the source track's estimate enters as an extra mode
  (docs/baselines.md §3.3).

The source sensor is an argument of the bank's update (``sensor=``): no filter is rebuilt, and the
bank may hold Kalman, extended, unscented, particle or learned mode filters.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmm.contract import BeliefArg, Finite, Gen, Int, Of, Real, Stochastic, entry_point
from torchmm.beliefs import Belief, GaussianBelief, ModeBelief, ModelSetBelief, SourceTrackBelief, cat, where
from torchmm.beliefs.ops import safe_log_normalize
from torchmm.filters.base import Filter, StepOutput
from torchmm.linalg import any_observed, cholesky, condition
from torchmm.models.base import MeasurementModel
from torchmm.models.linear import LinearMeasurement
from torchmm.multimodel.bank import FilterBank, IndexedBank
from torchmm.multimodel.imm import IMM, flag_run_failed, mode_posterior
from torchmm.multimodel.multirate import check_source_sensor, multirate_streams
from torchmm.multimodel.structure import ActiveSetMixing, DropBelow

__all__ = ["FusionIMM", "SourceModeVSIMM", "SourceTrackBelief", "SourceUpdateIMM"]


# --------------------------------------------------------------------------------------------
# IMM-SU
# --------------------------------------------------------------------------------------------
class SourceUpdateIMM(IMM):
    """IMM-SU: each mode updated with the source datum (``R_S``) when present, then with ``y_k``.

    Mode likelihoods are the product of both updates' likelihoods (the exact joint likelihood of
    the two conditionally independent data); where the source is NaN the step is the IMM step.

    Args:
        bank: one Kalman/EKF filter with mode-bank models.
        transition: ``(M, M)`` matrix or :class:`~torchmm.multimodel.ModeTransition`.
        source: the source sensor model (noise ``R_S``).

    Shapes:
        as :class:`TransferIMM` (``extras["source_log_likelihood"]`` ``(*B, M)``).
    """

    @entry_point(bank=Of((Filter, FilterBank, list, tuple),
                         what="a Filter, a list of filters or a FilterBank"),
                 transition=Stochastic(), source=Of(MeasurementModel))
    def __init__(self, bank, transition, source: MeasurementModel):
        super().__init__(bank, transition)
        self.source = check_source_sensor(source, self.bank.state_dim)

    def update(self, belief: ModeBelief, z, *, sensor=None, generator=None) -> StepOutput:
        if sensor is not None:
            raise TypeError("sensor: SourceUpdateIMM's sensors are the bank's (target) and source=")
        y, ys = multirate_streams(self, belief, z, self.source)
        first = self.bank.update(belief.components, ys.unsqueeze(-2), sensor=self.source, generator=generator)
        intermediate = ModeBelief(belief.mode_log_probs + first.log_likelihood, first.belief)
        out = self._update_modes(intermediate, y, observed=any_observed(y) | any_observed(ys), generator=generator)
        # log p(y, y_S | past): the source factor is folded into the prior weights above
        out.extras["source_log_likelihood"] = first.log_likelihood
        out.extras["mode_log_likelihood"] = out.extras["mode_log_likelihood"] + first.log_likelihood
        return out._replace(prior=belief)


# --------------------------------------------------------------------------------------------
# beliefs carrying a separate source-only track (IMM-FU, VSIMM)
# --------------------------------------------------------------------------------------------
class _SourceTrackIMM(IMM):
    """Shared set-up: the target IMM plus an independent source-only IMM over the same modes."""

    @entry_point(bank=Of((Filter, FilterBank, list, tuple),
                         what="a Filter, a list of filters or a FilterBank"),
                 transition=Stochastic(), source=Of(MeasurementModel))
    def __init__(self, bank, transition, source: MeasurementModel):
        super().__init__(bank, transition)
        self.source = check_source_sensor(source, self.bank.state_dim)

    @entry_point(belief=BeliefArg(), mode_probs=Finite(optional=True, check=False), generator=Gen())
    def initial_belief(self, belief: Belief, mode_probs=None, *, generator=None) -> SourceTrackBelief:
        """Both tracks start from ``belief`` (batch ``(*B,)``) -> :class:`SourceTrackBelief`."""
        start = super().initial_belief(belief, mode_probs, generator=generator)
        return SourceTrackBelief(start, start)

    def _source_step(self, belief: ModeBelief, ys: Tensor, u, generator) -> ModeBelief:
        """The source-only IMM track: the same bank and transition, updated with ``y_S`` alone."""
        prior = self._predict(self.mix(belief), u=u, generator=generator)
        return self._update_modes(prior, ys, sensor=self.source, generator=generator).belief

    def update(self, belief, z, **kwargs):
        raise NotImplementedError(f"{type(self).__name__}: call step()")


class FusionIMM(_SourceTrackIMM):
    r"""IMM-FU: track-to-track fusion of a source-only IMM track into the target IMM's modes.

    The source track is an IMM over the same mode bank driven by the source stream alone
    (prediction only between source data). When a source datum arrives, each mode's posterior is
    fused with the source track's combined estimate ``(x_s, P_s)`` by information fusion
    (``P_js = 0``): ``P_f = (P_j^{-1} + P_s^{-1})^{-1}``, ``x_f = P_f (P_j^{-1} x_j + P_s^{-1} x_s)``
    (docs/baselines.md §3.2 default), computed as the equivalent update with ``z = x_s``, ``R = P_s``.
    The fused mode estimates are what the next mixing uses (fusion inside the IMM); mode
    probabilities use the target likelihood only.

    Args:
        bank, transition: as :class:`TransferIMM`; source: the source sensor model.

    Shapes:
        belief: :class:`SourceTrackBelief`; ``z``: :class:`MultiRate`.
    """

    def step(self, belief: SourceTrackBelief, z, *, u: Tensor | None = None, generator=None) -> StepOutput:
        _check_track(belief, type(self).__name__)
        y, ys = multirate_streams(self, belief, z, self.source)
        source = self._source_step(belief.source, ys, u, generator)
        mixed = self.mix(belief.target)
        out = self._update_modes(self._predict(mixed, u=u, generator=generator), y, generator=generator)
        present = torch.isfinite(ys).all(-1)
        track = source.estimate().unsqueeze(-1).expand(*present.shape, self.num_modes)
        comps = out.belief.components
        if type(comps) is GaussianBelief:  # information fusion in closed form
            mean, cov, _ = condition(comps.mean, comps.cov, track.mean - comps.mean, comps.cov + track.cov, comps.cov)
            fused = GaussianBelief(mean, cov)
        else:  # any other mode filter: the track's estimate as a datum x_s with noise P_s
            eye = torch.eye(track.mean.shape[-1], dtype=track.mean.dtype, device=track.mean.device)
            pseudo = LinearMeasurement.unchecked(eye, track.cov)
            fused = self.bank.update(comps, track.mean, sensor=pseudo, generator=generator).belief
        fused = where(present.unsqueeze(-1), fused, comps)
        target = ModeBelief(out.belief.mode_log_probs, fused)
        out.extras["source_present"] = present
        return out._replace(belief=SourceTrackBelief(target, source), prior=belief)


class SourceModeVSIMM(_SourceTrackIMM):
    r"""VSIMM with a mode built from the source estimate (docs/baselines.md §3.3).

    The fixed set of ``M`` modes runs as an IMM on ``y``; mode ``e`` (index ``M``, dynamics of
    mode ``extra_model``) is active per run while its probability is at least ``drop_below``.
    When a source datum arrives, mode ``e``'s prediction at ``k`` is replaced by the source
    track's combined estimate at ``k`` (time-aligned: it includes ``y_{S,k}``) with predicted
    probability ``p_new`` (default ``1/(M+1)``), the fixed modes' predicted probabilities scaled to
    ``1 - p_new``. Transition matrix over ``M + {e}``: the fixed block, ``p_ee``,
    ``p_ei = (1 - p_ee)/M``, ``p_ie = eps``, rows renormalised; over a run's active set rows are
    renormalised again (``pi_ij = p_ij / sum_{l active} p_il``).

    Args:
        bank, transition, source: as :class:`FusionIMM`.
        extra_model: index of the fixed mode whose dynamics mode ``e`` uses (e.g. the CV mode).
        p_new, p_ee, eps, drop_below: as above (defaults ``1/(M+1)``, 0.9, 0.01, 1e-3).

    Shapes:
        belief: :class:`SourceTrackBelief` whose ``target`` has ``M + 1`` modes (inactive: log
        probability ``-inf``); ``z``: :class:`MultiRate`.
    """

    @entry_point(bank=Of((Filter, FilterBank, list, tuple),
                         what="a Filter, a list of filters or a FilterBank"),
                 transition=Stochastic(), source=Of(MeasurementModel), extra_model=Int(0),
                 p_new=Real(minimum=0.0, maximum=1.0, optional=True), p_ee=Real(minimum=0.0, maximum=1.0),
                 eps=Real(minimum=0.0, maximum=1.0), drop_below=Real(minimum=0.0, maximum=1.0))
    def __init__(self, bank, transition, source: MeasurementModel, *, extra_model: int = 0,
                 p_new: float | None = None, p_ee: float = 0.9, eps: float = 0.01, drop_below: float = 1e-3):
        super().__init__(bank, transition, source)
        M = self.num_modes
        if not 0 <= extra_model < M:
            raise ValueError(f"extra_model: expected an index in [0, {M}), got {extra_model}")
        p_new = 1.0 / (M + 1) if p_new is None else float(p_new)
        for name, value in {"p_new": p_new, "p_ee": p_ee, "eps": eps, "drop_below": drop_below}.items():
            if not 0.0 <= value < 1.0:
                raise ValueError(f"{name}: must lie in [0, 1), got {value}")
        self.extra_model, self.p_new, self.drop_below = extra_model, p_new, drop_below
        self.p_ee, self.eps = p_ee, eps
        # the fixed modes plus mode e (a second copy of extra_model's filter), over any bank; not a
        # registered submodule: it shares self.bank's modules (no duplicate state_dict entries)
        object.__setattr__(self, "extended", IndexedBank(self.bank, [*range(M), extra_model]))
        # the engine's pieces: mixing over the active set with renormalised rows, and the source
        # mode as a model-set policy (dropped below drop_below)
        self.set_mixing = ActiveSetMixing()
        self.set_policy = DropBelow(drop_below, [M])

    def extended_transition(self) -> Tensor:
        """``(M + 1, M + 1)`` matrix over the fixed modes and mode ``e`` (rows sum to one)."""
        P = self.transition.matrix()
        M = self.num_modes
        top = torch.cat([P, torch.full((M, 1), self.eps, dtype=P.dtype, device=P.device)], dim=-1)
        bottom = torch.cat([torch.full((1, M), (1 - self.p_ee) / M, dtype=P.dtype, device=P.device),
                            torch.full((1, 1), self.p_ee, dtype=P.dtype, device=P.device)], dim=-1)
        full = torch.cat([top, bottom], dim=-2)
        return full / full.sum(-1, keepdim=True)

    @entry_point(belief=BeliefArg(), mode_probs=Finite(optional=True, check=False), generator=Gen())
    def initial_belief(self, belief: Belief, mode_probs=None, *, generator=None) -> SourceTrackBelief:
        start = IMM.initial_belief(self, belief, mode_probs, generator=generator)
        batch = belief.batch_shape
        log_probs = torch.cat([start.mode_log_probs,
                               torch.full((*batch, 1), -torch.inf, dtype=belief.dtype, device=belief.device)], -1)
        extra = start.components.select(-1, self.extra_model).unsqueeze(-1)  # mode e: inactive until a source datum
        comps = cat([start.components, extra], dim=-1)
        active = torch.cat([torch.ones(log_probs.shape[-1] - 1, dtype=torch.bool, device=log_probs.device),
                            torch.zeros(1, dtype=torch.bool, device=log_probs.device)]).expand(log_probs.shape)
        return SourceTrackBelief(ModelSetBelief(log_probs, comps, active), start)

    def step(self, belief: SourceTrackBelief, z, *, u: Tensor | None = None, generator=None) -> StepOutput:
        _check_track(belief, type(self).__name__)
        y, ys = multirate_streams(self, belief, z, self.source)
        M = self.num_modes
        source = self._source_step(belief.source, ys, u, generator)
        present = torch.isfinite(ys).all(-1)  # (*B,)
        target = _with_active_set(belief.target, M)
        mixed = self.set_mixing(target, self.extended_transition())  # over the active set, rows renormalised
        uj = None if u is None else u.unsqueeze(-2)
        predicted = self.extended.predict(mixed.components, u=uj, generator=generator)
        # a source datum: mode e restarts from the source track's estimate at k, with probability p_new
        arrival = present.unsqueeze(-1) & (torch.arange(M + 1, device=present.device) == M)
        track = source.estimate().unsqueeze(-1).expand(*present.shape, M + 1)
        predicted = where(arrival, _as_component(track, predicted), predicted)
        cbar = mixed.mode_log_probs.exp()
        restart = torch.cat([cbar[..., :M] / cbar[..., :M].sum(-1, keepdim=True) * (1 - self.p_new),
                             torch.full_like(cbar[..., M:], self.p_new)], -1)
        tiny = torch.finfo(cbar.dtype).tiny
        restart = torch.where(restart > 0, restart.clamp_min(tiny).log(), -torch.inf)
        log_cbar = torch.where(present.unsqueeze(-1), restart, mixed.mode_log_probs)
        prior = ModeBelief(log_cbar, predicted)
        out = self.extended.update(predicted, y.unsqueeze(-2), generator=generator)
        log_mu, log_likelihood = mode_posterior(out.log_likelihood, log_cbar, any_observed(y))
        active, _ = self.set_policy.select(ModeBelief(log_mu, out.belief))  # mode e dropped below drop_below
        log_mu = torch.where(active, log_mu, -torch.inf)
        log_mu = safe_log_normalize(log_mu, torch.logsumexp(log_mu, dim=-1, keepdim=True))
        new_target = ModelSetBelief(log_mu, out.belief, active)
        extras = {"mode_log_likelihood": out.log_likelihood, "source_present": present,
                  "extra_mode_active": active[..., M], "active": active}
        if out.extras:
            extras["modes"] = dict(out.extras)
        extras["failed"] = flag_run_failed(log_likelihood)
        return StepOutput(SourceTrackBelief(new_target, source), prior, log_likelihood,
                          out.innovation, out.innovation_cov, extras)


def _with_active_set(target: ModeBelief, num_fixed: int) -> ModelSetBelief:
    """The target side with its active set (a plain mode belief: the fixed modes and, where its
    probability is positive, mode e)."""
    if isinstance(target, ModelSetBelief):
        return target
    lp = target.mode_log_probs
    fixed = torch.arange(lp.shape[-1], device=lp.device) < num_fixed
    return ModelSetBelief(lp, target.components, fixed | (lp > -torch.inf))


def _check_track(belief, who: str) -> None:
    if not isinstance(belief, SourceTrackBelief):
        raise TypeError(f"belief: {who} needs a SourceTrackBelief (from {who}.initial_belief), got "
                        f"{type(belief).__name__}")


def _as_component(track: GaussianBelief, like: Belief) -> Belief:
    """The source track's estimate as a mode filter's belief of ``like``'s type (a Gaussian is
    itself; a particle set is drawn from nothing new: its particles are moved to the track's
    moments by an affine map, keeping their weights)."""
    if type(like) is GaussianBelief:
        return track
    particles = getattr(like, "particles", None)
    if particles is None:
        raise TypeError(f"SourceModeVSIMM: cannot restart a mode filter belief of type {type(like).__name__} from "
                        "the source track's estimate")
    moments = like.estimate()
    # x -> m_s + L_s L^{-1} (x - m): the weighted particle set gets mean m_s and covariance P_s exactly
    L = cholesky(moments.cov)
    L_s = cholesky(track.cov)
    white = torch.linalg.solve_triangular(L.unsqueeze(-3), (particles - moments.mean.unsqueeze(-2)).unsqueeze(-1),
                                          upper=False).squeeze(-1)
    moved = track.mean.unsqueeze(-2) + (L_s.unsqueeze(-3) @ white.unsqueeze(-1)).squeeze(-1)
    return type(like)(moved, like.log_weights.expand(moved.shape[:-1]))

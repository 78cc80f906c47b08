r"""Integrated probabilistic data association (IPDA; Mušicki, Evans & Stanković, IEEE TAC 39(6), 1994):
PDA with the probability that the target exists.

The existence follows a Markov chain between scans: ``chi^- = p_S chi + p_B (1 - chi)`` (survival and
birth probabilities). At a scan the PDA's likelihood ratio of the target against "all clutter",
``L = 1 - delta = 1 - P_D P_G + sum_k P_D N(nu_k; 0, S) / lambda`` (:mod:`torchmm.association.pda`),
updates it: ``chi = L chi^- / (1 - delta chi^-)``, and the state given existence is the PDA's. The
scan's log-likelihood is ``log(1 - delta chi^-)``: "a target or none" against "all clutter".

JIPDA (Mušicki & Evans, IEEE TAES 40(3), 2004) is its joint form over a run's tracks: JPDA's joint
events with ``w_ij = chi_i^- P_D N(nu_ij; 0, S_i) / lambda`` and, for a track left without a detection,
``m_i = 1 - P_D P_G chi_i^-``. From the marginals ``beta_ij``: ``chi_i = beta_i0 (1 - P_D P_G) chi_i^- /
m_i + sum_j beta_ij``, and the state given existence collapses the hypotheses with weights
``beta_i0 (1 - P_D P_G) chi_i^- / (m_i chi_i)`` (missed) and ``beta_ij / chi_i``. A sure target
(``chi_i^- = 1``) keeps ``P(exists | missed) = 1``, also at ``P_D P_G = 1`` where it is ``0 / 0``: such a
JIPDA is the JPDA (docs/tracking.md, tests/test_sure_detection.py).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmm.association.jpda import (
    JPDA,
    exact_marginals,
    flat_runs,
    kbest_marginals,
    lbp_log_likelihood,
    lbp_marginals,
)
from torchmm.association.pda import PDA
from torchmm.beliefs import ExistenceBelief, GaussianBelief, ModeBelief, ModeExistenceBelief, with_existence
from torchmm.contract import BeliefArg, Choice, Int, Of, Probability, Real, entry_point
from torchmm.filters.base import Filter, StepOutput

__all__ = ["IPDA", "JIPDA"]


TRACK_BELIEFS = (ExistenceBelief, ModeExistenceBelief)


def _initial(assoc, belief, existence) -> ExistenceBelief | ModeExistenceBelief:
    if isinstance(belief, ModeBelief):  # a ready IMM belief (its own mode probabilities) is the state as it is
        if getattr(assoc.filter, "num_modes", None) != belief.num_modes:
            raise ValueError(f"belief: a ModeBelief of {belief.num_modes} modes needs an IMM of as many modes as the "
                             f"filter, got {type(assoc.filter).__name__}")
        state = belief.validate("belief")
    else:
        state = assoc.filter.initial_belief(belief)
    # (its type and values: the entry point's Probability; its size against the belief's batch here)
    e = torch.as_tensor(existence, dtype=state.dtype, device=state.device)
    batch = state.batch_shape
    try:
        fits = torch.broadcast_shapes(e.shape, batch) == batch
    except RuntimeError:
        fits = False
    if not fits:
        raise ValueError(f"existence: shape {tuple(e.shape)} does not broadcast to the belief's batch {tuple(batch)} "
                         "(a number, or one probability per run or track)")
    return with_existence(state, e.log().expand(batch))


def _check(assoc, belief) -> None:
    if not isinstance(belief, TRACK_BELIEFS):
        name = type(assoc).__name__
        raise TypeError(f"belief: {name} needs an ExistenceBelief or a ModeExistenceBelief ({name}.initial_belief), "
                        f"got {type(belief).__name__}")


def _predict(assoc, belief, u: Tensor | None) -> ExistenceBelief | ModeExistenceBelief:
    _check(assoc, belief)
    state = assoc.filter.predict(belief.state, u=u)
    e = belief.existence
    e = assoc.survival_probability * e + assoc.birth_probability * (1 - e)
    return with_existence(state, e.log())


class IPDA(PDA):
    r"""PDA with target existence (the module docstring gives the equations).

    Args:
        filter, detection_probability, clutter_density, gate_probability: as for
            :class:`~torchmm.association.PDA`: a filter whose belief is Gaussian, or an IMM over such
            filters (IMM-IPDA: the existence weighs the mode-mixed likelihood ratio, the state given
            existence is the IMM-PDA's).
        survival_probability: ``p_S``, that an existing target still exists at the next scan.
        birth_probability: ``p_B``, that a target that did not exist does at the next scan (default 0).

    Shapes:
        belief: :class:`~torchmm.beliefs.ExistenceBelief` (over an IMM:
        :class:`~torchmm.beliefs.ModeExistenceBelief`) with batch ``(*B,)`` (:meth:`initial_belief` makes it); ``z``: ``(*B, D, m)``. ``extras`` are PDA's and
        ``"existence"`` ``(*B,)``, the posterior ``P(exists)``.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> ipda = IPDA(KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0)),
        ...             detection_probability=0.9, clutter_density=0.01, survival_probability=0.98)
        >>> track = ipda.initial_belief(GaussianBelief(torch.zeros(2), torch.eye(2)), existence=0.5)
        >>> out = ipda.step(track, torch.tensor([[0.3], [9.0]]))
        >>> round(float(out.belief.existence), 3)  # a detection where the track expects one
        0.95
    """

    @entry_point(filter=Of(Filter), detection_probability=Real(0.0, 1.0), clutter_density=Real(positive=True),
                 gate_probability=Real(0.0, 1.0), survival_probability=Real(0.0, 1.0),
                 birth_probability=Real(0.0, 1.0))
    def __init__(self, filter: Filter, *, detection_probability: float, clutter_density: float,
                 gate_probability: float = 0.99, survival_probability: float = 0.98, birth_probability: float = 0.0):
        super().__init__(filter, detection_probability=detection_probability, clutter_density=clutter_density,
                         gate_probability=gate_probability)
        self.survival_probability = float(survival_probability)
        self.birth_probability = float(birth_probability)

    @entry_point(belief=BeliefArg(check=False), existence=Probability())
    def initial_belief(self, belief: GaussianBelief | ModeBelief, existence: float | Tensor = 0.5
                       ) -> ExistenceBelief | ModeExistenceBelief:
        """The wrapped filter's initial belief from ``belief`` (or ``belief`` itself, an IMM's
        ``ModeBelief``) and ``P(exists) = existence`` (a number in [0, 1] or a tensor broadcasting to the
        batch)."""
        return _initial(self, belief, existence)

    def predict(self, belief, *, u: Tensor | None = None) -> ExistenceBelief | ModeExistenceBelief:
        return _predict(self, belief, u)

    def update(self, belief, z: Tensor) -> StepOutput:
        _check(self, belief)
        out = super().update(belief.state, z)
        log_ratio = out.log_likelihood  # log L = log(1 - delta): target against all clutter
        log_e = belief.log_existence
        log_scan = torch.logaddexp(log_ratio + log_e, torch.log1p(-log_e.exp()))  # log(1 - delta chi^-)
        log_post = log_ratio + log_e - log_scan
        log_post = torch.where(torch.isneginf(log_e), log_e, log_post)  # a target that cannot exist stays so
        # (rounding: existence 1 is a repelling fixed point of a miss, so it is kept exactly, NaN kept)
        log_post = torch.where(log_e == 0, log_post.clamp(0.0, 0.0), log_post.clamp(max=0.0))
        post = out.belief
        extras = dict(out.extras)
        extras["existence"] = log_post.exp()
        return StepOutput(with_existence(post, log_post), belief, log_scan, out.innovation,
                          out.innovation_cov, extras)


class JIPDA(JPDA):
    r"""Joint IPDA: JPDA over a run's tracks, each with the probability that its target exists (the
    module docstring gives the equations).

    Args:
        filter, detection_probability, clutter_density, gate_probability, method, max_targets,
            iterations, tolerance, k: as for :class:`~torchmm.association.JPDA` (an IMM filter makes the
            IMM-JIPDA; ``method="kbest"``: the ``k`` most likely joint events, each track its own
            missed weight ``1 - P_D P_G chi_i``).
        survival_probability, birth_probability: as for :class:`IPDA`.

    Shapes:
        belief: :class:`~torchmm.beliefs.ExistenceBelief` (over an IMM:
        :class:`~torchmm.beliefs.ModeExistenceBelief`) with batch ``(*B, N)`` (:meth:`initial_belief`);
        ``z``: ``(*B, D, m)``, one scan per run. ``extras``: JPDA's (``"association"``: the joint
        marginals ``beta``) and ``"existence"`` ``(*B, N)``.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> jipda = JIPDA(KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0)),
        ...               detection_probability=0.9, clutter_density=0.01)
        >>> tracks = jipda.initial_belief(GaussianBelief(torch.tensor([[0.0, 0.0], [3.0, 0.0]]), torch.eye(2)))
        >>> out = jipda.step(tracks, torch.tensor([[0.2], [float("nan")]]))
        >>> out.belief.existence.shape  # track 0 saw a detection, track 1 none
        torch.Size([2])
    """

    @entry_point(filter=Of(Filter), detection_probability=Real(0.0, 1.0), clutter_density=Real(positive=True),
                 gate_probability=Real(0.0, 1.0), survival_probability=Real(0.0, 1.0),
                 birth_probability=Real(0.0, 1.0), method=Choice("exact", "lbp", "kbest"), max_targets=Int(1),
                 iterations=Int(1), tolerance=Real(minimum=0.0), k=Int(1))
    def __init__(self, filter: Filter, *, detection_probability: float, clutter_density: float,
                 gate_probability: float = 0.99, survival_probability: float = 0.98, birth_probability: float = 0.0,
                 method: str = "exact", max_targets: int = 12, iterations: int = 100, tolerance: float = 1e-13,
                 k: int = 100):
        super().__init__(filter, detection_probability=detection_probability, clutter_density=clutter_density,
                         gate_probability=gate_probability, method=method, max_targets=max_targets,
                         iterations=iterations, tolerance=tolerance, k=k)
        self.survival_probability = float(survival_probability)
        self.birth_probability = float(birth_probability)

    @entry_point(belief=BeliefArg(check=False), existence=Probability())
    def initial_belief(self, belief: GaussianBelief | ModeBelief, existence: float | Tensor = 0.5
                       ) -> ExistenceBelief | ModeExistenceBelief:
        """The wrapped filter's initial belief (batch ``(*B, N)``) and ``P(exists) = existence``."""
        return _initial(self, belief, existence)

    def predict(self, belief, *, u: Tensor | None = None) -> ExistenceBelief | ModeExistenceBelief:
        return _predict(self, belief, u)

    def update(self, belief, z: Tensor) -> StepOutput:
        _check(self, belief)
        state = belief.state
        hyp, validated, log_w, S, singular = self._scan(state, z)
        *runs, N, D = log_w.shape
        log_e = belief.log_existence.expand(*runs, N)
        pdpg = self.detection_probability * self.gate_probability
        log_w = log_w + log_e.unsqueeze(-1)  # chi_i P_D N / lambda
        # m_i = 1 - P_D P_G chi_i = (1 - P_D P_G) + P_D P_G (1 - chi_i): two terms >= 0, no cancellation
        # (0 exactly for a sure target, chi_i = 1, with P_D P_G = 1: it must take a detection)
        missed = (1.0 - pdpg) - pdpg * torch.expm1(log_e)
        log_m = missed.log()
        flat_w, flat_m = flat_runs(log_w, 2), flat_runs(log_m, 1)
        if self.method == "exact":
            log_beta, log_z = exact_marginals(flat_w, flat_m)
        elif self.method == "kbest":  # the k most likely joint events (Murty), each track its own miss weight
            log_beta, log_z = kbest_marginals(flat_w, flat_m, self.k)
        else:
            log_beta = lbp_marginals(flat_w, flat_m, self.iterations, self.tolerance,
                                     missed_may_vanish=pdpg >= 1)
            log_z = lbp_log_likelihood(flat_w, flat_m, missed_may_vanish=pdpg >= 1)
        log_z = torch.where(singular.any(-1), torch.nan, log_z.reshape(runs))  # a track without a gate: failed
        failed = torch.isnan(log_z)[..., None, None]
        # an impossible scan (no joint event has weight: sure targets that cannot all take a detection): as
        # the JPDA's, every track keeps its prior, its existence included
        impossible = torch.isneginf(log_z)[..., None, None]
        missed_only = (torch.arange(D + 1, device=log_w.device) == 0).to(log_w.dtype)
        beta = log_beta.reshape(*runs, N, 1 + D).exp()
        beta = torch.where(failed, torch.nan, torch.where(impossible, missed_only, beta))
        # P(exists | missed) = (1 - P_D P_G) chi / m: the state weights given existence; 1 for a sure target
        # (chi = 1: (1 - P_D P_G) / (1 - P_D P_G), and its limit P_D P_G -> 1, where it is 0 / 0)
        sure = log_e == 0
        ratio = (1.0 - pdpg) * log_e.exp() / torch.where(sure, 1.0, missed)
        missed_exists = beta[..., 0] * torch.where(sure, 1.0, ratio)
        # (at most 1; a track that exists for sure, a JPDA's, stays at exactly 1: existence 1 is a repelling
        # fixed point of the missed update, where rounding would grow by 1 / (1 - P_D P_G) a miss; NaN kept)
        existence = missed_exists + beta[..., 1:].sum(-1)
        existence = torch.where(sure, existence.clamp(1.0, 1.0), existence.clamp(max=1.0))
        existence = torch.where(impossible[..., 0], log_e.exp(), existence)
        weights = torch.cat([missed_exists.unsqueeze(-1), beta[..., 1:]], -1) / existence.unsqueeze(-1)
        none = (existence <= 0).unsqueeze(-1)  # no chance of existing: the prediction kept
        weights = torch.where(none, (torch.arange(D + 1, device=beta.device) == 0).to(beta.dtype), weights)
        out = self._finish(state, hyp, validated, weights, log_z, S, singular)
        post = out.belief
        extras = dict(out.extras)
        extras["association"] = beta
        extras["existence"] = existence
        return StepOutput(with_existence(post, existence.log()), belief, out.log_likelihood,
                          out.innovation, out.innovation_cov, extras)

r"""Integrated probabilistic data association (IPDA; Mušicki, Evans & Stanković, IEEE TAC 39(6), 1994):
PDA with the probability that the target exists.

The existence follows a Markov chain between scans: ``chi^- = p_S chi + p_B (1 - chi)`` (survival and
birth probabilities). At a scan the PDA's likelihood ratio of the target against "all clutter",
``L = 1 - delta = 1 - P_D P_G + sum_k P_D N(nu_k; 0, S) / lambda`` (:mod:`torchmm.association.pda`),
updates it: ``chi = L chi^- / (1 - delta chi^-)``, and the state given existence is the PDA's. The
scan's log-likelihood is ``log(1 - delta chi^-)``: "a target or none" against "all clutter".
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmm.association.pda import PDA
from torchmm.beliefs import ExistenceBelief, GaussianBelief
from torchmm.contract import Of, Real, entry_point
from torchmm.filters.base import Filter, StepOutput

__all__ = ["IPDA"]


class IPDA(PDA):
    r"""PDA with target existence (the module docstring gives the equations).

    Args:
        filter, detection_probability, clutter_density, gate_probability: as for
            :class:`~torchmm.association.PDA` (a filter whose belief is Gaussian).
        survival_probability: ``p_S``, that an existing target still exists at the next scan.
        birth_probability: ``p_B``, that a target that did not exist does at the next scan (default 0).

    Shapes:
        belief: :class:`~torchmm.beliefs.ExistenceBelief` with batch ``(*B,)``
        (:meth:`initial_belief` makes it); ``z``: ``(*B, D, m)``. ``extras`` are PDA's and
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

    def initial_belief(self, belief: GaussianBelief, existence: float | Tensor = 0.5) -> ExistenceBelief:
        """The wrapped filter's initial belief and ``P(exists) = existence`` (a number in [0, 1] or a
        tensor broadcasting to the batch)."""
        state = self.filter.initial_belief(belief)
        e = torch.as_tensor(existence, dtype=state.dtype, device=state.device)
        if bool(((e < 0) | (e > 1) | e.isnan()).any()):
            raise ValueError(f"existence: must be a probability in [0, 1], got {existence}")
        return ExistenceBelief(state.mean, state.cov, e.log().expand(state.batch_shape))

    def predict(self, belief: ExistenceBelief, *, u: Tensor | None = None) -> ExistenceBelief:
        if not isinstance(belief, ExistenceBelief):
            raise TypeError(f"belief: IPDA needs an ExistenceBelief (IPDA.initial_belief), got {type(belief).__name__}")
        state = self.filter.predict(belief.state, u=u)
        e = belief.existence
        e = self.survival_probability * e + self.birth_probability * (1 - e)
        return ExistenceBelief(state.mean, state.cov, e.log())

    def update(self, belief: ExistenceBelief, z: Tensor) -> StepOutput:
        if not isinstance(belief, ExistenceBelief):
            raise TypeError(f"belief: IPDA needs an ExistenceBelief (IPDA.initial_belief), got {type(belief).__name__}")
        out = super().update(belief.state, z)
        log_ratio = out.log_likelihood  # log L = log(1 - delta): target against all clutter
        log_e = belief.log_existence
        log_scan = torch.logaddexp(log_ratio + log_e, torch.log1p(-log_e.exp()))  # log(1 - delta chi^-)
        log_post = log_ratio + log_e - log_scan
        log_post = torch.where(torch.isneginf(log_e), log_e, log_post)  # a target that cannot exist stays so
        post = out.belief
        extras = dict(out.extras)
        extras["existence"] = log_post.exp()
        return StepOutput(ExistenceBelief(post.mean, post.cov, log_post), belief, log_scan, out.innovation,
                          out.innovation_cov, extras)

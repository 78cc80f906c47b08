"""The second-order generalised pseudo-Bayesian estimator, GPB2 (split from :mod:`torchmm.multimodel.imm` by
concern, issue 47): ``M^2`` mode-matched filters, one for every pair of modes at ``k - 1`` and ``k``, merged
after the update. Its step in the batch-last layout is :mod:`torchmm.kernels.batch_last.pairs`."""

from __future__ import annotations

import math

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import ModeBelief
from torchmm.beliefs.ops import dead_safe_logsumexp, safe_log_normalize
from torchmm.filters.base import StepOutput
from torchmm.multimodel.interaction import NoInteraction, flag_run_failed, mode_batch, mode_extras
from torchmm.multimodel.imm import MultipleModelFilter
from torchmm.validation import check_same_dtype

__all__ = ["GPB2"]


@kernels.joins("linear_gaussian")
class GPB2(MultipleModelFilter):
    r"""Second-order generalised pseudo-Bayesian estimator (``M^2`` mode-matched filters).

    For every pair ``(i, j)`` the mode-``j`` filter runs from mode ``i``'s posterior; pair weights
    ``log w_ij = ell_ij + log pi_ij + log mu_i``; mode ``j``'s posterior is the collapse over ``i``
    with weights ``w_ij / sum_i w_ij``.

    Shapes:
        as :class:`IMM`, except: :meth:`predict` returns a ``ModeBelief`` over the ``M^2`` pairs
        (mode axis ``i * M + j``), and ``innovation`` is ``(*B, M, M, m)`` (``[..., i, j, :]``).

    ``run_filter(..., update_first=True)``: step 0 updates the start belief without a prediction: every
    mode filter's update of its own start belief, weighted by the start mode probabilities (IMM's and
    GPB1's step 0; its ``prior`` is over the pairs, :meth:`start_pairs`). The kernels decline
    ``update_first`` (the steps run).
    """

    default_interaction = NoInteraction  # GPB2 forms the M^2 pair hypotheses itself (mix below)
    time_varying_transition = False  # (its pairs read one matrix)

    def mix(self, belief: ModeBelief, generator=None) -> ModeBelief:
        """Pair hypotheses: component ``(i, j)`` is mode ``i``'s posterior; weight ``mu_i pi_ij``."""
        M = self.num_modes
        mode_batch(belief)
        log_matrix = self.transition.log_matrix()
        if log_matrix.dtype != belief.mode_log_probs.dtype:
            check_same_dtype(log_matrix, "transition", belief.mode_log_probs)
        joint = belief.mode_log_probs.unsqueeze(-1) + log_matrix  # (*B, i, j)
        batch = belief.batch_shape
        components = belief.components.unsqueeze(-1).expand(*batch, M, M)
        return ModeBelief(joint.flatten(-2), components.reshape(*batch, M * M))

    def linear_gaussian(self):
        """As :meth:`MultipleModelFilter.linear_gaussian`, with the rule ``"pairs"`` (the batch-last
        kernel: :mod:`torchmm.kernels.batch_last.pairs`)."""
        model = super().linear_gaussian()
        return model if isinstance(model, str) else model._replace(rule="pairs")

    def predict(self, belief: ModeBelief, *, u: Tensor | None = None, motion=None, generator=None) -> ModeBelief:
        M = self.num_modes
        pairs = self.mix(belief)
        batch = belief.batch_shape
        components = pairs.components.reshape(*batch, M, M)
        u = None if u is None else u.unsqueeze(-2).unsqueeze(-2)
        prior = self.bank.predict(components, u=u, motion=motion, generator=generator)
        return ModeBelief(pairs.mode_log_probs, prior.reshape(*batch, M * M))

    def start_pairs(self, belief: ModeBelief) -> ModeBelief:
        """A mode belief (``M`` modes: :meth:`initial_belief`'s or a posterior) as the pair hypotheses of a
        datum at its own time, without a prediction (``run_filter(..., update_first=True)``): pair
        ``(i, j)`` holds mode ``j``'s belief, with weight ``mu_j`` where ``i = j`` and 0 (``-inf``)
        elsewhere, so that :meth:`update` gives every mode's update of its own belief and ``mu_j`` the
        mode posterior ``mu_j l_j / sum_l mu_l l_l`` exactly (IMM's and GPB1's update of the same belief).

        Shapes: ``mode_log_probs (*B, M)``, components ``(*B, M)`` -> ``(*B, M * M)``, mode axis ``i * M + j``.
        """
        M = self.num_modes
        batch = mode_batch(belief)
        diagonal = torch.eye(M, dtype=torch.bool, device=belief.mode_log_probs.device)
        joint = torch.where(diagonal, belief.mode_log_probs.unsqueeze(-2), -math.inf)  # (*B, i, j)
        components = belief.components.unsqueeze(-2).expand(*batch, M, M)  # (i, j): mode j's belief
        return ModeBelief(joint.flatten(-2), components.reshape(*batch, M * M))

    def update(self, belief: ModeBelief, z: Tensor, *, sensor=None, generator=None) -> StepOutput:
        """The pair updates and the merge. ``belief`` is :meth:`predict`'s, over the ``M^2`` pairs; a
        belief over the ``M`` modes (:meth:`initial_belief`'s: ``run_filter(..., update_first=True)``)
        is updated without a mode switch (:meth:`start_pairs`), as IMM's and GPB1's ``update``."""
        M = self.num_modes
        batch = mode_batch(belief)
        count = belief.mode_log_probs.shape[-1]
        if count != M * M:
            if count != M:
                raise ValueError(f"belief: expected {M} modes (a start belief or a posterior) or {M * M} pairs "
                                 f"(GPB2.predict's), got {count}")
            belief = self.start_pairs(belief)
        z = self._measurement(belief, z, sensor=sensor)
        prior_pairs = belief.components.reshape(*batch, M, M)
        rank = self.bank.measurement_rank
        out = self.bank.update(prior_pairs, z.unsqueeze(-1 - rank).unsqueeze(-1 - rank), sensor=sensor,
                               generator=generator)
        prior_joint = belief.mode_log_probs.unflatten(-1, (M, M))
        joint = out.log_likelihood + prior_joint  # log w_ij
        log_mode = dead_safe_logsumexp(joint, -2)  # (*B, j): unnormalised log mu_j (a dead j: no NaN gradient)
        log_likelihood = torch.logsumexp(log_mode, dim=-1)
        merge_weights = safe_log_normalize(joint, log_mode.unsqueeze(-2))  # mu_{i|j}, (*B, i, j)
        merged = out.belief.transpose_batch(-1, -2).collapse(merge_weights.mT.exp())  # (*B, j)
        mode_log_probs = safe_log_normalize(log_mode, log_likelihood.unsqueeze(-1))
        log_likelihood = torch.where(self.bank.informative(z), log_likelihood, 0.0)  # exactly 0 without a datum
        extras = mode_extras(out, mode_axes=2)
        extras["failed"] = flag_run_failed(log_likelihood)
        return StepOutput(
            belief=ModeBelief(mode_log_probs, merged),
            prior=belief,
            log_likelihood=log_likelihood,
            innovation=out.innovation,
            innovation_cov=out.innovation_cov,
            extras=extras,
        )

    def step(self, belief: ModeBelief, z: Tensor, *, u: Tensor | None = None, motion=None, sensor=None,
             generator=None) -> StepOutput:
        prior = self.predict(belief, u=u, motion=motion, generator=generator)
        return self.update(prior, z, sensor=sensor, generator=generator)

"""The multiple-model combinators' interactions and mode update (split from :mod:`torchmm.multimodel.imm` by
concern, issue 47): how the mode filters start each step (:class:`Interaction`: the IMM's :class:`MomentMixing`,
GPB1's :class:`Collapse`, the static bank's :class:`NoInteraction`), the predicted mode probabilities
``c_j = sum_i mu_i pi_ij``, and the Bayes mode update in log space (:func:`mode_posterior`) with its failure
flag; :mod:`torchmm.multimodel.imm` has the notation and the combinators."""

from __future__ import annotations

import torch
from torch import Tensor

from torchmm.beliefs import ModeBelief
from torchmm.beliefs.ops import live_log, safe_log_normalize
from torchmm.filters.base import StepOutput
from torchmm.validation import check_same_dtype

__all__ = ["Collapse", "Interaction", "MomentMixing", "NoInteraction", "flag_run_failed", "mode_batch", "mode_extras",
           "mode_posterior", "transition_matrix"]


def _tiny(x: Tensor) -> float:
    return torch.finfo(x.dtype).tiny


def _predicted(mode_probs: Tensor, transition: Tensor) -> Tensor:
    """``c_j = sum_i mu_i pi_ij``, shape ``(*B, M)`` (``transition`` ``(M, M)``, or ``(*B, M, M)``: a
    time-varying transition's matrices at the step).

    Mixing works on the *normalised* probabilities in linear space (no overflow possible; exact
    down to underflow below the smallest normal number), which saves the log-sum-exp over the
    mode axis; the likelihood combination in :meth:`MultipleModelFilter._update_modes` is in log
    space, where underflow actually happens.
    """
    if transition.dim() > 2:
        return (mode_probs.unsqueeze(-2) @ transition).squeeze(-2)
    return mode_probs @ transition


class Interaction:
    """How the mode filters start each step: ``(posterior at k-1, transition) -> (log c_j, start beliefs)``.

    Subclasses implement :meth:`__call__`; :class:`MultipleModelFilter` calls it in ``predict``
    (the result's ``mode_log_probs`` are the predicted ``log c_j``, its components the mode filters'
    start beliefs, batch ``(*B, M)``). Randomised interactions (the particle mixing) take
    ``generator``. A new interaction is one class (docs/architecture.md).
    """

    #: True if the interaction draws random numbers
    uses_generator: bool = False
    #: how the linear-Gaussian kernel computes it (:mod:`torchmm.kernels.linear`: ``"mix"``,
    #: ``"collapse"``, ``"static"``), or None: no kernel
    kernel_rule: str | None = None

    def __call__(self, belief: ModeBelief, transition, generator=None) -> ModeBelief:
        raise NotImplementedError


class MomentMixing(Interaction):
    """The IMM interaction (Blom and Bar-Shalom 1988): mode ``j`` starts from the mixture of the mode
    posteriors with weights ``mu_{i|j} = pi_ij mu_i / c_j`` (moment-matched for Gaussians, exact
    unions for particle sets, via the components' ``mix``)."""

    kernel_rule = "mix"

    def __call__(self, belief, transition, generator=None):
        mode_probs = belief.mode_probs
        matrix = transition_matrix(transition, mode_probs)
        cbar = _predicted(mode_probs, matrix)
        # mixing probabilities mu_{i|j} = pi_ij mu_i / c_j, (*B, i, j)
        weights = mode_probs.unsqueeze(-1) * matrix / cbar.clamp_min(_tiny(cbar)).unsqueeze(-2)
        return ModeBelief(live_log(cbar, _tiny(cbar)), belief.components.mix(weights))


class Collapse(Interaction):
    """The GPB1 interaction: every mode starts from the single collapsed posterior (weights ``mu_i``)."""

    kernel_rule = "collapse"

    def __call__(self, belief, transition, generator=None):
        mode_probs = belief.mode_probs
        cbar = _predicted(mode_probs, transition_matrix(transition, mode_probs))
        collapsed = belief.components.collapse(mode_probs)
        return ModeBelief(live_log(cbar, _tiny(cbar)), collapsed.unsqueeze(-1).expand(*collapsed.batch_shape,
                                                                               cbar.shape[-1]))


class NoInteraction(Interaction):
    """No interaction (the static multiple-model estimator): every mode continues from its own
    posterior and the mode probabilities are carried unchanged (identity transition)."""

    kernel_rule = "static"

    def __call__(self, belief, transition, generator=None):
        return ModeBelief(belief.mode_log_probs, belief.components)


def transition_matrix(transition, like: Tensor) -> Tensor:
    """The transition's matrix, checked to be of ``like``'s dtype (``TypeError`` naming ``transition``)."""
    matrix = transition.matrix()
    if matrix.dtype != like.dtype:
        check_same_dtype(matrix, "transition", like)
    return matrix


def mode_posterior(mode_log_likelihood: Tensor, prior_log_probs: Tensor,
                   observed: Tensor | None = None) -> tuple[Tensor, Tensor]:
    r"""The Bayes mode update in log space, shared by every multiple-model estimator.

    ``log mu_j = ell_j + log c_j - logsumexp_l(ell_l + log c_l)`` and
    ``log p(z_k | z_{1:k-1}) = logsumexp_l(ell_l + log c_l)``, exactly 0 where ``observed`` is False
    (no datum this step). Groups that are all ``-inf`` become uniform (:func:`safe_log_normalize`).

    Shapes:
        mode_log_likelihood, prior_log_probs: ``(*B, M)``; observed ``(*B,)`` -> ``(*B, M)``, ``(*B,)``
    """
    joint = mode_log_likelihood + prior_log_probs
    log_likelihood = torch.logsumexp(joint, dim=-1)
    mode_log_probs = safe_log_normalize(joint, log_likelihood.unsqueeze(-1))
    if observed is not None:
        log_likelihood = torch.where(observed, log_likelihood, 0.0)
    return mode_log_probs, log_likelihood


def flag_run_failed(log_likelihood: Tensor) -> Tensor:
    """``failed (*B,)`` of a multiple-model step: True where its log-likelihood is NaN. A mode filter
    that failed on a present datum (``extras["modes"]["failed"]``) has a NaN mode likelihood, which
    the ``logsumexp`` over the modes carries into the run's (and the mixing into every mode at the
    next step); without a datum the log-likelihood is exactly 0. One op, no host read
    (docs/robustness.md)."""
    return torch.isnan(log_likelihood)


def mode_batch(belief, name: str = "belief") -> torch.Size:
    """Batch shape of a mode belief (from its mode log-probabilities; shapes only)."""
    mode_log_probs = getattr(belief, "mode_log_probs", None)
    if not isinstance(mode_log_probs, Tensor):
        raise TypeError(f"{name}: expected a ModeBelief (from initial_belief), got {type(belief).__name__}")
    return mode_log_probs.shape[:-1]


def mode_extras(out: StepOutput, mode_axes: int = 1) -> dict:
    """The bank's diagnostics as ``extras["modes"]`` (batch ``(*B, M)``; e.g. the mode filters'
    ``singular`` flags) and its ``mode_log_likelihood``."""
    extras = {"mode_log_likelihood": out.log_likelihood}
    if out.extras:  # the mode filters' own diagnostics (e.g. VB iterations), batch (*B, M)
        extras["modes"] = dict(out.extras)
    return extras

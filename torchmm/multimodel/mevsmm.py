r"""Minimum-entropy variable-structure multiple-model estimation (paper 003) and EqMA baselines.

Paper 003 (Shen-Tu, Peng, Xue) selects, at every step, the candidate model set whose particle
approximation of ``p(x_k, m_k | Z_k)`` has the smallest Shannon entropy, and outputs the estimate
over that set. :class:`MinimumEntropyVSMM` is that recursion on the multiple-model particle filter
(:class:`~torchmm.multimodel.MultipleModelParticleFilter`: ``Np`` particles per model, weights
(33)-(34)); the selection rules (25)-(34) are the policies of :mod:`torchmm.multimodel.policies`
(re-exported here), which also run over any bank through
:class:`~torchmm.multimodel.VariableStructureIMM`.

**EqMA N+1** (docs/baselines.md §2.2, reconstruction): :class:`EqMAParticleFilter`, an acceleration-grid
MM-PF with one extra *equivalent* model per step whose acceleration mean and covariance match the
predicted mode distribution of the fixed grid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from torchmm.contract import (BeliefArg, Choice, Cov, DType, Finite, Flag, Gen, Int, Of, Real, Stochastic,
                              entry_point)
from torchmm.beliefs import GaussianBelief, ModeBelief, ModelSetBelief, psd_sqrt, symmetrize
from torchmm.beliefs.ops import normalize_log_probs
from torchmm.filters.base import StepOutput
from torchmm.filters.particle_ops import standard_normal
from torchmm.multimodel.particle import MultipleModelParticleFilter
from torchmm.models.base import MeasurementModel, MotionModel
from torchmm.models.linear import LinearMotion
from torchmm.multimodel.challenge import ChallengeMatch, challenge_match  # (re-exported: paper 003's policies)
from torchmm.multimodel.policies import (  # re-exported: paper 003's policies live in .policies and .challenge
    ExactMinimumEntropy,
    min_entropy_set,
    min_entropy_subset,
    model_statistics,
    subset_entropies,
    subset_masks,
)
from torchmm.validation import as_tensor, check_covariance, check_square

__all__ = [
    "ChallengeMatch",
    "EqMAParticleFilter",
    "ExactMinimumEntropy",
    "MinimumEntropyVSMM",
    "ModelSetBelief",
    "as_family",
    "challenge_match",
    "min_entropy_set",
    "min_entropy_subset",
    "model_statistics",
    "subset_entropies",
    "subset_masks",
    "uniform_transition",
]



# ------------------------------------------------------------------------------------------------
# filters
# ------------------------------------------------------------------------------------------------
def uniform_transition(num_models: int, stay: float = 0.9, *, dtype=None, device=None) -> Tensor:
    """``p_ii = stay``, off-diagonals ``(1 - stay) / (M - 1)`` (the docs/baselines.md default).

    Shapes:
        -> ``(M, M)``
    """
    if not 0 <= stay <= 1:
        raise ValueError(f"stay: must be in [0, 1], got {stay}")
    if num_models == 1:
        return torch.ones(1, 1, dtype=dtype, device=device)
    off = (1 - stay) / (num_models - 1)
    eye = torch.eye(num_models, dtype=dtype, device=device)
    return eye * stay + (1 - eye) * off


class MinimumEntropyVSMM(MultipleModelParticleFilter):
    r"""PF-MEVSMM: a multiple-model PF whose model set is re-selected every step (paper 003).

    Step ``k``: every model of the total set gets ``Np`` particles drawn from the interaction of
    the previous *selected* set (the sum over ``m_a in S_{k-1}`` of (27)/(33)), weights (33)-(34),
    then the ``selection`` policy chooses ``S_k`` (:class:`ExactMinimumEntropy` for (30) or
    :class:`ChallengeMatch` for section 3.4.3) and the belief is renormalised on ``S_k``; its
    ``estimate()`` is (31).

    Args:
        motion, measurement, transition, num_particles, mixing, generator, innovation_stats,
            noise_dtype: as :class:`~torchmm.multimodel.particle.MultipleModelParticleFilter`.
        selection: the model-set policy (callable ``(log_weights (*B, M, Np), generator) ->
            (active (*B, M), info)``).
        feedback: ``True`` (the paper's (27)/(33): the next step starts from the selected set
            only, its probabilities renormalised on it); ``False``: the selection only chooses the
            output set of (31) and the recursion keeps every model.

    Shapes:
        belief: :class:`ModelSetBelief`; ``extras``: ``"active"`` ``(*B, M)``, ``"model_count"``
        ``(*B,)``, ``"ess"`` ``(*B,)`` (all candidate particles), plus the policy's diagnostics
        (``"entropy"`` or ``"winner_counts"``, ``"fallback"``).

    Examples:
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> g = torch.Generator().manual_seed(0)
        >>> motion = ConstantVelocity(1, acceleration=[[1.0], [0.0], [-1.0]])
        >>> f = MinimumEntropyVSMM(motion, PositionMeasurement(2, [0], 1.0), uniform_transition(3), 100,
        ...                        selection=ChallengeMatch(30, 5), generator=g)
        >>> out = f.step(f.initial_belief(GaussianBelief(torch.zeros(4, 2), torch.eye(2))), torch.zeros(4, 1))
        >>> out.extras["active"].shape, out.belief.estimate().mean.shape
        (torch.Size([4, 3]), torch.Size([4, 2]))
    """

    @entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel), transition=Stochastic(),
                 num_particles=Int(1),
                 selection=Of(callable_ok=True,
                              what="a selection policy (ExactMinimumEntropy, ChallengeMatch)"),
                 feedback=Flag(), mixing=Choice("multinomial", "stratified", "systematic", "two_stage"),
                 generator=Gen(), innovation_stats=Flag(), noise_dtype=DType(strings=True))
    def __init__(self, motion: MotionModel, measurement: MeasurementModel, transition, num_particles: int, *,
                 selection, feedback: bool = True, mixing: str = "systematic",
                 generator: torch.Generator | None = None, innovation_stats: bool = True,
                 noise_dtype: torch.dtype | None = None):
        super().__init__(motion, measurement, transition, num_particles, mixing=mixing, generator=generator,
                         innovation_stats=innovation_stats, noise_dtype=noise_dtype)
        if isinstance(selection, ChallengeMatch) and selection.num_winners > self.num_modes * self.num_particles:
            raise ValueError(f"selection: num_winners {selection.num_winners} exceeds the {self.num_modes} x "
                             f"{self.num_particles} particles")
        self.selection, self.feedback = selection, bool(feedback)

    @entry_point(belief=BeliefArg(), mode_probs=Finite(optional=True, check=False), generator=Gen())
    def initial_belief(self, belief: GaussianBelief, mode_probs=None, *,
                       generator: torch.Generator | None = None) -> ModelSetBelief:
        """Every model active with ``Np`` particles from the prior (32). Shapes as the base class."""
        base = super().initial_belief(belief, mode_probs, generator=generator)
        active = torch.ones(base.mode_log_probs.shape, dtype=torch.bool, device=belief.device)
        return ModelSetBelief(base.mode_log_probs, base.components, active)

    def predict(self, belief: ModeBelief, *, u: Tensor | None = None, motion=None,
                generator: torch.Generator | None = None) -> ModelSetBelief:
        return self._as_prior(super().predict(belief, u=u, motion=motion, generator=generator))

    def _as_prior(self, prior: ModeBelief) -> ModelSetBelief:
        active = torch.ones(prior.mode_log_probs.shape, dtype=torch.bool, device=prior.mode_log_probs.device)
        return ModelSetBelief(prior.mode_log_probs, prior.components, active)

    def _update(self, belief: ModeBelief, z: Tensor, generator, loglik: Tensor | None = None) -> StepOutput:
        """The joint update (33)-(34), then the selection of the model set."""
        out = super()._update(belief, z, generator, loglik)
        post = out.belief
        extras = dict(out.extras)
        joint = extras.pop("joint_log_weights")  # (33); the policies are invariant to its normalisation
        active, info = self.selection(joint, self._generator(generator))
        carried = post.mode_log_probs
        if self.feedback:
            carried = normalize_log_probs(torch.where(active, carried, torch.full_like(carried, -math.inf)))
        selected = ModelSetBelief(carried, post.components, active)
        extras.update(info)
        extras["active"] = active
        extras["model_count"] = active.sum(-1)
        return out._replace(belief=selected, extras=extras)


class EqMAParticleFilter(MultipleModelParticleFilter):
    r"""EqMA ``N+1`` on particle filters (docs/baselines.md §2.2, reconstruction).

    ``N`` fixed acceleration models ``x_k = F x_{k-1} + G a_i + G w``, ``w ~ N(0, Q_a)``, plus one
    equivalent model per step, ``a_e = sum_i c_i a_i`` and ``Q_e = Q_a + sum_i c_i (a_i - a_e)(a_i
    - a_e)^T`` with ``c_i`` the predicted probabilities of the fixed models renormalised over
    them (variant A). The equivalent model keeps slot ``N`` in the ``(N+1, N+1)`` transition matrix
    (its predecessor is the previous equivalent model). Particles: ``Np`` per model (interaction as
    the MM-PF).

    Args:
        F: ``(n, n)``; gain: ``G`` ``(n, d)``; accelerations: ``(N, d)``; accel_noise_cov: ``Q_a`` ``(d, d)``.
        measurement: the measurement model.
        num_particles: ``Np`` per model.
        transition: ``(N+1, N+1)``; default :func:`uniform_transition` with ``stay``.
        mixing, generator, innovation_stats, noise_dtype: as
            :class:`~torchmm.multimodel.particle.MultipleModelParticleFilter`.

    Shapes:
        as :class:`~torchmm.multimodel.particle.MultipleModelParticleFilter` with ``M = N + 1``;
        ``extras["equivalent_acceleration"]`` is not recorded (the prior belief's model N carries it).
    """

    @entry_point(F=Finite(square=True, check=False), gain=Finite(check=False),
                 accelerations=Finite(check=False), accel_noise_cov=Cov(check=False),
                 measurement=Of(MeasurementModel), num_particles=Int(1),
                 transition=Stochastic(optional=True), stay=Real(minimum=0.0, maximum=1.0),
                 mixing=Choice("multinomial", "stratified", "systematic", "two_stage"), generator=Gen(),
                 innovation_stats=Flag(), noise_dtype=DType(strings=True))
    def __init__(self, F, gain, accelerations, accel_noise_cov, measurement: MeasurementModel, num_particles: int, *,
                 transition=None, stay: float = 0.9, mixing: str = "systematic",
                 generator: torch.Generator | None = None, innovation_stats: bool = True,
                 noise_dtype: torch.dtype | None = None):
        F = as_tensor(F, "F")
        n = check_square(F, "F")
        if F.dim() != 2:
            raise ValueError(f"F: expected one (n, n) matrix, got shape {tuple(F.shape)}")
        gain = as_tensor(gain, "gain", dtype=F.dtype, device=F.device)
        if gain.dim() != 2 or gain.shape[0] != n:
            raise ValueError(f"gain: expected shape ({n}, d), got {tuple(gain.shape)}")
        d = gain.shape[-1]
        acc = as_tensor(accelerations, "accelerations", dtype=F.dtype, device=F.device)
        qa = as_tensor(accel_noise_cov, "accel_noise_cov", dtype=F.dtype, device=F.device)
        if acc.dim() != 2 or acc.shape[-1] != d or acc.shape[0] < 1:
            raise ValueError(f"accelerations: expected (N, {d}) with N >= 1, got {tuple(acc.shape)}")
        if qa.shape != (d, d):
            raise ValueError(f"accel_noise_cov: expected shape ({d}, {d}), got {tuple(qa.shape)}")
        check_covariance(qa, "accel_noise_cov")
        num_fixed = acc.shape[0]
        motion = LinearMotion(F, symmetrize(gain @ qa @ gain.mT), offset=acc @ gain.mT)
        if transition is None:
            transition = uniform_transition(num_fixed + 1, stay, dtype=F.dtype, device=F.device)
        self._num_fixed = num_fixed
        super().__init__(motion, measurement, transition, num_particles, mixing=mixing, generator=generator,
                         innovation_stats=innovation_stats, noise_dtype=noise_dtype)
        if self.num_modes != num_fixed + 1:
            raise ValueError(f"transition: expected {num_fixed + 1} models (N + 1), got {self.num_modes}")
        self.register_buffer("accelerations", acc)
        self.register_buffer("gain", gain)
        self.register_buffer("accel_noise_cov", qa)

    def _motion_modes(self) -> int:
        """The bank holds the ``N`` fixed models; the equivalent model is built every step."""
        return self._num_fixed

    def equivalent_model(self, log_cbar: Tensor) -> tuple[Tensor, Tensor]:
        """Mean acceleration and noise covariance of the equivalent model.

        Shapes:
            log_cbar: ``(*B, N + 1)`` predicted log-probabilities -> ``(*B, d)``, ``(*B, d, d)``
        """
        c = normalize_log_probs(log_cbar[..., : self._num_fixed]).exp()  # (*B, N)
        mean = c @ self.accelerations
        diff = self.accelerations - mean.unsqueeze(-2)  # (*B, N, d)
        spread = (diff * c.unsqueeze(-1)).mT @ diff
        return mean, symmetrize(self.accel_noise_cov + spread)

    def _propagate(self, particles: Tensor, *, u: Tensor | None, log_cbar: Tensor,
                   generator: torch.Generator | None = None) -> Tensor:
        if u is not None:
            raise ValueError("u: EqMAParticleFilter takes no control input")
        F, G = self.motion.F, self.gain
        mean, cov = self.equivalent_model(log_cbar)
        batch = log_cbar.shape[:-1]
        acc = torch.cat([self.accelerations.expand(*batch, *self.accelerations.shape), mean.unsqueeze(-2)], -2)
        qa = self.accel_noise_cov.expand(*batch, self._num_fixed, *self.accel_noise_cov.shape)
        factor = psd_sqrt(torch.cat([qa, cov.unsqueeze(-3)], -3))  # (*B, N+1, d, d); Q_a may be singular
        eps = standard_normal((*particles.shape[:-1], G.shape[-1]), particles, generator=generator,
                              noise_dtype=self.noise_dtype)
        accel = acc.unsqueeze(-2) + eps @ factor.mT  # (*B, N+1, Np, d)
        return particles @ F.mT + accel @ G.mT


def as_family(sets: Sequence[Sequence[int]], num_models: int) -> Tensor:
    """Indicator matrix of a family of candidate sets given as lists of model indices.

    Shapes:
        -> ``(K, M)`` bool
    """
    return ExactMinimumEntropy(list(map(list, sets)))._family(num_models, None)

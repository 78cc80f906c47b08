r"""Variable structure as a policy: a model-set policy picks the active models every step.

A variable-structure multiple-model (VSMM) estimator runs a bank over the *total* model set with
static shapes and keeps an ``active`` mask ``(*B, M)`` per run: every step

1. the interaction (IMM mixing) starts from the previous active set only: models outside it
   carry probability 0 (``-inf`` in log space), so ``c_j = sum_{i in S_{k-1}} mu_i pi_ij`` (paper
   003's (27)/(33) for particle banks);
2. every model of the total set is predicted and updated (one batched call of the bank);
3. the policy selects ``S_k`` from the posterior, and the belief is renormalised on it
   (``feedback=True``) or the set only chooses the output (``feedback=False``).

Policies are objects with ``select(posterior, generator) -> (active (*B, M) bool, info dict)`` and,
optionally, ``check_bank(bank, name)``, which :class:`VariableStructureIMM` calls once when it is built
to refuse a policy that does not fit the bank (a model index past ``M``, a particle rule over
Gaussian mode filters) before any step:
:class:`AllModels` and :class:`FixedSet` here, paper 003's
:class:`~torchmm.multimodel.mevsmm.ExactMinimumEntropy` (any bank whose beliefs define
``entropy()``: Kalman, unscented, particle) and :class:`~torchmm.multimodel.mevsmm.ChallengeMatch`
(particle banks). A new policy is one class with a ``select`` method (docs/architecture.md).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.contract import Flag, Indices, Of, Real, Stochastic, entry_point
from torchmm.beliefs import Belief, ModeBelief, ModelSetBelief
from torchmm.beliefs.ops import normalize_log_probs
from torchmm.filters.base import Filter, StepOutput
from torchmm.multimodel.bank import FilterBank, IndexedBank, ListBank, VectorizedBank
from torchmm.validation import broadcast_shape
from torchmm.multimodel.imm import IMM, Interaction

__all__ = ["ActiveSetMixing", "AllModels", "DropBelow", "FixedSet", "ModelSetPolicy", "VariableStructureIMM"]


class ModelSetPolicy:
    """Interface of a model-set policy (see the module docstring)."""

    def select(self, belief: ModeBelief, generator: torch.Generator | None = None) -> tuple[Tensor, dict]:
        """The active set ``(*B, M)`` bool (never empty) and diagnostics (tensors with batch ``(*B, ...)``)
        from the posterior ``belief`` over the total set (normalised mode probabilities)."""
        raise NotImplementedError

    def check_bank(self, bank: FilterBank, name: str = "policy") -> None:
        """Refuse (``ValueError``/``TypeError`` naming ``name.<argument>``) a policy that cannot run over
        ``bank``; called once by :class:`VariableStructureIMM` when it is built. The default accepts any
        bank."""


def mode_filters(bank: FilterBank) -> list[Filter] | None:
    """The mode filters of ``bank``, one per mode (a :class:`~torchmm.multimodel.VectorizedBank`'s one
    filter ``M`` times); None for a bank of another kind, whose filters are not known."""
    if isinstance(bank, VectorizedBank):
        return [bank.filter] * bank.num_modes
    if isinstance(bank, ListBank):
        return list(bank.filters)
    if isinstance(bank, IndexedBank):
        inner = mode_filters(bank.bank)
        return None if inner is None else [inner[i] for i in bank.index]
    return None


def particle_counts(bank: FilterBank) -> list[int | None] | None:
    """Per mode, the particle count of a particle mode filter (its ``num_particles``; None where it
    keeps the prior's count) and None for the list when a mode filter is not a particle filter (one
    whose beliefs the particle smoother takes, ``smoother == "particles"`` as
    :class:`~torchmm.ParticleFilter`'s, or one with an integer ``num_particles``) or the bank's filters
    are not known (:func:`mode_filters`)."""
    filters = mode_filters(bank)
    if filters is None:
        return None
    counts = []
    for f in filters:
        count = getattr(f, "num_particles", None)
        if getattr(f, "smoother", None) != "particles" and not isinstance(count, int):
            return None
        counts.append(count)
    return counts


def check_indices(indices: list[int], num_models: int, name: str) -> None:
    """Refuse a model index outside ``[0, num_models)``: ``ValueError`` naming ``name``."""
    bad = [i for i in indices if not 0 <= i < num_models]
    if bad:
        raise ValueError(f"{name}: {list(indices)} has model index {bad[0]}, out of range for the bank's "
                         f"{num_models} models (0..{num_models - 1})")


class AllModels(ModelSetPolicy):
    """Every model, every step: the VSMM estimator is then the fixed-structure IMM."""

    def select(self, belief, generator=None):
        return torch.ones(belief.mode_log_probs.shape, dtype=torch.bool, device=belief.mode_log_probs.device), {}


class FixedSet(ModelSetPolicy):
    """A given model set, the same every step.

    Args:
        members: indices of the active models (non-empty).
    """

    @entry_point(members=Indices())
    def __init__(self, members):
        self.members = sorted({int(i) for i in members})
        if not self.members:
            raise ValueError("members: the model set must not be empty")

    def check_bank(self, bank, name="policy"):
        check_indices(self.members, bank.num_modes, f"{name}.members")

    def select(self, belief, generator=None):
        mask = _index_mask(self, self.members, belief.num_modes, belief.mode_log_probs.device, "members")
        return mask.expand(belief.mode_log_probs.shape), {}


def _index_mask(policy, indices: list[int], size: int, device, name: str) -> Tensor:
    """``(size,)`` bool, True at ``indices`` (the policy's argument ``name``, checked against ``size``): made
    once per size and device and kept on the policy (a mask built from a Python list is a host-to-device
    copy on a GPU, not for every step)."""
    cache = policy.__dict__.setdefault("_masks", {})
    key = (size, str(device))
    if key not in cache:
        check_indices(indices, size, name)
        mask = torch.zeros(size, dtype=torch.bool)
        mask[indices] = True
        cache[key] = mask.to(device)
    return cache[key]


class DropBelow(ModelSetPolicy):
    """Keep every model except the ``candidates`` whose posterior probability falls below ``threshold``
    (or is 0): VSIMM's rule for its source mode (docs/baselines.md §3.3).

    Args:
        threshold: probability in ``[0, 1)``.
        candidates: indices of the models that may be dropped (the others are always active).
    """

    @entry_point(threshold=Real(minimum=0.0, maximum=1.0), candidates=Indices(empty=True))
    def __init__(self, threshold: float, candidates):
        self.threshold = float(threshold)
        if not 0.0 <= self.threshold < 1.0:
            raise ValueError(f"threshold: must lie in [0, 1), got {threshold}")
        self.candidates = sorted({int(i) for i in candidates})

    def check_bank(self, bank, name="policy"):
        check_indices(self.candidates, bank.num_modes, f"{name}.candidates")

    def select(self, belief, generator=None):
        lp = belief.mode_log_probs
        candidate = _index_mask(self, self.candidates, lp.shape[-1], lp.device, "candidates")
        low = lp < (math.log(self.threshold) if self.threshold > 0 else -math.inf)
        return ~(candidate & (low | (lp == -math.inf))), {}


def check_active_set(active, shape: torch.Size, name: str = "policy") -> Tensor:
    """A policy's active set: a bool tensor that broadcasts to the mode probabilities' ``(*B, M)``.
    Shapes and dtype only (no values read: an empty set is flagged by the caller, per run)."""
    if not isinstance(active, Tensor):
        raise TypeError(f"{name}: select returned {type(active).__name__} for the active set, expected a "
                        f"bool tensor of shape {tuple(shape)}")
    if active.dtype != torch.bool:
        raise TypeError(f"{name}: select returned an active set of dtype {active.dtype}, expected torch.bool")
    if active.shape != shape:
        try:
            ok = broadcast_shape(active.shape, shape) == shape
        except RuntimeError:
            ok = False
        if not ok:
            raise ValueError(f"{name}: select returned an active set of shape {tuple(active.shape)}, "
                             f"expected {tuple(shape)} (*B, M)")
        active = active.expand(shape)
    return active


class ActiveSetMixing(Interaction):
    r"""IMM mixing over the active models of a :class:`~torchmm.beliefs.ModelSetBelief`, with every
    row of the transition matrix renormalised over the active set,
    ``pi_ij = p_ij / sum_{l active} p_il`` (docs/baselines.md §3.3: the mixing of a set that
    changes). The plain :class:`~torchmm.multimodel.MomentMixing` restricts the set only through
    the zero probabilities of inactive models (the rows keep their full mass).

    ``transition`` may be a :class:`~torchmm.multimodel.ModeTransition` or a matrix ``(M, M)``.

    Shapes:
        belief: ``ModelSetBelief`` (or a ``ModeBelief``: all active), batch ``(*B,)`` -> ``log c``
        ``(*B, M)`` (``-inf`` where no active model leads) and start beliefs with batch ``(*B, M)``
    """

    def __call__(self, belief, transition, generator=None):
        mu = belief.mode_probs
        matrix = transition if isinstance(transition, Tensor) else transition.matrix()
        active = getattr(belief, "active", None)
        if active is not None:
            matrix = matrix * active.unsqueeze(-2).to(mu.dtype)  # restrict to the active set
            matrix = matrix / matrix.sum(-1, keepdim=True)
        cbar = (mu.unsqueeze(-2) @ matrix).squeeze(-2)
        weights = mu.unsqueeze(-1) * matrix / cbar.clamp_min(torch.finfo(mu.dtype).tiny).unsqueeze(-2)
        log_cbar = torch.where(cbar > 0, cbar.clamp_min(torch.finfo(mu.dtype).tiny).log(), -math.inf)
        return ModeBelief(log_cbar, belief.components.mix(weights))


#: the steps the batch-last kernels replace (a subclass that overrides one runs its own, eagerly)
_KERNEL_STEPS = ("step", "predict", "update", "mix", "select_models")


@kernels.joins("linear_gaussian", _KERNEL_STEPS)
@kernels.joins("nonlinear_gaussian", _KERNEL_STEPS)
class VariableStructureIMM(IMM):
    r"""A variable-structure IMM over any bank: IMM interaction from the active set, a policy after
    every update (see the module docstring).

    Args:
        bank: the mode filters of the total model set (any bank, as :class:`~torchmm.multimodel.IMM`).
        transition: ``(M, M)`` over the total set.
        policy: a :class:`ModelSetPolicy` (e.g. ``ExactMinimumEntropy()`` for paper 003's rule); its
            ``check_bank(bank, "policy")``, where it has one, refuses here a policy that does not fit the
            bank (``FixedSet``/``DropBelow``/``family`` indices past ``M``; ``ChallengeMatch`` over
            mode filters that are not particle filters, or with more winners than particles).
        feedback: ``True``: the recursion continues from the selected set (probabilities
            renormalised on it); ``False``: the recursion keeps every model and the set only
            chooses the output :meth:`~torchmm.beliefs.ModelSetBelief.estimate`.

    Shapes:
        belief: :class:`~torchmm.beliefs.ModelSetBelief` (``active (*B, M)``); ``z (*B, m)``;
        ``extras`` as :class:`~torchmm.multimodel.IMM` plus ``"active"`` ``(*B, M)``,
        ``"model_count"`` ``(*B,)`` and the policy's diagnostics.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> from torchmm.multimodel.mevsmm import ExactMinimumEntropy
        >>> motion = ConstantVelocity(1, q=1.0, acceleration=[[0.5], [0.0], [-0.5]])
        >>> vs = VariableStructureIMM(KalmanFilter(motion, PositionMeasurement(2, [0], 1.0)),
        ...                           torch.full((3, 3), 0.1) + 0.7 * torch.eye(3), ExactMinimumEntropy())
        >>> out = vs.step(vs.initial_belief(GaussianBelief(torch.zeros(4, 2), torch.eye(2))), torch.zeros(4, 1))
        >>> out.extras["active"].shape, out.belief.estimate().mean.shape
        (torch.Size([4, 3]), torch.Size([4, 2]))
    """

    smoother = None  # its beliefs carry the active set (ModelSetBelief): no smoother yet (torchmm.smooth says so)

    @entry_point(bank=Of((Filter, FilterBank, list, tuple),
                         what="a Filter, a list of filters or a FilterBank"),
                 transition=Stochastic(),
                 policy=Of(methods=("select",), what="a model-set policy (with a select method)"),
                 feedback=Flag())
    def __init__(self, bank, transition, policy: ModelSetPolicy, *, feedback: bool = True):
        super().__init__(bank, transition)
        check = getattr(policy, "check_bank", None)
        if callable(check):  # (once, here: a policy that does not fit the bank is refused before any step)
            check(self.bank, "policy")
        self.policy, self.feedback = policy, bool(feedback)

    @property
    def uses_generator(self) -> bool:
        return True  # policies may draw random numbers (e.g. the challenge-match tournament)

    def initial_belief(self, belief: Belief, mode_probs=None, *, generator=None) -> ModelSetBelief:
        """Every model active. Shapes as :meth:`~torchmm.multimodel.IMM.initial_belief`."""
        start = super().initial_belief(belief, mode_probs, generator=generator)
        active = torch.ones(start.mode_log_probs.shape, dtype=torch.bool, device=start.mode_log_probs.device)
        return ModelSetBelief(start.mode_log_probs, start.components, active)

    def mix(self, belief: ModeBelief, generator=None) -> ModeBelief:
        mixed = super().mix(belief, generator)
        return ModeBelief(mixed.mode_log_probs, mixed.components)

    def update(self, belief: ModeBelief, z: Tensor, *, sensor=None, generator=None) -> StepOutput:
        return self.select_models(super().update(belief, z, sensor=sensor, generator=generator), generator)

    def linear_gaussian(self):
        """The IMM's description (:meth:`MultipleModelFilter.linear_gaussian`) with :meth:`select_models`
        as its ``post_update``: the batch-last IMM kernel runs the steps and this policy after each."""
        model = super().linear_gaussian()
        return model if isinstance(model, str) else model._replace(post_update=self.select_models)

    def nonlinear_gaussian(self):
        """The IMM's nonlinear-Gaussian description (:meth:`IMM.nonlinear_gaussian`, extended or unscented
        modes) with :meth:`select_models` as its ``post_update``, as :meth:`linear_gaussian`."""
        model = super().nonlinear_gaussian()
        return model if isinstance(model, str) else model._replace(post_update=self.select_models)

    def select_models(self, out: StepOutput, generator=None) -> StepOutput:
        """The policy after the IMM update ``out`` (batch-first, batch ``(*B,)``): the selected set, the
        carried probabilities (restricted to the set with ``feedback``), the extras ``"active"``,
        ``"model_count"``, ``"empty_set"`` and the policy's, a NaN log-likelihood for an empty set."""
        post = out.belief
        selected = self.policy.select(post, generator)
        if not isinstance(selected, tuple) or len(selected) != 2 or not isinstance(selected[1], dict):
            raise TypeError(f"policy: {type(self.policy).__name__}.select must return (active, info dict), "
                            f"got {type(selected).__name__}")
        active, info = selected
        carried = post.mode_log_probs
        active = check_active_set(active, carried.shape)
        # an empty set is that run's failure (never the others'): flagged, its likelihood NaN
        empty = ~active.any(-1)
        if self.feedback:
            carried = normalize_log_probs(torch.where(active, carried, -math.inf))
        extras = dict(out.extras or {})  # (None: a kernel's run that keeps no extras)
        extras.update(info)
        extras["active"] = active
        extras["model_count"] = active.sum(-1)
        extras["empty_set"] = empty
        log_likelihood = torch.where(empty, math.nan, out.log_likelihood)
        return out._replace(belief=ModelSetBelief(carried, post.components, active), extras=extras,
                            log_likelihood=log_likelihood)

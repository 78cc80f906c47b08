r"""Multiple-model combinators over any filter bank: IMM, GPB1 and GPB2, in log space.

Notation (Bar-Shalom, Li, Kirubarajan 2001, ch. 11; paper 001 eqs. (2.7)-(2.14); paper 000
section 2.2): ``mu_i`` posterior mode probabilities at ``k-1``, ``pi_ij`` the transition matrix
(``P(mode_k = j | mode_{k-1} = i)``), ``ell_j`` the mode-matched log-likelihoods at ``k``.

.. math::
    \bar c_j = \textstyle\sum_i \mu_i \pi_{ij},\qquad
    \mu_{i|j} = \pi_{ij}\,\mu_i / \bar c_j

    \log\mu^+_j = \ell_j + \log\bar c_j - \operatorname{logsumexp}_l(\ell_l + \log\bar c_l),\qquad
    \log p(z_k | z_{1:k-1}) = \operatorname{logsumexp}_l(\ell_l + \log\bar c_l)

Every mode and every run is handled by one batched call of the bank. Mode probabilities are stored
as logarithms. The interaction uses the *normalised* probabilities in linear space (one matmul,
no overflow possible, exact down to underflow below the smallest normal number); the likelihoods,
which do underflow (a far outlier gives ``exp(ell) = 0`` for every mode), are combined in log space.
"""

from __future__ import annotations

import copy
import math

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import Belief, ModeBelief
from torchmm.beliefs.ops import live_log
from torchmm.contract import BeliefArg, Finite, Gen, Int, Of, Stochastic, entry_point
from torchmm.filters.base import Filter, StepOutput, check_state_dim
from torchmm.models.transition import as_transition
from torchmm.multimodel.bank import FilterBank, make_bank, motion_reads_inputs
from torchmm.multimodel.interaction import (  # (re-exported: the combinators' interactions and mode update)
    Collapse,
    Interaction,
    MomentMixing,
    NoInteraction,
    flag_run_failed,
    mode_batch,
    mode_extras,
    mode_posterior,
    transition_matrix,
)
from torchmm.validation import (
    broadcast_shape,
    check_filter_dtype,
    check_measurement,
    check_parameter_batch,
    check_probabilities,
)

__all__ = ["GPB1", "IMM", "Collapse", "Interaction", "MomentMixing", "MultipleModelFilter", "NoInteraction",
           "StaticMM"]


class MultipleModelFilter(Filter):
    """Shared set-up of the multiple-model combinators.

    Args:
        bank: the mode-matched filters (see :func:`~torchmm.multimodel.make_bank`): one filter
            with mode-bank models, a list of filters, or a :class:`~torchmm.multimodel.FilterBank`.
        transition: ``(M, M)`` row-stochastic matrix or a
            :class:`~torchmm.multimodel.ModeTransition` (learnable).
    """

    smoother = "modes"  # (torchmm.smooth's backward pass: Filter.smoother)

    #: the interaction of subclasses that do not pass one (IMM: :class:`MomentMixing`)
    default_interaction: type[Interaction] | None = None

    @entry_point(bank=Of((Filter, FilterBank, list, tuple),
                         what="a Filter, a list of filters or a FilterBank"),
                 transition=Stochastic(), interaction=Of(Interaction, optional=True))
    def __init__(self, bank, transition, interaction: Interaction | None = None):
        super().__init__()
        self.transition = as_transition(transition)
        self.num_modes = self.transition.num_modes
        self.bank = make_bank(bank, self.num_modes)
        if interaction is None:
            if self.default_interaction is None:
                raise TypeError("interaction: MultipleModelFilter needs an Interaction (e.g. MomentMixing() for IMM)")
            interaction = self.default_interaction()
        if not isinstance(interaction, Interaction):
            raise TypeError(f"interaction: expected an Interaction (MomentMixing, Collapse, NoInteraction, "
                            f"ParticleMixing), got {type(interaction).__name__}")
        if getattr(self.transition, "takes_inputs", False) and not (
                self.time_varying_transition and isinstance(interaction, (MomentMixing, Collapse, NoInteraction))):
            raise TypeError(f"transition: a time-varying transition (LogisticTransition) is supported by IMM, GPB1 and "
                            f"a static bank, not {type(self).__name__} with {type(interaction).__name__}")
        self.interaction = interaction

    def check_parameter_batch(self, batch: torch.Size) -> None:
        """The transition's batch (per-run matrices ``(*B, M, M)``) against the start belief's ``batch``: it
        must broadcast to it, adding neither runs nor axes (a ``ValueError`` naming ``transition``; shapes
        only)."""
        super().check_parameter_batch(batch)
        shape = getattr(self.transition, "batch_shape", None)
        if shape is not None:
            check_parameter_batch(shape, batch, "transition", exact=True)

    @property
    def meas_dim(self) -> int | None:
        return self.bank.meas_dim

    @property
    def state_dim(self) -> int | None:
        return self.bank.state_dim

    @property
    def uses_generator(self) -> bool:
        return self.bank.uses_generator or self.interaction.uses_generator

    def with_sensor(self, sensor) -> MultipleModelFilter:
        """This filter with every mode filter's sensor replaced (see :meth:`Filter.with_sensor`)."""
        return self._with_bank(self.bank.with_sensor(sensor))

    def with_motion(self, motion) -> MultipleModelFilter:
        """This filter with the mode filters' motion models replaced (a mode bank model, or one per mode)."""
        return self._with_bank(self.bank.with_motion(motion))

    def _with_bank(self, bank) -> MultipleModelFilter:
        if bank is self.bank:
            return self
        clone = copy.copy(self)
        for table in ("_modules", "_buffers", "_parameters"):
            clone.__dict__[table] = dict(self.__dict__[table])
        clone._modules["bank"] = bank
        return clone

    def _measurement(self, belief, z, name: str = "z", sensor=None) -> Tensor:
        """``z (*B, m)`` checked against the sensor (default the bank's) and the belief's batch."""
        batch = mode_batch(belief)
        m = self.bank.meas_dim if sensor is None or isinstance(sensor, (list, tuple)) else sensor.meas_dim
        like = belief.mode_log_probs
        if m is None:  # a set of detections (an association's scan): checked in the user's shape, here
            if not isinstance(z, Tensor):
                if z is None or isinstance(z, (str, bytes)):
                    raise TypeError(f"{name}: expected a tensor, got {type(z).__name__}")
                try:
                    z = torch.as_tensor(z, dtype=like.dtype, device=like.device)
                except (TypeError, ValueError, RuntimeError) as err:
                    raise TypeError(f"{name}: cannot convert to a tensor ({err})") from None
            if sensor is None:
                self.bank.check_measurements(z, batch, name, time=False)
            return z
        return check_measurement(z, m, batch, like, name)

    def check_measurements(self, measurements: Tensor, batch: torch.Size, name: str = "measurements", *,
                           time: bool = True) -> None:
        """The mode filters' check (:meth:`~torchmm.filters.Filter.check_measurements`: an IMM over an
        association checks the scans), with this filter's batch ``(*B,)``."""
        self.bank.check_measurements(measurements, batch, name, time=time)

    def _matrix(self, like: Tensor) -> Tensor:
        return transition_matrix(self.transition, like)

    @entry_point(belief=BeliefArg(), mode_probs=Finite(optional=True, check=False), generator=Gen())
    def initial_belief(self, belief: Belief, mode_probs=None, *, generator=None) -> ModeBelief:
        """Start every mode from ``belief`` with prior mode probabilities ``mode_probs``.

        The mode filters turn ``belief`` into their own belief type (a particle-filter bank draws
        its particles from the Gaussian prior with ``generator``; Kalman-type banks keep it).

        Shapes:
            belief: batch ``(*B,)``; mode_probs: ``(M,)`` or ``(*B, M)``, default uniform
            -> :class:`ModeBelief` with batch ``(*B,)``
        """
        M = self.num_modes
        belief.validate("belief")
        check_filter_dtype(self, belief, "belief")
        check_state_dim(self.bank, belief, "belief")
        batch = belief.batch_shape
        if mode_probs is None:
            log_probs = torch.full((M,), -math.log(M), dtype=belief.dtype, device=belief.device)
        else:
            probs = check_probabilities(mode_probs, "mode_probs", M, dtype=belief.dtype, device=belief.device)
            try:
                batch = broadcast_shape(batch, probs.shape[:-1])
            except RuntimeError:
                raise ValueError(f"mode_probs: batch {tuple(probs.shape[:-1])} does not broadcast with the "
                                 f"belief's {tuple(batch)}") from None
            if batch != belief.batch_shape:
                raise ValueError(f"mode_probs: batch {tuple(probs.shape[:-1])} would enlarge the belief's batch "
                                 f"{tuple(belief.batch_shape)}")
            log_probs = live_log(probs, 0.0)  # (a zero probability: no NaN gradient; test_transition_zeros.py)
        log_probs = log_probs.expand(*batch, M)
        components = self.bank.initial_belief(belief.unsqueeze(-1).expand(*batch, M), generator=generator)
        return ModeBelief(log_probs, components)

    def _update_modes(self, prior: ModeBelief, z: Tensor, *, observed: Tensor | None = None, sensor=None,
                      generator=None) -> StepOutput:
        """Mode-matched updates and the mode-probability update (shared by IMM and GPB1).

        Where ``z`` has no finite component (or ``observed (*B,)`` is False: no datum at all this
        step) the log-likelihood is exactly 0 (``logsumexp_j(log c_j)`` is 0 only up to rounding).
        """
        z = self._measurement(prior, z, sensor=sensor)
        rank = self.bank.measurement_rank  # the mode axis goes before the measurement's own axes
        out = self.bank.update(prior.components, z.unsqueeze(-1 - rank), sensor=sensor, generator=generator)
        observed = self.bank.informative(z) if observed is None else observed
        mode_log_probs, log_likelihood = mode_posterior(out.log_likelihood, prior.mode_log_probs, observed)
        extras = mode_extras(out)
        extras["failed"] = flag_run_failed(log_likelihood)
        return StepOutput(
            belief=ModeBelief(mode_log_probs, out.belief),
            prior=prior,
            log_likelihood=log_likelihood,
            innovation=out.innovation,
            innovation_cov=out.innovation_cov,
            extras=extras,
        )

    def linear_gaussian(self):
        """The description of this filter for the linear-Gaussian kernel (:mod:`torchmm.kernels.linear`):
        the bank's matrices, the transition matrix and the interaction's rule; or the reason there is
        none (a bank that is not linear-Gaussian, an interaction without a kernel rule, a class that
        has not joined the kernel family or overrides its steps)."""
        if not kernels.joined(self, "linear_gaussian"):
            return f"{type(self).__name__} has not joined the linear-Gaussian kernels (or overrides their steps)"
        rule = self.interaction.kernel_rule
        if rule is None:
            return f"the interaction {type(self.interaction).__name__} has no kernel rule"
        describe = getattr(self.bank, "linear_gaussian", None)
        model = describe() if describe is not None else f"the bank {type(self.bank).__name__} is not linear-Gaussian"
        if isinstance(model, str):
            return model
        if getattr(self.transition, "takes_inputs", False):  # (its matrices are the controls': kernels that take them)
            return model._replace(transition=None, rule=rule, time_varying=self.transition)
        return model._replace(transition=self._matrix(model.F), rule=rule)

    def nonlinear_gaussian(self):
        """The description of this filter for the nonlinear-Gaussian kernel (:mod:`torchmm.kernels.nonlinear`):
        the bank's extended or unscented filter, the transition matrix and the interaction's rule; or the
        reason there is none."""
        if not kernels.joined(self, "nonlinear_gaussian"):
            return f"{type(self).__name__} has not joined the nonlinear-Gaussian kernels (or overrides their steps)"
        rule = self.interaction.kernel_rule
        if rule not in ("mix", "collapse"):
            return f"the interaction {type(self.interaction).__name__} has no nonlinear kernel rule"
        if getattr(self.transition, "takes_inputs", False):
            return "a time-varying transition (it reads each step's controls)"
        describe = getattr(self.bank, "nonlinear_gaussian", None)
        model = describe() if describe is not None else f"the bank {type(self.bank).__name__} is not nonlinear-Gaussian"
        if isinstance(model, str):
            return model
        return model._replace(transition=self.transition.matrix(), rule=rule)

    #: whether the class takes a time-varying transition (:class:`~torchmm.models.transition.LogisticTransition`)
    time_varying_transition: bool = True

    def transition_at(self, u: Tensor | None = None):
        """The step's transition: the filter's, or a time-varying one's matrices at the step's controls ``u``
        (:class:`~torchmm.models.transition.LogisticTransition`: ``(*B, M, M)``)."""
        if getattr(self.transition, "takes_inputs", False):
            return self.transition.at(u)
        return self.transition

    def mix(self, belief: ModeBelief, generator=None, *, u: Tensor | None = None) -> ModeBelief:
        """Interaction step: predicted mode log-probs and the mode-conditioned start beliefs (``u``: the step's
        controls, read by a time-varying transition)."""
        mode_batch(belief)
        return self.interaction(belief, self.transition_at(u), generator)

    def _mixed(self, belief: ModeBelief, generator, u: Tensor | None) -> ModeBelief:
        """:meth:`mix`, given the step's controls where the transition reads them (a subclass's own ``mix``
        without ``u`` keeps working for a fixed transition)."""
        if getattr(self.transition, "takes_inputs", False):
            return self.mix(belief, generator, u=u)
        return self.mix(belief, generator)

    def predict(self, belief: ModeBelief, *, u: Tensor | None = None, motion=None, generator=None) -> ModeBelief:
        """Interaction (:meth:`mix`) and every mode's time update (``motion``: per-step mode models)."""
        return self._predict(self._mixed(belief, generator, u), u=u, motion=motion, generator=generator)

    def _predict(self, mixed: ModeBelief, *, u=None, motion=None, generator=None) -> ModeBelief:
        if u is not None and getattr(self.transition, "takes_inputs", False) and not motion_reads_inputs(
                self.bank, motion):
            u = None  # the controls are the time-varying transition's only (the linear kernel's reading too)
        u = None if u is None else u.unsqueeze(-2)
        components = self.bank.predict(mixed.components, u=u, motion=motion, generator=generator)
        return ModeBelief(mixed.mode_log_probs, components)

    def update(self, belief: ModeBelief, z: Tensor, *, sensor=None, generator=None) -> StepOutput:
        """Mode-matched updates and the mode probabilities; ``sensor`` replaces the bank's
        measurement model for this update (e.g. a second sensor at the same time step)."""
        return self._update_modes(belief, z, sensor=sensor, generator=generator)

    def update_each(self, belief: ModeBelief, zs: Tensor) -> StepOutput:
        """:meth:`~torchmm.filters.Filter.update_each`: the bank's ``update_each`` (a Kalman bank
        shares each mode's gain over the measurements), then each measurement's mode probabilities.
        A combinator with its own update (GPB2, variable structure, transfer) takes the default.

        Shapes: belief batch ``(*B,)`` (components ``(*B, M)``); zs ``(D, *B, m)`` -> batch ``(D, *B)``."""
        if (type(self).update is not MultipleModelFilter.update or
                type(self)._update_modes is not MultipleModelFilter._update_modes or self.bank.uses_generator):
            return super().update_each(belief, zs)
        batch = mode_batch(belief)
        m = self.bank.meas_dim
        if m is not None:
            zs = check_measurement(zs, m, torch.Size([zs.shape[0] if zs.dim() else 0, *batch]),
                                   belief.mode_log_probs, "zs")
            zs = torch.where(torch.isfinite(zs).all(-1, keepdim=True), zs, torch.nan)
        rank = self.bank.measurement_rank
        out = self.bank.update_each(belief.components, zs.unsqueeze(-1 - rank))
        mode_log_probs, log_likelihood = mode_posterior(out.log_likelihood, belief.mode_log_probs,
                                                        self.bank.informative(zs))
        extras = mode_extras(out)
        extras["failed"] = flag_run_failed(log_likelihood)
        return StepOutput(ModeBelief(mode_log_probs, out.belief), belief, log_likelihood, out.innovation,
                          out.innovation_cov, extras)

    def step(self, belief: ModeBelief, z: Tensor, *, u: Tensor | None = None, motion=None, sensor=None,
             generator=None) -> StepOutput:
        mixed = self._mixed(belief, generator, u)
        prior = self._predict(mixed, u=u, motion=motion, generator=generator)
        out = self.update(prior, z, sensor=sensor, generator=generator)
        out.extras["mixed"] = mixed
        return out


@kernels.joins("linear_gaussian")
@kernels.joins("nonlinear_gaussian")
class IMM(MultipleModelFilter):
    r"""Interacting multiple model estimator (Blom and Bar-Shalom 1988) over any filter bank.

    Mixing: mode ``j`` starts from the moment-matched mixture of the mode posteriors with weights
    ``mu_{i|j}``; each mode filter then runs one step; the output estimate (not fed back) is the
    moment-matched collapse, ``belief.estimate()``.

    Args:
        bank: mode-matched filters (one vectorised filter, a list, or a ``FilterBank``).
        transition: ``(M, M)`` matrix with ``P[i, j] = P(mode_k = j | mode_{k-1} = i)``.

    Shapes:
        belief: :class:`ModeBelief`, ``mode_log_probs (*B, M)``, components batch ``(*B, M)``;
        ``z``: ``(*B, m)``; the step's ``innovation`` is ``(*B, M, m)``. ``extras`` holds
        ``"mixed"`` (``ModeBelief`` of the mixed start beliefs with ``log c_j``),
        ``"mode_log_likelihood"`` ``(*B, M)``, ``"failed"`` ``(*B,)`` (a mode filter failed on a
        present datum - a NaN prediction -: the log-likelihood is NaN, docs/robustness.md) and, when
        the mode filters report diagnostics, ``"modes"`` (their ``extras``, batch ``(*B, M)``).

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> motion = ConstantVelocity(1, q=1.0, acceleration=[[0.25], [0.0], [-0.25]])
        >>> imm = IMM(KalmanFilter(motion, PositionMeasurement(2, [0], 100.0)),
        ...           torch.tensor([[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.25, 0.25, 0.5]]))
        >>> belief = imm.initial_belief(GaussianBelief(torch.zeros(8, 2), 100 * torch.eye(2)))
        >>> out = imm.step(belief, torch.randn(8, 1))
        >>> out.belief.mode_probs.shape, out.belief.estimate().mean.shape
        (torch.Size([8, 3]), torch.Size([8, 2]))
    """

    default_interaction = MomentMixing


@kernels.joins("linear_gaussian")
class StaticMM(MultipleModelFilter):
    r"""Static multiple-model estimator (Magill 1965): a bank of filters that never interact.

    The mode is constant over time (identity transition): each mode filter runs on its own, and
    the mode probabilities are the running posterior ``mu_j ∝ mu_j p_j(z_k | z_{1:k-1})``. It is
    :class:`IMM` with ``transition = I`` without the (then trivial) mixing.

    Args:
        bank: the mode filters (as :class:`IMM`).
        num_modes: ``M`` (default: the length of a list bank or ``bank.num_modes``; required for
            one vectorised filter whose models have no mode axis).

    Shapes:
        as :class:`IMM` (``extras`` without ``"mixed"``).

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> sensors = [PositionMeasurement(2, [0], r) for r in (1.0, 10.0)]
        >>> mm = StaticMM([KalmanFilter(ConstantVelocity(1), s) for s in sensors])
        >>> out = mm.step(mm.initial_belief(GaussianBelief(torch.zeros(4, 2), torch.eye(2))), torch.zeros(4, 1))
        >>> out.belief.mode_probs.shape
        torch.Size([4, 2])
    """

    @entry_point(bank=Of((Filter, FilterBank, list, tuple),
                         what="a Filter, a list of filters or a FilterBank"),
                 num_modes=Int(1, optional=True))
    def __init__(self, bank, num_modes: int | None = None):
        if num_modes is None:
            if isinstance(bank, (list, tuple)):
                num_modes = len(bank)
            elif hasattr(bank, "num_modes"):
                num_modes = bank.num_modes
            else:
                shape = getattr(bank, "param_batch_shape", None)
                if not shape:
                    raise ValueError("num_modes: give it for a single filter whose models have no mode axis")
                num_modes = shape[-1]
        like = _floating_tensor(bank)  # (the identity in the bank's dtype and device, not the default's)
        eye = torch.eye(int(num_modes), dtype=torch.get_default_dtype() if like is None else like.dtype,
                        device=None if like is None else like.device)
        super().__init__(bank, eye, NoInteraction())

    def step(self, belief: ModeBelief, z: Tensor, *, u: Tensor | None = None, motion=None, sensor=None,
             generator=None) -> StepOutput:
        prior = self._predict(self.mix(belief), u=u, motion=motion, generator=generator)
        return self.update(prior, z, sensor=sensor, generator=generator)


def _floating_tensor(bank) -> Tensor | None:
    """The first floating-point parameter or buffer of a filter, a list of filters or a bank, or None."""
    for module in bank if isinstance(bank, (list, tuple)) else [bank]:
        for t in (*module.parameters(), *module.buffers()) if isinstance(module, torch.nn.Module) else ():
            if t.is_floating_point():
                return t
    return None


@kernels.joins("linear_gaussian")
@kernels.joins("nonlinear_gaussian")
class GPB1(MultipleModelFilter):
    """First-order generalised pseudo-Bayesian estimator.

    Every mode filter starts from the single collapsed belief of the previous step (the mixing
    weights are ``mu_i`` for every ``j``). Same interface and shapes as :class:`IMM`.
    """

    default_interaction = Collapse

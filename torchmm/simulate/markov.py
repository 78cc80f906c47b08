r"""Batched simulation of Markov-jump systems: all Monte Carlo runs at once, loops over time only.

System (paper 000, eqs. (1)-(2); paper 001, eqs. (1.1)-(1.2)):

.. math::
    r_k \sim \pi_{r_{k-1}, \cdot},\qquad x_k = f_{r_k}(x_{k-1}) + w_k,\ w_k \sim N(0, Q_{r_k}),
    \qquad z_k = h_{(r_k)}(x_k) + v_k,\ v_k \sim N(0, R)

with ``x_0 ~ N(x0_mean, x0_cov)`` and ``r_0 ~ initial_mode_probs``; ``r_k`` is the mode in force
over ``(k-1, k]``. Randomness comes only from the ``generator`` argument.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchmm.beliefs import GaussianBelief, psd_sqrt
from torchmm.contract import (
    BeliefArg,
    Device,
    DType,
    Finite,
    Gen,
    Int,
    Labels,
    Mask,
    Of,
    Real,
    Shape,
    Stochastic,
    entry_point,
)
from torchmm.models.base import MeasurementModel, MotionModel
from torchmm.models.streams import MultiRate
from torchmm.models.transition import validate_transition
from torchmm.validation import as_tensor, check_probabilities, module_tensors

__all__ = [
    "JumpSimulation",
    "bernoulli_mask",
    "periodic_mask",
    "sample_categorical",
    "simulate_jump_system",
    "simulate_measurements",
    "simulate_modes",
    "simulate_multirate",
]


@dataclass(frozen=True)
class JumpSimulation:
    """Ground truth of a batch of Markov-jump trajectories.

    Shapes:
        states: ``(T, *B, n)`` - ``x_1 .. x_T``
        modes: ``(T, *B)`` (int64) - ``r_1 .. r_T``
        initial_state: ``(*B, n)`` - ``x_0``
        initial_mode: ``(*B,)`` - ``r_0``
    """

    states: Tensor
    modes: Tensor
    initial_state: Tensor
    initial_mode: Tensor

    def to(self, dtype: torch.dtype) -> JumpSimulation:
        """The states in ``dtype`` (the modes stay integers), e.g. float64 data for a float32 filter."""
        return JumpSimulation(self.states.to(dtype), self.modes, self.initial_state.to(dtype), self.initial_mode)


@entry_point(probs=Finite(check=False), generator=Gen())
def sample_categorical(probs: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """One draw per batch element from ``probs (*B, M)`` (rows sum to one) -> ``(*B,)`` int64.

    Raises:
        ValueError: naming ``probs`` if it is not a finite, non-negative ``(*B, M)`` tensor whose
            rows sum to one.
    """
    probs = as_tensor(probs, "probs")
    if probs.dim() < 1 or probs.shape[-1] < 1:
        raise ValueError(f"probs: expected shape (*B, M), got {tuple(probs.shape)}")
    probs = check_probabilities(probs, "probs", probs.shape[-1])
    return _sample_categorical(probs, generator)


def _sample_categorical(probs: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """:func:`sample_categorical` without the checks (inside the simulation loop)."""
    u = torch.rand(probs.shape[:-1], generator=generator, dtype=probs.dtype, device=probs.device)
    cdf = probs.cumsum(-1)
    return (u.unsqueeze(-1) >= cdf).sum(-1).clamp_max(probs.shape[-1] - 1)


@entry_point(transition=Stochastic(check=False), steps=Int(1), batch_shape=Shape(),
             initial_probs=Finite(optional=True, check=False), generator=Gen())
def simulate_modes(
    transition,
    steps: int,
    batch_shape=(),
    *,
    initial_probs=None,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Markov chain paths ``r_1 .. r_T`` for every batch element.

    Args:
        transition: ``(M, M)`` row-stochastic matrix.
        steps: ``T >= 1``.
        batch_shape: ``*B``, e.g. ``(mc_runs,)``.
        initial_probs: distribution of ``r_0``, ``(M,)`` (or ``(*B, M)``), default uniform.
        generator: the only source of randomness.

    Returns:
        ``(modes (T, *B), initial_mode (*B,))``
    """
    transition = validate_transition(transition)
    if transition.dim() != 2:
        raise ValueError(f"transition: expected one (M, M) matrix, got shape {tuple(transition.shape)}")
    M = transition.shape[-1]
    if initial_probs is None:
        initial_probs = torch.full((M,), 1.0 / M, dtype=transition.dtype, device=transition.device)
    else:
        initial_probs = check_probabilities(initial_probs, "initial_probs", M, dtype=transition.dtype,
                                            device=transition.device)
    try:
        start = initial_probs.expand(*batch_shape, M)
    except RuntimeError:
        raise ValueError(f"initial_probs: shape {tuple(initial_probs.shape)} does not broadcast to the batch "
                         f"{tuple(batch_shape)}") from None
    mode = _sample_categorical(start, generator)
    initial_mode = mode
    modes = []
    for _ in range(steps):
        mode = _sample_categorical(transition[mode], generator)
        modes.append(mode)
    return torch.stack(modes), initial_mode


def _gather_mode(values: Tensor, modes: Tensor, event: int) -> Tensor:
    """Pick the active mode per batch element.

    ``values`` has a mode axis (size ``M``, or 1 for a shared model, or absent) just left of its
    ``event`` dims and leading dims broadcastable to ``modes.shape``.

    Shapes:
        values: ``([*B,] [M,] *event)``, modes: ``(*B,)`` -> ``(*B, *event)``
    """
    if values.dim() < event + 1:
        values = values.unsqueeze(0)
    event_shape = values.shape[values.dim() - event :]
    values = values.expand(*modes.shape, values.shape[-1 - event], *event_shape)
    if values.shape[-1 - event] == 1:
        return values.squeeze(-1 - event)
    index = modes.reshape(*modes.shape, 1, *([1] * event)).expand(*modes.shape, 1, *event_shape)
    return torch.take_along_dim(values, index, dim=-1 - event).squeeze(-1 - event)


def _motion_models(motion, M: int, initial: GaussianBelief) -> list[MotionModel] | MotionModel:
    """Check ``motion`` (a bank, or one model per mode) against the transition and the initial belief."""
    models = list(motion) if isinstance(motion, (list, tuple, nn.ModuleList)) else None
    for j, m in enumerate(models if models is not None else [motion]):
        label = "motion" if models is None else f"motion[{j}]"
        if not isinstance(m, MotionModel):
            raise TypeError(f"{label}: expected a MotionModel, got {type(m).__name__}")
        if m.state_dim != initial.state_dim:
            raise ValueError(f"{label}: state_dim {m.state_dim} does not match the initial belief's "
                             f"{initial.state_dim}")
        for name, tensor in (*m.named_parameters(), *m.named_buffers()):
            if tensor.is_floating_point() and tensor.dtype != initial.dtype:
                raise TypeError(f"initial: dtype {initial.dtype} differs from the motion model's "
                                f"{tensor.dtype} ({label}.{name}); convert one of them")
    if models is not None and len(models) != M:
        raise ValueError(f"motion: {len(models)} models for the {M} modes of the transition matrix")
    if models is None:
        shape = getattr(motion, "param_batch_shape", None)
        if shape is not None and len(shape):
            _check_mode_axis(shape[-1], M, f"parameter batch {tuple(shape)}")
    return models if models is not None else motion


def _check_mode_axis(size: int, M: int, what: str) -> None:
    """A model's mode axis (``size``: 1 for a shared model) against the transition's ``M`` modes (its declared
    parameter batch's, or, for a model that declares none, its output's)."""
    if size not in (1, M):
        raise ValueError(f"transition: {M} modes, but motion is a bank of {size} modes ({what}); give a "
                         f"({size}, {size}) transition")


def _all_modes(motion, x: Tensor) -> tuple[Tensor, Tensor]:
    """Every mode's propagated state ``(*B, M, n)`` and noise factor ``(*B, M, n, n)`` (or a shared
    mode axis of size 1) at ``x (*B, n)``."""
    if isinstance(motion, list):
        n = x.shape[-1]
        mean = torch.stack([m(x).expand(x.shape) for m in motion], -2)
        scale = torch.stack([psd_sqrt(m.noise_cov(x)).expand(*x.shape[:-1], n, n) for m in motion], -3)
        return mean, scale
    return motion(x.unsqueeze(-2)), psd_sqrt(motion.noise_cov(x.unsqueeze(-2)))


@entry_point(motion=Of((MotionModel, list, tuple, nn.ModuleList),
                       what="a MotionModel (a mode bank) or a sequence of one MotionModel per mode"),
             transition=Stochastic(check=False), initial=BeliefArg(validate=True), steps=Int(1),
             batch_shape=Shape(), initial_mode_probs=Finite(optional=True, check=False), generator=Gen())
def simulate_jump_system(
    motion: MotionModel,
    transition,
    initial: GaussianBelief,
    steps: int,
    batch_shape=(),
    *,
    initial_mode_probs=None,
    generator: torch.Generator | None = None,
) -> JumpSimulation:
    """Simulate ``steps`` transitions of a Markov-jump system for a batch of runs.

    Args:
        motion: a motion model whose parameters form a mode bank (batch ``(M,)``, or shared),
            evaluated for all modes at once, or a list (tuple) of ``M`` single-mode motion models
            of the same state (e.g. ``[ConstantVelocity(1), CoordinatedTurn(...)]``, as for an
            IMM), each evaluated every step; the active mode is picked per run.
        transition: ``(M, M)`` row-stochastic matrix.
        initial: distribution of ``x_0`` (a :class:`GaussianBelief`, batch ``()`` or ``(*B,)``;
            its dtype is the simulation's and must be the motion model's).
        steps: ``T >= 1``.
        batch_shape: ``*B``, e.g. ``(mc_runs,)``.
        initial_mode_probs: distribution of ``r_0``, default uniform.
        generator: the only source of randomness.

    Returns:
        :class:`JumpSimulation`.

    Raises:
        ValueError: naming ``transition`` if its ``M`` is not the bank's number of modes (a bank's
            parameter batch, or its outputs' mode axis, must be ``M`` or 1: shared), ``motion`` for a
            list of another length, ``initial`` if its batch does not broadcast to ``batch_shape``.
    """
    if not isinstance(initial, GaussianBelief):
        raise TypeError(f"initial: expected a GaussianBelief, got {type(initial).__name__}")
    transition = validate_transition(transition)
    if transition.dim() != 2:
        raise ValueError(f"transition: expected one (M, M) matrix, got shape {tuple(transition.shape)}")
    motion = _motion_models(motion, transition.shape[-1], initial)
    if initial_mode_probs is not None:
        M = transition.shape[-1]
        initial_mode_probs = check_probabilities(initial_mode_probs, "initial_mode_probs", M,
                                                 dtype=transition.dtype, device=transition.device)
    modes, initial_mode = simulate_modes.__wrapped__(
        transition, steps, batch_shape, initial_probs=initial_mode_probs, generator=generator
    )
    dtype, device = initial.dtype, initial.device
    n = initial.state_dim
    try:
        fits = torch.broadcast_shapes(initial.batch_shape, tuple(batch_shape)) == tuple(batch_shape)
    except RuntimeError:
        fits = False
    if not fits:
        raise ValueError(f"initial: batch {tuple(initial.batch_shape)} does not broadcast to batch_shape "
                         f"{tuple(batch_shape)}")
    noise = torch.randn(*batch_shape, n, generator=generator, dtype=dtype, device=device)
    x = initial.mean + (psd_sqrt(initial.cov) @ noise.unsqueeze(-1)).squeeze(-1)
    x = x.expand(*batch_shape, n)
    initial_state = x
    states = []
    for k in range(steps):
        mode = modes[k]
        means, scales = _all_modes(motion, x)
        if k == 0 and not isinstance(motion, list):  # (shapes only: no value is read)
            M, noise_modes = transition.shape[-1], scales.shape[-3] if scales.dim() >= 3 else 1
            _check_mode_axis(means.shape[-2], M, f"its state has a mode axis of {means.shape[-2]}")
            _check_mode_axis(noise_modes, M, f"its noise covariance has a mode axis of {noise_modes}")
        propagated = _gather_mode(means, mode, event=1)
        scale = _gather_mode(scales, mode, event=2)
        eps = torch.randn(*batch_shape, n, generator=generator, dtype=dtype, device=device)
        x = propagated + (scale @ eps.unsqueeze(-1)).squeeze(-1)
        states.append(x)
    return JumpSimulation(torch.stack(states), modes, initial_state, initial_mode)


@entry_point(measurement=Of(MeasurementModel), states=Finite(), modes=Labels(optional=True),
             available=Mask(optional=True), generator=Gen())
def simulate_measurements(
    measurement: MeasurementModel,
    states: Tensor,
    *,
    modes: Tensor | None = None,
    available: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Noisy measurements of a state sequence; NaN where ``available`` is false.

    Args:
        measurement: the sensor model. With ``modes`` given it is treated as a mode bank
            (parameters with batch ``(M,)``) and the mode in force is used per run and step.
        states: ``(T, *B, n)``.
        modes: ``(T, *B)`` mode indices, for mode-dependent sensors.
        available: ``(T, *B)`` bool; False entries become NaN (missing, e.g. slow-rate sensors).
        generator: the only source of randomness.

    Returns:
        ``(T, *B, m)`` measurements.

    Raises:
        ValueError: naming ``modes`` if an index is not a mode of the sensor bank (a shared sensor takes
            any), ``measurement`` if its parameter batch does not broadcast to ``(T, *B)`` without
            ``modes`` (a bank of sensors needs them).
    """
    if states.dim() < 1 or states.shape[-1] != measurement.state_dim:
        raise ValueError(f"states: expected shape (T, *B, {measurement.state_dim}) for the sensor's state, "
                         f"got {tuple(states.shape)}")
    if modes is not None and modes.shape != states.shape[:-1]:
        raise ValueError(f"modes: expected shape {tuple(states.shape[:-1])}, got {tuple(modes.shape)}")
    return _simulate_measurements(measurement, states, modes=modes, available=available, generator=generator)


def _sensor_outputs(measurement, x: Tensor, name: str, *, bank: bool = False) -> tuple[Tensor, Tensor]:
    """``h(x)`` and ``R`` at ``x (*L, n)``; a ValueError naming ``name`` where the sensor's parameters
    do not broadcast to ``*L`` (``bank``: a mode axis of any size may replace the last axis of ``*L``,
    which is 1)."""
    lead = tuple(x.shape[:-1])
    tensors = module_tensors(measurement) if isinstance(measurement, nn.Module) else []
    other = next(((key, t.dtype) for key, t in tensors if t.is_floating_point() and t.dtype != x.dtype), None)
    if other is not None:  # (a RuntimeError below would read as a batch mismatch)
        raise TypeError(f"{name}: the sensor's {other[0]} is {other[1]}, the states {x.dtype}; build both in "
                        f"one dtype (e.g. sensor.to({x.dtype}))")
    try:
        predicted, cov = measurement(x), measurement.noise_cov(x)
        out = tuple(predicted.shape[:-1])
        fits = out[: len(out) - bank] == lead[: len(lead) - bank] and len(out) == len(lead)
        fits = fits and torch.broadcast_shapes(tuple(cov.shape[:-2]), out) == out
    except RuntimeError:
        fits = False
    if not fits:
        shape = getattr(measurement, "param_batch_shape", None)
        what = f"parameter batch {tuple(shape)}" if shape is not None else "parameters"
        hint = " (a bank of sensors needs modes=)" if name == "measurement" and not bank else ""
        raise ValueError(f"{name}: the sensor's {what} do not broadcast to the states' batch "
                         f"{lead[: len(lead) - bank]}{hint}")
    return predicted, cov


def _simulate_measurements(measurement, states, *, modes=None, available=None, generator=None,
                           name: str = "measurement") -> Tensor:
    if modes is None:
        predicted, cov = _sensor_outputs(measurement, states, name)
    else:
        predicted, cov = _sensor_outputs(measurement, states.unsqueeze(-2), name, bank=True)
        size = max(predicted.shape[-2], cov.shape[-3] if cov.dim() >= 3 else 1)  # (1: a shared sensor)
        if size > 1 and modes.numel() and int(modes.max()) >= size:
            raise ValueError(f"modes: mode {int(modes.max())} out of range for a bank of {size} sensors "
                             f"({name})")
        predicted = _gather_mode(predicted, modes, event=1)
        cov = _gather_mode(cov, modes, event=2)
    eps = torch.randn(predicted.shape, generator=generator, dtype=predicted.dtype, device=predicted.device)
    z = predicted + (psd_sqrt(cov) @ eps.unsqueeze(-1)).squeeze(-1)
    if available is not None:
        if available.shape != z.shape[:-1]:
            raise ValueError(f"available: expected shape {tuple(z.shape[:-1])}, got {tuple(available.shape)}")
        z = torch.where(available.unsqueeze(-1), z, torch.nan)
    return z


@entry_point(steps=Int(0), batch_shape=Shape(), probability=Real(0.0, 1.0), generator=Gen(), device=Device(),
             dtype=DType())
def bernoulli_mask(steps: int, batch_shape, probability: float, *, generator=None, device=None,
                   dtype: torch.dtype = torch.float64) -> Tensor:
    """``(T, *B)`` bool mask, each entry true with ``probability`` (irregular slow-rate data).

    The uniforms are drawn in ``dtype`` (float64 by default, not the process's default dtype), so
    the mask and every later draw from ``generator`` do not depend on ``torch.get_default_dtype()``.
    """
    u = torch.rand(steps, *batch_shape, generator=generator, device=device, dtype=dtype)
    return u < probability


@entry_point(steps=Int(0), batch_shape=Shape(), period=Int(1), offset=Int(), device=Device())
def periodic_mask(steps: int, batch_shape, period: int, *, offset: int = 0, device=None) -> Tensor:
    """``(T, *B)`` bool mask true at steps ``k`` (1-based) with ``(k - offset) % period == 0``."""
    k = torch.arange(1, steps + 1, device=device)
    mask = (k - offset) % period == 0
    return mask.reshape(steps, *([1] * len(batch_shape))).expand(steps, *batch_shape)


@entry_point(target=Of(MeasurementModel), source=Of(MeasurementModel), states=Finite(),
             probability=Real(0.0, 1.0, optional=True), period=Int(1, optional=True), offset=Int(),
             generator=Gen())
def simulate_multirate(
    target: MeasurementModel,
    source: MeasurementModel,
    states: Tensor,
    *,
    probability: float | None = None,
    period: int | None = None,
    offset: int = 0,
    generator: torch.Generator | None = None,
):
    """Fast target data every step and slow, irregular source data (paper 000, (2)-(3)).

    The source is present with ``probability`` per run and step (``gamma_k ~ Bernoulli``) or every
    ``period`` steps (exactly one of the two); it is NaN elsewhere. The target stream is drawn
    first, then the availability mask, then the source noise, from the one ``generator``.

    Args:
        target: the fast sensor (noise ``R``); source: the slow sensor (noise ``R_S``).
        states: ``(T, *B, n)``, e.g. ``simulate_jump_system(...).states``.

    Returns:
        :class:`~torchmm.multimodel.MultiRate` with ``target (T, *B, m)`` and ``source
        (T, *B, m_S)``.

    Examples:
        >>> from torchmm.models import PositionMeasurement
        >>> z = simulate_multirate(PositionMeasurement(2, [0], 100.0), PositionMeasurement(2, [0], 10.0),
        ...                        torch.zeros(50, 8, 2), probability=0.6, generator=torch.Generator().manual_seed(0))
        >>> z.target.shape, z.source.shape, bool(z.source.isnan().any())
        (torch.Size([50, 8, 1]), torch.Size([50, 8, 1]), True)
    """

    if (probability is None) == (period is None):
        raise ValueError("probability, period: give exactly one of them")
    if states.dim() < 2:
        raise ValueError(f"states: expected shape (T, *B, n), got {tuple(states.shape)}")
    for name, sensor in (("target", target), ("source", source)):
        if states.shape[-1] != sensor.state_dim:
            raise ValueError(f"{name}: state_dim {sensor.state_dim} does not match the states' "
                             f"{states.shape[-1]}")
    steps, batch = states.shape[0], states.shape[1:-1]
    y = _simulate_measurements(target, states, generator=generator, name="target")
    if probability is not None:
        mask = bernoulli_mask.__wrapped__(steps, batch, probability, generator=generator,
                                          device=states.device)
    else:
        mask = periodic_mask.__wrapped__(steps, batch, period, offset=offset, device=states.device)
    return MultiRate(y, _simulate_measurements(source, states, available=mask, generator=generator,
                                               name="source"))

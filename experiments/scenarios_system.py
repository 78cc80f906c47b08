"""The generic study's system (split from :mod:`experiments.scenarios` by concern, issue 47; ``system`` is
re-exported there, the config's ``_target_: experiments.scenarios.system``): any modes, any sensors,
simulated or recorded data (:func:`read_data`), per-step motions for uneven time stamps."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmm import GaussianBelief, LinearMotion, MeasurementModel, validate_transition
from torchmm.fusion.augmented import block_diagonal2
from torchmm.simulate import (
    JumpSimulation,
    bernoulli_mask,
    periodic_mask,
    simulate_jump_system,
    simulate_measurements,
)

__all__ = ["Concatenated", "SystemScenario", "build_node", "copy_motion", "default_dtype", "is_list_node",
           "per_step_motions", "read_data", "stationary_probs", "system"]


# -- the generic study's system: any modes, any sensors, simulated or recorded data ------------------
class Concatenated(MeasurementModel):
    """Several sensors of one state as one measurement ``z = [h_1(x); h_2(x); ...]`` with block-diagonal
    noise (independent sensors). A sensor that did not report leaves its components NaN (missing), which
    every torchmm filter skips component by component: a multi-rate, multi-sensor stream in one tensor.
    """

    def __init__(self, sensors: Sequence[MeasurementModel]):
        super().__init__()
        self.sensors = torch.nn.ModuleList(sensors)
        self.state_dim = sensors[0].state_dim
        self.meas_dim = sum(int(s.meas_dim) for s in sensors)
        self.param_batch_shape = torch.Size(())

    def forward(self, x: Tensor) -> Tensor:
        return torch.cat([s(x) for s in self.sensors], -1)

    def noise_cov(self, x: Tensor | None = None) -> Tensor:
        return functools.reduce(block_diagonal2, [s.noise_cov(x) for s in self.sensors])

    def jacobian(self, x: Tensor) -> Tensor:
        return torch.cat([s.jacobian(x) for s in self.sensors], -2)


@contextmanager
def default_dtype(dtype: torch.dtype):
    """``torch``'s default dtype set to ``dtype`` inside the ``with`` block (restored after)."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(previous)


def build_node(node, key: str, dtype, device, **extra):
    """A config node (``_target_``) as a model in ``dtype`` on ``device``; a ``ConfigError`` naming ``key``
    if it cannot be built."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    from experiments.config import ConfigError

    try:
        with default_dtype(dtype):
            built = instantiate(node, **extra)
    except InstantiationException as err:
        cause = err.__cause__ or err
        raise ConfigError(key, dict(node) if hasattr(node, "items") else node,
                          f"cannot be built: {str(cause).splitlines()[0]}") from None
    if isinstance(built, torch.nn.Module):
        built = built.to(device=device, dtype=dtype)
    return built


@dataclass
class SystemScenario:
    """The generic study's scenario (:func:`system`): a Markov-jump system of any modes and sensors, and
    either a simulator or recorded data. Duck-type compatible with :class:`JumpScenario` for the
    estimator builders (``motion``, ``measurement``, ``transition``, ``initial``, ``initial_mode_probs``).

    ``motion`` is one mode-bank model or a list of single-mode models (one per mode);
    ``measurement`` the sensor (several sensors: :class:`Concatenated`); ``groups`` the state components
    each RMSE is taken over; ``data`` the recorded data (None: simulated); ``motions`` per-step motion
    models where recorded time stamps are irregular (None: the models' own ``dt``).
    """

    name: str
    motion: Any
    measurement: MeasurementModel
    transition: Tensor
    initial: GaussianBelief
    steps: int
    initial_mode_probs: Tensor | None
    mode_labels: list[str]
    groups: dict[str, list[int]]
    sensor_dims: list[int]
    missing: list[float]
    every: list[int]
    data: Any = None
    motions: list | None = None
    #: ``initial_mode_probs: ergodic``: the start's mode probabilities are the transition matrix's
    #: stationary ones (estimating the matrix re-derives them at every evaluation)
    ergodic: bool = False
    #: the ``learn.parameters`` of ``learn.parameters: auto`` (a builder that knows what it estimates:
    #: :func:`markov_switching`), or None
    learn_parameters: list | None = None

    @property
    def num_modes(self) -> int:
        count = getattr(self.transition, "num_modes", None)  # (a time-varying transition module)
        return int(count) if count is not None else self.transition.shape[-1]

    @property
    def mode_sensors(self) -> bool:
        """One sensor per mode (``measurement`` is their list): mode-dependent measurements."""
        return isinstance(self.measurement, list)

    @property
    def position(self) -> list[int]:
        return next(iter(self.groups.values()))

    @property
    def velocity(self) -> list[int]:
        values = list(self.groups.values())
        return values[1] if len(values) > 1 else values[0]

    @property
    def simulated(self) -> bool:
        return self.data is None

    def simulate(self, runs: int, generator: torch.Generator) -> tuple[JumpSimulation, Tensor]:
        """Truth and measurements of ``runs`` runs: ``(T, runs, n)``, ``(T, runs, m)``; each sensor's
        components are NaN where it did not report (every ``every``-th step, then missing with
        probability ``missing``)."""
        sim = simulate_jump_system(self.motion, self.transition, self.initial, self.steps, (runs,),
                                   initial_mode_probs=self.initial_mode_probs, generator=generator)
        if self.mode_sensors:  # each mode's sensor, then the one in force per run and step
            every = torch.stack([simulate_measurements(s, sim.states, generator=generator) for s in self.measurement])
            index = sim.modes[None, ..., None].expand(1, *every.shape[1:])
            z = every.gather(0, index)[0]
        else:
            z = simulate_measurements(self.measurement, sim.states, generator=generator)
        start = 0
        for dim, p, period in zip(self.sensor_dims, self.missing, self.every):
            keep = periodic_mask(self.steps, (runs,), int(period), device=z.device)
            if p > 0:
                keep = keep & ~bernoulli_mask(self.steps, (runs,), float(p), generator=generator, device=z.device)
            z[..., start:start + dim] = torch.where(keep.unsqueeze(-1), z[..., start:start + dim], torch.nan)
            start += dim
        return sim, z


def system(
    *,
    name: str = "system",
    modes: Any,
    sensors: Any,
    transition: Sequence[Sequence[float]] | None = None,
    initial_mean: Sequence[float],
    initial_cov: Sequence[Sequence[float]],
    initial_mode_probs: Sequence[float] | None = None,
    labels: Sequence[str] | None = None,
    groups: dict | None = None,
    steps: int = 100,
    missing: Any = 0.0,
    every: Any = 1,
    data: Any = None,
    mode_sensors: bool = False,
    dt_key: str = "dt",
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> SystemScenario:
    """The generic study's scenario from config nodes (``conf/experiment/compare.yaml``).

    Args:
        modes: a list of motion-model nodes (one per mode: linear, nonlinear or a learned
            ``nn.Module``, each by ``_target_``), or one mode-bank node.
        sensors: a sensor node or a list of them (concatenated: :class:`Concatenated`).
        transition: ``(M, M)`` row-stochastic; default ``[[1]]`` for one mode.
        initial_mean, initial_cov: the prior of ``x_0``; ``initial_mode_probs`` of ``r_0`` (default uniform).
        labels: mode names (default the models' class names); groups: ``{name: [state components]}``
            scored by RMSE (default one group of all components).
        steps, missing, every: simulated data: ``T``; per sensor (or one value for all) the probability
            that a report is missing and the reporting period in steps (multi-rate).
        data: recorded data instead (``{path, measurements, truth, time, series}``, :func:`experiments.datafile.read_series`).
        mode_sensors: ``sensors`` lists one sensor per mode (mode-dependent measurements, e.g. a
            Markov-switching mean and variance) instead of sensors to stack.
        initial_mode_probs: a list, or ``ergodic`` (the transition matrix's stationary distribution).
        dt_key: the keyword of the mode nodes that irregular time stamps set per step.
    """
    from experiments.config import ConfigError

    mode_nodes = list(modes) if is_list_node(modes) else None
    if mode_nodes is not None and not mode_nodes:
        raise ConfigError("scenario.modes", [], "needs at least one mode")
    if mode_nodes is not None:
        motion = [build_node(node, f"scenario.modes[{i}]", dtype, device) for i, node in enumerate(mode_nodes)]
        motion = motion if len(motion) > 1 else motion[0]
        count = len(mode_nodes)
    else:
        motion = build_node(modes, "scenario.modes", dtype, device)
        batch = tuple(getattr(motion, "param_batch_shape", ()) or ())
        count = batch[0] if batch else 1
    sensor_nodes = list(sensors) if is_list_node(sensors) else [sensors]
    built = [build_node(node, f"scenario.sensors[{i}]" if is_list_node(sensors) else "scenario.sensors", dtype, device)
             for i, node in enumerate(sensor_nodes)]
    sensors_built = list(built)  # (mode_sensors keeps the first below; each is checked against the prior)
    if mode_sensors:
        if len(built) != count or len({int(s.meas_dim) for s in built}) != 1:
            raise ConfigError("scenario.sensors", len(built), f"mode_sensors: needs one sensor per mode ({count}), "
                              "all of one measurement size")
        sensor = [s.to(device) for s in built]
        dims = [int(built[0].meas_dim)]
        built = built[:1]
    else:
        sensor = built[0] if len(built) == 1 else Concatenated(built)
        dims = [int(s.meas_dim) for s in built]
    if transition is None:
        if count != 1:
            raise ConfigError("scenario.transition", None, f"needed for {count} modes")
        transition = [[1.0]]
    try:
        matrix = validate_transition(torch.tensor([list(r) for r in transition], dtype=dtype), "transition")
    except ValueError as err:
        raise ConfigError("scenario.transition", transition, str(err).split(": ", 1)[-1]) from None
    if matrix.shape[-1] != count:
        raise ConfigError("scenario.transition", transition, f"is {matrix.shape[-1]}x{matrix.shape[-1]} for {count} modes")
    try:
        initial = GaussianBelief.create(list(initial_mean), [list(r) for r in initial_cov], dtype=dtype)
    except ValueError as err:
        raise ConfigError("scenario.initial_cov", initial_cov, str(err)) from None
    n = initial.state_dim
    motions = motion if isinstance(motion, list) else [motion]
    first = getattr(motions[0], "state_dim", n)
    if first not in (None, n):
        raise ConfigError("scenario.initial_mean", list(initial_mean),
                          f"has {n} components; the models' state has {first}")
    for i, m in enumerate(motions[1:], 1):  # each model, each sensor by its own key (the prior fits mode 0)
        if getattr(m, "state_dim", n) not in (None, n):
            raise ConfigError(f"scenario.modes[{i}]", mode_nodes[i].get("_target_"),
                              f"has a {m.state_dim}-component state; mode 0's model and "
                              f"scenario.initial_mean have {n}")
    for i, s in enumerate(sensors_built):
        if getattr(s, "state_dim", n) not in (None, n):
            key = f"scenario.sensors[{i}]" if is_list_node(sensors) else "scenario.sensors"
            own = "state_dim" in sensor_nodes[i]
            raise ConfigError(f"{key}.state_dim" if own else key,
                              s.state_dim if own else sensor_nodes[i].get("_target_"),
                              f"the sensor measures a {s.state_dim}-component state; the models' state and "
                              f"scenario.initial_mean have {n}")
    labels = list(labels) if labels else (
        [type(m).__name__ for m in motion] if isinstance(motion, list) else [f"mode {j}" for j in range(count)])
    if len(labels) != count:
        raise ConfigError("scenario.labels", labels, f"needs one name per mode ({count})")
    if len(set(map(str, labels))) != len(labels):
        raise ConfigError("scenario.labels", labels, "the modes' names must differ (each names a mode's curves)")
    groups = {str(k): [int(i) for i in v] for k, v in (groups or {"state": list(range(n))}).items()}
    for key, idx in groups.items():
        if not idx or any(not 0 <= i < n for i in idx):
            raise ConfigError(f"scenario.groups.{key}", idx, f"must list state components in 0..{n - 1}")
        if len(set(idx)) != len(idx):
            raise ConfigError(f"scenario.groups.{key}", idx, "lists a state component twice")
    per_sensor = []
    def number(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    for key, value, check in (("missing", missing, lambda p: number(p) and 0 <= p < 1),
                              ("every", every, lambda k: number(k) and k >= 1 and float(k).is_integer())):
        values = list(value) if is_list_node(value) else [value] * len(built)
        if len(values) != len(built) or not all(check(v) for v in values):
            raise ConfigError(f"scenario.{key}", value, "one value per sensor, "
                              + ("probabilities in [0, 1)" if key == "missing" else "integer periods >= 1"))
        per_sensor.append(values)
    if isinstance(initial_mode_probs, str):
        if initial_mode_probs != "ergodic":
            raise ConfigError("scenario.initial_mode_probs", initial_mode_probs, "a list of probabilities or ergodic")
        probs = stationary_probs(matrix)
    else:
        probs = None if initial_mode_probs is None else torch.tensor(list(initial_mode_probs), dtype=dtype)
        if probs is not None and (probs.shape != (count,) or bool((probs < 0).any())
                                  or abs(float(probs.sum()) - 1) > 1e-6):
            raise ConfigError("scenario.initial_mode_probs", list(initial_mode_probs),
                              f"expected {count} probabilities (one per mode) summing to 1")
    recorded, motions = None, None
    if data is not None:
        recorded = read_data(data, n, sum(dims))
        steps = recorded.steps
        if recorded.times is not None:
            regular, motions = per_step_motions(mode_nodes if mode_nodes is not None else modes, recorded.times,
                                                 dt_key, dtype, device)
            motion = regular if regular is not None else motion
    return SystemScenario(
        name=name, motion=motion, measurement=sensor if isinstance(sensor, list) else sensor.to(device),
        transition=matrix.to(device),
        initial=initial.to(device), steps=int(steps), initial_mode_probs=None if probs is None else probs.to(device),
        mode_labels=labels, groups=groups, sensor_dims=dims, missing=[float(p) for p in per_sensor[0]],
        every=[int(k) for k in per_sensor[1]], data=recorded, motions=motions,
        ergodic=isinstance(initial_mode_probs, str))


def read_data(data: Any, n: int, m: int):
    """The recorded data of ``scenario.data`` for a state of ``n`` and a sensor of ``m`` components
    (:func:`experiments.datafile.read_series`), with the config's errors named by key.

    ``truth`` lists one column per state component, ``null`` for a component the file does not hold
    (e.g. ``[px, null, py, null]``: position-only truth); such a component, or a column with no finite
    cell, has no truth (NaN) and the metrics that need it are dropped and named (``compare``)."""
    from experiments.config import ConfigError
    from experiments.datafile import DataFileError, read_series

    truth = list(data["truth"]) if data.get("truth") else None
    if truth is not None and len(truth) != n:
        raise ConfigError("scenario.data.truth", truth, f"{len(truth)} columns for a state of {n} (one column per "
                          "state component, null for one the file does not hold)")
    columns = None if truth is None else [c for c in truth if c is not None]
    try:
        recorded = read_series(data["path"], measurements=list(data["measurements"]), truth=columns or None,
                               time=data.get("time"), series=data.get("series"),
                               inputs=list(data["inputs"]) if data.get("inputs") else None)
    except DataFileError as err:  # one line naming the file, the column and the row
        raise ConfigError("scenario.data", data["path"], str(err)) from None
    except (TypeError, ValueError) as err:  # an argument of the reader: `measurements[1]: ...` and the like
        name, _, why = str(err).partition(": ")
        key = name.split("[", 1)[0]
        raise ConfigError(f"scenario.data.{key}", data.get(key), f"{name}: {why}" if "[" in name else why) from None
    if recorded.measurements.shape[-1] != m:
        raise ConfigError("scenario.data.measurements", list(data["measurements"]),
                          f"{recorded.measurements.shape[-1]} columns for a sensor of {m}")
    if not np.isfinite(recorded.measurements).any():
        raise ConfigError("scenario.data.measurements", list(data["measurements"]),
                          f"{data['path']}: every measurement cell is missing (nothing to filter)")
    if truth is not None:
        full = np.full(recorded.measurements.shape[:2] + (n,), np.nan)
        if columns:
            full[..., [i for i, c in enumerate(truth) if c is not None]] = recorded.truth
        recorded.truth = full if np.isfinite(full).any() else None
    return recorded


def copy_motion(motion: LinearMotion) -> LinearMotion:
    """An independent copy of a linear motion model (each regime its own)."""
    return LinearMotion(motion.F.clone(), motion.Q.clone(),
                        input_matrix=None if motion.input_matrix is None else motion.input_matrix.clone())


def stationary_probs(matrix: Tensor) -> Tensor:
    """The stationary distribution ``pi = pi P`` of a row-stochastic ``(M, M)`` matrix (solved exactly)."""
    M = matrix.shape[-1]
    A = torch.cat([(matrix.T - torch.eye(M, dtype=matrix.dtype))[:-1], torch.ones(1, M, dtype=matrix.dtype)])
    b = torch.zeros(M, dtype=matrix.dtype)
    b[-1] = 1.0
    return torch.linalg.solve(A, b)


def is_list_node(value) -> bool:
    return isinstance(value, (list, tuple)) or type(value).__name__ == "ListConfig"


def per_step_motions(nodes, times, dt_key: str, dtype, device):
    """``(motion, motions)`` for the time stamps ``times (T,)``: with one step length (every stamp on the
    grid ``t_0 + k dt`` to :data:`experiments.datafile_io.GRID_TOLERANCE`), the models rebuilt with that
    ``dt`` and no per-step models; otherwise one motion model per step (step ``k`` covers
    ``t_k - t_{k-1}``), built once per distinct step length (:func:`experiments.datafile_io.step_lengths`).
    Step 0, the prediction from the prior to the first stamp, covers the first step's length
    ``t_1 - t_0`` in both cases (the prior one step before the first stamp), so that a series' numbers
    do not depend on whether another series makes the shared grid irregular; a single stamp keeps the
    nodes' own ``dt``."""
    from omegaconf import OmegaConf

    from experiments.datafile_io import step_lengths

    cache: dict[float, Any] = {}

    def models(dt: float):
        if dt not in cache:
            def one(node, key):
                return build_node(OmegaConf.merge(node, {dt_key: dt}), key, dtype, device)
            if is_list_node(nodes):
                built = [one(node, f"scenario.modes[{i}]") for i, node in enumerate(nodes)]
                cache[dt] = built if len(built) > 1 else built[0]
            else:
                cache[dt] = one(nodes, "scenario.modes")
        return cache[dt]

    dt, steps = step_lengths(times)
    if dt is not None or not len(steps):
        return (None if dt is None else models(dt)), None
    return None, [models(float(steps[0]))] + [models(float(d)) for d in steps]

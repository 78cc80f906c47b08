"""Scenario builders for studies (instantiated from ``conf/scenario/*.yaml``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from torchmm import (
    ConstantVelocity,
    CoordinatedTurn,
    GaussianBelief,
    LinearMotion,
    PositionMeasurement,
    validate_transition,
)
from torchmm.simulate import JumpSimulation, simulate_jump_system, simulate_measurements

__all__ = ["JumpScenario", "kinematic_1d", "stay_matrix", "turning_2d"]


@dataclass
class JumpScenario:
    """A Markov-jump linear scenario: mode bank, sensor, chain and initial state.

    ``position`` / ``velocity`` are the state components scored by the RMSE tables.
    """

    name: str
    motion: LinearMotion
    measurement: PositionMeasurement
    transition: Tensor
    initial: GaussianBelief
    steps: int
    initial_mode_probs: Tensor | None
    mode_labels: list[str]
    position: list[int]
    velocity: list[int]

    @property
    def num_modes(self) -> int:
        return self.transition.shape[-1]

    def simulate(self, runs: int, generator: torch.Generator) -> tuple[JumpSimulation, Tensor]:
        """Truth and measurements for ``runs`` Monte Carlo runs: ``(T, runs, n)``, ``(T, runs, m)``."""
        sim = simulate_jump_system(
            self.motion, self.transition, self.initial, self.steps, (runs,),
            initial_mode_probs=self.initial_mode_probs, generator=generator,
        )
        z = simulate_measurements(self.measurement, sim.states, generator=generator)
        return sim, z


def kinematic_1d(
    *,
    name: str,
    accelerations: Sequence[float],
    q: float,
    R: float,
    transition: Sequence[Sequence[float]],
    initial_mean: Sequence[float],
    initial_cov: Sequence[Sequence[float]],
    steps: int,
    dt: float = 1.0,
    noise: str = "discrete",
    initial_mode_probs: Sequence[float] | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> JumpScenario:
    """1-D target ``[p, v]`` whose acceleration jumps between ``accelerations`` (paper 000, eq. (37)).

    ``x_k = F x_{k-1} + G (a_{r_k} + w_k)``, ``w_k ~ N(0, q)``; ``y_k = p_k + v_k``,
    ``v_k ~ N(0, R)``.
    """
    acc = torch.tensor(list(accelerations), dtype=dtype).unsqueeze(-1)
    motion = ConstantVelocity(1, dt=dt, q=q, noise=noise, acceleration=acc, dtype=dtype)
    measurement = PositionMeasurement(2, [0], torch.tensor(R, dtype=dtype), dtype=dtype)
    matrix = validate_transition(torch.tensor(transition, dtype=dtype), f"scenario {name}: transition")
    if matrix.shape[-1] != acc.shape[0]:
        raise ValueError(
            f"scenario {name}: transition: {matrix.shape[-1]} modes but {acc.shape[0]} accelerations"
        )
    initial = GaussianBelief.create(initial_mean, initial_cov, dtype=dtype)
    probs = None if initial_mode_probs is None else torch.tensor(initial_mode_probs, dtype=dtype)
    return JumpScenario(
        name=name,
        motion=motion.to(device),
        measurement=measurement.to(device),
        transition=matrix.to(device),
        initial=initial.to(device),
        steps=int(steps),
        initial_mode_probs=None if probs is None else probs.to(device),
        mode_labels=[f"a={a:g}" for a in accelerations],
        position=[0],
        velocity=[1],
    )


def stay_matrix(stay: float, modes: int = 3, *, dtype=torch.float64, device="cpu") -> Tensor:
    """``(modes, modes)`` matrix with ``stay`` on the diagonal and ``(1 - stay) / (modes - 1)`` elsewhere."""
    off = (1 - stay) / (modes - 1)
    eye = torch.eye(modes, dtype=dtype, device=device)
    return torch.full((modes, modes), off, dtype=dtype, device=device) + (stay - off) * eye


def turning_2d(
    *,
    name: str = "turning_2d",
    turn_rate: float,
    q: float,
    R: float,
    stay: float,
    steps: int,
    initial_mean: Sequence[float],
    initial_std: Sequence[float],
    dt: float = 1.0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> JumpScenario:
    """2-D target ``[x, vx, y, vy]`` switching (Markov chain, ``stay`` on the diagonal) between
    constant velocity and coordinated turns at ``+turn_rate`` and ``-turn_rate`` rad/s;
    white-acceleration noise ``Q = q G G^T``, positions measured with noise ``R I``."""
    w = float(turn_rate)
    if not 0.0 < float(stay) <= 1.0:
        raise ValueError(f"scenario {name}: stay: must lie in (0, 1], got {stay}")
    motion = CoordinatedTurn(torch.tensor([0.0, w, -w], dtype=dtype), dt=float(dt), q=float(q), dtype=dtype)
    sensor = PositionMeasurement(4, [0, 2], torch.tensor(float(R), dtype=dtype), dtype=dtype)
    std = torch.tensor(list(initial_std), dtype=dtype)
    initial = GaussianBelief.create(list(initial_mean), torch.diag(std.square()), dtype=dtype)
    return JumpScenario(
        name=name, motion=motion.to(device), measurement=sensor.to(device),
        transition=stay_matrix(float(stay), 3, dtype=dtype).to(device), initial=initial.to(device), steps=int(steps),
        initial_mode_probs=None, mode_labels=["CV", f"CT(+{w:g})", f"CT(-{w:g})"],
        position=[0, 2], velocity=[1, 3],
    )

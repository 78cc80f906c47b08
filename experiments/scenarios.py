"""Scenario builders for studies (instantiated from ``conf/scenario/*.yaml``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
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

from experiments.scenarios_system import (
    Concatenated,
    SystemScenario,
    copy_motion,
    read_data,
    stationary_probs,
    system,
)

__all__ = ["Concatenated", "JumpScenario", "SystemScenario", "kinematic_1d", "stay_matrix", "system", "turning_2d"]


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


def markov_switching(
    *,
    name: str = "markov_switching",
    data: Any,
    k_regimes: int = 2,
    trend: str = "c",
    switching_trend: bool = True,
    switching_exog: bool = True,
    switching_variance: bool = True,
    transition: Sequence[Sequence[float]] | None = None,
    start: dict | None = None,
    labels: Sequence[str] | None = None,
    tvtp: Sequence[str] | None = None,
    tvtp_constant: bool = True,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> SystemScenario:
    r"""A Markov-switching regression from one's own data, as statsmodels' ``MarkovRegression``:
    ``y_t = c_{s_t} + x_t^T beta_{s_t} + e_t``, ``e_t ~ N(0, sigma2_{s_t})``, ``s_t`` a Markov chain of
    ``k_regimes`` (docs/studies.md, "Estimating a Markov-switching model").

    Written as an IMM over the exactly known state ``(1, x_t)`` (covariance 0, ``Q = 0``): the first
    component is constant (``F = diag(1, 0, ..)``), the others are the inputs (``input_matrix``
    ``[0; I]``: ``x_t = u_t``, the data's ``inputs`` columns), and regime ``s`` measures it with
    ``H_s = (c_s, beta_s)``, ``R_s = sigma2_s``: every Kalman gain is 0, the mixing has no spread, so
    the IMM is Hamilton's filter and Kim's smoother is Kim's.

    Args:
        data: the data node (``{path, measurements: [y], inputs: [x1, ...] or null, series, time}``).
        k_regimes: the number of regimes.
        trend: ``"c"`` a constant (intercept) or ``"n"`` none.
        switching_trend, switching_exog, switching_variance: whether the constant, the regressors'
            coefficients and the variance differ between the regimes (statsmodels' ``switching_trend``,
            ``switching_exog``, ``switching_variance``); non-switching ones are one value shared by every
            regime when estimated (``learn.parameters: auto``).
        transition: the start of the transition matrix (rows = from); default every entry ``1/k``.
        start: start values ``{const: [...], exog: [[...] per regime], variance: [...]}``; default
            statsmodels' ``start_params``: the regression by least squares, regime ``i``'s coefficients
            ``i / k`` of it, the variances ``linspace(var / 10, var, k)`` of its residual variance.
        labels: the regimes' names (default ``regime 0``, ...).
        tvtp: columns of the data whose values drive time-varying transition probabilities (statsmodels'
            ``exog_tvtp``): :class:`~torchmm.LogisticTransition` over them (with a constant when
            ``tvtp_constant``), started at 0 (every row ``1/k``, statsmodels' start); then ``transition``
            must be null, and the start's regime probabilities are the first step's matrix's ergodic ones.

    The scenario's ``learn_parameters`` (``learn.parameters: auto``) estimate the transition matrix, every
    coefficient and the variances, shared as the switching flags say; the start's mode probabilities are
    the transition matrix's ergodic ones (statsmodels' default).
    """
    from experiments.config import ConfigError

    if data is None:
        raise ConfigError("scenario.data", None, "a Markov-switching regression is estimated from data: give "
                          "{path, measurements: [y], inputs: [...] or null}")
    if trend not in ("c", "n"):
        raise ConfigError("scenario.trend", trend, "expected c (a constant) or n (none)")
    if int(k_regimes) < 2:
        raise ConfigError("scenario.k_regimes", k_regimes, "needs at least 2 regimes")
    K = int(k_regimes)
    if labels is not None and len(list(labels)) != K:  # (before: regimes past the names lost their curves)
        raise ConfigError("scenario.labels", list(labels),
                          f"needs one name per regime ({K}: scenario.k_regimes)")
    if labels is not None and len(set(map(str, labels))) != K:
        raise ConfigError("scenario.labels", list(labels),
                          "the regimes' names must differ (each names a regime's curves)")
    if len(list(data["measurements"])) != 1:
        raise ConfigError("scenario.data.measurements", list(data["measurements"]), "one column: the dependent "
                          "variable y")
    inputs = list(data.get("inputs") or [])
    if trend == "n" and not inputs:
        raise ConfigError("scenario.trend", trend, "without a constant the model needs inputs (regressors)")
    n = 1 + len(inputs)
    tvtp = [str(c) for c in (tvtp or [])]
    if tvtp and transition is not None:
        raise ConfigError("scenario.transition", [list(r) for r in transition], "give no transition matrix with "
                          "tvtp (the transition probabilities are the logistic of the tvtp columns)")
    reading = dict(data)
    extra = [c for c in tvtp if c not in inputs]
    if extra:
        reading["inputs"] = inputs + extra
    recorded = read_data(reading, n, 1)
    regressors = None if not inputs else recorded.inputs[..., :len(inputs)]
    y = recorded.measurements[..., 0]
    X = np.concatenate([np.ones(y.shape + (1,))] + ([regressors] if inputs else []), -1)
    if trend == "n":
        X = X[..., 1:]
    ok = recorded.present & np.isfinite(y)
    if start is None:  # statsmodels' start_params (MarkovRegression.start_params)
        Xo, yo = X[ok], y[ok]
        beta = np.linalg.pinv(Xo) @ yo
        variance = float(np.var(yo - Xo @ beta))
        coef = np.stack([beta * (i / K) for i in range(K)]) if (switching_trend or switching_exog) else \
            np.stack([beta] * K)
        if not switching_trend and trend == "c":
            coef[:, 0] = beta[0]
        if not switching_exog and inputs:
            coef[:, -len(inputs):] = beta[-len(inputs):]
        variances = np.linspace(variance / 10, variance, K) if switching_variance else np.full(K, variance)
    else:
        consts = K if trend == "c" else "null: trend n"
        expected = f"expected const ({consts}), exog ({K} x {len(inputs)}) and variance ({K})"
        try:
            const = [float(c) for c in (start.get("const") or [])]
            exog = [[float(b) for b in r] for r in (start.get("exog") or [])]
            variances = np.array([float(v) for v in (start.get("variance") or [])], dtype=float)
        except (TypeError, ValueError, AttributeError):
            raise ConfigError("scenario.start", dict(start), f"{expected}: numbers") from None
        if len(const) != (K if trend == "c" else 0) or len(exog) != (K if inputs else 0) \
                or any(len(r) != len(inputs) for r in exog) or variances.shape != (K,):
            raise ConfigError("scenario.start", dict(start), expected)
        coef = np.array([([const[i]] if trend == "c" else []) + (exog[i] if inputs else []) for i in range(K)])
    if trend == "n":  # the state keeps its constant component; its coefficient is 0 and fixed
        coef = np.concatenate([np.zeros((K, 1)), coef], -1)
    matrix = [[1.0 / K] * K for _ in range(K)] if transition is None else [list(r) for r in transition]
    try:
        P = validate_transition(torch.tensor(matrix, dtype=dtype), "transition")
    except ValueError as err:
        raise ConfigError("scenario.transition", matrix, str(err).split(": ", 1)[-1]) from None
    if P.shape[-1] != K:
        raise ConfigError("scenario.transition", matrix, f"is {P.shape[-1]}x{P.shape[-1]} for {K} regimes")
    from torchmm import LinearMeasurement

    from torchmm import LogisticTransition

    # the controls: the regressors, then the transition's inputs (a constant first, then its columns)
    if tvtp:
        columns = {c: i for i, c in enumerate(list(data.get("inputs") or []) + extra)}
        parts = ([regressors] if inputs else []) + ([np.ones(y.shape + (1,))] if tvtp_constant else []) + \
            [recorded.inputs[..., [columns[c]]] for c in tvtp]
        recorded.inputs = np.concatenate(parts, -1)
        recorded.inputs[~recorded.present] = 0.0
        q = len(tvtp) + int(tvtp_constant)
        transition_model = LogisticTransition(torch.zeros(K, K - 1, q, dtype=dtype),
                                              columns=list(range(len(inputs), len(inputs) + q))).to(device)
    width = 0 if recorded.inputs is None else recorded.inputs.shape[-1]
    F = torch.zeros(n, n, dtype=dtype)
    F[0, 0] = 1.0
    B = torch.zeros(n, max(width, 1), dtype=dtype)
    if inputs:
        B[1:, :len(inputs)] = torch.eye(len(inputs), dtype=dtype)
    motion = LinearMotion(F, torch.zeros(n, n, dtype=dtype), input_matrix=B if width else None)
    sensors = [LinearMeasurement(torch.as_tensor(coef[i], dtype=dtype).reshape(1, n),
                                 torch.full((1, 1), float(variances[i]), dtype=dtype)).to(device) for i in range(K)]
    initial = GaussianBelief(torch.eye(n, dtype=dtype)[0], torch.zeros(n, n, dtype=dtype))
    # what `learn.parameters: auto` estimates: the switching entries per regime, the others shared
    switching = ([switching_trend] if trend == "c" else [True]) + [switching_exog] * len(inputs)
    fixed_const = [False] * n if trend == "c" else [True] + [False] * len(inputs)
    names = [["const" if trend == "c" else "(no constant)"] + [str(c) for c in inputs]]
    transition_names = None if not tvtp else [
        f"p[{i}->{j}].{c}" for i in range(K) for j in range(K - 1) for c in (["const"] if tvtp_constant else []) + tvtp]
    learn = [{"name": "transition", **({"names": transition_names} if tvtp else {})},
             {"model": "sensors", "name": "H", "kind": "free", "shared": [[not s for s in switching]],
              "fixed": [fixed_const], "names": names},
             {"model": "sensors", "name": "R", "kind": "variance", "shared": not switching_variance,
              "names": [["sigma2"]]}]
    return SystemScenario(
        name=name, motion=[copy_motion(motion) for _ in range(K)],
        measurement=sensors, transition=transition_model if tvtp else P.to(device), initial=initial.to(device),
        steps=recorded.steps,
        initial_mode_probs=_first_ergodic(transition_model, recorded.inputs, dtype, device) if tvtp
        else stationary_probs(P).to(device), mode_labels=list(labels) if labels else
        [f"regime {i}" for i in range(K)], groups={"state": list(range(n))}, sensor_dims=[1], missing=[0.0],
        every=[1], data=recorded, motions=None, ergodic=True, learn_parameters=learn)


def _first_ergodic(transition, inputs: np.ndarray, dtype, device) -> Tensor:
    """Each series' start regime probabilities under a time-varying transition: the ergodic ones of its
    first step's matrix (statsmodels' ``exog_tvtp`` default), ``(runs, M)``."""
    from torchmm.learn import stationary

    u0 = torch.as_tensor(inputs[0], dtype=dtype, device=device)  # (runs, k)
    return stationary(transition.at(u0).matrix())

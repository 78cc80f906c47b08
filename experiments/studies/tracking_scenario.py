"""The tracking study's targets and detections (``experiment=tracking``, :mod:`experiments.studies.tracking`):
the targets' paths (crossing and manoeuvring, waypoints, motion schedules), their lifetimes, the sensors and
their schedules, and the simulated scans; split from the study's module by concern (issue 47)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.beliefs import psd_sqrt
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.simulate import simulate_detections


def motion_bank(t, dtype) -> ConstantVelocity:
    a = float(t.maneuver_acceleration)
    return ConstantVelocity(2, dt=float(t.dt), q=float(t.q), acceleration=[[0.0, 0.0], [0.0, a], [0.0, -a]],
                            dtype=dtype)


def waypoint_paths(t, dtype=torch.float64) -> tuple[Tensor, Tensor, Tensor]:
    """``tracking.waypoints``' targets: the states ``(T, N, 4)``, which exist ``(T, N)`` and the states one
    period before the first scan ``(N, 4)``. A target flies straight between its waypoints
    ``[scan, x, y]`` (constant velocity on each leg) and exists from its first waypoint's scan to its last."""
    T, dt = int(t.steps), float(t.dt)
    paths = [torch.tensor([[float(v) for v in point] for point in target], dtype=dtype) for target in t.waypoints]
    k = torch.arange(-1, T, dtype=dtype)
    states, present = [], []
    for path in paths:
        scans, xy = path[:, 0].contiguous(), path[:, 1:]
        leg = (torch.searchsorted(scans, k, right=True) - 1).clamp(0, len(scans) - 2)  # the leg of each scan
        a, b = scans[leg], scans[leg + 1]
        velocity = (xy[leg + 1] - xy[leg]) / ((b - a) * dt).unsqueeze(-1)
        position = xy[leg] + velocity * ((k - a) * dt).unsqueeze(-1)
        states.append(torch.stack([position[:, 0], velocity[:, 0], position[:, 1], velocity[:, 1]], -1))
        present.append((k >= scans[0]) & (k <= scans[-1]))
    states, present = torch.stack(states, 1), torch.stack(present, 1)  # (T + 1, N, ...)
    return states[1:], present[1:], states[0]


def motion_paths(t, dtype=torch.float64) -> tuple[Tensor, Tensor, Tensor]:
    """``tracking.motions``' targets, as :func:`waypoint_paths` returns them. Each target is at ``start``
    ``[x, vx, y, vy]`` at scan ``first`` (default 0) and flies its legs in turn, ``scans`` scans each:
    constant velocity, a coordinated turn (``turn_rate`` rad/s, positive anticlockwise) or a constant
    ``acceleration`` ``[ax, ay]`` (exact motion, no noise); it exists from ``first`` to the end of its last
    leg. Its state one period before ``first`` is its first leg run backwards."""
    T, dt = int(t.steps), float(t.dt)
    states, present, before = [], [], []
    for target in t.motions:
        first = int(target.get("first") or 0)
        x = torch.tensor([float(v) for v in target["start"]], dtype=dtype)
        legs = [(int(leg["scans"]), float(leg.get("turn_rate") or 0.0),
                 [float(a) for a in (leg.get("acceleration") or [0.0, 0.0])]) for leg in target["legs"]]
        path = torch.full((T + 1, 4), math.nan, dtype=dtype)  # scans -1 .. T - 1
        back = _exact_step(x, -dt, legs[0][1], legs[0][2])
        if first == 0:
            path[0] = back
        path[first + 1] = x
        k = first
        for scans, rate, acc in legs:
            for _ in range(scans):
                x = _exact_step(x, dt, rate, acc)
                k += 1
                path[k + 1] = x
        states.append(path)
        present.append(torch.isfinite(path[1:]).all(-1))
        before.append(back)
    states = torch.stack(states, 1)
    return states[1:].nan_to_num(0.0), torch.stack(present, 1), torch.stack(before)


def _exact_step(x: Tensor, dt: float, rate: float, acc: list[float]) -> Tensor:
    """``[x, vx, y, vy]`` after ``dt``: a coordinated turn at ``rate``, or constant acceleration ``acc``."""
    px, vx, py, vy = x.unbind(-1)
    if rate != 0.0:
        s, c = math.sin(rate * dt), math.cos(rate * dt)
        return torch.stack([px + (s * vx - (1 - c) * vy) / rate, c * vx - s * vy,
                            py + ((1 - c) * vx + s * vy) / rate, s * vx + c * vy], -1)
    ax, ay = acc
    return torch.stack([px + vx * dt + ax * dt * dt / 2, vx + ax * dt, py + vy * dt + ay * dt * dt / 2, vy + ay * dt], -1)


def _paths(t):
    """The targets' paths from ``tracking.waypoints`` or ``tracking.motions`` (None: the circle)."""
    if t.get("waypoints") is not None:
        return waypoint_paths(t)
    if t.get("motions") is not None:
        return motion_paths(t)
    return None


def lifetimes(t) -> Tensor:
    """``(T, N)`` bool: which targets exist at each scan (``tracking.lifetimes``, or the waypoints' or
    motions' spans; all, where null)."""
    paths = _paths(t)
    if paths is not None:
        return paths[1]
    T, N = int(t.steps), int(t.targets)
    if t.lifetimes is None:
        return torch.ones(T, N, dtype=torch.bool)
    k = torch.arange(T).unsqueeze(-1)
    first, stop = (torch.tensor([int(life[i]) for life in t.lifetimes]) for i in (0, 1))
    return (k >= first) & (k < stop)


def simulate(t, runs: int, generator: torch.Generator, dtype=torch.float64):
    """Truth ``(T, runs, N, 4)``, detections ``(T, runs, D, 2)``, the tracks' start ``(runs, N, 4)`` and
    which targets exist ``(T, runs, N)`` (a target that does not exist makes no detection; it still
    moves, so that the draws do not depend on the lifetimes). With ``tracking.waypoints`` the targets fly
    their legs (:func:`waypoint_paths`) in every run, without process noise."""
    if _paths(t) is not None:
        return _simulate_paths(t, runs, generator, dtype)
    N, T, dt = int(t.targets), int(t.steps), float(t.dt)
    bank = motion_bank(t, dtype)
    F, Q, offset = bank.F, bank.Q, bank.offset  # offset (3, 4): each mode's G a
    angle = 2 * math.pi * torch.arange(N, dtype=dtype) / N
    speed = float(t.radius) / (T / 2 * dt)  # at the centre at mid-run
    start = torch.stack([float(t.radius) * angle.cos(), -speed * angle.cos(),
                         float(t.radius) * angle.sin(), -speed * angle.sin()], -1).expand(runs, N, 4)
    push = torch.where(torch.arange(N) % 2 == 0, 1, 2)  # the mode each target takes in the manoeuvre
    LQ = psd_sqrt(Q)  # q G G^T: singular
    x, states = start, []
    for k in range(T):
        turning = int(t.maneuver_start) <= k < int(t.maneuver_stop)
        x = x @ F.mT + (offset[push] if turning else 0.0) + torch.randn(runs, N, 4, generator=generator,
                                                                          dtype=dtype) @ LQ.mT
        states.append(x)
    truth = torch.stack(states)
    present = lifetimes(t).unsqueeze(1).expand(T, runs, N)
    seen = truth if t.lifetimes is None else torch.where(present.unsqueeze(-1), truth, math.nan)
    return truth, _scans(t, seen, generator, dtype), _start(t, start, generator, dtype), present


def sensor_list(t) -> list[dict]:
    """The sensors: ``tracking.sensors``, or the one of ``tracking.R``, ``detection_probability`` and
    ``clutter_rate`` (every scan); each ``{name, R, detection_probability, clutter_rate, period, offset}``."""
    given = t.get("sensors")
    if given is None:
        return [{"name": "sensor", "R": float(t.R), "detection_probability": float(t.detection_probability),
                 "clutter_rate": float(t.clutter_rate), "period": float(t.dt), "offset": 0.0}]
    return [{"name": str(s["name"]), "R": float(s["R"]), "detection_probability": float(s["detection_probability"]),
             "clutter_rate": float(s["clutter_rate"]), "period": float(s.get("period") or t.dt),
             "offset": float(s.get("offset") or 0.0)} for s in given]


def schedule(t, T: int) -> Tensor:
    """``(T, S)`` bool: which sensor reports at which scan (``offset``, then every ``period``)."""
    dt, k = float(t.dt), torch.arange(T)
    steps = [(round(s["period"] / dt), round(s["offset"] / dt)) for s in sensor_list(t)]
    return torch.stack([(k >= o) & ((k - o) % p == 0) for p, o in steps], -1)


def _scans(t, seen: Tensor, generator: torch.Generator, dtype) -> Tensor:
    """The scans of the targets ``seen``: ``(T, runs, D, 2)``, or with ``tracking.sensors`` each sensor's
    ``(T, runs, S, D, 2)`` (drawn at every scan in the sensors' order, NaN where it does not report)."""
    if t.get("sensors") is None:
        return _detect(t, seen, generator, dtype)
    T = seen.shape[0]
    on = schedule(t, T)
    zs = [torch.where(on[:, s].view(T, 1, 1, 1), _detect(t, seen, generator, dtype, sensor), math.nan)
          for s, sensor in enumerate(sensor_list(t))]
    D = max(z.shape[-2] for z in zs)
    return torch.stack([torch.nn.functional.pad(z, (0, 0, 0, D - z.shape[-2]), value=math.nan) for z in zs], 2)


def _detect(t, seen: Tensor, generator: torch.Generator, dtype, sensor: dict | None = None) -> Tensor:
    """The scans ``(T, runs, D, 2)`` of the targets ``seen`` (NaN rows: absent) in clutter, by ``sensor``
    (:func:`sensor_list`; the study's one by default)."""
    sensor = sensor or sensor_list(t)[0]
    model = PositionMeasurement(4, [0, 2], sensor["R"], dtype=dtype)
    L = float(t.region)
    rate = sensor["clutter_rate"]
    return simulate_detections(model, seen, detection_probability=sensor["detection_probability"],
                               clutter_rate=rate, region=torch.tensor([[-L, L], [-L, L]], dtype=dtype),
                               max_clutter=int(rate + 6 * math.sqrt(rate) + 5), generator=generator).z


def _start(t, start: Tensor, generator: torch.Generator, dtype) -> Tensor:
    """The tracks' start: the true state one period before the first scan plus ``N(0, diag(P0))``."""
    P0 = torch.tensor(list(t.P0), dtype=dtype)
    return start + torch.randn(start.shape, generator=generator, dtype=dtype) * P0.sqrt()


def _simulate_paths(t, runs: int, generator: torch.Generator, dtype):
    states, exists, before = (v.to(dtype) if v.is_floating_point() else v for v in _paths(t))
    T, N = exists.shape
    truth = states.unsqueeze(1).expand(T, runs, N, 4)
    present = exists.unsqueeze(1).expand(T, runs, N)
    seen = torch.where(present.unsqueeze(-1), truth, math.nan)
    return truth, _scans(t, seen, generator, dtype), _start(t, before.expand(runs, N, 4), generator, dtype), present

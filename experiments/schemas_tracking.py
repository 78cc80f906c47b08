"""The tracking study's keys (conf/experiment/tracking.yaml; experiments/studies/tracking.py): the typed
schema and its cross-key checks, split from :mod:`experiments.schemas` by study (issue 47), which lists it
in ``STUDIES``. The same rules as there: a key the YAML sets has no default here (``MISSING``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, List, Optional

from omegaconf import MISSING

from experiments.checks import (
    NO_VALUE,
    ConfigError,
    both,
    each,
    non_empty,
    non_negative,
    one_of,
    open_probability,
    positive,
    positive_int,
    probability,
    spec,
)

__all__ = ["EXACT_JPDA", "MANAGED_TRACKERS", "TRACKERS", "Tracking", "TrackingSection"]


def _unit_interval_closed_above(value) -> str | None:
    return None if value is None or 0 < value <= 1 else "must lie in (0, 1]"


TRACKERS = ("IMM-JPDAF", "JPDAF", "IMM-PDAF", "GNN-IMM", "IMM-JPDAF-LBP", "IMM-JPDAF-kbest", "IMM-MHT")  # one track per
# target, known from the first scan (IMM-JPDAF's association: tracking.jpda.method; the -LBP and -kbest ones fixed)
EXACT_JPDA = ("IMM-JPDAF", "JPDAF")  # (with tracking.jpda.method exact: at most 12 targets)
MANAGED_TRACKERS = ("JIPDA-TM", "IMM-JIPDA-TM")  # start with no track: initiation, confirmation, deletion


@dataclass
class JPDASettings:
    method: str = spec(MISSING, one_of("exact", "lbp", "kbest"))  # IMM-JPDAF's and JPDAF's joint association
    k: int = spec(MISSING, positive_int)  # kbest: the joint events a scan


@dataclass
class MHTSettings:
    hypotheses: int = spec(MISSING, positive_int)  # IMM-MHT: global hypotheses a run
    k: Optional[int] = spec(MISSING, lambda v: None if v is None else positive_int(v))  # events a hypothesis (None: hypotheses)
    n_scan: int = spec(MISSING, non_negative)  # N-scan pruning: decisions n_scan scans back fixed (0: none)


@dataclass
class TrackManagement:
    capacity: int = spec(MISSING, positive_int)
    method: str = spec(MISSING, one_of("lbp", "exact", "kbest"))
    k: int = spec(MISSING, positive_int)  # kbest: the joint events a scan
    survival_probability: float = spec(MISSING, _unit_interval_closed_above)
    birth_existence: float = spec(MISSING, open_probability)
    unexplained: float = spec(MISSING, open_probability)
    delete: float = spec(MISSING, probability)
    confirm: float = spec(MISSING, _unit_interval_closed_above)
    m_of_n: Optional[List[int]] = spec(MISSING, each(positive_int))
    max_misses: Optional[int] = spec(MISSING, positive_int)
    velocity_variance: float = spec(MISSING, positive)


@dataclass
class Initiation:
    """``tracking.initiation``: the trackers without existence (JPDA, GNN) with ``tracking.start:
    detections``: M-of-N confirmation and deletion by misses."""

    m_of_n: List[int] = spec(MISSING, each(positive_int))
    max_misses: int = spec(MISSING, positive_int)
    birth_rate: float = spec(MISSING, positive)  # IMM-MHT: new targets a scan over the region
    confirm_score: Optional[float] = MISSING  # IMM-MHT: also confirmed once its score (log-likelihood ratio) reaches it
    delete_drop: Optional[float] = spec(MISSING, positive)  # IMM-MHT: deleted once its score falls this far below its peak


@dataclass
class TrackingTruthFile:
    """``tracking.detections.truth``: one row per target and time stamp where it exists."""

    path: str = "???"  # required
    time: str = "???"
    target: str = "???"
    position: List[str] = spec(factory=list, check=non_empty)
    series: Optional[str] = None


@dataclass
class TrackingStartFile:
    """``tracking.detections.start``: one row per target (and series): the tracks' start."""

    path: str = "???"  # required
    target: str = "???"
    state: List[str] = spec(factory=list, check=non_empty)  # [x, vx, y, vy]
    variances: Optional[List[str]] = None  # the four diagonal entries (tracking.P0 where null)
    series: Optional[str] = None


@dataclass
class TrackingDetections:
    """``tracking.detections``: one's own detections file instead of the simulation
    (experiments/studies/tracking_data.py)."""

    path: str = "???"  # required
    measurements: List[str] = spec(factory=list, check=non_empty)
    time: str = "???"
    series: Optional[str] = None
    sensor: Optional[str] = None  # a column naming each row's sensor (tracking.sensors' names)
    truth: Optional[TrackingTruthFile] = None
    start: Optional[TrackingStartFile] = None


@dataclass
class TrackingSection:
    targets: int = spec(MISSING, positive_int)
    steps: int = spec(MISSING, positive_int)
    dt: float = spec(MISSING, positive)
    radius: float = spec(MISSING, positive)
    q: float = spec(MISSING, positive)
    maneuver_start: int = spec(MISSING, non_negative)
    maneuver_stop: int = spec(MISSING, non_negative)
    maneuver_acceleration: float = MISSING
    R: float = spec(MISSING, positive)
    detection_probability: float = spec(MISSING, _unit_interval_closed_above)
    clutter_rate: float = spec(MISSING, positive)
    region: float = spec(MISSING, positive)
    gate_probability: float = spec(MISSING, _unit_interval_closed_above)
    P0: List[float] = spec(MISSING, check=each(non_negative))
    stay: float = spec(MISSING, open_probability)
    q_cv: float = spec(MISSING, positive)
    gospa_c: float = spec(MISSING, positive)
    gospa_p: float = spec(MISSING, lambda v: None if v is None or v >= 1 else "must be at least 1")
    gospa_switching: float = spec(MISSING, non_negative)
    lifetimes: Optional[List[List[int]]] = MISSING
    waypoints: Optional[List[Any]] = spec(MISSING, finite=False)  # per target [[scan, x, y], ...] (checked,
    # a non-finite value named with its waypoint, in _check_waypoints)
    motions: Optional[List[Any]] = MISSING  # per target {start, first, legs: [{scans, turn_rate | acceleration}]}
    sensors: Optional[List[Any]] = MISSING  # [{name, R, detection_probability, clutter_rate, period, offset}]
    start: str = spec(MISSING, one_of("truth", "detections"))
    initiation: Initiation = field(default_factory=Initiation)
    management: TrackManagement = field(default_factory=TrackManagement)
    jpda: JPDASettings = field(default_factory=JPDASettings)
    mht: MHTSettings = field(default_factory=MHTSettings)
    estimators: List[str] = spec(MISSING, check=both(non_empty, each(one_of(*TRACKERS, *MANAGED_TRACKERS))))
    detections: Optional[TrackingDetections] = MISSING
    export: bool = MISSING


@dataclass
class Tracking:
    tracking: TrackingSection = field(default_factory=TrackingSection)

    @staticmethod
    def check(data: dict) -> None:
        t = data["tracking"]
        _check_sensors(t)
        if t["maneuver_start"] > t["maneuver_stop"]:
            raise ConfigError("tracking.maneuver_start", t["maneuver_start"], f"is after maneuver_stop "
                              f"({t['maneuver_stop']}): the manoeuvre spans the scans [maneuver_start, maneuver_stop)")
        if len(t["P0"]) != 4:
            raise ConfigError("tracking.P0", t["P0"], "expected 4 variances, [x, vx, y, vy]")
        _check_start(t)
        if t["detections"] is not None:
            if t["lifetimes"] is not None:
                raise ConfigError("tracking.lifetimes", t["lifetimes"], "with tracking.detections the truth file says "
                                  "when each target exists (set lifetimes: null)")
            for key in ("waypoints", "motions"):
                if t[key] is not None:
                    raise ConfigError(f"tracking.{key}", t[key], "with tracking.detections the truth file says "
                                      f"where the targets are (set {key}: null)")
            if t["export"]:
                raise ConfigError("tracking.export", True, "exports the simulated scenario; with tracking.detections "
                                  "there is none (set export: false)")
            fixed = _fixed(t)
            if fixed and t["detections"]["start"] is None:
                raise ConfigError("tracking.detections.start", NO_VALUE,
                                  f"missing: {', '.join(fixed)} keep one track per target from the first scan: give the "
                                  f"tracks' start (a file, one row per target), or start every tracker with no track "
                                  f"(tracking.start: detections)")
            return _check_management(t)
        if t["waypoints"] is not None and t["motions"] is not None:
            raise ConfigError("tracking.motions", t["motions"], "give the targets by waypoints or by motions, not both "
                              "(set one to null)")
        if t["waypoints"] is not None:
            return _check_waypoints(t)
        if t["motions"] is not None:
            return _check_motions(t)
        method = (t.get("jpda") or {}).get("method", "exact")
        if t["targets"] > 12 and method == "exact" and any(name in EXACT_JPDA for name in t["estimators"]):
            raise ConfigError("tracking.targets", t["targets"], "the exact JPDA takes at most 12 targets (tracking."
                              "jpda.method: lbp or kbest, or the estimators IMM-JPDAF-LBP / IMM-JPDAF-kbest, take any "
                              "number)")
        _check_management(t)
        lives = t["lifetimes"]
        if lives is None:
            return
        if len(lives) != t["targets"] or any(len(life) != 2 for life in lives):
            raise ConfigError("tracking.lifetimes", lives, f"expected [first, stop] for each of the {t['targets']} "
                                                           "targets")
        if any(not 0 <= first < stop <= t["steps"] for first, stop in lives):
            raise ConfigError("tracking.lifetimes", lives, f"each [first, stop] needs 0 <= first < stop <= steps "
                                                           f"({t['steps']})")
        known = _fixed(t)
        if known:
            raise ConfigError("tracking.estimators", t["estimators"],
                              f"{', '.join(known)} start one track per target at the first scan; with "
                              "tracking.lifetimes (births and deaths) start them with no track (tracking.start: "
                              f"detections) or use the managed trackers ({', '.join(MANAGED_TRACKERS)})")


def _check_waypoints(t: dict) -> None:
    """``tracking.waypoints``: per target, at least two ``[scan, x, y]`` with increasing scans in
    ``0 .. steps - 1``; not with ``lifetimes`` (the waypoints give the spans); the fixed-track estimators
    need every target from scan 0; the exact JPDA at most 12 targets."""
    ways = t["waypoints"]
    if t["lifetimes"] is not None:
        raise ConfigError("tracking.lifetimes", t["lifetimes"], "with tracking.waypoints each target exists from its "
                          "first waypoint's scan to its last (set lifetimes: null)")
    if not ways:
        raise ConfigError("tracking.waypoints", ways, "no target (one list of [scan, x, y] waypoints per target)")
    for i, target in enumerate(ways):
        key = f"tracking.waypoints[{i}]"
        if not isinstance(target, list) or len(target) < 2 or any(
                not isinstance(point, list) or len(point) != 3 or
                not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in point)
                for point in target):
            raise ConfigError(key, target, "expected at least two waypoints [scan, x, y] (numbers)")
        for j, point in enumerate(target):  # a NaN or infinite entry: named, not "two waypoints"
            for name, v in zip(("scan", "x", "y"), point):
                if not math.isfinite(v):
                    raise ConfigError(f"{key}[{j}]", point, f"its {name} is {v!r}: expected a finite number")
        scans = [point[0] for point in target]
        if any(s != int(s) for s in scans) or any(b <= a for a, b in zip(scans, scans[1:])):
            raise ConfigError(key, target, "the waypoints' scans must be whole numbers, increasing")
        if scans[0] < 0 or scans[-1] > t["steps"] - 1:
            raise ConfigError(key, target, f"the scans must lie in 0 .. steps - 1 = {t['steps'] - 1}")
    _check_targets(t, "waypoints", [i for i, target in enumerate(ways) if target[0][0] != 0])


def _check_targets(t: dict, key: str, late: list[int]) -> None:
    """The targets of ``tracking.<key>`` (waypoints, motions): the fixed-track estimators need every one
    from scan 0 (``late``: those born after it); the exact JPDA takes at most 12; the management keys."""
    fixed = _fixed(t)
    if late and fixed:
        raise ConfigError("tracking.estimators", t["estimators"],
                          f"{', '.join(fixed)} start one track per target at the first scan; target(s) {late} start "
                          f"later (births): start them with no track (tracking.start: detections) or use the managed "
                          f"trackers ({', '.join(MANAGED_TRACKERS)})")
    method = (t.get("jpda") or {}).get("method", "exact")
    count = len(t[key])
    if count > 12 and method == "exact" and any(name in EXACT_JPDA for name in t["estimators"]):
        raise ConfigError(f"tracking.{key}", f"{count} targets", "the exact JPDA takes at most 12 targets "
                          "(tracking.jpda.method: lbp or kbest)")
    _check_management(t)


def _check_management(t: dict) -> None:
    m = t["management"]
    if m["method"] == "exact" and m["capacity"] > 12 and set(MANAGED_TRACKERS) & set(t["estimators"]):
        raise ConfigError("tracking.management.capacity", m["capacity"],
                          "the exact JIPDA takes at most 12 track slots (method: lbp takes any number)")
    exact = [name for name in t["estimators"] if name in EXACT_JPDA]
    method = (t.get("jpda") or {}).get("method", "exact")
    if t["start"] == "detections" and method == "exact" and m["capacity"] > 12 and exact:
        raise ConfigError("tracking.management.capacity", m["capacity"],
                          f"with tracking.start: detections {', '.join(exact)} {'runs' if len(exact) == 1 else 'run'} "
                          "the exact JPDA over the track slots, which takes at most 12 (tracking.jpda.method: lbp "
                          "or kbest takes any number)")
    mn = m["m_of_n"]
    if mn is not None and (len(mn) != 2 or mn[0] > mn[1]):
        raise ConfigError("tracking.management.m_of_n", mn, "expected [M, N] with 1 <= M <= N")


#: a sensor's keys (tracking.sensors[i]); period and offset are optional (tracking.dt and 0)
SENSOR_KEYS = {"name": None, "R": positive, "detection_probability": _unit_interval_closed_above,
               "clutter_rate": positive, "period": positive, "offset": non_negative}


def _check_sensors(t: dict) -> None:
    """``tracking.sensors``: each ``{name, R, detection_probability, clutter_rate}`` with optional
    ``period`` (a whole multiple of ``dt``) and ``offset`` (a whole multiple of ``dt`` below the period);
    distinct names; with a detections file, its ``sensor`` column when there are several."""
    sensors, dt = t["sensors"], t["dt"]
    column = (t["detections"] or {}).get("sensor")
    if sensors is None:
        if column is not None:
            raise ConfigError("tracking.sensors", None, f"missing: tracking.detections.sensor ({column!r}) names "
                              "each row's sensor; list the sensors (name, R, detection_probability, clutter_rate)")
        return
    if not isinstance(sensors, list) or not sensors:
        raise ConfigError("tracking.sensors", sensors, "expected a list of sensors, each {name, R, "
                          "detection_probability, clutter_rate, period, offset}")
    names = []
    for i, sensor in enumerate(sensors):
        key = f"tracking.sensors[{i}]"
        if not isinstance(sensor, dict):
            raise ConfigError(key, sensor, "expected {name, R, detection_probability, clutter_rate} (period, "
                              "offset optional)")
        unknown = sorted(set(sensor) - set(SENSOR_KEYS))
        if unknown:
            raise ConfigError(f"{key}.{unknown[0]}", sensor[unknown[0]], f"not a sensor's key (keys: "
                              f"{', '.join(SENSOR_KEYS)})")
        for name, check in SENSOR_KEYS.items():
            value = sensor.get(name)
            if value is None:
                if name in ("period", "offset"):
                    continue
                raise ConfigError(f"{key}.{name}", NO_VALUE, "missing")
            if name == "name":
                if not isinstance(value, str) or not value.strip():
                    raise ConfigError(f"{key}.name", value, "expected the sensor's name (text)")
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"{key}.{name}", value, "expected a number")
            why = check(value)
            if why:
                raise ConfigError(f"{key}.{name}", value, why)
        period = sensor.get("period") or dt
        for name, value in (("period", period), ("offset", sensor.get("offset") or 0.0)):
            ratio = value / dt
            if abs(ratio - round(ratio)) > 1e-9 * max(1.0, ratio):
                raise ConfigError(f"{key}.{name}", value, f"must be a whole multiple of tracking.dt ({dt:g}), the "
                                  "scans' grid")
        if (sensor.get("offset") or 0.0) >= period:
            raise ConfigError(f"{key}.offset", sensor["offset"], f"must be below the sensor's period ({period:g})")
        names.append(sensor["name"])
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ConfigError("tracking.sensors", names, f"the sensor {twice[0]!r} is named twice")
    if t["detections"] is not None and len(sensors) > 1 and column is None:
        raise ConfigError("tracking.detections.sensor", NO_VALUE, f"missing: {len(sensors)} sensors in "
                          "tracking.sensors; name the column of each row's sensor")


#: with tracking.start: detections, the trackers that cannot start with no track (and why)
NO_INITIATION = {"IMM-PDAF": "associates each track alone (no joint initiation); IMM-JPDAF starts from detections"}


def _fixed(t: dict) -> list[str]:
    """The estimators that keep one track per target from the first scan (none with ``start: detections``)."""
    return [] if t["start"] == "detections" else [name for name in t["estimators"] if name in TRACKERS]


def _check_start(t: dict) -> None:
    """``tracking.start: detections``: every estimator that can starts with no track; M-of-N's ``[M, N]``."""
    if t["start"] != "detections":
        return
    refused = [name for name in t["estimators"] if name in NO_INITIATION]
    if refused:
        raise ConfigError("tracking.estimators", t["estimators"], f"{refused[0]} {NO_INITIATION[refused[0]]} "
                          "(tracking.start: detections)")
    mn = t["initiation"]["m_of_n"]
    if len(mn) != 2 or mn[0] > mn[1]:
        raise ConfigError("tracking.initiation.m_of_n", mn, "expected [M, N] with 1 <= M <= N")


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check_motions(t: dict) -> None:
    """``tracking.motions``: per target ``{start: [x, vx, y, vy], first: scan (optional), legs: [{scans: n,
    turn_rate: w} | {scans: n, acceleration: [ax, ay]} | {scans: n}]}``, inside ``0 .. steps - 1``; not with
    ``lifetimes``; the fixed-track estimators need every target from scan 0; the exact JPDA at most 12."""
    motions = t["motions"]
    if t["lifetimes"] is not None:
        raise ConfigError("tracking.lifetimes", t["lifetimes"], "with tracking.motions each target exists from its "
                          "first scan to the end of its last leg (set lifetimes: null)")
    if not isinstance(motions, list) or not motions:
        raise ConfigError("tracking.motions", motions, "no target (one {start, first, legs} per target)")
    for i, target in enumerate(motions):
        key = f"tracking.motions[{i}]"
        if not isinstance(target, dict) or set(target) - {"start", "first", "legs"}:
            raise ConfigError(key, target, "expected {start: [x, vx, y, vy], first: scan, legs: [...]}")
        start = target.get("start")
        if not isinstance(start, list) or len(start) != 4 or not all(_number(v) for v in start):
            raise ConfigError(f"{key}.start", start, "expected [x, vx, y, vy] (numbers)")
        first = target.get("first") or 0
        if not isinstance(first, int) or isinstance(first, bool) or first < 0:
            raise ConfigError(f"{key}.first", first, "expected the scan it appears at (a whole number >= 0)")
        legs = target.get("legs")
        if not isinstance(legs, list) or not legs:
            raise ConfigError(f"{key}.legs", legs, "expected a list of legs, each {scans, turn_rate} or "
                              "{scans, acceleration: [ax, ay]} or {scans}")
        for j, leg in enumerate(legs):
            where = f"{key}.legs[{j}]"
            if not isinstance(leg, dict) or set(leg) - {"scans", "turn_rate", "acceleration"}:
                raise ConfigError(where, leg, "expected {scans, turn_rate} or {scans, acceleration: [ax, ay]} or {scans}")
            scans = leg.get("scans")
            if not isinstance(scans, int) or isinstance(scans, bool) or scans < 1:
                raise ConfigError(f"{where}.scans", scans, "expected a whole number of scans >= 1")
            if leg.get("turn_rate") is not None and leg.get("acceleration") is not None:
                raise ConfigError(where, leg, "a turn or an acceleration, not both")
            if leg.get("turn_rate") is not None and not _number(leg["turn_rate"]):
                raise ConfigError(f"{where}.turn_rate", leg["turn_rate"], "expected a number (rad/s)")
            acc = leg.get("acceleration")
            if acc is not None and (not isinstance(acc, list) or len(acc) != 2 or not all(_number(v) for v in acc)):
                raise ConfigError(f"{where}.acceleration", acc, "expected [ax, ay] (numbers)")
        last = first + sum(leg["scans"] for leg in legs)
        if last > t["steps"] - 1:
            raise ConfigError(key, target, f"its legs end at scan {last}, after the last scan (steps - 1 = "
                              f"{t['steps'] - 1})")
    _check_targets(t, "motions", [i for i, target in enumerate(motions) if (target.get("first") or 0) != 0])

"""The trackers the tracking study compares (split from :mod:`experiments.studies.tracking` by concern, issue 47;
its docstring describes each): :func:`estimators` builds them from the study's ``tracking`` node, each an
:class:`Estimator` (the filter, its start, and how the scans reach it)."""

from __future__ import annotations

from typing import Callable, NamedTuple

import torch
from torch import Tensor

from experiments.studies.tracking_scenario import motion_bank, sensor_list
from torchmm import IMM, KalmanFilter
from torchmm.association import (
    GNN,
    JIPDA,
    JPDA,
    MHT,
    PDA,
    ManagedMHT,
    ManagedTracks,
    SequentialSensors,
    position_initiator,
)
from torchmm.models import ConstantVelocity, PositionMeasurement

__all__ = ["ESTIMATORS", "Estimator", "estimators"]

ESTIMATORS = ("IMM-JPDAF", "JPDAF", "IMM-PDAF", "GNN-IMM", "IMM-JPDAF-LBP", "IMM-JPDAF-kbest", "IMM-MHT")


class Estimator(NamedTuple):
    filter: object
    initial: Callable  # the tracks' start (a GaussianBelief (runs, N, 4)) -> the filter's initial belief
    per_track: bool    # the scans go to every track alone (IMM-PDAF)
    managed: bool      # starts empty, confirms and deletes its tracks (a track table each step)
    record: Callable | None = None  # a managed filter's step -> its track table (ManagedMHT: the best hypothesis)


def estimators(t, dtype, targets: int | None = None) -> dict[str, Estimator]:
    """The configured estimators by name (``targets``: the tracks of the fixed-track estimators, the
    start file's where one is read; ``tracking.targets`` by default). With ``tracking.sensors`` each is
    a :class:`~torchmm.association.SequentialSensors` of the estimator built for each sensor (its
    ``R``, detection probability and clutter density), which takes :class:`SensorScans`."""
    if t.get("sensors") is None:
        return _estimators(t, dtype, targets, sensor_list(t)[0])
    each = [_estimators(t, dtype, targets, sensor) for sensor in sensor_list(t)]
    return {name: first._replace(filter=SequentialSensors([made[name].filter for made in each]))
            for name, first in each[0].items()}


def _estimators(t, dtype, targets: int | None, scanner: dict) -> dict[str, Estimator]:
    """The estimators over one sensor (:func:`sensor_list`'s)."""
    bank = motion_bank(t, dtype)
    cv = ConstantVelocity(2, dt=float(t.dt), q=float(t.q_cv), dtype=dtype)
    sensor = PositionMeasurement(4, [0, 2], scanner["R"], dtype=dtype)
    M, stay = 3, float(t.stay)
    off = (1 - stay) / (M - 1)
    Pi = torch.full((M, M), off, dtype=dtype) + (stay - off) * torch.eye(M, dtype=dtype)
    opts = {"detection_probability": scanner["detection_probability"],
            "clutter_density": scanner["clutter_rate"] / (2 * float(t.region)) ** 2,
            "gate_probability": float(t.gate_probability)}
    imm = IMM(KalmanFilter(bank, sensor), Pi)
    jp = t.get("jpda") or {}
    chosen = {"method": str(jp.get("method", "exact")), "k": int(jp.get("k", 100)),
              "max_targets": max(12, int(t.targets if targets is None else targets))}
    made = {
        "IMM-JPDAF": lambda: Estimator(JPDA(imm, **opts, **chosen), imm.initial_belief, False, False),
        "IMM-JPDAF-LBP": lambda: Estimator(JPDA(imm, **opts, method="lbp"), imm.initial_belief, False, False),
        "IMM-JPDAF-kbest": lambda: Estimator(JPDA(imm, **opts, method="kbest", k=chosen["k"]), imm.initial_belief,
                                             False, False),
        "JPDAF": lambda: Estimator(JPDA(KalmanFilter(cv, sensor), **opts, **chosen), lambda b: b, False, False),
        "IMM-MHT": lambda: _mht(t, imm, opts),
        "IMM-PDAF": lambda: _per_track(IMM(PDA(KalmanFilter(bank, sensor), **opts), Pi)),
        "GNN-IMM": lambda: Estimator(GNN(imm, **opts), imm.initial_belief, False, False),
        "JIPDA-TM": lambda: _managed(t, KalmanFilter(cv, sensor), opts, dtype, scanner["R"]),
        "IMM-JIPDA-TM": lambda: _managed(t, imm, opts, dtype, scanner["R"]),
    }
    if t.get("start") == "detections":  # every estimator starts with no track (the trackers without existence:
        R, k = scanner["R"], chosen["k"]  # a JIPDA whose tracks exist for sure, M-of-N confirmation and deletion)
        made |= {
            "IMM-JPDAF": lambda: _initiated(t, imm, opts, dtype, R, chosen["method"], k),
            "IMM-JPDAF-LBP": lambda: _initiated(t, imm, opts, dtype, R, "lbp", k),
            "IMM-JPDAF-kbest": lambda: _initiated(t, imm, opts, dtype, R, "kbest", k),
            "JPDAF": lambda: _initiated(t, KalmanFilter(cv, sensor), opts, dtype, R, chosen["method"], k),
            "GNN-IMM": lambda: _initiated(t, imm, opts, dtype, R, "kbest", 1),  # (the best event: GNN)
            "IMM-MHT": lambda: _managed_mht(t, imm, opts, R),
        }
    return {name: made[name]() for name in t.estimators}


def _mht(t, imm, opts: dict) -> Estimator:
    """``MHT(IMM(...))`` with ``tracking.mht``'s settings (the IMM-MHT: the best hypothesis's tracks shown)."""
    h = t.get("mht") or {}
    hypotheses = int(h.get("hypotheses", 10))
    k = h.get("k")
    mht = MHT(imm, **opts, hypotheses=hypotheses, k=int(k) if k is not None else hypotheses,
              n_scan=int(h.get("n_scan", 3)))
    return Estimator(mht, mht.initial_belief, False, False)


def _per_track(filt) -> Estimator:
    return Estimator(filt, filt.initial_belief, True, False)


def _managed(t, filt, opts: dict, dtype, R: float) -> Estimator:
    """``ManagedTracks(JIPDA(filt))`` with ``tracking.management``'s settings (new tracks from the sensor's
    detections, noise variance ``R`` per axis)."""
    m = t.management
    jipda = JIPDA(filt, survival_probability=float(m.survival_probability), method=str(m.method),
                  max_targets=max(12, int(m.capacity)), k=int(m.get("k") or 100), **opts)
    start = position_initiator(4, [0, 2], R, float(m.velocity_variance))
    manager = ManagedTracks(jipda, capacity=int(m.capacity), initiate=start, birth_existence=float(m.birth_existence),
                            unexplained=float(m.unexplained), delete=float(m.delete), confirm=float(m.confirm),
                            m_of_n=None if m.m_of_n is None else tuple(int(v) for v in m.m_of_n),
                            max_misses=None if m.max_misses is None else int(m.max_misses))
    return Estimator(manager, lambda b: manager.initial_belief(b.batch_shape[:-1], dtype=dtype), False, True)


def _managed_mht(t, imm, opts: dict, R: float) -> Estimator:
    """``ManagedMHT(IMM(...))`` (``tracking.start: detections``): ``tracking.mht``'s hypotheses, the new-target
    rate ``tracking.initiation.birth_rate`` over the region, M-of-N and misses as the JPDAs'; the best
    hypothesis's confirmed tracks shown."""
    h, m, i = t.mht, t.management, t.initiation
    hypotheses = int(h.hypotheses)
    mht = ManagedMHT(imm, **opts, hypotheses=hypotheses, k=int(h.k) if h.k is not None else hypotheses,
                     n_scan=int(h.n_scan), capacity=int(m.capacity),
                     initiate=position_initiator(4, [0, 2], R, float(m.velocity_variance)),
                     birth_density=float(i.birth_rate) / (2 * float(t.region)) ** 2,
                     m_of_n=tuple(int(v) for v in i.m_of_n), max_misses=int(i.max_misses),
                     confirm_score=None if i.get("confirm_score") is None else float(i.confirm_score),
                     delete_drop=None if i.get("delete_drop") is None else float(i.delete_drop))
    return Estimator(mht, lambda b: mht.initial_belief(b.batch_shape[:-1], dtype=b.dtype), False, True, _best)


def _best(out):
    """A ManagedMHT's step as its best hypothesis's track table (what the study shows and scores), its
    count of new targets without a slot (:func:`unstarted`) and its failed runs (``extras["failed"]``)."""
    return out._replace(belief=out.belief.best(), prior=None,
                        extras={"unstarted": unstarted(out.extras), "failed": out.extras.get("failed")})


def unstarted(extras: dict) -> Tensor:
    """A managed tracker's unexplained detections (new targets) that found no free slot, ``(..., runs)``
    (the steps' ``extras["unstarted"]``; with ``SequentialSensors`` summed over the sensors that reported)."""
    if "unstarted" in extras:
        return extras["unstarted"]
    reports = extras["reports"]
    return sum(e["unstarted"] * reports[..., s] for s, e in enumerate(extras["sensors"]))


def _initiated(t, filt, opts: dict, dtype, R: float, method: str, k: int) -> Estimator:
    """A JPDA (or GNN: ``kbest`` with ``k = 1``) that starts with no track (``tracking.start: detections``):
    ``ManagedTracks`` over a JIPDA whose tracks exist for sure (survival and birth existence 1: the JPDA's
    own update, tests/test_tracks.py), confirmed and deleted by ``tracking.initiation``'s M-of-N logic and
    misses; the slots, new-track velocity variance and unexplained threshold ``tracking.management``'s."""
    m, i = t.management, t.initiation  # (the exact method's limit of 12 slots kept: the config refuses more)
    jipda = JIPDA(filt, survival_probability=1.0, method=method, k=k, **opts)
    manager = ManagedTracks(jipda, capacity=int(m.capacity), initiate=position_initiator(4, [0, 2], R,
                                                                                         float(m.velocity_variance)),
                            birth_existence=1.0, unexplained=float(m.unexplained), delete=0.0, confirm=1.0,
                            m_of_n=tuple(int(v) for v in i.m_of_n), max_misses=int(i.max_misses))
    return Estimator(manager, lambda b: manager.initial_belief(b.batch_shape[:-1], dtype=dtype), False, True)

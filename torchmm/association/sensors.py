r"""Several sensors, each with its own model, detection probability, clutter and period, updating one set
of tracks in turn (docs/tracking.md, "Several sensors").

Each step, :class:`SequentialSensors` predicts once (with its first filter: every filter shares the
motion) and then updates with every sensor that reported at that step, in the sensors' order: sensor
``s``'s filter (e.g. ``JPDA(imm.with_sensor(radar), detection_probability=0.9, clutter_density=...)``)
takes the posterior of sensor ``s - 1``. A sensor that did not report leaves the belief as it was; one
that reported and saw nothing (an empty scan) is an update (every track missed). This is the sequential
multi-sensor update (Bar-Shalom, Willett & Tian, *Tracking and Data Fusion*, 2011, sec. 8.4): exact
for a single target with independent sensor noises (the sensors' likelihoods multiply); for data
association it is the usual sequential approximation (each sensor's association given the previous
sensors' posterior).

The data of each step is a :class:`SensorScans` pytree: the sensors' scans (each its own shape: a
position radar's ``(*B, D_1, 2)``, a range-bearing sensor's ``(*B, D_2, 2)``, a plain sensor's
``(*B, m)``) and ``reports (*R, S)``, which sensors reported. The scans of every sensor are updated at
every step and the results kept only where the sensor reported (no host read: the step runs
asynchronously on a GPU); the scan of a sensor that did not report is not read (any padding).

The step's log-likelihood is the sum of the reporting sensors' (the chain rule over the sensors);
``extras``: ``"failed"`` (a reporting sensor's update failed), ``"reports"`` and ``"sensors"`` (each
sensor's own extras, a tuple).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from torchmm.beliefs import where
from torchmm.contract import Of, entry_point
from torchmm.filters.base import Filter, StepOutput, call_with

__all__ = ["SensorScans", "SequentialSensors"]


class SensorScans(NamedTuple):
    """The data of ``S`` sensors (a pytree :func:`~torchmm.run_filter` indexes at each step).

    Shapes:
        scans: a tuple of ``S`` tensors, sensor ``s``'s data ``(T, *B, ...)`` (one step: ``(*B, ...)``),
            e.g. scans of detections ``(T, *B, D_s, m_s)``; NaN padding
        reports: ``(T, *R, S)`` bool (one step: ``(*R, S)``), True where sensor ``s`` reported (an empty
            scan too); ``*R`` a prefix of the belief's batch (the runs), or empty (one schedule for all)
    """

    scans: tuple
    reports: Tensor


class SequentialSensors(Filter):
    r"""Several sensors updating one belief in turn (the module docstring's sequential update).

    Args:
        filters: one filter per sensor, all over the same motion (build them from one filter with
            :meth:`~torchmm.filters.Filter.with_sensor`, each wrapped in its association with the
            sensor's detection probability and clutter density); the first one's ``initial_belief``
            and ``predict`` serve all.

    Shapes:
        belief: the filters' belief, batch ``(*B,)``; ``z``: :class:`SensorScans` (one step); the
        log-likelihood has the filters' shape (``(*B,)``, or the runs for a joint association).

    Examples:
        >>> from torchmm.association import JPDA
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> kf = KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0))
        >>> fine = kf.with_sensor(PositionMeasurement(2, [0], 0.1))
        >>> both = SequentialSensors([JPDA(kf, detection_probability=0.9, clutter_density=0.01),
        ...                           JPDA(fine, detection_probability=0.7, clutter_density=0.05)])
        >>> b0 = GaussianBelief(torch.tensor([[0.0, 1.0], [5.0, -1.0]]), torch.eye(2))  # 2 tracks
        >>> z = SensorScans((torch.tensor([[1.1], [3.9]]), torch.tensor([[0.9], [float("nan")]])),
        ...                 torch.tensor([True, False]))  # the second sensor did not report
        >>> both.step(b0, z).belief.mean.shape
        torch.Size([2, 2])
    """

    checks_pytrees = True  # (run_filter passes SensorScans to check_measurements)

    @entry_point(filters=Of((list, tuple, nn.ModuleList), what="a list of filters, one per sensor"))
    def __init__(self, filters: Sequence[Filter]):
        super().__init__()
        filters = list(filters) if isinstance(filters, (list, tuple, nn.ModuleList)) else filters
        if not isinstance(filters, list) or not filters:
            raise TypeError("filters: expected a non-empty list of filters, one per sensor")
        for s, f in enumerate(filters):
            if not isinstance(f, Filter):
                raise TypeError(f"filters[{s}]: expected a torchmm filter, got {type(f).__name__}")
            if isinstance(f, SequentialSensors):
                raise TypeError(f"filters[{s}]: a SequentialSensors inside another; give its filters instead")
            n, n0 = f.state_dim, filters[0].state_dim
            if n is not None and n0 is not None and n != n0:
                raise ValueError(f"filters[{s}]: state_dim {n} differs from filters[0]'s {n0} (the sensors "
                                 "share the motion)")
            if getattr(f, "joint", False) != getattr(filters[0], "joint", False):
                raise ValueError(f"filters[{s}]: a joint association and a per-track filter cannot share a "
                                 "belief (filters[0] is " + ("" if getattr(filters[0], "joint", False) else "not ")
                                 + "joint)")
        self.filters = nn.ModuleList(filters)
        self.uses_generator = any(f.uses_generator for f in filters)
        self.joint = getattr(filters[0], "joint", False)

    @property
    def state_dim(self) -> int | None:
        return self.filters[0].state_dim

    @property
    def meas_dim(self) -> None:
        return None  # several sensors' data (SensorScans)

    @property
    def num_sensors(self) -> int:
        return len(self.filters)

    def informative(self, z: SensorScans) -> Tensor:
        return z.reports.any(-1)

    def check_bank_member(self, name: str, num_modes: int) -> None:
        raise TypeError(f"{name}: SequentialSensors cannot be a mode filter; give each sensor's filter the "
                        "multiple-model filter instead (e.g. JPDA(imm.with_sensor(s), ...) per sensor)")

    def check_measurements(self, measurements: Any, batch: torch.Size, name: str = "measurements", *,
                           time: bool = True) -> None:
        """:class:`SensorScans` (``time``: ``(T, ...)`` leaves): one datum per sensor, each checked by its
        filter; ``reports`` bool ``(T, *R, S)`` with ``*R`` a prefix of the belief's batch. Shapes only."""
        S = self.num_sensors
        if not (isinstance(measurements, tuple) and len(measurements) == 2):
            raise TypeError(f"{name}: expected SensorScans(scans, reports) for {S} sensors, got "
                            f"{type(measurements).__name__}")
        scans, reports = measurements
        if not isinstance(scans, (tuple, list)) or len(scans) != S:
            got = len(scans) if isinstance(scans, (tuple, list)) else type(scans).__name__
            raise ValueError(f"{name}.scans: expected one datum per sensor ({S}), got {got}")
        if not isinstance(reports, Tensor) or reports.dtype != torch.bool:
            raise TypeError(f"{name}.reports: expected a bool tensor (T, *R, {S}) (which sensors reported), got "
                            f"{getattr(reports, 'dtype', type(reports).__name__)}")
        lead = 1 if time else 0
        runs = reports.shape[lead:-1]
        if reports.dim() < lead + 1 or reports.shape[-1] != S or tuple(runs) != tuple(batch[:len(runs)]):
            form = f"(T, *R, {S})" if time else f"(*R, {S})"
            raise ValueError(f"{name}.reports: expected {form} with *R a prefix of the belief's batch "
                             f"{tuple(batch)}, got {tuple(reports.shape)}")
        for s, (f, z) in enumerate(zip(self.filters, scans)):
            if not isinstance(z, Tensor):
                raise TypeError(f"{name}.scans[{s}]: expected a tensor, got {type(z).__name__}")
            if time and z.shape[:1] != reports.shape[:1]:
                raise ValueError(f"{name}.scans[{s}]: {z.shape[0] if z.dim() else 0} steps, reports has "
                                 f"{reports.shape[0]}")
            m = f.meas_dim
            if m is None:
                f.check_measurements(z, batch, f"{name}.scans[{s}]", time=time)
            elif z.dim() < 1 or z.shape[-1] != m:
                raise ValueError(f"{name}.scans[{s}]: expected the sensor's measurements (..., {m}), got "
                                 f"{tuple(z.shape)}")

    def initial_belief(self, belief, **kwargs):
        return self.filters[0].initial_belief(belief, **kwargs)

    def predict(self, belief, *, u: Tensor | None = None, generator: torch.Generator | None = None):
        return call_with(self.filters[0], "predict", belief, u=u, generator=generator)

    def update(self, belief, z: SensorScans, *, generator: torch.Generator | None = None) -> StepOutput:
        scans, reports = z
        prior, log_like, failed, extras = belief, None, None, []
        for s, f in enumerate(self.filters):
            out = call_with(f, "update", belief, scans[s], generator=generator)
            said = reports[..., s]
            rank = len(out.belief.batch_shape)  # (the runs lead: a joint belief's tracks, an MHT's hypotheses follow)
            belief = where(said.reshape(*said.shape, *(1,) * (rank - said.dim())), out.belief, belief)
            ll = out.log_likelihood
            step = torch.where(said.reshape(*said.shape, *(1,) * (ll.dim() - said.dim())), ll, 0.0)
            log_like = step if log_like is None else log_like + step
            bad = (out.extras or {}).get("failed")
            if bad is not None:
                bad = bad & said.reshape(*said.shape, *(1,) * (bad.dim() - said.dim()))
                failed = bad if failed is None else failed | bad
            extras.append(out.extras or {})
        more = {"reports": reports, "sensors": tuple(extras)}
        if failed is not None:
            more["failed"] = failed
        return StepOutput(belief, prior, log_like, None, None, more)

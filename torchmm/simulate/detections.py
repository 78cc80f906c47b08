r"""Detections of many targets in clutter, batched (issue 32): what a tracker sees at each scan.

At every step each true target is detected with probability ``P_D`` (its measurement
``z = h(x) + v``, ``v ~ N(0, R)`` of the sensor model), and a Poisson number of false detections
(clutter, mean ``clutter_rate`` a scan) falls uniformly in a box ``region`` of measurement space:
the clutter density is ``clutter_rate / V`` with ``V`` the box's volume. The detections of a scan come
in random order (their index says nothing of their origin), as a padded set: ``z (T, *B, D, m)``, NaN
where ``present`` is False, with the true ``origin`` of each (target index, -1 for clutter and
padding) for scoring. All runs and steps are drawn at once; randomness comes only from ``generator``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchmm.beliefs import psd_sqrt
from torchmm.contract import Finite, Gen, Int, Of, Real, Sets, entry_point
from torchmm.models.base import MeasurementModel

__all__ = ["Detections", "simulate_detections"]


class Detections(NamedTuple):
    """A padded set of detections per scan.

    Attributes:
        z: ``(T, *B, D, m)`` measurements, NaN where absent.
        present: ``(T, *B, D)`` bool, which rows are detections (the present ones first).
        origin: ``(T, *B, D)`` long: the index of the target that made each detection, -1 for clutter
            and for absent rows.
    """

    z: Tensor
    present: Tensor
    origin: Tensor


@entry_point(measurement=Of(MeasurementModel), states=Sets(missing=None), detection_probability=Real(0.0, 1.0),
             clutter_rate=Real(minimum=0.0), region=Finite(optional=True), max_clutter=Int(0, optional=True),
             generator=Gen())
def simulate_detections(measurement: MeasurementModel, states: Tensor, *, detection_probability: float,
                        clutter_rate: float = 0.0, region: Tensor | None = None, max_clutter: int | None = None,
                        generator: torch.Generator | None = None) -> Detections:
    """Detections of ``N`` targets with missed detections and Poisson clutter.

    Args:
        measurement: the sensor model (``h`` and ``R``), shared by the targets.
        states: ``(T, *B, N, n)`` the targets' states, in the sensor model's floating dtype (integer
            states take it); a row with a non-finite entry is a target that does not exist at that
            step (not yet born, or dead): never detected. ``N`` may be 0 (clutter only).
        detection_probability: ``P_D`` in [0, 1], the same for every target.
        clutter_rate: the mean number of false detections a scan (>= 0).
        region: ``(m, 2)`` the box ``[low, high]`` per measurement component where clutter falls
            uniformly; needed when ``clutter_rate > 0``.
        max_clutter: the padding for clutter: at most this many false detections a scan (the Poisson
            draws above it are cut to it, a documented truncation: choose it well above
            ``clutter_rate``); default the largest count drawn (one host read, at simulation time).
        generator: the only source of randomness (every draw in the states' dtype: the detections do not
            depend on torch's default dtype).

    Returns:
        :class:`Detections` with ``D = N + max_clutter`` rows a scan.

    Examples:
        >>> from torchmm.models import PositionMeasurement
        >>> sensor = PositionMeasurement(4, [0, 2], 1.0)
        >>> states = torch.zeros(5, 3, 2, 4)  # 5 steps, 3 runs, 2 targets
        >>> out = simulate_detections(sensor, states, detection_probability=0.9, clutter_rate=2.0,
        ...                           region=torch.tensor([[-50.0, 50.0], [-50.0, 50.0]]),
        ...                           generator=torch.Generator().manual_seed(0))
        >>> out.z.shape[:2], out.z.shape[-1], out.present.shape == out.z.shape[:-1]
        (torch.Size([5, 3]), 2, True)
    """
    n, m = measurement.state_dim, measurement.meas_dim
    if states.dim() < 3 or states.shape[-1] != n:
        raise ValueError(f"states: expected (T, *B, N, {n}) (targets' states for the sensor), got {tuple(states.shape)}")
    model = next((t.dtype for t in (*measurement.parameters(), *measurement.buffers()) if t.is_floating_point()),
                 None)  # the sensor model's dtype (None: a model without tensors)
    if not states.is_floating_point():
        states = states.to(model or torch.get_default_dtype())
    if clutter_rate > 0 and region is None:
        raise ValueError("region: needed for clutter (the box [low, high] per measurement component, (m, 2))")
    dtype, device = states.dtype, states.device
    if region is not None:
        region = torch.as_tensor(region, dtype=dtype, device=device)
        if region.shape != (m, 2) or not bool((region[:, 1] > region[:, 0]).all()):
            raise ValueError(f"region: expected ({m}, 2) rows [low, high] with low < high, got "
                             f"{tuple(region.shape)}")
    if model is not None and states.dtype != model:
        raise TypeError(f"states: dtype {states.dtype} differs from the measurement model's {model}; convert one "
                        f"of them (states.to({model}) or measurement.to({states.dtype}))")
    lead, N = states.shape[:-2], states.shape[-2]
    # the targets' detections
    exists = torch.isfinite(states).all(-1)  # (T, *B, N)
    safe = torch.where(exists.unsqueeze(-1), states, torch.zeros((), dtype=dtype, device=device))
    predicted = measurement(safe)
    noise = torch.randn(predicted.shape, generator=generator, dtype=dtype, device=device)
    z_target = predicted + (psd_sqrt(measurement.noise_cov(safe)) @ noise.unsqueeze(-1)).squeeze(-1)
    detected = exists & (torch.rand(exists.shape, generator=generator, dtype=dtype, device=device) < detection_probability)
    # clutter
    if clutter_rate > 0:
        counts = torch.poisson(torch.full(lead, float(clutter_rate), dtype=dtype, device=device), generator=generator).long()
        C = int(counts.max()) if max_clutter is None else int(max_clutter)
        counts = counts.clamp(max=C)
        u = torch.rand(*lead, C, m, generator=generator, dtype=dtype, device=device)
        z_clutter = region[:, 0] + (region[:, 1] - region[:, 0]) * u
        clutter_present = torch.arange(C, device=device) < counts.unsqueeze(-1)
    else:  # no clutter: max_clutter rows of padding, if asked for (the same D whatever the rate)
        C = 0 if max_clutter is None else int(max_clutter)
        z_clutter = torch.zeros(*lead, C, m, dtype=dtype, device=device)
        clutter_present = torch.zeros(*lead, C, dtype=torch.bool, device=device)
    z = torch.cat([z_target, z_clutter], dim=-2)
    present = torch.cat([detected, clutter_present], dim=-1)
    origin = torch.cat([torch.where(detected, torch.arange(N, device=device), -1),
                        torch.full((*lead, C), -1, dtype=torch.long, device=device)], dim=-1)
    # a random order of the present rows, the absent ones after them
    key = torch.rand(present.shape, generator=generator, dtype=dtype, device=device) + (~present).to(dtype)
    order = key.argsort(dim=-1)
    z = z.gather(-2, order.unsqueeze(-1).expand(z.shape))
    present = present.gather(-1, order)
    origin = origin.gather(-1, order)
    z = torch.where(present.unsqueeze(-1), z, torch.full((), torch.nan, dtype=dtype, device=device))
    return Detections(z, present, origin)

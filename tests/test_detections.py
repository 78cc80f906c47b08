"""torchmm.simulate.simulate_detections (issue 32): missed detections, Poisson clutter, padded sets.

The statistical checks use tolerances of five standard errors (the draws differ between processors)."""

from __future__ import annotations

import math

import pytest
import torch

from torchmm.models import PositionMeasurement, RangeBearing
from torchmm.simulate import simulate_detections

REGION = torch.tensor([[-500.0, 500.0], [-200.0, 300.0]], dtype=torch.float64)


def _targets(steps=20, runs=50, N=3, seed=0):
    x = torch.randn(steps, runs, N, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 100
    return x


def test_each_detection_is_its_target_s_measurement_or_clutter_inside_the_region():
    sensor = PositionMeasurement(4, [0, 2], 1e-14, dtype=torch.float64)  # noise-free to 1e-7
    x = _targets()
    x[3, :, 1] = math.nan  # target 1 does not exist at step 3
    out = simulate_detections(sensor, x, detection_probability=0.8, clutter_rate=2.5, region=REGION,
                              generator=torch.Generator().manual_seed(1))
    T, R, D, m = out.z.shape
    assert (T, R, m) == (20, 50, 2) and D >= 3 and out.present.shape == out.origin.shape == (T, R, D)
    assert out.z.dtype == torch.float64 and out.origin.dtype == torch.long and out.present.dtype == torch.bool
    assert torch.isnan(out.z[~out.present]).all() and torch.isfinite(out.z[out.present]).all()
    assert (out.origin[~out.present] == -1).all()
    # the present rows first
    assert not (out.present[..., 1:] & ~out.present[..., :-1]).any()
    own = out.present & (out.origin >= 0)
    truth = x[..., [0, 2]].gather(-2, out.origin.clamp_min(0).unsqueeze(-1).expand(T, R, D, 2))
    assert (out.z[own] - truth[own]).abs().max() < 1e-5
    clutter = out.present & (out.origin < 0)
    zc = out.z[clutter]
    assert ((zc >= REGION[:, 0]) & (zc <= REGION[:, 1])).all()
    assert not (out.origin[3] == 1).any()  # the absent target is never detected
    # each target at most once a scan
    for k in range(3):
        assert ((out.origin == k).sum(-1) <= 1).all()


def test_detection_rate_and_clutter_count_follow_their_laws():
    sensor = PositionMeasurement(4, [0, 2], 1.0, dtype=torch.float64)
    x = _targets(steps=40, runs=200, N=4)
    pd, rate = 0.7, 1.8
    out = simulate_detections(sensor, x, detection_probability=pd, clutter_rate=rate, region=REGION,
                              generator=torch.Generator().manual_seed(2))
    scans = 40 * 200
    hits = (out.origin >= 0).sum().item()
    assert abs(hits / (4 * scans) - pd) < 5 * math.sqrt(pd * (1 - pd) / (4 * scans))
    clutter = (out.present & (out.origin < 0)).sum(-1).double()
    assert abs(clutter.mean().item() - rate) < 5 * math.sqrt(rate / scans)
    assert abs(clutter.var().item() - rate) < 0.15 * rate  # Poisson: variance = mean
    # the order says nothing of the origin: a target's detection sits anywhere among the present rows
    first = out.origin[..., 0]
    assert (first == -1).any() and all((first == k).any() for k in range(4))


def test_certain_detection_without_clutter_is_every_target_and_max_clutter_pads():
    sensor = RangeBearing(4, torch.diag(torch.tensor([1.0, 1e-4], dtype=torch.float64)), origin=(-1e3, 0.0))
    x = _targets(steps=4, runs=6, N=2)
    out = simulate_detections(sensor, x, detection_probability=1.0, generator=torch.Generator().manual_seed(3))
    assert out.z.shape == (4, 6, 2, 2) and out.present.all()
    assert torch.equal(out.origin.sort(-1).values, torch.tensor([0, 1]).expand(4, 6, 2))
    padded = simulate_detections(sensor, x, detection_probability=0.0, clutter_rate=0.5,
                                 region=torch.tensor([[0.0, 2e3], [-1.0, 1.0]]), max_clutter=7,
                                 generator=torch.Generator().manual_seed(4))
    assert padded.z.shape == (4, 6, 9, 2) and (padded.origin == -1).all()
    quiet = simulate_detections(sensor, x, detection_probability=1.0, max_clutter=3,
                                generator=torch.Generator().manual_seed(5))
    assert quiet.z.shape == (4, 6, 5, 2) and quiet.present[..., :2].all() and not quiet.present[..., 2:].any()


def test_clear_errors():
    sensor = PositionMeasurement(4, [0, 2], 1.0)
    x = _targets(steps=2, runs=2, N=2).float()
    with pytest.raises(ValueError, match="states"):
        simulate_detections(sensor, x[..., :3], detection_probability=0.9)
    with pytest.raises(ValueError, match="region"):
        simulate_detections(sensor, x, detection_probability=0.9, clutter_rate=1.0)
    with pytest.raises(ValueError, match="region"):
        simulate_detections(sensor, x, detection_probability=0.9, clutter_rate=1.0, region=torch.zeros(2, 2))
    with pytest.raises(ValueError, match="detection_probability"):
        simulate_detections(sensor, x, detection_probability=1.5)
    with pytest.raises(ValueError, match="clutter_rate"):
        simulate_detections(sensor, x, detection_probability=0.5, clutter_rate=-1.0)


def test_states_of_another_dtype_than_the_sensor_name_states():
    """Issue 44: float32 states for a float64 sensor (or the reverse) were a raw dtype error of a matrix
    product; now a TypeError naming ``states``. Integer states take the sensor's dtype; no targets
    (N = 0) give the clutter alone."""
    sensor = PositionMeasurement(4, [0, 2], 1.0, dtype=torch.float64)
    x = _targets(steps=2, runs=2, N=2)
    for states, model in ((x.float(), sensor), (x, PositionMeasurement(4, [0, 2], 1.0, dtype=torch.float32))):
        with pytest.raises(TypeError, match=r"^states: dtype torch.float\d\d differs from the measurement model's"):
            simulate_detections(model, states, detection_probability=0.9, clutter_rate=1.0, region=REGION)
    det = simulate_detections(sensor, x.round().long(), detection_probability=1.0)
    assert det.z.dtype == torch.float64 and det.present.all()
    det = simulate_detections(sensor, x[..., :0, :], detection_probability=0.9, clutter_rate=2.0, region=REGION,
                              generator=torch.Generator().manual_seed(0))
    assert (det.origin == -1).all() and det.z.shape[:2] == (2, 2)


def test_the_draws_do_not_depend_on_the_default_dtype():
    """Every draw takes the states' dtype: a float64 simulation is the same under either default."""
    sensor = PositionMeasurement(4, [0, 2], 4.0, dtype=torch.float64)
    states = torch.randn(6, 3, 2, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 10
    box = torch.tensor([[-50.0, 50.0], [-50.0, 50.0]], dtype=torch.float64)
    made = {}
    before = torch.get_default_dtype()
    try:
        for default in (torch.float32, torch.float64):
            torch.set_default_dtype(default)
            det = simulate_detections(sensor, states, detection_probability=0.8, clutter_rate=4.0, region=box,
                                      generator=torch.Generator().manual_seed(1))
            made[default] = det
    finally:
        torch.set_default_dtype(before)
    a, b = made[torch.float32], made[torch.float64]
    assert torch.equal(a.present, b.present) and torch.equal(a.origin, b.origin)
    assert torch.equal(a.z.nan_to_num(-1.0), b.z.nan_to_num(-1.0))

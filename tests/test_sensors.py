"""Several sensors updating one belief in turn (torchmm.association.SequentialSensors, issue 46): the
linear Gaussian case against the stacked sensor (the theory: sequential = joint update with independent
noises), a silent sensor against the other alone, alternating copies of one sensor against that sensor on
the merged scans (JPDA, MHT, managed tracks: every belief type through the report mask), no host read,
and the errors."""

from __future__ import annotations

import math

import pytest
import torch

from tests.test_jpda import _imm, _scene
from torchmm import GaussianBelief, KalmanFilter, run_filter
from torchmm.association import (
    JIPDA,
    JPDA,
    MHT,
    ManagedTracks,
    SensorScans,
    SequentialSensors,
    position_initiator,
)
from torchmm.models import ConstantVelocity, LinearMeasurement, PositionMeasurement
from torchmm.runtime import no_host_sync

f64 = torch.float64


def test_linear_gaussian_sensors_in_turn_equal_the_stacked_sensor():
    """Two independent position sensors (x only, and x and y) updated in turn = one Kalman update with
    the stacked measurement and block-diagonal noise; a step where the second did not report = the stacked
    measurement with its components missing (1e-12, log-likelihood too)."""
    gen = torch.Generator().manual_seed(3)
    motion = ConstantVelocity(2, dt=1.0, q=0.3, dtype=f64)
    a = PositionMeasurement(4, [0], 2.0, dtype=f64)
    b = PositionMeasurement(4, [0, 2], 0.5, dtype=f64)
    H = torch.zeros(3, 4, dtype=f64)
    H[0, 0] = H[1, 0] = H[2, 2] = 1.0
    stacked = LinearMeasurement(H, torch.diag(torch.tensor([2.0, 0.5, 0.5], dtype=f64)))
    T, runs = 9, 4
    z = torch.randn(T, runs, 3, generator=gen, dtype=f64) * 3
    reports = torch.ones(T, runs, 2, dtype=torch.bool)
    reports[2, :, 1] = reports[5, 1, 1] = False  # the second sensor silent (one run at step 5)
    reports[7, 2, 0] = False
    kf = KalmanFilter(motion, a)
    seq = SequentialSensors([kf, kf.with_sensor(b)])
    prior = GaussianBelief(torch.zeros(runs, 4, dtype=f64), 10 * torch.eye(4, dtype=f64))
    ours = run_filter(seq, prior, SensorScans((z[..., :1], z[..., 1:]), reports))
    missing = torch.cat([z[..., :1].masked_fill(~reports[..., :1], math.nan),
                         z[..., 1:].masked_fill(~reports[..., 1:], math.nan)], -1)
    ref = run_filter(KalmanFilter(motion, stacked), prior, missing)
    torch.testing.assert_close(ours.belief.mean, ref.belief.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ours.belief.cov, ref.belief.cov, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ours.log_likelihood, ref.log_likelihood, rtol=1e-12, atol=1e-12)


def _alternate(z: torch.Tensor):
    """The scans ``z (T, runs, D, m)`` split between two sensors: the first reports the even steps, the
    second the odd ones (the other's scan at a silent step is noise, never read)."""
    T = z.shape[0]
    even = (torch.arange(T) % 2 == 0).view(T, 1)
    reports = torch.stack([even, ~even], -1).expand(T, z.shape[1], 2)
    junk = torch.full_like(z, 1e3)
    return SensorScans((torch.where(even.view(T, 1, 1, 1), z, junk), torch.where(even.view(T, 1, 1, 1), junk, z)),
                       reports)


@pytest.mark.parametrize("kind", ["jpda", "imm-mht", "managed"])
def test_alternating_copies_of_one_sensor_equal_that_sensor(kind):
    """Two copies of one sensor (own filter objects) reporting on alternate steps = one sensor reporting
    every step, for every belief type the report mask passes through (a joint Gaussian, an MHT's
    hypotheses over IMM tracks, a managed track table): 1e-12."""
    motion, sensor, prior, det, truth, options = _scene(8, 3, 3, seed=7, clutter=5.0)

    def make():
        if kind == "jpda":
            return JPDA(KalmanFilter(motion, sensor), **options), prior
        if kind == "imm-mht":
            imm = _imm(2)
            mht = MHT(imm, hypotheses=4, n_scan=2, **options)
            return mht, mht.initial_belief(prior)
        start = position_initiator(4, [0, 2], sensor.R, 4.0)
        managed = ManagedTracks(JIPDA(KalmanFilter(motion, sensor), survival_probability=0.99, method="lbp",
                                      **options), capacity=6, initiate=start)
        return managed, managed.initial_belief((3,), dtype=f64)

    single, belief = make()
    ref = run_filter(single, belief, det.z, record="estimate")
    seq = SequentialSensors([make()[0], make()[0]])
    ours = run_filter(seq, belief, _alternate(det.z), record="estimate")
    torch.testing.assert_close(ours.belief.mean, ref.belief.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ours.log_likelihood, ref.log_likelihood, rtol=1e-12, atol=1e-12)


def test_a_silent_sensor_changes_nothing_and_an_empty_scan_does():
    """A sensor that never reports leaves the other's run as it is (1e-12, its scans of garbage unread);
    one that reports empty scans is an update (every track missed: the likelihood changes)."""
    motion, sensor, prior, det, truth, options = _scene(6, 2, 2, seed=4)
    kf = KalmanFilter(motion, sensor)
    jpda = JPDA(kf, **options)
    other = JPDA(kf.with_sensor(PositionMeasurement(4, [0, 2], 0.3, dtype=f64)), detection_probability=0.8,
                 clutter_density=1e-3)
    ref = run_filter(jpda, prior, det.z)
    T = det.z.shape[0]
    silent = torch.tensor([True, False]).expand(T, 2)
    garbage = torch.full((T, 2, 3, 2), math.inf, dtype=f64)
    ours = run_filter(SequentialSensors([jpda, other]), prior, SensorScans((det.z, garbage), silent))
    torch.testing.assert_close(ours.belief.mean, ref.belief.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ours.log_likelihood, ref.log_likelihood, rtol=1e-12, atol=1e-12)
    empty = torch.full((T, 2, 3, 2), math.nan, dtype=f64)
    heard = run_filter(SequentialSensors([jpda, other]), prior, SensorScans((det.z, empty), torch.ones(T, 2, 2, dtype=torch.bool)))
    assert bool((heard.log_likelihood < ref.log_likelihood).all())  # (1 - P_D P_G) per track, every scan


def test_the_steps_never_read_values_on_the_host():
    motion, sensor, prior, det, truth, options = _scene(4, 2, 2, seed=1)
    kf = KalmanFilter(motion, sensor)
    seq = SequentialSensors([JPDA(kf, **options), JPDA(kf.with_sensor(PositionMeasurement(4, [0, 2], 0.3, dtype=f64)),
                                                        **options)])
    z = _alternate(det.z)
    belief = seq.step(prior, SensorScans(tuple(s[0] for s in z.scans), z.reports[0])).belief
    with no_host_sync("SequentialSensors.step"):
        out = seq.step(belief, SensorScans(tuple(s[1] for s in z.scans), z.reports[1]))
    assert out.belief.mean.shape == (2, 2, 4)


def test_errors_name_the_argument():
    motion, sensor, prior, det, truth, options = _scene(3, 2, 2, seed=1)
    kf = KalmanFilter(motion, sensor)
    jpda = JPDA(kf, **options)
    seq = SequentialSensors([jpda, JPDA(kf, **options)])
    with pytest.raises(TypeError, match="filters: expected a non-empty list"):
        SequentialSensors([])
    with pytest.raises(ValueError, match=r"filters\[1\]: state_dim 2 differs"):
        SequentialSensors([jpda, KalmanFilter(ConstantVelocity(1, dtype=f64), PositionMeasurement(2, [0], 1.0))])
    with pytest.raises(ValueError, match=r"filters\[1\]: a joint association and a per-track"):
        SequentialSensors([jpda, kf])
    with pytest.raises(TypeError, match="measurements: expected SensorScans"):
        run_filter(seq, prior, det.z)
    reports = torch.ones(3, 2, 2, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"measurements.scans: expected one datum per sensor \(2\), got 1"):
        run_filter(seq, prior, SensorScans((det.z,), reports))
    with pytest.raises(TypeError, match="measurements.reports: expected a bool tensor"):
        run_filter(seq, prior, SensorScans((det.z, det.z), reports.double()))
    with pytest.raises(ValueError, match=r"measurements.reports: expected \(T, \*R, 2\)"):
        run_filter(seq, prior, SensorScans((det.z, det.z), torch.ones(3, 5, 2, dtype=torch.bool)))
    with pytest.raises(ValueError, match=r"measurements.scans\[1\]"):
        run_filter(seq, prior, SensorScans((det.z, det.z[..., :1]), reports))
    with pytest.raises(TypeError, match="SequentialSensors cannot be a mode filter"):
        seq.check_bank_member("filter", 2)

"""A trajectory knows what made it (issue 29, defect 2): ``smooth`` checks the filter, the data, the
controls, the per-step models and the trajectory itself against the run's record, and refuses a
mismatch with an error naming the argument, instead of returning finite wrong numbers."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
import pickle

import pytest
import torch

from torchmm import (
    IMM,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    LinearMotion,
    PositionMeasurement,
    Trajectory,
    parallel,
    run_filter,
    smooth,
)
from torchmm.runtime import no_host_sync

D = torch.float64


def _kalman(steps=12, runs=3, seed=0):
    sensor = PositionMeasurement(2, [0], 1.0, dtype=D)
    kf = KalmanFilter(ConstantVelocity(1, q=0.1, dtype=D), sensor)
    g = torch.Generator().manual_seed(seed)
    z = torch.cumsum(torch.randn(steps, runs, 1, generator=g, dtype=D), 0)
    z[3, 1] = float("nan")
    belief0 = GaussianBelief(torch.zeros(runs, 2, dtype=D), 4 * torch.eye(2, dtype=D).expand(runs, 2, 2))
    return kf, sensor, belief0, z


def _imm(steps=10, runs=3, seed=1):
    sensor = PositionMeasurement(2, [0], 1.0, dtype=D)
    bank = ConstantVelocity(1, q=0.1, acceleration=[[0.0], [1.0]], dtype=D)
    imm = IMM(KalmanFilter(bank, sensor), torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=D))
    g = torch.Generator().manual_seed(seed)
    z = torch.cumsum(torch.randn(steps, runs, 1, generator=g, dtype=D), 0)
    belief0 = imm.initial_belief(GaussianBelief(torch.zeros(runs, 2, dtype=D), 4 * torch.eye(2, dtype=D)))
    return imm, belief0, z


# -- the filter --------------------------------------------------------------------------------------

def test_another_filter_is_refused():
    """The issue's example: a filter with dt = 5 smoothing a dt = 1 run was off by 39, silently."""
    kf, sensor, belief0, z = _kalman()
    traj = run_filter(kf, belief0, z)
    with pytest.raises(ValueError, match="filter: not the filter that made this trajectory"):
        smooth(KalmanFilter(ConstantVelocity(1, dt=5.0, q=0.1, dtype=D), sensor), traj)
    # an equal filter built again is refused too (identity, documented in docs/robustness.md)
    with pytest.raises(ValueError, match="filter: not the filter"):
        smooth(KalmanFilter(ConstantVelocity(1, q=0.1, dtype=D), sensor), traj)
    with pytest.raises(TypeError, match="filter: a UnscentedKalmanFilter, but a KalmanFilter made"):
        from torchmm import UnscentedKalmanFilter

        smooth(UnscentedKalmanFilter(kf.motion, sensor), traj)
    # the filter that ran, or none (the trajectory's own), give the same smoother
    want = smooth(kf, traj).belief
    for got in (smooth(traj).belief, smooth(traj, z).belief, smooth(kf, traj, z).belief):
        torch.testing.assert_close(got.mean, want.mean, rtol=0, atol=0)
        torch.testing.assert_close(got.cov, want.cov, rtol=0, atol=0)


def test_a_filter_changed_in_place_since_the_run_is_refused():
    kf, _, belief0, z = _kalman()
    traj = run_filter(kf, belief0, z)
    with torch.no_grad():
        kf.motion.Q.mul_(10.0)  # e.g. an optimiser step between run_filter and smooth
    with pytest.raises(ValueError, match="filter: its parameters or buffers changed"):
        smooth(kf, traj)


# -- the data -------------------------------------------------------------------------------------------

def test_other_data_are_refused_by_the_two_filter_smoother():
    """``smooth(imm, traj, z.flip(0))`` smoothed the reversed data silently."""
    imm, belief0, z = _imm()
    traj = run_filter(imm, belief0, z)
    want = smooth(imm, traj, z).belief
    for bad in (z.flip(0), z[:, [1, 0, 2]], z + 1e-3,
                torch.where(torch.arange(10).view(10, 1, 1) == 4, float("nan"), z)):
        with pytest.raises(ValueError, match="measurements: not the data run_filter filtered"):
            smooth(imm, traj, bad)
    with pytest.raises(ValueError, match=r"measurements: expected shape \(10, 3, 1\)"):
        smooth(imm, traj, z[:9])
    with pytest.raises(TypeError, match="measurements: dtype torch.float32 differs"):
        smooth(imm, traj, z.float())
    # a copy of the same data, and the trajectory's own (carried), give the same smoother
    for got in (smooth(imm, traj, z.clone()).belief, smooth(imm, traj).belief, smooth(traj).belief):
        torch.testing.assert_close(got.mode_probs, want.mode_probs, rtol=0, atol=0)
        torch.testing.assert_close(got.estimate().mean, want.estimate().mean, rtol=0, atol=0)


def test_data_changed_in_place_after_the_run_are_refused():
    imm, belief0, z = _imm()
    traj = run_filter(imm, belief0, z)
    z[2, 0] += 1.0
    with pytest.raises(ValueError,
                       match="measurements: the measurements given to run_filter were changed in place"):
        smooth(imm, traj)
    with pytest.raises(ValueError, match="measurements: not the data run_filter filtered"):
        smooth(imm, traj, z)
    z[2, 0] -= 1.0  # restored: the checksum agrees again
    smooth(imm, traj)


def test_the_rts_smoother_checks_data_it_is_given_and_reads_nothing_for_the_runs_own():
    kf, _, belief0, z = _kalman()
    traj = run_filter(kf, belief0, z)
    with pytest.raises(ValueError, match="measurements: not the data"):
        smooth(kf, traj, z.flip(0))
    with no_host_sync("smooth with the run's own objects"):  # identity and version counters: no host read
        smooth(kf, traj, z)
        smooth(traj)


def test_controls_are_checked_and_carried():
    kf, sensor, belief0, z = _kalman()
    driven = KalmanFilter(LinearMotion(kf.motion.F, kf.motion.Q,
                                       input_matrix=torch.tensor([[0.5], [1.0]], dtype=D)),
                          sensor)
    u = torch.randn(12, 3, 1, generator=torch.Generator().manual_seed(2), dtype=D)
    traj = run_filter(driven, belief0, z, controls=u)
    want = smooth(driven, traj, controls=u).belief
    torch.testing.assert_close(smooth(driven, traj).belief.mean, want.mean, rtol=0, atol=0)  # carried
    with pytest.raises(ValueError, match="controls: not the data run_filter filtered"):
        smooth(driven, traj, controls=u.flip(0))
    plain = run_filter(kf, belief0, z)
    with pytest.raises(ValueError, match="controls: run_filter ran without controls"):
        smooth(kf, plain, controls=u)


# -- the per-step models ----------------------------------------------------------------------------------

def test_per_step_motions_are_carried_and_checked():
    """A run with per-step motions (a per-step dt) smoothed without them used the filter's model."""
    kf, sensor, belief0, z = _kalman()
    dts = [0.5 + 0.25 * (k % 4) for k in range(12)]
    motions = [ConstantVelocity(1, dt=dt, q=0.1, dtype=D) for dt in dts]
    traj = run_filter(kf, belief0, z, motions=motions)
    want = smooth(kf, traj, motions=motions).belief
    for got in (smooth(kf, traj).belief, smooth(traj).belief, smooth(kf, traj, motions=list(motions)).belief):
        torch.testing.assert_close(got.mean, want.mean, rtol=0, atol=0)
    assert (smooth(kf, dataclasses.replace(traj, provenance=None)).belief.mean - want.mean).abs().max() > 1e-3
    with pytest.raises(ValueError, match="motions: entry 0 is not the model given to run_filter for step 0"):
        smooth(kf, traj, motions=[ConstantVelocity(1, dt=dt, q=0.1, dtype=D) for dt in dts])
    with pytest.raises(ValueError, match="motions: run_filter ran without per-step motions"):
        smooth(kf, run_filter(kf, belief0, z), motions=motions)
    # a callable k -> model, as run_filter takes it, is carried too
    traj = run_filter(kf, belief0, z, motions=lambda k: motions[k])
    torch.testing.assert_close(smooth(traj).belief.mean, want.mean, rtol=0, atol=0)


def test_per_step_motions_of_a_multiple_model_filter_are_carried():
    imm, belief0, z = _imm()
    bank = ConstantVelocity(1, dt=0.5, q=0.1, acceleration=[[0.0], [1.0]], dtype=D)
    motions = [None if k % 2 else bank for k in range(10)]  # None: the filter's own at that step
    traj = run_filter(imm, belief0, z, motions=motions)
    want = smooth(imm, traj, z, motions=motions).belief
    got = smooth(traj).belief
    torch.testing.assert_close(got.mode_probs, want.mode_probs, rtol=0, atol=0)
    kim = smooth(imm, traj, method="kim").belief
    torch.testing.assert_close(kim.mode_probs,
                               smooth(imm, traj, method="kim", motions=motions).belief.mode_probs)


# -- the trajectory itself ---------------------------------------------------------------------------------

def _reversed(b):
    return b.map_tensors(lambda t, e: t.flip(0))


def test_a_reversed_or_sliced_trajectory_is_refused():
    kf, _, belief0, z = _kalman()
    traj = run_filter(kf, belief0, z)
    for bad in (dataclasses.replace(traj, belief=_reversed(traj.belief), prior=_reversed(traj.prior)),
                dataclasses.replace(traj, belief=traj.belief[:6], prior=traj.prior[:6])):
        with pytest.raises(ValueError, match="trajectory: its beliefs are not the ones run_filter returned"):
            smooth(kf, bad)
    # dropping a field that smooth does not use keeps the record valid
    smooth(kf, dataclasses.replace(traj, innovation=None, innovation_cov=None))


def test_trajectories_without_a_record_are_smoothed_as_given():
    """Built by hand, unpickled, deep-copied or mapped: no record, so the filter must be passed."""
    kf, _, belief0, z = _kalman()
    traj = run_filter(kf, belief0, z)
    want = smooth(kf, traj).belief.mean
    hand = Trajectory(traj.belief, traj.prior, traj.log_likelihood, None, None, None)
    for other in (hand, pickle.loads(pickle.dumps(traj)), copy.deepcopy(traj)):
        assert other.provenance is None
        torch.testing.assert_close(smooth(kf, other).belief.mean, want)
        with pytest.raises(TypeError, match="filter: this trajectory carries no record"):
            smooth(other)
    import torch.utils._pytree as pytree

    assert pytree.tree_map(lambda a: a, traj.provenance) is None


def test_parallel_filter_trajectories_carry_their_record():
    kf, _, belief0, z = _kalman()
    par = parallel.filter(kf, belief0, z)
    assert par.provenance.made_by == "torchmm.parallel.filter"
    want = smooth(kf, run_filter(kf, belief0, z)).belief
    torch.testing.assert_close(smooth(par).belief.mean, want.mean, rtol=1e-9, atol=1e-9)
    with pytest.raises(ValueError, match="measurements: not the data torchmm.parallel.filter filtered"):
        smooth(kf, par, z.flip(0))
    with pytest.raises(ValueError, match="filter: not the filter"):
        smooth(KalmanFilter(ConstantVelocity(1, dt=5.0, q=0.1, dtype=D), kf.measurement), par)


@pytest.mark.parametrize("small", [False, True], ids=["torch", "numpy"])
def test_the_fingerprint_is_read_once_at_entry_not_per_step(small, monkeypatch):
    """run_filter reads the data's checksums once (with the infinite count), never per step: the
    number of host reads does not grow with T, and every stream's fingerprint comes in one read (the
    torch pass of a device's or a large tensor); a small CPU tensor's are computed in NumPy, no read."""
    import torchmm.provenance as provenance

    if not small:
        monkeypatch.setattr(provenance, "_stats_numpy", lambda t: None)
    reads = []
    real = torch.Tensor.tolist

    def counting(self):
        reads.append(tuple(self.shape))
        return real(self)

    counts = []
    for steps in (5, 40):
        kf, sensor, belief0, z = _kalman(steps=steps)
        driven = KalmanFilter(LinearMotion(kf.motion.F, kf.motion.Q, input_matrix=torch.ones(2, 1, dtype=D)),
                              sensor)
        reads.clear()
        torch.Tensor.tolist = counting
        try:
            traj = run_filter(driven, belief0, z, controls=torch.zeros(steps, 3, 1, dtype=D))
        finally:
            torch.Tensor.tolist = real
        counts.append(len(reads))
        assert ((2, 7) in reads) != small  # measurements and controls: one (streams, statistics) read
        assert traj.provenance.data[0].shape == (steps, 3, 1)
    assert counts[0] == counts[1], counts


def test_the_fingerprint_in_blocks_equals_a_numpy_reference(monkeypatch):
    """The pass runs in blocks (bounded memory at any size): any block size gives the float64 sums a
    NumPy reference computes, and the exact pattern of missing entries."""
    import numpy as np

    from torchmm import provenance

    rng = np.random.default_rng(3)
    data = rng.normal(size=(13, 5, 2))
    data[rng.uniform(size=data.shape) < 0.1] = np.nan
    data[0, 0, 0] = np.inf
    x = data.reshape(-1)
    finite = np.isfinite(x)
    index = np.arange(1, x.size + 1)
    value = np.where(finite, x, 0.0)
    want = [1.0, finite.sum(), value.sum(), np.abs(value).sum(), value @ index / x.size,
            np.abs(value) @ index / x.size, index[finite].sum()]
    for block in (7, 64, 1 << 18):
        monkeypatch.setattr(provenance, "_BLOCK", block)
        got = provenance._stats(torch.tensor(data)).tolist()
        np.testing.assert_allclose(got, want, rtol=1e-12)
        assert got[6] == want[6]  # exact


def test_the_numpy_fingerprint_equals_the_torch_pass():
    """A small CPU tensor's statistics in NumPy (issue 47: the one-shot call's cost) equal the torch
    pass's (sums to 1e-13 relative, the count of finite entries and their index sum exactly), with
    missing and infinite entries, float32 and float64."""
    from torchmm.provenance import _stats, _stats_numpy

    g = torch.Generator().manual_seed(2)
    for dtype, missing in itertools.product((torch.float64, torch.float32), (True, False)):
        x = torch.randn(37, 3, 2, generator=g, dtype=dtype) * 100
        if missing:  # (else every entry finite: the NumPy pass's shorter route)
            x[3, 1, 0], x[7, 2, 1], x[0, 0, 0] = math.nan, math.inf, -math.inf
        ours, theirs = _stats_numpy(x), _stats(x).tolist()
        assert ours[0] == theirs[0] == (2 if missing else 0) and ours[1] == theirs[1] and ours[6] == theirs[6]
        assert ours[2:6] == pytest.approx(theirs[2:6], rel=1e-13)
    assert _stats_numpy(torch.arange(5)) is None  # (integers: the torch pass)

"""MHT that starts, confirms and deletes its own tracks (torchmm.association.ManagedMHT, issue 46): the MHT
where no target is born, targets found from nothing with their labels kept, IMM tracks, batched = per run,
no host read, and the errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.test_jpda import R, _imm, _scene
from torchmm import KalmanFilter, run_filter
from torchmm.association import MHT, ManagedMHT, TrackHypotheses, position_initiator
from torchmm.metrics import gospa
from torchmm.runtime import no_host_sync


def _managed(filt, options, **kw):
    kw = {"hypotheses": 6, "capacity": 6, "n_scan": 3, "birth_density": 1e-5,
          "initiate": position_initiator(4, [0, 2], R, 4.0)} | kw
    return ManagedMHT(filt, **options, **kw)


@pytest.mark.parametrize("imm", [False, True])
def test_without_births_it_is_the_mht(imm):
    """Started from the MHT's tracks, every slot full and births all but impossible: the MHT's estimate and
    log-likelihood (1e-12) over crossing targets in clutter."""
    motion, sensor, prior, det, truth, options = _scene(12, 4, 3, seed=11, clutter=6.0)
    filt = _imm(2) if imm else KalmanFilter(motion, sensor)
    mht = MHT(filt, hypotheses=5, k=5, n_scan=2, **options)
    ref = run_filter(mht, mht.initial_belief(prior), det.z, record="estimate")
    ours = _managed(filt, options, hypotheses=5, k=5, n_scan=2, capacity=3, birth_density=1e-300, m_of_n=(1, 1),
                    max_misses=None)
    got = run_filter(ours, ours.initial_belief(tracks=prior), det.z, record="estimate")
    torch.testing.assert_close(got.belief.mean, ref.belief.mean, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(got.log_likelihood, ref.log_likelihood, rtol=1e-12, atol=1e-10)


@pytest.mark.parametrize("imm", [False, True])
def test_targets_are_found_from_nothing_and_keep_their_labels(imm):
    """From an empty table: after the first scans every target has one confirmed track within 3 sigma of
    the noise, each with one label from its confirmation on (the best hypothesis's), and clutter makes no
    confirmed track that lasts (GOSPA's false part small over the last half)."""
    motion, sensor, prior, det, truth, options = _scene(24, 4, 3, seed=5, clutter=3.0)
    mht = _managed(_imm(2) if imm else KalmanFilter(motion, sensor), options, m_of_n=(3, 4))
    traj = run_filter(mht, mht.initial_belief((4,)), det.z, record=lambda out: out._replace(
        belief=out.belief.best(), prior=None, extras=None))
    table = traj.belief  # the best hypothesis's slots (T, runs, K)
    shown = table.confirmed()
    position = table.estimate().mean[..., [0, 2]]
    out = gospa(position, truth[..., [0, 2]], c=10.0, p=2.0, estimate_present=shown)
    late = slice(12, None)
    # measured: missed 0, false 3.1 (one clutter track confirmed 3 of 4 in one run, 1/16 of a target's 50)
    assert float(out["missed"][late].mean()) < 10.0 and float(out["false"][late].mean()) < 10.0, out
    assigned = out["assigned"][late]  # (T/2, runs, N): each target's track
    labels = torch.where(assigned >= 0, table.label[late].gather(-1, assigned.clamp(min=0)), -1)
    assert bool((labels >= 0).float().mean() > 0.9)
    assert bool((labels == labels[-1:]).float().mean() > 0.9)  # one label a target


def test_batched_equals_per_run_and_no_host_read():
    motion, sensor, prior, det, truth, options = _scene(8, 3, 2, seed=2, clutter=4.0)
    mht = _managed(KalmanFilter(motion, sensor), options)
    every = run_filter(mht, mht.initial_belief((3,)), det.z)
    one = run_filter(mht, mht.initial_belief((1,)), det.z[:, 1:2])
    torch.testing.assert_close(every.log_likelihood[:, 1:2], one.log_likelihood, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(every.belief.estimate().mean[:, 1:2], one.belief.estimate().mean, rtol=1e-12, atol=1e-12)
    belief = mht.step(mht.initial_belief((3,)), det.z[0]).belief
    with no_host_sync("ManagedMHT.step"):
        out = mht.step(belief, det.z[1])
    assert isinstance(out.belief, TrackHypotheses) and out.belief.alive.shape == (3, 6, 6)


def test_a_new_track_takes_its_detection_and_the_mode_probabilities():
    motion, sensor, prior, det, truth, options = _scene(1, 1, 1, seed=0, clutter=1e-9)
    mht = _managed(_imm(2), options, mode_probs=[0.3, 0.7])
    z = torch.tensor([[[5.0, -2.0]]], dtype=torch.float64)
    out = mht.step(mht.initial_belief((1,)), z).belief
    best = out.best()
    assert int(best.label[0, 0]) == 0 and bool(best.log_existence[0, 0] == 0) and not bool(best.confirmed()[0, 0])
    torch.testing.assert_close(best.mode_log_probs[0, 0].exp(), torch.tensor([0.3, 0.7], dtype=torch.float64))
    torch.testing.assert_close(best.estimate().mean[0, 0, [0, 2]], z[0, 0])


def test_errors_name_the_argument():
    motion, sensor, prior, det, truth, options = _scene(1, 2, 2, seed=0)
    kf = KalmanFilter(motion, sensor)
    with pytest.raises(ValueError, match="m_of_n"):
        _managed(kf, options, m_of_n=(3, 2))
    with pytest.raises(TypeError, match="initiate"):
        _managed(kf, options, initiate=3)
    with pytest.raises(ValueError, match="birth_density"):
        _managed(kf, options, birth_density=0.0)
    with pytest.raises(ValueError, match="tracks: 2 tracks, the table has 1 slots"):
        _managed(kf, options, capacity=1).initial_belief(tracks=prior)
    with pytest.raises(ValueError, match="mode_probs"):
        _managed(kf, options, mode_probs=[0.5, 0.5])
    mht = _managed(kf, options)
    with pytest.raises(TypeError, match="belief: ManagedMHT takes its TrackHypotheses"):
        mht.update(prior, det.z[0])


def test_track_scores_are_the_log_likelihood_ratios_and_confirm_and_delete():
    """The track-oriented rule (trackerTOMHT's): one target, practically no clutter, P_D = 0.8 (misses): the
    track's score is log(b) at its birth plus log(P_D N(nu; 0, S) / lambda) at each detection (nu, S from a
    float64 NumPy Kalman filter of its own detections) and log(1 - P_D P_G) at each miss (1e-9); it is
    confirmed when the score reaches confirm_score, and a drop of delete_drop below its peak deletes it."""
    motion, sensor, prior, det, truth, options = _scene(12, 1, 1, seed=4, pd=0.8, clutter=1e-9)
    z = det.z[:, :, :1].clone()  # the target's detection (the clutter rows are empty), NaN where missed
    z[:3] = truth[:3, :, :, [0, 2]]  # detected at first (else the track's ratio falls below clutter's and the
    z[8:10] = math.nan                # best hypothesis drops it); two misses running (the deletion below)
    options = options | {"clutter_density": 1e-6}
    b = 1e-5
    mht = _managed(KalmanFilter(motion, sensor), options, birth_density=b, m_of_n=None, confirm_score=30.0,
                   max_misses=None, delete_drop=1e9)
    traj = run_filter(mht, mht.initial_belief((1,)), z, record=lambda out: out._replace(
        belief=(out.belief.best(), out.belief.best_scores()), prior=None, extras=None))
    table, scores = traj.belief
    F, Q = motion.F.numpy(), motion.Q.numpy()
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 2] = 1.0
    Rm = R.numpy()
    x = np.array([z[0, 0, 0, 0].item(), 0.0, z[0, 0, 0, 1].item(), 0.0])
    P = H.T @ Rm @ H + np.diag([0.0, 4.0, 0.0, 4.0])
    pd, pg, lam = options["detection_probability"], options["gate_probability"], options["clutter_density"]
    expected, firm = math.log(b / lam), False
    for k in range(12):
        if k > 0:
            x, P = F @ x, F @ P @ F.T + Q
            y = z[k, 0, 0].numpy()
            if np.isfinite(y).all():
                S = H @ P @ H.T + Rm
                nu = y - H @ x
                ll = -0.5 * (nu @ np.linalg.solve(S, nu) + np.log(np.linalg.det(2 * np.pi * S)))
                expected += math.log(pd) + ll - math.log(lam)
                K = P @ H.T @ np.linalg.inv(S)
                x, P = x + K @ nu, (np.eye(4) - K @ H) @ P
            else:
                expected += math.log1p(-pd * pg)
        firm = firm or expected >= 30.0
        slot = int(torch.nonzero(table.label[k, 0] == 0)[0])
        assert float(scores[k, 0, slot]) == pytest.approx(expected, rel=1e-9, abs=1e-9)
        assert bool(table.confirmed()[k, 0, slot]) == firm
    assert firm  # (confirmed along the way)
    # a drop of 2 below the peak deletes it: a miss costs log(1 - 0.8 * 0.99) = -1.57, the second -3.1
    strict = _managed(KalmanFilter(motion, sensor), options, birth_density=b, m_of_n=None, confirm_score=30.0,
                      max_misses=None, delete_drop=2.0)
    end = run_filter(strict, strict.initial_belief((1,)), z, record=lambda out: out._replace(
        belief=out.belief.best(), prior=None, extras=None)).belief
    assert bool((end.label[8, 0] == 0).any()) and not bool((end.label[9, 0] == 0).any())
    assert bool((end.label[10:, 0] == 1).any(-1).all())  # the next detection starts a new track


def test_new_targets_left_without_a_slot_are_counted():
    """Capacity 2, five far-apart detections, births far likelier than clutter: the best hypothesis makes
    five new targets, two take the slots, three are counted in extras["unstarted"]."""
    from torchmm.models import ConstantVelocity, PositionMeasurement

    filt = KalmanFilter(ConstantVelocity(2, dt=1.0, q=0.1, dtype=torch.float64),
                        PositionMeasurement(4, [0, 2], 1.0, dtype=torch.float64))
    mht = ManagedMHT(filt, detection_probability=0.9, clutter_density=1e-9, hypotheses=3, capacity=2,
                     birth_density=1e-3, initiate=position_initiator(4, [0, 2], 1.0, 1.0))
    z = torch.tensor([[[100.0 * j, 0.0] for j in range(5)]], dtype=torch.float64)
    out = mht.update(mht.initial_belief((1,), dtype=torch.float64), z)
    assert out.extras["unstarted"].tolist() == [3]

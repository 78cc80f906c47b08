"""Track management by existence (torchmm.association.ManagedTracks): a target that appears is found
and confirmed, clutter's tentative tracks are deleted, labels stay with their tracks, batched equals
per run, no host read."""

from __future__ import annotations

import math

import pytest
import torch

from torchmm import IMM, KalmanFilter, run_filter
from torchmm.association import JIPDA, ManagedTracks, ModeTrackTable, TrackTable, position_initiator
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.simulate import simulate_detections

TURNS = [[0.0, 0.0], [0.5, 0.0], [-0.5, 0.0]]  # an IMM of three accelerations on the x axis


def _scene(runs=6, steps=25, seed=0, modes=None):
    """Two targets, the second from scan 8; ``modes``: the tracks are an IMM over these accelerations
    of the constant-velocity model (a list of ``[ax, ay]``), else one Kalman filter."""
    motion = ConstantVelocity(2, dt=1.0, q=0.1, dtype=torch.float64)
    sensor = PositionMeasurement(4, [0, 2], 4.0, dtype=torch.float64)
    gen = torch.Generator().manual_seed(seed)
    start = torch.tensor([[-40.0, 2.0, 0.0, 0.5], [30.0, -1.0, 30.0, -1.5]], dtype=torch.float64)
    truth = start + torch.cumsum(torch.randn(steps, runs, 2, 4, generator=gen, dtype=torch.float64) * 0.1, 0)
    truth = truth + torch.arange(1, steps + 1, dtype=torch.float64)[:, None, None, None] * \
        torch.stack([start[:, 1], torch.zeros(2), start[:, 3], torch.zeros(2)], -1).to(torch.float64)
    truth[:8, :, 1] = math.nan  # the second target appears at scan 8
    det = simulate_detections(sensor, truth, detection_probability=0.95, clutter_rate=3.0,
                              region=torch.tensor([[-100.0, 100.0], [-100.0, 100.0]]), generator=gen)
    filt = KalmanFilter(motion, sensor)
    if modes is not None:
        M = len(modes)
        bank = ConstantVelocity(2, dt=1.0, q=0.1, acceleration=modes, dtype=torch.float64)
        filt = IMM(KalmanFilter(bank, sensor), torch.full((M, M), 0.1 / max(M - 1, 1), dtype=torch.float64)
                   + (0.9 - 0.1 / max(M - 1, 1)) * torch.eye(M, dtype=torch.float64))
    jipda = JIPDA(filt, detection_probability=0.95, clutter_density=3.0 / 200**2,
                  survival_probability=0.99, method="lbp")
    manager = ManagedTracks(jipda, capacity=8, initiate=position_initiator(4, [0, 2], 4.0, 25.0),
                            birth_existence=0.05, delete=0.01)
    return manager, truth, det


@pytest.mark.parametrize("modes", [None, TURNS], ids=["kalman", "imm"])
def test_targets_are_found_confirmed_and_keep_their_labels(modes):
    manager, truth, det = _scene(modes=modes)
    out = run_filter(manager, manager.initial_belief((6,)), det.z)
    table = out.belief  # batch (T, runs, K)
    assert isinstance(table, TrackTable if modes is None else ModeTrackTable)
    confirmed = table.confirmed(0.9)
    pos = table.estimate().mean[..., [0, 2]]
    for r in range(6):
        for target in range(2):
            near = (pos[-1, r] - truth[-1, r, target, [0, 2]]).norm(dim=-1) < 10  # (K,)
            hits = (near & confirmed[-1, r]).nonzero().flatten()
            assert len(hits) == 1, (r, target, hits)  # exactly one confirmed track on each target
            slot = int(hits[0])
            labels = table.label[-6:, r, slot]
            assert (labels == labels[0]).all() and labels[0] >= 0  # its label stayed the same
        false = confirmed[-1, r].sum() - 2
        assert false == 0, (r, false)  # clutter confirmed no track at the end
    # the second target (from scan 8) was not confirmed before it appeared
    early = confirmed[:8]
    near_b = (pos[:8] - truth[8, :, 1, [0, 2]].unsqueeze(-2)).norm(dim=-1) < 10
    assert not (early & near_b).any()
    assert (table.next_label[-1] >= 2).all()  # labels count up and are never reused


@pytest.mark.parametrize("modes", [None, TURNS], ids=["kalman", "imm"])
def test_batched_equals_per_run_and_no_host_read(modes):
    from torchmm.runtime import no_host_sync

    manager, truth, det = _scene(runs=3, steps=10, seed=1, modes=modes)
    out = run_filter(manager, manager.initial_belief((3,)), det.z)
    one = run_filter(manager, manager.initial_belief((1,)), det.z[:, 1:2])
    torch.testing.assert_close(out.belief.estimate().mean[:, 1], one.belief.estimate().mean[:, 0], rtol=1e-12,
                               atol=1e-10)
    assert torch.equal(out.belief.label[:, 1], one.belief.label[:, 0])
    b = manager.initial_belief((3,))
    with no_host_sync("the track manager's step"):
        for k in range(3):
            b = manager.step(b, det.z[k]).belief
    assert torch.isfinite(b.estimate().mean).all()


def test_an_imm_of_identical_modes_manages_the_same_tracks():
    """Over an IMM of two identical modes the table is the Kalman one's: labels, existence, states."""
    kalman, _, det = _scene(runs=4, steps=16, seed=2)
    imm, _, _ = _scene(runs=4, steps=16, seed=2, modes=[[0.0, 0.0], [0.0, 0.0]])
    a = run_filter(kalman, kalman.initial_belief((4,)), det.z).belief
    b = run_filter(imm, imm.initial_belief((4,)), det.z).belief
    assert torch.equal(a.label, b.label)
    assert (a.label[-1] >= 0).sum() >= 8  # tracks were started (two targets and clutter, 4 runs)
    torch.testing.assert_close(a.log_existence.exp(), b.log_existence.exp(), rtol=0, atol=1e-12)
    live = a.label >= 0
    torch.testing.assert_close(a.mean[live], b.estimate().mean[live], rtol=0, atol=1e-9)


def test_new_tracks_take_the_mode_probabilities_given():
    manager, _, det = _scene(runs=2, steps=3, modes=TURNS)
    given = ManagedTracks(manager.association, capacity=8, initiate=manager.initiate, mode_probs=[0.8, 0.1, 0.1])
    out = given.step(given.predict(given.initial_belief((2,))), det.z[0])
    born = out.extras["born"]
    assert born.any()
    torch.testing.assert_close(out.belief.mode_log_probs[born].exp(),
                               torch.tensor([0.8, 0.1, 0.1], dtype=torch.float64).expand(int(born.sum()), 3))
    with pytest.raises(ValueError, match="mode_probs"):
        ManagedTracks(manager.association, capacity=8, initiate=manager.initiate, mode_probs=[0.5, 0.5])
    kalman, _, _ = _scene(runs=1, steps=2)
    with pytest.raises(ValueError, match="mode_probs: the JIPDA's filter"):
        ManagedTracks(kalman.association, capacity=8, initiate=kalman.initiate, mode_probs=[1.0])


def test_errors_name_the_argument():
    manager, _, det = _scene(runs=1, steps=2)
    with pytest.raises(TypeError, match="initiate"):
        ManagedTracks(manager.association, capacity=4, initiate=3)
    with pytest.raises(TypeError, match="belief: ManagedTracks over KalmanFilter needs a TrackTable"):
        manager.step(manager.initial_belief((1,)).tracks, det.z[0])
    with pytest.raises(ValueError, match="capacity"):
        ManagedTracks(manager.association, capacity=0, initiate=position_initiator(4, [0, 2], 4.0, 25.0))


def test_a_birth_existence_of_zero_and_more_slots_than_the_exact_jipda_takes_are_refused():
    """Issue 44: ``birth_existence=0`` filled every free slot with a labelled track of existence 0 at every
    scan (a slot of existence 0 is a free slot: a contradiction, and the labels ran on); it is refused,
    naming ``birth_existence``. A table larger than the exact JIPDA's ``max_targets`` failed at the first
    scan naming ``belief``; it is refused when the manager is built, naming ``capacity``."""
    manager, _, _ = _scene(runs=1, steps=2)
    initiate = position_initiator(4, [0, 2], 4.0, 25.0)
    with pytest.raises(ValueError, match="^birth_existence: must be positive"):
        ManagedTracks(manager.association, capacity=4, initiate=initiate, birth_existence=0.0)
    exact = JIPDA(manager.association.filter, detection_probability=0.9, clutter_density=1e-4, max_targets=5)
    with pytest.raises(ValueError, match="^capacity: 6 slots exceed max_targets=5"):
        ManagedTracks(exact, capacity=6, initiate=initiate)
    ManagedTracks(exact, capacity=5, initiate=initiate)
    lbp = JIPDA(manager.association.filter, detection_probability=0.9, clutter_density=1e-4, method="lbp",
                max_targets=5)
    ManagedTracks(lbp, capacity=40, initiate=initiate)  # loopy belief propagation: no limit


def _still_target(**rule):
    """One target at rest at the origin, no clutter to speak of; ``rule``: the manager's M-of-N and
    misses settings."""
    motion = ConstantVelocity(2, dt=1.0, q=0.01, dtype=torch.float64)
    sensor = PositionMeasurement(4, [0, 2], 1.0, dtype=torch.float64)
    jipda = JIPDA(KalmanFilter(motion, sensor), detection_probability=0.9, clutter_density=1e-6,
                  survival_probability=0.99)
    return ManagedTracks(jipda, capacity=3, initiate=position_initiator(4, [0, 2], 1.0, 1.0), birth_existence=0.1,
                         delete=0.0, **rule)


def _play(manager, seen):
    """Scans of one detection at the origin where ``seen[k]``, none elsewhere: the tables after each."""
    table, out = manager.initial_belief((1,)), []
    for k, s in enumerate(seen):
        z = torch.tensor([[[0.05 * k, 0.0] if s else [math.nan, math.nan]]], dtype=torch.float64)
        table = manager.step(table, z).belief
        out.append(table)
    return out


def test_m_of_n_confirms_at_the_mth_hit_and_keeps_it():
    tables = _play(_still_target(m_of_n=(3, 4)), [1, 0, 1, 1, 0, 0, 0])
    slot0 = [(int(t.age[0, 0]), int(t.hits[0, 0]), int(t.misses[0, 0]), bool(t.confirmed()[0, 0])) for t in tables]
    assert slot0 == [(1, 1, 0, False), (2, 1, 1, False), (3, 2, 0, False), (4, 3, 0, True), (5, 3, 1, True),
                     (6, 3, 2, True), (7, 3, 3, True)]
    assert all(int(t.label[0, 0]) == 0 for t in tables) and all(int((t.label >= 0).sum()) == 1 for t in tables)


def test_m_of_n_deletes_a_track_unconfirmed_after_n_scans():
    tables = _play(_still_target(m_of_n=(3, 4)), [1, 0, 1, 0, 0])
    assert [int(t.label[0, 0]) for t in tables] == [0, 0, 0, -1, -1]  # 2 hits in 4 scans: deleted at the 4th
    assert not any(bool(t.confirmed().any()) for t in tables)
    assert int(tables[-1].age[0, 0]) == 0 and int(tables[-1].hits[0, 0]) == 0


def test_max_misses_deletes_a_confirmed_track():
    tables = _play(_still_target(m_of_n=(2, 3), max_misses=2), [1, 1, 0, 1, 0, 0, 1])
    labels = [int(t.label[0, 0]) for t in tables]
    assert labels[:5] == [0, 0, 0, 0, 0] and labels[5] == -1  # confirmed at the 2nd scan, 2 misses: deleted
    assert [bool(t.confirmed()[0, 0]) for t in tables[:5]] == [False, True, True, True, True]
    assert int(tables[6].label.max()) == 1  # the detection after starts a new track with a new label


def test_existence_rule_is_the_existence_threshold():
    manager, truth, det = _scene(runs=3, steps=12, seed=4)
    table = run_filter(manager, manager.initial_belief((3,)), det.z).belief
    assert torch.equal(table.confirmed(), table.confirmed(0.9) & (table.label >= 0))
    assert bool(table.confirmed().any())


def test_m_of_n_errors_name_the_argument():
    manager, _, _ = _scene(runs=1, steps=2)
    for bad in [(3, 2), (0, 2), (2,), (2.0, 3)]:
        with pytest.raises(ValueError, match="m_of_n"):
            ManagedTracks(manager.association, capacity=4, initiate=manager.initiate, m_of_n=bad)
    with pytest.raises(ValueError, match="max_misses"):
        ManagedTracks(manager.association, capacity=4, initiate=manager.initiate, max_misses=0)


def test_position_initiator_reads_a_number_as_r_times_the_identity():
    """A number for noise_cov is r I, as PositionMeasurement reads it (before: a matrix of r's, every new
    track's measured components fully correlated); a vector is the diagonal."""
    for noise in (4.0, [4.0, 4.0], [[4.0, 0.0], [0.0, 4.0]]):
        cov = position_initiator(4, [0, 2], noise, 25.0)(torch.zeros(1, 2, dtype=torch.float64)).cov[0]
        torch.testing.assert_close(cov, torch.diag(torch.tensor([4.0, 25.0, 4.0, 25.0], dtype=torch.float64)))


def test_one_point_initiation_with_a_velocity_bound_and_the_two_point_update():
    """position_initiator(max_speed=v): the unmeasured components' variance v^2 / 3 (uniform on [-v, v]);
    with a diffuse velocity, a new track's first update is two-point initiation: its velocity the two
    detections' difference over the period (to R / variance), its position the second detection's
    (weighted by the noise)."""
    from torchmm.models import ConstantVelocity, PositionMeasurement

    start = position_initiator(4, [0, 2], 4.0, max_speed=30.0)
    first = start(torch.tensor([10.0, -5.0], dtype=torch.float64))
    assert first.cov.diagonal().tolist() == pytest.approx([4.0, 300.0, 4.0, 300.0])
    diffuse = position_initiator(4, [0, 2], 4.0, 1e12)
    kf = KalmanFilter(ConstantVelocity(2, dt=2.0, q=0.0, dtype=torch.float64), PositionMeasurement(4, [0, 2], 4.0,
                                                                                                  dtype=torch.float64))
    z1, z2 = torch.tensor([10.0, -5.0], dtype=torch.float64), torch.tensor([16.0, 3.0], dtype=torch.float64)
    out = kf.step(diffuse(z1), z2).belief
    assert out.mean[[1, 3]].tolist() == pytest.approx([3.0, 4.0], rel=1e-9)  # (z2 - z1) / dt
    with pytest.raises(TypeError, match="unobserved_variance: give it or max_speed"):
        position_initiator(4, [0, 2], 4.0)
    with pytest.raises(TypeError, match="unobserved_variance: give it or max_speed"):
        position_initiator(4, [0, 2], 4.0, 25.0, max_speed=3.0)


@pytest.mark.parametrize("modes", [None, 2])
def test_tracks_that_exist_for_sure_are_jpdas_and_stay_at_existence_one(modes):
    """A JIPDA whose tracks exist for sure (existence and survival 1) is the JPDA (exact and LBP) and, with
    the single best event (kbest, k = 1), GNN: 1e-12 over a run of crossing targets in clutter; the
    existence never leaves 1 (it is a repelling fixed point of a miss: before clamping, rounding grew by
    1 / (1 - P_D P_G) a miss until the updates failed, the managed JPDA's failure found in issue 46)."""
    from tests.test_jpda import _imm, _scene
    from torchmm.association import GNN, JPDA

    motion, sensor, prior, det, truth, options = _scene(30, 4, 3, seed=7, clutter=8.0)
    filt = KalmanFilter(motion, sensor) if modes is None else _imm(modes)
    start = prior if modes is None else filt.initial_belief(prior)
    for kw, ref in (({"method": "exact"}, JPDA(filt, **options)), ({"method": "lbp"}, JPDA(filt, method="lbp", **options)),
                    ({"method": "kbest", "k": 1}, GNN(filt, **options))):
        jipda = JIPDA(filt, survival_probability=1.0, **kw, **options)
        ours = run_filter(jipda, jipda.initial_belief(prior, existence=1.0), det.z, record="estimate")
        theirs = run_filter(ref, start, det.z, record="estimate")
        torch.testing.assert_close(ours.belief.mean, theirs.belief.mean, rtol=1e-12, atol=1e-10)
        torch.testing.assert_close(ours.log_likelihood, theirs.log_likelihood, rtol=1e-12, atol=1e-10)
        full = run_filter(jipda, jipda.initial_belief(prior, existence=1.0), det.z)
        assert bool((full.belief.log_existence == 0).all()) and not bool(full.extras["failed"].any())


def test_a_track_that_exists_for_sure_under_ipda_is_the_pda():
    """IPDA from existence 1 with survival 1: the PDA's posterior and likelihood (1e-12), existence 1."""
    from tests.test_jpda import _scene
    from torchmm.association import IPDA, PDA

    motion, sensor, prior, det, truth, options = _scene(30, 4, 1, seed=3, clutter=8.0)
    kf = KalmanFilter(motion, sensor)
    ipda = IPDA(kf, survival_probability=1.0, **options)
    ours = run_filter(ipda, ipda.initial_belief(prior[:, 0], existence=1.0), det.z)
    theirs = run_filter(PDA(kf, **options), prior[:, 0], det.z)
    torch.testing.assert_close(ours.belief.state.mean, theirs.belief.mean, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(ours.log_likelihood, theirs.log_likelihood, rtol=1e-12, atol=1e-10)
    assert bool((ours.belief.log_existence == 0).all())


def test_detections_left_without_a_slot_are_counted():
    """Capacity 2, an empty table, five far-apart detections: two start tracks (the first two in detection
    order), three are counted in extras["unstarted"]; the next scan the two tracks explain their own and
    the other three again find no slot."""
    motion = ConstantVelocity(2, dt=1.0, q=0.1, dtype=torch.float64)
    sensor = PositionMeasurement(4, [0, 2], 1.0, dtype=torch.float64)
    jipda = JIPDA(KalmanFilter(motion, sensor), detection_probability=0.9, clutter_density=1e-6)
    manager = ManagedTracks(jipda, capacity=2, initiate=position_initiator(4, [0, 2], 1.0, 1.0),
                            birth_existence=0.5, delete=0.01)
    z = torch.tensor([[[100.0 * j, 0.0] for j in range(5)]], dtype=torch.float64).expand(2, 1, 5, 2)
    out = run_filter(manager, manager.initial_belief((1,), dtype=torch.float64), z)
    assert out.extras["unstarted"].tolist() == [[3], [3]]
    assert out.extras["born"][0].sum().item() == 2
    torch.testing.assert_close(out.belief.mean[0, 0, :, [0, 2]], z[0, 0, :2])  # the first two detections

"""The engine contract: sensors and motion models as per-step arguments, randomness per call, and the
paper-000 estimators over any bank (unscented, extended, list and particle banks)."""

from __future__ import annotations

import pytest
import torch

from tests.multimodel.test_transfer import all_estimators, paper_setup
from torchmm import (
    IMM,
    ConstantVelocity,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    PositionMeasurement,
    UnscentedKalmanFilter,
    run_filter,
)
from torchmm.beliefs import where
from torchmm.filters.particle import ParticleFilter
from torchmm.multimodel import IndexedBank, make_bank


def _run(f, prior, z, **kwargs):
    return run_filter(f, f.initial_belief(prior, **({"generator": kwargs["generator"]} if "generator" in kwargs
                                                     else {})), z, **kwargs)


# -- the paper-000 estimators over other banks -------------------------------------------------------
@pytest.mark.parametrize("name", ["IMM-TF", "IF-TF", "IMM-TF corrected", "IMM-SU", "IMM-FU", "VSIMM"])
@pytest.mark.parametrize("kind", ["unscented", "extended", "list"])
def test_paper000_estimators_over_gaussian_banks_equal_kalman(name, kind):
    """On paper 000's linear model an unscented, extended or list bank computes the Kalman version."""
    kf, P, source, prior, z, _ = paper_setup(runs=5, steps=25)
    if kind == "unscented":
        bank = UnscentedKalmanFilter(kf.motion, kf.measurement)
    elif kind == "extended":
        bank = ExtendedKalmanFilter(kf.motion, kf.measurement)
    else:  # three separate EKFs, one per mode (a ListBank: one call per filter)
        bank = [ExtendedKalmanFilter(kf.motion.select_mode(j), kf.measurement) for j in range(3)]
    reference = _run(all_estimators(kf, P, source)[name], prior, z)
    estimator = all_estimators(bank, P, source)[name]
    if kind == "list":
        assert type(estimator.bank).__name__ == "ListBank"
    other = _run(estimator, prior, z)
    ref, got = reference.estimate(), other.estimate()
    torch.testing.assert_close(got.mean, ref.mean, rtol=0, atol=1e-8)
    torch.testing.assert_close(got.cov, ref.cov, rtol=0, atol=1e-8)
    torch.testing.assert_close(other.belief.mode_probs, reference.belief.mode_probs, rtol=0, atol=1e-8)
    torch.testing.assert_close(other.log_likelihood, reference.log_likelihood, rtol=0, atol=1e-8)


@pytest.mark.parametrize("name", ["IMM-TF", "IF-TF", "IMM-SU", "IMM-FU", "VSIMM"])
def test_paper000_estimators_over_a_particle_bank(name):
    """With a particle-filter bank every estimator runs, reproducibly for a seeded generator, and with
    many particles its estimate lies near the Kalman version's (Monte Carlo error of 4000 particles)."""
    kf, P, source, prior, z, truth = paper_setup(runs=4, steps=20)
    pf = ParticleFilter(kf.motion, kf.measurement, num_particles=4000, ess_threshold=0.5)
    estimator = all_estimators(pf, P, source)[name]
    a = _run(estimator, prior, z, generator=torch.Generator().manual_seed(3))
    # randomness per call: the same generator state gives the same run (its first 5 steps, run again alone)
    first = torch.utils._pytree.tree_map(lambda t: t[:5], z)  # (the streams of paper 000's measurements)
    b = _run(estimator, prior, first, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(a.estimate().mean[:5], b.estimate().mean, rtol=0, atol=0)
    reference = _run(all_estimators(kf, P, source)[name], prior, z).estimate()
    got = a.estimate()
    assert torch.isfinite(got.mean).all() and torch.isfinite(got.cov).all()
    # error of the particle version relative to the Kalman one, in units of the Kalman posterior sd
    sd = reference.cov.diagonal(dim1=-2, dim2=-1).sqrt()
    gap = ((got.mean - reference.mean) / sd).abs()
    assert gap.mean() < 0.15, gap.mean()
    assert gap.max() < 1.0, gap.max()
    # and it tracks the truth about as well as the Kalman version
    err_pf = (got.mean[..., 0] - truth.states[..., 0]).square().mean().sqrt()
    err_kf = (reference.mean[..., 0] - truth.states[..., 0]).square().mean().sqrt()
    assert err_pf < 1.2 * err_kf, (err_pf, err_kf)


# -- sensors and motion models per call -------------------------------------------------------------
def test_update_with_a_sensor_equals_a_filter_built_with_it(generator):
    cv = ConstantVelocity(1, q=0.5)
    first, second = PositionMeasurement(2, [0], 4.0), PositionMeasurement(2, [0], 0.25)
    prior = GaussianBelief(torch.randn(6, 2, generator=generator), torch.eye(2).expand(6, 2, 2) * 3)
    z = torch.randn(6, 1, generator=generator)
    for make in (KalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter):
        f = make(cv, first)
        got = f.update(prior, z, sensor=second)
        want = make(cv, second).update(prior, z)
        torch.testing.assert_close(got.belief.mean, want.belief.mean, rtol=0, atol=1e-14)
        torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=0, atol=1e-14)
        assert f.measurement is first  # the filter itself is unchanged
        assert f.with_sensor(second) is f.with_sensor(second)  # cached: no rebuild per step


def test_two_sensors_in_one_step_through_an_imm(generator):
    """Sequential updates with two sensors equal one update with the stacked sensor (no rebuilt filter)."""
    motion = ConstantVelocity(1, q=1.0, acceleration=[[0.5], [0.0], [-0.5]])
    s1, s2 = PositionMeasurement(2, [0], 2.0), PositionMeasurement(2, [0], 5.0)
    stacked = PositionMeasurement(2, [0], 1.0)
    stacked = type(stacked).unchecked(torch.tensor([[1.0, 0.0], [1.0, 0.0]]), torch.diag(torch.tensor([2.0, 5.0])))
    P = torch.full((3, 3), 0.1) + 0.7 * torch.eye(3)
    imm = IMM(KalmanFilter(motion, s1), P)
    belief = imm.initial_belief(GaussianBelief(torch.zeros(4, 2), 10 * torch.eye(2)))
    z1, z2 = torch.randn(4, 1, generator=generator), torch.randn(4, 1, generator=generator)
    prior = imm.predict(belief)
    seq = imm.update(imm.update(prior, z1).belief, z2, sensor=s2)
    joint = imm.update(prior, torch.cat([z1, z2], -1), sensor=stacked)
    torch.testing.assert_close(seq.belief.estimate().mean, joint.belief.estimate().mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(seq.belief.mode_probs, joint.belief.mode_probs, rtol=0, atol=1e-12)


def test_with_sensor_rejects_a_wrong_model():
    kf = KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0))
    with pytest.raises(ValueError, match="sensor: state_dim 4"):
        kf.with_sensor(PositionMeasurement(4, [0], 1.0))
    from torchmm import RangeBearing

    kf4 = KalmanFilter(ConstantVelocity(2), PositionMeasurement(4, [0, 2], 1.0))
    with pytest.raises(ValueError, match="sensor: KalmanFilter needs a LinearMeasurement"):
        kf4.with_sensor(RangeBearing(4, torch.eye(2)))
    with pytest.raises(TypeError, match="sensor: expected a torchmm model"):
        kf.with_sensor("radar")


def test_run_filter_per_step_motion_models_and_sensors(generator):
    """A per-step dt (time-varying model) and a per-step sensor equal the hand-written loop."""
    dts = [0.5, 1.0, 2.0, 0.25, 1.5]
    motions = [ConstantVelocity(1, dt=dt, q=0.3) for dt in dts]
    sensors = [PositionMeasurement(2, [0], r) for r in (1.0, 4.0, 0.5, 2.0, 9.0)]
    kf = KalmanFilter(motions[0], sensors[0])
    belief0 = GaussianBelief(torch.zeros(3, 2), torch.eye(2))
    z = torch.randn(5, 3, 1, generator=generator)
    traj = run_filter(kf, belief0, z, motions=motions, sensors=lambda k: sensors[k])
    belief = belief0
    for k in range(5):
        belief = KalmanFilter(motions[k], sensors[k]).step(belief, z[k]).belief
        torch.testing.assert_close(traj.belief[k].mean, belief.mean, rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match=r"^motions: expected one entry per step \(5\)"):
        run_filter(kf, belief0, z, motions=motions[:3])


def test_run_filter_update_first(generator):
    kf = KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0))
    belief0 = GaussianBelief(torch.zeros(3, 2), torch.eye(2))
    z = torch.randn(4, 3, 1, generator=generator)
    first = kf.update(belief0, z[0]).belief
    second = kf.step(first, z[1]).belief
    # the eager steps bit for bit; the default to rounding (it takes a kernel where one applies:
    # torchmm.kernels.linear once Numba is loaded in the process)
    for fast_path, tol in ((False, 0.0), (None, 1e-12)):
        traj = run_filter(kf, belief0, z, update_first=True, fast_path=fast_path)
        torch.testing.assert_close(traj.belief[0].mean, first.mean, rtol=tol, atol=tol)
        torch.testing.assert_close(traj.belief[1].mean, second.mean, rtol=tol, atol=tol)


# -- randomness per call ----------------------------------------------------------------------------
def test_particle_filters_take_their_random_stream_per_call():
    from torchmm.multimodel.particle import MultipleModelParticleFilter

    cv = ConstantVelocity(1, acceleration=[[0.5], [0.0], [-0.5]])
    sensor = PositionMeasurement(2, [0], 1.0)
    P = torch.full((3, 3), 0.05) + 0.85 * torch.eye(3)
    prior = GaussianBelief(torch.zeros(3, 2), torch.eye(2))
    z = torch.randn(6, 3, 1, generator=torch.Generator().manual_seed(0))
    for f in (ParticleFilter(ConstantVelocity(1), sensor, num_particles=64),
              MultipleModelParticleFilter(cv, sensor, P, 64),
              IMM(ParticleFilter(cv, sensor, num_particles=64), P)):
        runs = []
        for seed in (7, 7, 8):
            g = torch.Generator().manual_seed(seed)
            runs.append(run_filter(f, f.initial_belief(prior, generator=g), z, generator=g).estimate().mean)
        assert torch.equal(runs[0], runs[1]), type(f).__name__  # same stream, same numbers
        assert not torch.equal(runs[0], runs[2]), type(f).__name__
        assert f.uses_generator
        assert not any("generator" in k for k in f.state_dict())


# -- beliefs and banks ------------------------------------------------------------------------------
def test_belief_where_selects_per_batch_element(generator):
    a = GaussianBelief(torch.randn(4, 3, 2, generator=generator), torch.eye(2).expand(4, 3, 2, 2))
    b = GaussianBelief(torch.randn(4, 3, 2, generator=generator), 2 * torch.eye(2).expand(4, 3, 2, 2))
    cond = torch.tensor([[True, False, True]] * 2 + [[False, False, True]] * 2)
    c = where(cond, a, b)
    for i in range(4):
        for j in range(3):
            src = a if cond[i, j] else b
            assert torch.equal(c.mean[i, j], src.mean[i, j]) and torch.equal(c.cov[i, j], src.cov[i, j])


def test_indexed_bank_repeats_modes(generator):
    motion = ConstantVelocity(1, q=1.0, acceleration=[[0.5], [0.0], [-0.5]])
    bank = make_bank(KalmanFilter(motion, PositionMeasurement(2, [0], 1.0)), 3)
    index = [2, 0, 1, 0, 0]
    indexed = IndexedBank(bank, index)
    belief = GaussianBelief(torch.randn(4, 5, 2, generator=generator), torch.eye(2).expand(4, 5, 2, 2))
    z = torch.randn(4, 1, 1, generator=generator)
    prior = indexed.predict(belief)
    out = indexed.update(prior, z)
    for slot, mode in enumerate(index):
        single = KalmanFilter(motion.select_mode(mode), PositionMeasurement(2, [0], 1.0))
        p = single.predict(belief.select(-1, slot))
        o = single.update(p, z.select(-2, 0))
        torch.testing.assert_close(prior.mean[:, slot], p.mean, rtol=0, atol=1e-14)
        torch.testing.assert_close(out.belief.mean[:, slot], o.belief.mean, rtol=0, atol=1e-14)
        torch.testing.assert_close(out.log_likelihood[:, slot], o.log_likelihood, rtol=0, atol=1e-14)


# -- one engine: the particle multiple-model filter is an interaction over a particle bank ---------
@pytest.mark.parametrize("scheme", ["systematic", "two_stage", "multinomial"])
def test_particle_engine_equals_the_multiple_model_particle_filter(scheme):
    """``MultipleModelFilter(ParticleFilter bank, ParticleMixing)`` with the generic update computes the
    MM-PF's numbers from the same random numbers (its fused joint update differs only in rounding)."""
    from torchmm.multimodel import MultipleModelFilter, MultipleModelParticleFilter, ParticleMixing

    motion = ConstantVelocity(1, q=0.5, acceleration=[[1.0], [0.0], [-1.0]])
    sensor = PositionMeasurement(2, [0], 2.0)
    P = torch.full((3, 3), 0.05) + 0.85 * torch.eye(3)
    prior = GaussianBelief(torch.zeros(4, 2), 4 * torch.eye(2))
    z = torch.cumsum(torch.randn(15, 4, 1, generator=torch.Generator().manual_seed(5)), 0)
    z[6, 2] = torch.nan
    mmpf = MultipleModelParticleFilter(motion, sensor, P, 200, mixing=scheme)
    engine = MultipleModelFilter(ParticleFilter(motion, sensor, num_particles=200, ess_threshold=0.0), P,
                                 ParticleMixing(scheme))
    outs = []
    for f in (mmpf, engine):
        g = torch.Generator().manual_seed(11)
        outs.append(run_filter(f, f.initial_belief(prior, generator=g), z, generator=g))
    a, b = outs
    torch.testing.assert_close(b.estimate().mean, a.estimate().mean, rtol=0, atol=1e-9)
    torch.testing.assert_close(b.belief.mode_probs, a.belief.mode_probs, rtol=0, atol=1e-12)
    torch.testing.assert_close(b.log_likelihood, a.log_likelihood, rtol=0, atol=1e-9)
    torch.testing.assert_close(b.belief.components.particles, a.belief.components.particles, rtol=0, atol=1e-9)
    # the same estimator as IMM's moment-free particle mixing would give in distribution: IMM over the
    # same bank (mixture of unions, then resampling) runs on the same interface
    imm = IMM(ParticleFilter(motion, sensor, num_particles=200), P)
    g = torch.Generator().manual_seed(11)
    c = run_filter(imm, imm.initial_belief(prior, generator=g), z, generator=g)
    assert torch.isfinite(c.estimate().mean).all()


def test_per_step_mode_bank_models_through_an_imm(generator):
    """A per-step dt for an IMM: the mode-bank motion of each step, equal to the hand-written loop."""
    P = torch.full((3, 3), 0.05) + 0.85 * torch.eye(3)
    acc = [[0.5], [0.0], [-0.5]]
    dts = [1.0, 0.5, 2.0, 1.5]
    banks = [ConstantVelocity(1, dt=dt, q=0.3, acceleration=acc) for dt in dts]
    sensor = PositionMeasurement(2, [0], 1.0)
    imm = IMM(KalmanFilter(banks[0], sensor), P)
    belief0 = imm.initial_belief(GaussianBelief(torch.zeros(3, 2), torch.eye(2)))
    z = torch.randn(4, 3, 1, generator=generator)
    traj = run_filter(imm, belief0, z, motions=banks)
    belief = belief0
    for k, bank in enumerate(banks):
        belief = IMM(KalmanFilter(bank, sensor), P).step(belief, z[k]).belief
        torch.testing.assert_close(traj.belief[k].estimate().mean, belief.estimate().mean, rtol=0, atol=1e-14)


def test_variational_and_particle_filters_take_a_sensor_per_call(generator):
    from torchmm import SkewTVBFilter, StudentTVBFilter

    cv = ConstantVelocity(2, q=0.5)
    s1, s2 = PositionMeasurement(4, [0, 2], 4.0), PositionMeasurement(4, [0, 2], 0.5)
    prior = GaussianBelief(torch.randn(5, 4, generator=generator), 2 * torch.eye(4).expand(5, 4, 4))
    z = torch.randn(5, 2, generator=generator)
    for make in (lambda s: StudentTVBFilter(cv, s, df=4.0), lambda s: SkewTVBFilter(cv, s, skewness=1.0, df=5.0)):
        got = make(s1).update(prior, z, sensor=s2)
        want = make(s2).update(prior, z)
        torch.testing.assert_close(got.belief.mean, want.belief.mean, rtol=0, atol=1e-13)
        torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=0, atol=1e-13)
    pf1, pf2 = ParticleFilter(cv, s1, num_particles=64), ParticleFilter(cv, s2, num_particles=64)
    particles = pf1.initial_belief(prior, generator=torch.Generator().manual_seed(0))
    a = pf1.update(particles, z, sensor=s2, generator=torch.Generator().manual_seed(1))
    b = pf2.update(particles, z, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(a.belief.particles, b.belief.particles, rtol=0, atol=0)
    torch.testing.assert_close(a.log_likelihood, b.log_likelihood, rtol=0, atol=0)


def test_list_bank_keeps_every_mode_filters_diagnostics(generator):
    """A Kalman mode beside a particle mode: shared keys stacked, the particle filter's own per mode."""
    cv = ConstantVelocity(1, q=0.5)
    sensor = PositionMeasurement(2, [0], 1.0)
    imm = IMM([KalmanFilter(cv, sensor), ParticleFilter(cv, sensor, num_particles=50)], torch.tensor([[0.9, 0.1],
                                                                                                     [0.1, 0.9]]))
    with pytest.raises(TypeError):  # a Gaussian mode and a particle mode cannot be mixed into one belief type
        g = torch.Generator().manual_seed(0)
        run_filter(imm, imm.initial_belief(GaussianBelief(torch.zeros(3, 2), torch.eye(2)), generator=g),
                   torch.randn(4, 3, 1, generator=generator), generator=g)
    from torchmm.multimodel.bank import _stack_extras

    kf_extras = {"singular": torch.zeros(3, dtype=torch.bool)}
    pf_extras = {"singular": torch.ones(3, dtype=torch.bool), "ess": torch.full((3,), 40.0)}
    out = _stack_extras([kf_extras, pf_extras], axis=-1)
    assert out["singular"].shape == (3, 2) and out["singular"][:, 1].all()
    assert torch.equal(out["by_mode"][1]["ess"], pf_extras["ess"])


def _bad_inputs():
    from torchmm.fusion import fuse_tracks
    from torchmm.multimodel import (DropBelow, FixedSet, MultipleModelFilter, ParticleMixing,
                                    VariableStructureIMM)

    motion = ConstantVelocity(1, acceleration=[[0.5], [0.0], [-0.5]])
    kf = KalmanFilter(motion, PositionMeasurement(2, [0], 1.0))
    P = torch.full((3, 3), 1 / 3)
    belief0 = GaussianBelief(torch.zeros(2, 2), torch.eye(2))
    return {
        "no interaction": (lambda: MultipleModelFilter(kf, P), TypeError, "interaction: MultipleModelFilter needs"),
        "interaction string": (lambda: MultipleModelFilter(kf, P, "imm"), TypeError, "interaction: expected"),
        "policy object": (lambda: VariableStructureIMM(kf, P, object()), TypeError, "policy: expected"),
        "empty fixed set": (lambda: FixedSet([]), ValueError, "members"),
        "drop threshold": (lambda: DropBelow(1.5, [0]), ValueError, "threshold"),
        "indexed bank": (lambda: IndexedBank(make_bank(kf, 3), [0, 5]), ValueError, "index"),
        "mixing scheme": (lambda: ParticleMixing("bogus"), ValueError, "scheme"),
        "sensors type": (lambda: run_filter(kf, belief0, torch.zeros(3, 2, 1), sensors=42), TypeError, "sensors"),
        "motions count": (lambda: run_filter(kf, belief0, torch.zeros(3, 2, 1), motions=[motion]), ValueError,
                          "motions"),
        "no tracks": (lambda: fuse_tracks([]), TypeError, "tracks"),
        # (refused when the estimator is built, naming the policy's argument; before: at the first step)
        "fixed set range": (lambda: VariableStructureIMM(kf, P, FixedSet([7])), ValueError,
                            r"policy\.members"),
    }


@pytest.mark.parametrize("case", sorted(_bad_inputs()))
def test_engine_entry_points_reject_bad_input_naming_the_argument(case):
    build, error, pattern = _bad_inputs()[case]
    with pytest.raises(error, match=rf"^{pattern}"):
        build()


def test_run_filter_names_per_step_models_a_filter_cannot_take():
    kf, P, source, prior, z, _ = paper_setup(runs=2, steps=3)
    from torchmm.multimodel import TransferIMM

    tf = TransferIMM(kf, P, source)
    with pytest.raises(TypeError, match="^sensors: TransferIMM.step takes no per-step sensor"):
        run_filter(tf, tf.initial_belief(prior), z, sensors=[source] * 3)

"""Defects 7 and 12, and the entry-point contract class by class.

Every public constructor and entry point answers an invalid input with a ``ValueError`` (a wrong
value or shape) or ``TypeError`` (a wrong type or dtype) whose message starts with the argument
the user passed; legitimate edge cases - lists, integer tensors, singular process noise, empty
batches, documented broadcasting - are accepted with finite, well-shaped output.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchmm.multimodel import IndexedBank, make_bank

from tests.robustness.cases import CASES
from torchmm import (
    GPB2,
    IMM,
    VBAKFPR,
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    EqMAParticleFilter,
    ExtendedKalmanFilter,
    GaussianBelief,
    JulierSigmaPoints,
    KalmanFilter,
    LearnedMotion,
    LinearMeasurement,
    LinearMotion,
    MerweScaledSigmaPoints,
    MinimumEntropyVSMM,
    ModeTransition,
    MultipleModelParticleFilter,
    NonlinearCoordinatedTurn,
    ParticleFilter,
    PositionMeasurement,
    RangeBearing,
    SkewTIWVBFilter,
    SkewTVBFilter,
    StudentTVBFilter,
    UnscentedKalmanFilter,
    alpha_transition,
    gimmaf,
    imm_vbt,
    learnable_noise,
    run_filter,
    validate_transition,
)
from torchmm.multimodel import FusionIMM, InfluenceGate, MultiRate, SourceUpdateIMM, TransferIMM
from torchmm.multimodel.mevsmm import ChallengeMatch, ExactMinimumEntropy, uniform_transition

NAN = float("nan")
# module-level set-ups in float64 (the suite's default dtype is set per test by conftest)
_DEFAULT = torch.get_default_dtype()
torch.set_default_dtype(torch.float64)
CV = ConstantVelocity(1, q=0.5)
POS = PositionMeasurement(2, [0], 1.0)
KF = KalmanFilter(CV, POS)
BANK = ConstantVelocity(1, q=0.5, acceleration=[[0.5], [0.0], [-0.5]])
P3 = torch.full((3, 3), 1 / 3)
PRIOR = GaussianBelief(torch.zeros(2), torch.eye(2))
CV2, POS2 = ConstantVelocity(2), PositionMeasurement(4, [0, 2], 1.0)
torch.set_default_dtype(_DEFAULT)


def _imm_pf_without_num_particles():
    return IMM(ParticleFilter(BANK, POS), P3)


INVALID = {
    # kinematic models
    "ndim zero": (lambda: ConstantVelocity(0), ValueError, "ndim"),
    "ndim float": (lambda: ConstantVelocity(1.5), TypeError, "ndim"),
    "ndim ca": (lambda: ConstantAcceleration(-1), ValueError, "ndim"),
    "dt zero": (lambda: ConstantVelocity(1, dt=0.0), ValueError, "dt"),
    "dt nan": (lambda: ConstantVelocity(1, dt=NAN), ValueError, "dt"),
    "dt string": (lambda: ConstantVelocity(1, dt="1"), TypeError, "dt"),
    "q negative": (lambda: ConstantVelocity(1, q=-1.0), ValueError, "q"),
    "noise kind": (lambda: ConstantVelocity(1, noise="white"), ValueError, "noise"),
    "acceleration shape": (lambda: ConstantVelocity(2, acceleration=[0.1, 0.2, 0.3]), ValueError, "acceleration"),
    "acceleration nan": (lambda: ConstantVelocity(1, acceleration=[[NAN]]), ValueError, "acceleration"),
    "omega nan": (lambda: CoordinatedTurn(NAN), ValueError, "omega"),
    "q_omega negative": (lambda: NonlinearCoordinatedTurn(q_omega=-1), ValueError, "q_omega"),
    "nct dt": (lambda: NonlinearCoordinatedTurn(dt=-1.0), ValueError, "dt"),
    # linear models
    "F non-square": (lambda: LinearMotion(torch.ones(2, 3), torch.eye(2)), ValueError, "F"),
    "F empty": (lambda: LinearMotion(torch.zeros(0, 0), torch.zeros(0, 0)), ValueError, "F"),
    "F nan": (lambda: LinearMotion([[NAN, 0.0], [0.0, 1.0]], torch.eye(2)), ValueError, "F"),
    "Q shape": (lambda: LinearMotion(torch.eye(2), torch.eye(3)), ValueError, "Q"),
    "Q non-symmetric": (lambda: LinearMotion(torch.eye(2), [[1.0, 0.5], [0.0, 1.0]]), ValueError, "Q"),
    "Q indefinite": (lambda: LinearMotion(torch.eye(2), [[1.0, 2.0], [2.0, 1.0]]), ValueError, "Q"),
    "Q inf": (lambda: LinearMotion(torch.eye(2), [[math.inf, 0.0], [0.0, 1.0]]), ValueError, "Q"),
    "offset shape": (lambda: LinearMotion(torch.eye(2), torch.eye(2), offset=torch.zeros(3)), ValueError, "offset"),
    "input_matrix shape": (lambda: LinearMotion(torch.eye(2), torch.eye(2), input_matrix=torch.ones(3, 1)),
                           ValueError, "input_matrix"),
    "bank batches": (lambda: LinearMotion(torch.eye(2).expand(3, 2, 2), torch.eye(2).expand(2, 2, 2)),
                     ValueError, "LinearMotion"),
    "F string": (lambda: LinearMotion("eye", torch.eye(2)), TypeError, "F"),
    "H vector": (lambda: LinearMeasurement(torch.ones(2), torch.eye(1)), ValueError, "H"),
    "R shape": (lambda: LinearMeasurement(torch.ones(1, 2), torch.eye(2)), ValueError, "R"),
    "R negative": (lambda: LinearMeasurement(torch.ones(1, 2), -torch.eye(1)), ValueError, "R"),
    "R nan": (lambda: LinearMeasurement(torch.ones(1, 2), [[NAN]]), ValueError, "R"),
    "indices float": (lambda: PositionMeasurement(2, [0.5], 1.0), TypeError, "indices"),
    "indices range": (lambda: PositionMeasurement(2, [5], 1.0), ValueError, "indices"),
    "indices empty": (lambda: PositionMeasurement(2, [], 1.0), ValueError, "indices"),
    "indices scalar": (lambda: PositionMeasurement(2, 0, 1.0), TypeError, "indices"),
    "state_dim zero": (lambda: PositionMeasurement(0, [0], 1.0), ValueError, "state_dim"),
    "rb indices": (lambda: RangeBearing(4, torch.eye(2), position_indices=(0, 7)), ValueError, "position_indices"),
    "rb same index": (lambda: RangeBearing(4, torch.eye(2), position_indices=(0, 0)), ValueError, "position_indices"),
    "rb origin": (lambda: RangeBearing(4, torch.eye(2), origin=[1.0, 2.0, 3.0]), ValueError, "origin"),
    "rb R singular": (lambda: RangeBearing(4, torch.zeros(2, 2)), ValueError, "R"),
    # filters
    "kf nonlinear": (lambda: KalmanFilter(NonlinearCoordinatedTurn(), PositionMeasurement(5, [0], 1.0)),
                     ValueError, "motion"),
    "ekf dims": (lambda: ExtendedKalmanFilter(CV, PositionMeasurement(3, [0], 1.0)), ValueError, "measurement"),
    "ekf types": (lambda: ExtendedKalmanFilter(POS, CV), TypeError, "motion"),
    "merwe alpha": (lambda: MerweScaledSigmaPoints(alpha=0.0), ValueError, "alpha"),
    "merwe kappa": (lambda: MerweScaledSigmaPoints(kappa="a"), TypeError, "kappa"),
    "ukf merwe n+lambda": (lambda: UnscentedKalmanFilter(CV2, POS2, MerweScaledSigmaPoints(alpha=1e-3, kappa=-4)),
                           ValueError, "sigma_points"),
    "ukf julier": (lambda: UnscentedKalmanFilter(CV, POS, JulierSigmaPoints(kappa=-5.0)), ValueError, "sigma_points"),
    "ukf points type": (lambda: UnscentedKalmanFilter(CV, POS, "merwe"), TypeError, "sigma_points"),
    # multiple models
    "imm empty": (lambda: IMM([], torch.zeros(0, 0)), ValueError, "transition"),
    "imm rows": (lambda: IMM(KF, [[0.9, 0.2], [0.1, 0.9]]), ValueError, "transition"),
    "imm negative": (lambda: IMM(KF, [[1.1, -0.1], [0.5, 0.5]]), ValueError, "transition"),
    "imm nan": (lambda: IMM(KF, [[NAN, 1.0], [0.5, 0.5]]), ValueError, "transition"),
    "imm bank size": (lambda: IMM(KalmanFilter(BANK, POS), torch.eye(2)), ValueError, "bank"),
    "imm list size": (lambda: IMM([KF, KF], P3), ValueError, "bank"),
    "imm bank type": (lambda: IMM("kf", P3), TypeError, "bank"),
    "imm bank entry": (lambda: IMM([KF, "kf", KF], P3), TypeError, r"bank\[1\]"),
    "imm state dims": (lambda: IMM([KF, KalmanFilter(CV2, POS2)], torch.eye(2)), ValueError, "bank"),
    "imm pf particles": (_imm_pf_without_num_particles, ValueError, "bank.*num_particles"),
    "gpb2 rows": (lambda: GPB2(KalmanFilter(BANK, POS), torch.ones(3, 3)), ValueError, "transition"),
    "transition nan": (lambda: ModeTransition([[NAN, 1.0], [0.0, 1.0]]), ValueError, "matrix"),
    "validate transition": (lambda: validate_transition([[0.5, 0.6], [0.5, 0.5]]), ValueError, "transition"),
    "alpha negative": (lambda: alpha_transition([0.1, -0.1]), ValueError, "alpha"),
    "mode_probs nan": (lambda: IMM(KalmanFilter(BANK, POS), P3).initial_belief(PRIOR, [NAN, 0.5, 0.5]),
                       ValueError, "mode_probs"),
    "mode_probs size": (lambda: IMM(KalmanFilter(BANK, POS), P3).initial_belief(PRIOR, [0.5, 0.5]),
                        ValueError, "mode_probs"),
    "initial belief type": (lambda: IMM(KalmanFilter(BANK, POS), P3).initial_belief(torch.zeros(2)),
                            TypeError, "belief"),
    "float32 transition": (lambda: IMM(KalmanFilter(BANK, POS), P3.float()).initial_belief(PRIOR),
                           TypeError, "belief.*float32"),
    "transfer bank": (lambda: TransferIMM(IndexedBank(make_bank(KalmanFilter(BANK, POS), 3), [0, 1, 2]), P3, POS),
                      ValueError, "bank"),
    "transfer source dims": (lambda: TransferIMM(KalmanFilter(BANK, POS), P3, PositionMeasurement(4, [0], 1.0)),
                             ValueError, "source"),
    "transfer source type": (lambda: TransferIMM(KalmanFilter(BANK, POS), P3, CV), TypeError, "source"),
    "su source": (lambda: SourceUpdateIMM(KalmanFilter(BANK, POS), P3, PositionMeasurement(4, [0], 1.0)),
                  ValueError, "source"),
    "fu source": (lambda: FusionIMM(KalmanFilter(BANK, POS), P3, PositionMeasurement(4, [0], 1.0)),
                  ValueError, "source"),
    "gate weight": (lambda: InfluenceGate(weight="both"), ValueError, "weight"),
    # variational
    "student R zero": (lambda: StudentTVBFilter(CV, PositionMeasurement(2, [0], 0.0)), ValueError, "measurement.R"),
    "student df": (lambda: StudentTVBFilter(CV, POS, df=-1.0), ValueError, "df"),
    "student iterations": (lambda: StudentTVBFilter(CV, POS, iterations=0), ValueError, "iterations"),
    "student iterations float": (lambda: StudentTVBFilter(CV, POS, iterations=2.5), TypeError, "iterations"),
    "skew R diagonal": (lambda: SkewTVBFilter(CV2, LinearMeasurement(torch.eye(2, 4), [[1.0, 0.5], [0.5, 1.0]])),
                        ValueError, "measurement.R"),
    "skew shape": (lambda: SkewTIWVBFilter(CV2, POS2, skewness=[1.0, 2.0, 3.0]), ValueError, "skewness"),
    "skew tau": (lambda: SkewTIWVBFilter(CV2, POS2, tau=0.0), ValueError, "tau"),
    "skew gamma_shape": (lambda: SkewTIWVBFilter(CV2, POS2, gamma_shape="x"), ValueError, "gamma_shape"),
    "vbakf rho": (lambda: VBAKFPR(CV, POS, rho=2.0), ValueError, "rho"),
    "vbakf R0": (lambda: VBAKFPR(CV, POS).initial_belief(PRIOR, -torch.eye(1)), ValueError, "R0"),
    "vb nonlinear": (lambda: StudentTVBFilter(NonlinearCoordinatedTurn(), PositionMeasurement(5, [0], 1.0)),
                     ValueError, "motion"),
    "gimmaf modes": (lambda: gimmaf(CoordinatedTurn(torch.tensor([0.0, 0.1, 0.2])), POS2, torch.eye(2),
                                    skewness=1.0, df=5.0), ValueError, "motion"),
    "imm_vbt modes": (lambda: imm_vbt(CoordinatedTurn(torch.tensor([0.0, 0.1, 0.2])), POS2, torch.eye(2), df=5.0),
                      ValueError, "motion"),
    # particle filters
    "pf resampling": (lambda: ParticleFilter(CV, POS, resampling="bogus"), ValueError, "resampling"),
    "pf ess": (lambda: ParticleFilter(CV, POS, ess_threshold=-1), ValueError, "ess_threshold"),
    "pf ess nan": (lambda: ParticleFilter(CV, POS, ess_threshold=NAN), ValueError, "ess_threshold"),
    "pf particles": (lambda: ParticleFilter(CV, POS, num_particles=0), ValueError, "num_particles"),
    "pf particles float": (lambda: ParticleFilter(CV, POS, num_particles=2.5), TypeError, "num_particles"),
    "pf generator": (lambda: ParticleFilter(CV, POS, generator=0), TypeError, "generator"),
    "pf noise dtype": (lambda: ParticleFilter(CV, POS, noise_dtype=torch.int32), TypeError, "noise_dtype"),
    "pf singular R": (lambda: ParticleFilter(CV, PositionMeasurement(2, [0], 0.0)), ValueError, "measurement.R"),
    "pf no particle count": (lambda: ParticleFilter(CV, POS).initial_belief(PRIOR), ValueError, "num_particles"),
    "mmpf mixing": (lambda: MultipleModelParticleFilter(BANK, POS, P3, 10, mixing="residual"), ValueError, "mixing"),
    "mmpf particles": (lambda: MultipleModelParticleFilter(BANK, POS, P3, 0), ValueError, "num_particles"),
    "mmpf transition": (lambda: MultipleModelParticleFilter(BANK, POS, torch.ones(3, 3), 10), ValueError,
                        "transition"),
    "mmpf motion": (lambda: MultipleModelParticleFilter(BANK, POS, torch.eye(2), 10), ValueError, "motion"),
    "mmpf mode_probs": (lambda: MultipleModelParticleFilter(BANK, POS, P3, 10).initial_belief(PRIOR, [NAN, .5, .5]),
                        ValueError, "mode_probs"),
    "mevsmm selection": (lambda: MinimumEntropyVSMM(BANK, POS, P3, 10, selection=None), TypeError, "selection"),
    "mevsmm winners": (lambda: MinimumEntropyVSMM(BANK, POS, P3, 10, selection=ChallengeMatch(100, 3)),
                       ValueError, "selection"),
    "challenge winners": (lambda: ChallengeMatch(num_winners=0), ValueError, "num_winners"),
    "challenge threshold": (lambda: ChallengeMatch(threshold=-1), ValueError, "threshold"),
    "challenge method": (lambda: ChallengeMatch(method="bogus"), ValueError, "method"),
    "exact chunk": (lambda: ExactMinimumEntropy(chunk_size=0), ValueError, "chunk_size"),
    "uniform stay": (lambda: uniform_transition(3, 1.5), ValueError, "stay"),
    "eqma noise shape": (lambda: EqMAParticleFilter(CV.F, torch.tensor([[0.5], [1.0]]), torch.zeros(3, 1),
                                                    torch.eye(2), POS, 10), ValueError, "accel_noise_cov"),
    "eqma noise indefinite": (lambda: EqMAParticleFilter(CV.F, torch.tensor([[0.5], [1.0]]), torch.zeros(3, 1),
                                                         -torch.eye(1), POS, 10), ValueError, "accel_noise_cov"),
    "eqma gain": (lambda: EqMAParticleFilter(CV.F, torch.ones(3, 1), torch.zeros(3, 1), torch.eye(1), POS, 10),
                  ValueError, "gain"),
    "eqma F": (lambda: EqMAParticleFilter(torch.ones(2, 3), torch.ones(2, 1), torch.zeros(3, 1), torch.eye(1), POS,
                                          10), ValueError, "F"),
    # learned models
    "learnable kind": (lambda: learnable_noise(ConstantVelocity(1), "Q", "bogus"), ValueError, "kind"),
    "learnable name": (lambda: learnable_noise(ConstantVelocity(1), "P"), ValueError, "name"),
    "learnable diagonal": (lambda: learnable_noise(ConstantVelocity(1), "Q", "log_diagonal"), ValueError, "Q"),
    "learnable cholesky": (lambda: learnable_noise(ConstantVelocity(1), "Q", "cholesky"), ValueError, "Q"),
    "learned noise kind": (lambda: LearnedMotion(torch.nn.Linear(2, 2), 2, Q=0.1, noise="bogus"), ValueError, "noise"),
    "learned state_dim": (lambda: LearnedMotion(torch.nn.Linear(2, 2), 0, Q=0.1), ValueError, "state_dim"),
    # beliefs and the driver
    "create cov": (lambda: GaussianBelief.create(torch.zeros(2), [[1.0, 0.3], [0.0, 1.0]]), ValueError, "cov"),
    "run zero steps": (lambda: run_filter(KF, PRIOR, torch.zeros(0, 1)), ValueError, "measurements"),
    "run belief type": (lambda: run_filter(KF, torch.zeros(2), torch.zeros(3, 1)), TypeError, "belief0"),
    "run measurements type": (lambda: run_filter(KF, PRIOR, [[1.0]]), TypeError, "measurements"),
    "run dtype": (lambda: run_filter(KF, PRIOR.to(torch.float32), torch.zeros(3, 1)), TypeError, "belief0"),
    "run controls": (lambda: run_filter(KF, PRIOR, torch.zeros(3, 1), controls=torch.zeros(2, 1)), ValueError,
                     "controls"),
    "run streams": (lambda: run_filter(TransferIMM(KalmanFilter(BANK, POS), P3, POS), PRIOR,
                                       MultiRate(torch.zeros(3, 1), torch.zeros(2, 1))), ValueError, "measurements"),
    "u without input": (lambda: KF.predict(PRIOR, u=torch.zeros(1)), ValueError, "u"),
}


@pytest.mark.parametrize("name", INVALID)
def test_invalid_input_raises_naming_the_argument(name):
    build, error, pattern = INVALID[name]
    with pytest.raises(error, match=rf"^{pattern}"):
        build()


def test_u_of_the_wrong_size_is_an_error():
    motion = LinearMotion(torch.eye(2), torch.eye(2), input_matrix=torch.ones(2, 1))
    with pytest.raises(ValueError, match=r"^u: expected shape \(\*B, 1\)"):
        KalmanFilter(motion, POS).predict(PRIOR, u=torch.zeros(3))


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_empty_batch_is_accepted_with_well_shaped_output(case):
    """MEVSMM with an empty batch raised from a reshape."""
    f = case.make()
    traj = run_filter(f, case.start(f, 0), case.data(3, 0))
    est = traj.estimate()
    assert est.mean.shape[:2] == (3, 0) and est.cov.shape[:2] == (3, 0)
    assert traj.log_likelihood.shape == (3, 0)


def test_lists_integer_tensors_and_singular_process_noise_are_accepted():
    motion = LinearMotion([[1, 1], [0, 1]], torch.tensor([[0, 0], [0, 1]]))  # lists, integers, singular Q
    sensor = LinearMeasurement([[1, 0]], [[4]])
    assert motion.F.dtype == torch.get_default_dtype()
    for f in (KalmanFilter(motion, sensor), UnscentedKalmanFilter(motion, sensor),
              ParticleFilter(motion, sensor, num_particles=50, generator=torch.Generator().manual_seed(0))):
        start = f.initial_belief(PRIOR.expand(3)) if isinstance(f, ParticleFilter) else PRIOR.expand(3)
        traj = run_filter(f, start, torch.ones(4, 3, 1))
        assert traj.estimate().mean.shape == (4, 3, 2) and torch.isfinite(traj.estimate().cov).all()


def test_documented_broadcasting_is_accepted():
    # a covariance shared by every run, a model bank against the mode axis, a 0-d R
    prior = GaussianBelief(torch.zeros(5, 2), torch.eye(2))
    out = KF.step(prior, torch.zeros(5, 1))
    assert out.belief.mean.shape == (5, 2) and out.belief.cov.shape == (5, 2, 2)
    imm = IMM(KalmanFilter(BANK, PositionMeasurement(2, [0], torch.tensor(2.0))), P3)
    traj = run_filter(imm, imm.initial_belief(prior), torch.zeros(4, 5, 1))
    assert traj.belief.components.mean.shape == (4, 5, 3, 2)


def test_imm_over_particle_filters_keeps_the_particle_count():
    """Without num_particles the count grew M-fold every step (30, 90, 270, 810): now an error at
    construction; with it, the count stays."""
    pf = ParticleFilter(BANK, POS, num_particles=30, generator=torch.Generator().manual_seed(0))
    imm = IMM(pf, P3)
    belief = imm.initial_belief(pf.initial_belief(PRIOR.expand(2)))
    for _ in range(4):
        belief = imm.step(belief, torch.zeros(2, 1)).belief
        assert belief.components.particles.shape == (2, 3, 30, 2)
    IMM(ParticleFilter(CV, POS), torch.ones(1, 1))  # one mode: nothing is merged, no count needed

"""A valid example call of every public entry point, and the public callables that are not entry
points (with the reason), for ``tests/robustness/test_api_contract.py``.

An example is a function returning a :class:`Call`: the entry point and valid arguments. The
contract test replaces one argument at a time with every invalid input its declared kind lists.
Keys are the ``module.qualname`` where the object is defined (a method: its function's).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

import torchmm
from torchmm import models

_DEFAULT = torch.get_default_dtype()


@dataclass
class Call:
    fn: Callable
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)


def call(fn, *args, **kwargs) -> Call:
    return Call(fn, args, kwargs)


def _f64(build: Callable[[], Call]) -> Callable[[], Call]:
    """Build the example in float64 (the suite's default dtype is set per test)."""

    def wrapped():
        previous = torch.get_default_dtype()
        torch.set_default_dtype(torch.float64)
        try:
            return build()
        finally:
            torch.set_default_dtype(previous)

    return wrapped


_RECORD = ("a result record (a dataclass or NamedTuple the library returns); built by the library, "
           "not validated")
_INTERFACE = "an interface (abstract base) to subclass; its subclasses are the entry points"
_PER_STEP = ("a plain constructor that every filter step calls (shapes checked in __post_init__); values are "
             "checked where a user hands a belief in: Belief.validate at run_filter, initial_belief, create")
_OP = ("a step-level operation (called inside every filter step: shapes only, no value checks, no host "
       "synchronisation)")
_KERNEL = "a particle stage of the fused CPU step (torchmm.kernels.particle), called by the filters inside a step"
_SEAM = ("the kernels seam (torchmm.kernels): a developer's hook that filters, kernels and the engine call; "
         "the user's arguments were checked at the entry point that called it")
_NO_ARGS = "takes no arguments: nothing to check"

NOT_ENTRY_POINTS: dict[str, str] = {
    # interfaces
    "torchmm.beliefs.base.Belief": _INTERFACE,
    "torchmm.filters.base.Filter": _INTERFACE,
    "torchmm.multimodel.bank.FilterBank": _INTERFACE,
    "torchmm.models.base.MotionModel": _INTERFACE,
    "torchmm.models.base.MeasurementModel": _INTERFACE,
    "torchmm.filters.unscented.SigmaPointStrategy": _INTERFACE,
    "torchmm.multimodel.interaction.Interaction": _INTERFACE,
    "torchmm.multimodel.structure.ModelSetPolicy": _INTERFACE,
    # records
    "torchmm.typing.StepOutput": _RECORD + " (re-exported by torchmm.filters)",
    "torchmm.run.Trajectory": _RECORD + " (run_filter makes it; smooth checks where it came from)",
    "torchmm.analysis.imm.ConclusionCheck": _RECORD,
    "torchmm.analysis.imm.InteractionDeviations": _RECORD,
    "torchmm.fusion.cross.CrossStats": _RECORD,
    "torchmm.fusion.local.LocalStats": _RECORD,
    "torchmm.fusion.weights.FusedEstimate": _RECORD,
    "torchmm.fusion.system.FusionSimulation": _RECORD,
    "torchmm.fusion.system.MeasurementSequence": _RECORD,
    "torchmm.fusion.steady.SteadyState": _RECORD,
    "torchmm.learn.trainer.TrainRecord": _RECORD,
    "torchmm.learn.trainer.NonFiniteLossError": "an exception type (Trainer raises it; a ValueError)",
    "torchmm.simulate.markov.JumpSimulation": _RECORD,
    "torchmm.simulate.detections.Detections": _RECORD,
    # beliefs: built inside every step
    "torchmm.beliefs.gaussian.GaussianBelief":
        _PER_STEP + " (GaussianBelief.create is the checked constructor)",
    "torchmm.beliefs.mode.ModeBelief": _PER_STEP,
    "torchmm.beliefs.mode.ModelSetBelief": _PER_STEP,
    "torchmm.beliefs.particle.ParticleBelief": _PER_STEP,
    "torchmm.beliefs.adaptive.AdaptiveGaussianBelief": _PER_STEP,
    "torchmm.beliefs.existence.ExistenceBelief": _PER_STEP + " (IPDA.initial_belief checks the existence)",
    "torchmm.association.tracks.TrackTable": _PER_STEP + " (ManagedTracks.initial_belief makes it)",
    "torchmm.association.tracks.ModeTrackTable": _PER_STEP + " (ManagedTracks.initial_belief makes it)",
    "torchmm.beliefs.existence.ModeExistenceBelief": _PER_STEP + " (IPDA.initial_belief checks the existence)",
    "torchmm.beliefs.existence.with_existence": _PER_STEP + " (a belief with its existence; IPDA.initial_belief "
                                                            "checks the values)",
    "torchmm.beliefs.track.SourceTrackBelief": _PER_STEP,
    "torchmm.models.streams.MultiRate": _PER_STEP.replace("every filter step calls", "every step indexes")
    + "; run_filter checks its streams",
    # step-level operations
    "torchmm.beliefs.base.cat": _OP,
    "torchmm.beliefs.base.stack": _OP,
    "torchmm.beliefs.base.where": _OP,
    "torchmm.beliefs.ops.mix_gaussians": _OP,
    "torchmm.beliefs.ops.normalize_log_probs": _OP,
    "torchmm.linalg.psd_sqrt": _OP,
    "torchmm.linalg.symmetrize": _OP,
    "torchmm.models.base.forward_jacobian": _OP + " (the EKF's Jacobians)",
    "torchmm.filters.smoother.rts_step": _OP + " (rts_smoother is the entry point)",
    "torchmm.multimodel.transfer.influence_value": _OP + " (IMM-TF's gate, every step; NaN data are missing)",
    "torchmm.multimodel.particle_mixing.mixing_indices": _OP + " (the particle interaction's ancestors)",
    "torchmm.beliefs.base.register_belief": "a class decorator for new belief types (a developer's hook)",
    # kernels
    "torchmm.kernels.particle.available": _KERNEL,
    "torchmm.kernels.particle.applies": _KERNEL,
    "torchmm.kernels.particle.enabled": _KERNEL,
    "torchmm.kernels.particle.challenge_pass": _KERNEL,
    "torchmm.kernels.particle.propagate_log_likelihood": _KERNEL,
    "torchmm.kernels.particle.two_stage_indices": _KERNEL,
    "torchmm.kernels.particle.LinearParticles": _RECORD + " (a filter's description of itself)",
    "torchmm.kernels.linear.LinearGaussian": _RECORD + " (a filter's description of itself)",
    "torchmm.kernels.linear_run.load": _SEAM,
    "torchmm.kernels.Request": _RECORD + " (what run_filter asks of a kernel)",
    "torchmm.kernels.describe": _SEAM,
    "torchmm.kernels.joined": _SEAM,
    "torchmm.kernels.joins": _SEAM + " (a class decorator)",
    "torchmm.kernels.names": _NO_ARGS,
    "torchmm.kernels.by_size": _NO_ARGS,
    "torchmm.kernels.plan": _SEAM,
    "torchmm.kernels.choose": _SEAM,
    "torchmm.kernels.table": _NO_ARGS,
    "torchmm.kernels.count_run": _SEAM + " (run_filter calls it once a run)",
    "torchmm.kernels.counting": _NO_ARGS + " (a context manager: tests/kernels/test_kernel_record.py)",
    "torchmm.kernels.Choice": _RECORD + " (choose's answer)",
    "torchmm.kernels.plan_smooth": _SEAM,
    "torchmm.kernels.register": _SEAM,
    "torchmm.kernels.registered": _NO_ARGS,
    "torchmm.kernels.stack_steps": _SEAM,
    "torchmm.kernels.switched_off": ("a context manager over *names (no parameter to declare): each name is "
                                     "checked by the kernel-name kind, naming it names[i] "
                                     "(tests/kernels/test_switches.py)"),
    "torchmm.kernels.switched_on": ("a context manager over *names, as switched_off (tests/kernels/test_switches.py)"),
    # no arguments
    "torchmm.filters.unscented.CubatureSigmaPoints": _NO_ARGS,
    "torchmm.multimodel.interaction.MomentMixing": _NO_ARGS,
    "torchmm.multimodel.interaction.Collapse": _NO_ARGS,
    "torchmm.multimodel.interaction.NoInteraction": _NO_ARGS,
    "torchmm.multimodel.structure.ActiveSetMixing": _NO_ARGS,
    "torchmm.multimodel.structure.AllModels": _NO_ARGS,
    "torchmm.models.adapters.CholeskyCovariance":
        _NO_ARGS + " (a parametrization: learnable_noise applies it)",
    "torchmm.models.adapters.LogDiagonalCovariance":
        _NO_ARGS + " (a parametrization: learnable_noise applies it)",
}


# -- shared set-ups (float64) ----------------------------------------------------------------------
def cv():
    return models.ConstantVelocity(1, q=0.5, dtype=torch.float64)


def pos():
    return models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)


EXAMPLES: dict[str, Callable[[], Call]] = {}


def example(key: str):
    def register(build):
        EXAMPLES[key] = _f64(build)
        return build

    return register


# -- models -----------------------------------------------------------------------------------------
example("torchmm.models.motion.ConstantVelocity")(
    lambda: call(models.ConstantVelocity, 1, 1.0, 0.5, noise="discrete", acceleration=[[0.5], [-0.5]],
                 dtype=torch.float64))
example("torchmm.models.motion.ConstantAcceleration")(
    lambda: call(models.ConstantAcceleration, 1, 1.0, 0.5, noise="continuous", dtype=torch.float64))
example("torchmm.models.motion.CoordinatedTurn")(
    lambda: call(models.CoordinatedTurn, [0.1, -0.1], 1.0, 0.5, noise="discrete", dtype=torch.float64))
example("torchmm.models.motion.kinematic_matrices")(
    lambda: call(models.kinematic_matrices, 2, 1.0, 0.5, "discrete", torch.float64))

example("torchmm.models.motion.NonlinearCoordinatedTurn")(
    lambda: call(models.NonlinearCoordinatedTurn, 1.0, 0.5, 1e-3, noise="discrete", dtype=torch.float64))
example("torchmm.models.linear.LinearMotion")(
    lambda: call(models.LinearMotion, [[1.0, 1.0], [0.0, 1.0]], 0.1 * torch.eye(2), [0.0, 0.5],
                 [[0.0], [1.0]]))
example("torchmm.models.linear.LinearMeasurement")(
    lambda: call(models.LinearMeasurement, [[1.0, 0.0]], [[2.0]]))
example("torchmm.models.measurement.PositionMeasurement")(
    lambda: call(models.PositionMeasurement, 4, [0, 2], torch.eye(2), dtype=torch.float64))
example("torchmm.models.measurement.RangeBearing")(
    lambda: call(models.RangeBearing, 4, torch.diag(torch.tensor([1.0, 0.01])), (0, 2), (1.0, -1.0),
                 dtype=torch.float64))
example("torchmm.models.transition.validate_transition")(
    lambda: call(torchmm.validate_transition, [[0.9, 0.1], [0.2, 0.8]], "P"))
example("torchmm.models.transition.alpha_transition")(
    lambda: call(torchmm.alpha_transition, [0.05, 0.1, 0.05], dtype=torch.float64))
example("torchmm.models.transition.transition_alpha")(
    lambda: call(torchmm.multimodel.transition_alpha, torch.tensor([[0.9, 0.1], [0.2, 0.8]]), 1e-12))
example("torchmm.models.transition.ModeTransition")(
    lambda: call(torchmm.ModeTransition, [[0.9, 0.1], [0.2, 0.8]], learnable=True))
example("torchmm.models.transition.LogisticTransition")(
    lambda: call(torchmm.LogisticTransition, torch.zeros(2, 1, 2), columns=[0, 1]))
example("torchmm.models.adapters.LearnedMotion")(
    lambda: call(models.LearnedMotion, torch.nn.Linear(2, 2).double(), 2, 0.1 * torch.eye(2),
                 noise="cholesky", residual=True, uses_input=False))
example("torchmm.models.adapters.LearnedMeasurement")(
    lambda: call(models.LearnedMeasurement, torch.nn.Linear(2, 1).double(), 2, 1, torch.eye(1),
                 noise="log_diagonal"))
example("torchmm.models.adapters.LogScaleCovariance")(
    lambda: call(models.LogScaleCovariance, torch.eye(2), (3,)))
example("torchmm.models.adapters.learnable_noise")(
    lambda: call(models.learnable_noise, models.LinearMotion(torch.eye(2), torch.eye(2)), "Q", "scale",
                 scale_shape=()))

# -- filters ----------------------------------------------------------------------------------------
def prior(n=2):
    return torchmm.GaussianBelief(torch.zeros(n), torch.eye(n))


example("torchmm.beliefs.gaussian.GaussianBelief.create")(
    lambda: call(torchmm.GaussianBelief.create, [0.0, 1.0], torch.eye(2), dtype=torch.float64, device="cpu"))
example("torchmm.filters.base.Filter.initial_belief")(
    lambda: call(torchmm.KalmanFilter.initial_belief, torchmm.KalmanFilter(cv(), pos()), prior()))
example("torchmm.filters.kalman.KalmanFilter")(lambda: call(torchmm.KalmanFilter, cv(), pos(), joseph=True))
example("torchmm.filters.kalman.ExtendedKalmanFilter")(
    lambda: call(torchmm.ExtendedKalmanFilter, models.NonlinearCoordinatedTurn(),
                 models.RangeBearing(5, torch.diag(torch.tensor([1.0, 0.01])), position_indices=(0, 2)),
                 joseph=False))
example("torchmm.filters.unscented.UnscentedKalmanFilter")(
    lambda: call(torchmm.UnscentedKalmanFilter, cv(), pos(), torchmm.MerweScaledSigmaPoints(1.0),
                 joseph=None))
example("torchmm.filters.unscented.MerweScaledSigmaPoints")(
    lambda: call(torchmm.MerweScaledSigmaPoints, 0.5, 2.0, 0.0))
example("torchmm.filters.unscented.JulierSigmaPoints")(lambda: call(torchmm.JulierSigmaPoints, 1.0))
example("torchmm.filters.particle.ParticleFilter")(
    lambda: call(torchmm.ParticleFilter, cv(), pos(), resampling="systematic", ess_threshold=0.5,
                 num_particles=50, generator=torch.Generator().manual_seed(0), state_dependent_noise=False,
                 noise_dtype=torch.float64))
example("torchmm.filters.particle.ParticleFilter.initial_belief")(
    lambda: call(torchmm.ParticleFilter.initial_belief, torchmm.ParticleFilter(cv(), pos()), prior(), 20,
                 generator=torch.Generator().manual_seed(0)))
example("torchmm.filters.variational.StudentTVBFilter")(
    lambda: call(torchmm.StudentTVBFilter, cv(), pos(), 5.0, 5, elbo_history=True, joseph=None))
example("torchmm.filters.skew_t.SkewTVBFilter")(
    lambda: call(torchmm.SkewTVBFilter, cv(), pos(), [1.0], 5.0, 5, joseph=None))
example("torchmm.filters.skew_t.SkewTIWVBFilter")(
    lambda: call(torchmm.SkewTIWVBFilter, cv(), pos(), [1.0], [5.0], 3.0, 5, "derived", False, None))
example("torchmm.filters.vbakf.VBAKFPR")(
    lambda: call(torchmm.VBAKFPR, cv(), pos(), 3.0, 0.98, 5, 3.0, None))
example("torchmm.filters.vbakf.VBAKFPR.initial_belief")(
    lambda: call(torchmm.VBAKFPR.initial_belief, torchmm.VBAKFPR(cv(), pos()), prior(), 2.0 * torch.eye(1)))


def _rts():
    kf = torchmm.KalmanFilter(cv(), pos())
    traj = torchmm.run_filter(kf, prior().expand(3),
                              torch.randn(5, 3, 1, generator=torch.Generator().manual_seed(0)))
    return call(torchmm.rts_smoother, kf.motion, traj.belief, traj.prior, controls=None)


example("torchmm.filters.smoother.rts_smoother")(_rts)

# -- multiple models ------------------------------------------------------------------------------------
P2 = [[0.9, 0.1], [0.2, 0.8]]
mm = torchmm.multimodel


def cv_bank():
    return models.ConstantVelocity(1, q=0.5, acceleration=[[0.5], [-0.5]], dtype=torch.float64)


def kf_bank():
    return torchmm.KalmanFilter(cv_bank(), pos())


def _gen():
    return torch.Generator().manual_seed(0)


for _cls in (mm.IMM, mm.GPB1, mm.GPB2, mm.MultipleModelFilter, torchmm.VariationalIMM):
    example(f"{_cls.__module__}.{_cls.__qualname__}")(
        lambda cls=_cls: call(cls, kf_bank(), torch.tensor(P2), mm.MomentMixing()))
example("torchmm.multimodel.imm.MultipleModelFilter.initial_belief")(
    lambda: call(mm.IMM.initial_belief, mm.IMM(kf_bank(), P2), prior(), [0.5, 0.5], generator=None))
example("torchmm.multimodel.imm.StaticMM")(lambda: call(mm.StaticMM, kf_bank(), 2))
example("torchmm.multimodel.bank.make_bank")(lambda: call(mm.make_bank, kf_bank(), 2))
example("torchmm.multimodel.bank.VectorizedBank")(lambda: call(mm.VectorizedBank, kf_bank(), 2))
example("torchmm.multimodel.bank.ListBank")(
    lambda: call(mm.ListBank, [torchmm.KalmanFilter(cv(), pos()), torchmm.KalmanFilter(cv(), pos())]))
example("torchmm.multimodel.bank.IndexedBank")(
    lambda: call(mm.IndexedBank, mm.make_bank(kf_bank(), 2), [0, 1, 1]))
example("torchmm.multimodel.embedding.kinematic_index")(lambda: call(mm.kinematic_index, 2, 3, ndim=2))
example("torchmm.multimodel.embedding.Embedded")(
    lambda: call(mm.Embedded, torchmm.KalmanFilter(cv(), pos()), [0, 1], 3, fill_mean=[0.0, 0.0, 0.0],
                 fill_cov=[0.0, 0.0, 4.0]))
example("torchmm.multimodel.structure.FixedSet")(lambda: call(mm.FixedSet, [0, 2]))
example("torchmm.multimodel.structure.DropBelow")(lambda: call(mm.DropBelow, 0.01, [1]))
example("torchmm.multimodel.structure.VariableStructureIMM")(
    lambda: call(mm.VariableStructureIMM, kf_bank(), P2, mm.FixedSet([0, 1]), feedback=False))
example("torchmm.multimodel.policies.ExactMinimumEntropy")(
    lambda: call(torchmm.ExactMinimumEntropy, [[0], [0, 1]], chunk_size=64, entropy="literal"))
example("torchmm.multimodel.challenge.ChallengeMatch")(
    lambda: call(torchmm.ChallengeMatch, 20, 5, method="cm", passes=2))
example("torchmm.multimodel.particle_mixing.ParticleMixing")(lambda: call(mm.ParticleMixing, "stratified", 30))
example("torchmm.multimodel.particle.MultipleModelParticleFilter")(
    lambda: call(torchmm.MultipleModelParticleFilter, cv_bank(), pos(), P2, 30, mixing="two_stage",
                 generator=_gen(), innovation_stats=False, noise_dtype=torch.float64))
example("torchmm.multimodel.particle.MultipleModelParticleFilter.initial_belief")(
    lambda: call(torchmm.MultipleModelParticleFilter.initial_belief,
                 torchmm.MultipleModelParticleFilter(cv_bank(), pos(), P2, 30), prior(), [0.5, 0.5],
                 generator=_gen()))
example("torchmm.multimodel.mevsmm.MinimumEntropyVSMM")(
    lambda: call(torchmm.MinimumEntropyVSMM, cv_bank(), pos(), P2, 30,
                 selection=torchmm.ChallengeMatch(20, 5), feedback=True, mixing="systematic",
                 generator=_gen(), innovation_stats=True, noise_dtype=None))
example("torchmm.multimodel.mevsmm.MinimumEntropyVSMM.initial_belief")(
    lambda: call(torchmm.MinimumEntropyVSMM.initial_belief,
                 torchmm.MinimumEntropyVSMM(cv_bank(), pos(), P2, 30,
                                            selection=torchmm.ExactMinimumEntropy()),
                 prior(), [0.5, 0.5], generator=_gen()))
example("torchmm.multimodel.mevsmm.EqMAParticleFilter")(
    lambda: call(torchmm.EqMAParticleFilter, [[1.0, 1.0], [0.0, 1.0]], [[0.5], [1.0]], [[0.0], [1.0]],
                 [[0.1]], pos(), 30, transition=None, stay=0.9, mixing="systematic", generator=_gen(),
                 innovation_stats=True, noise_dtype=None))


def _source():
    return models.PositionMeasurement(2, [0], 4.0, dtype=torch.float64)


for _cls in (mm.SourceUpdateIMM, mm.FusionIMM):
    example(f"{_cls.__module__}.{_cls.__qualname__}")(lambda cls=_cls: call(cls, kf_bank(), P2, _source()))
example("torchmm.multimodel.source_baselines.SourceModeVSIMM")(
    lambda: call(mm.SourceModeVSIMM, kf_bank(), P2, _source(), extra_model=1, p_new=0.1, p_ee=0.9, eps=0.01,
                 drop_below=0.001))
example("torchmm.multimodel.source_baselines._SourceTrackIMM.initial_belief")(
    lambda: call(mm.FusionIMM.initial_belief, mm.FusionIMM(kf_bank(), P2, _source()), prior(), [0.5, 0.5],
                 generator=None))
example("torchmm.multimodel.source_baselines.SourceModeVSIMM.initial_belief")(
    lambda: call(mm.SourceModeVSIMM.initial_belief, mm.SourceModeVSIMM(kf_bank(), P2, _source()), prior(),
                 [0.5, 0.5], generator=None))
example("torchmm.multimodel.transfer.TransferIMM")(
    lambda: call(mm.TransferIMM, kf_bank(), P2, _source(), smoothing_reference="mixed",
                 mode_likelihood="corrected", gate=mm.InfluenceGate(0.0, 1, "process")))
example("torchmm.multimodel.transfer.InfluenceGate")(lambda: call(mm.InfluenceGate, 0.5, 1, "process"))
example("torchmm.multimodel.variational.gimmaf")(
    lambda: call(torchmm.gimmaf, cv_bank(), pos(), P2, skewness=[1.0], df=[5.0], tau=3.0, iterations=5,
                 gamma_shape="derived", elbo_history=False, joseph=None))
example("torchmm.multimodel.variational.imm_vbt")(
    lambda: call(torchmm.imm_vbt, cv_bank(), pos(), P2, df=5.0, iterations=5, elbo_history=False,
                 joseph=None))

# -- run_filter -------------------------------------------------------------------------------------------
def _run_filter():
    kf = torchmm.KalmanFilter(cv(), pos())
    z = torch.randn(4, 3, 1, generator=_gen())
    return call(torchmm.run_filter, kf, prior().expand(3), z, controls=None, motions=[cv()] * 4,
                sensors=None, generator=None, update_first=True, record=None, progress=False,
                fast_path=False, compile=False)


example("torchmm.run.run_filter")(_run_filter)

# -- the kernels' switches (the valid calls keep the switch as it is) -------------------------------
from torchmm import kernels  # noqa: E402

example("torchmm.kernels.enabled")(lambda: call(kernels.enabled, "particle_stages"))
example("torchmm.kernels.set_enabled")(
    lambda: call(kernels.set_enabled, "particle_stages", kernels.enabled("particle_stages")))

# -- the other subpackages' examples (one module each; they register into EXAMPLES / NOT_ENTRY_POINTS)
from tests.robustness import (
    api_examples_fusion,  # noqa: E402,F401
    api_examples_more,  # noqa: E402,F401
)

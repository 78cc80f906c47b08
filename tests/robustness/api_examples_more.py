"""Examples of the entry points of torchmm.analysis, metrics, simulate, learn and distributions
(see tests/robustness/api_examples.py)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import torch

from tests.robustness.api_examples import _OP, NOT_ENTRY_POINTS, call, example
from torchmm import (
    IMM,
    ParticleFilter,
    analysis,
    assignment,
    association,
    distributions,
    filters,
    learn,
    metrics,
    models,
    simulate,
)
from torchmm.beliefs import GaussianBelief, ParticleBelief
from torchmm.filters import KalmanFilter

NOT_ENTRY_POINTS.update({
    "torchmm.learn.estimation.Estimate": "a result record (what estimate found), built by estimate",
    "torchmm.learn.em.EMResult": "a result record (what em found), built by em",
    "torchmm.learn.em_switching.SwitchingEMResult": "a result record (what em_switching found), built by em_switching",
    "torchmm.association.mht.HypothesisBelief": "a belief built inside every step (MHT.initial_belief makes it; "
    "its validate checks the log-weights, history and tracks)",
    "torchmm.association.mht_tracks.TrackHypotheses": "a belief built inside every step (ManagedMHT.initial_belief "
    "makes it)",
    "torchmm.association.sensors.SensorScans": "a data record (the sensors' scans and which reported): "
    "SequentialSensors.check_measurements checks it at run_filter's entry, naming each field",
    "torchmm.distributions.truncated_normal_moments": _OP + " (the variational filters call it inside every "
    "step; its inputs are the filter's own moments)",
})


# -- shared set-ups (built inside the examples, so in float64) ----------------------------------------
def _gen():
    return torch.Generator().manual_seed(0)


def _cv(q=0.5):
    return models.ConstantVelocity(1, q=q, dtype=torch.float64)


def _pos():
    return models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)


def _alpha():
    return torch.tensor([0.05, 0.1])


def _probs():
    return torch.tensor([[0.3, 0.7], [0.6, 0.4]])


def _transition():
    return torch.tensor([[0.9, 0.1], [0.2, 0.8]])


def _means():
    return torch.tensor([[[0.0, 1.0], [2.0, 1.0]], [[1.0, 0.0], [0.5, 0.5]]])  # (B=2, M=2, n=2)


def _mixed():
    return _means() + 0.1


def _matched():
    return torch.tensor([0, 1])


# -- analysis -------------------------------------------------------------------------------------------
_IMM = "torchmm.analysis.imm."
example(_IMM + "predicted_mode_probs")(lambda: call(analysis.predicted_mode_probs, _alpha(), _probs()))
example(_IMM + "mixed_probability_bounds")(lambda: call(analysis.mixed_probability_bounds, _alpha()))
example(_IMM + "ratio_bounds")(lambda: call(analysis.ratio_bounds, _alpha(), _probs()))
example(_IMM + "delta_ratio")(lambda: call(analysis.delta_ratio, _alpha(), _probs(), _matched()))
example(_IMM + "zeta_ratio")(lambda: call(analysis.zeta_ratio, _transition(), _probs(), _matched()))
example(_IMM + "matched_model")(
    lambda: call(analysis.matched_model, _means(), torch.tensor([[0.0, 1.0], [0.4, 0.5]])))
example(_IMM + "interaction_deviations")(
    lambda: call(analysis.interaction_deviations, _probs(), _means(), _mixed(), _matched()))
example(_IMM + "check_conclusions")(
    lambda: call(analysis.check_conclusions, _transition(), _probs(), _means(), _mixed(), _matched(),
                 tol=1e-9))
example(_IMM + "check_probability_bounds")(
    lambda: call(analysis.check_probability_bounds, _alpha(), _probs(),
                 analysis.predicted_mode_probs(_alpha(), _probs()), tol=1e-9))


# -- metrics --------------------------------------------------------------------------------------------
def _estimate():
    return torch.arange(12.0).reshape(3, 2, 2) / 4  # (T=3, B=2, n=2)


_M = "torchmm.metrics."
example(_M + "squared_error")(lambda: call(metrics.squared_error, _estimate(), torch.zeros(3, 2, 2), [0]))
example(_M + "rmse")(lambda: call(metrics.rmse, _estimate(), torch.zeros(3, 2, 2), [0, 1]))
example(_M + "armse")(lambda: call(metrics.armse, _estimate(), torch.zeros(3, 2, 2), components=[1]))
example(_M + "nees")(
    lambda: call(metrics.nees, GaussianBelief(_estimate(), torch.eye(2).expand(3, 2, 2, 2)),
                 torch.zeros(3, 2, 2)))
example(_M + "nis")(
    lambda: call(metrics.nis, torch.tensor([[1.0, 2.0], [float("nan"), 1.0]]),
                 torch.tensor([[4.0, 1.0], [1.0, 2.0]]).expand(2, 2, 2)))
example(_M + "mode_hits")(lambda: call(metrics.mode_hits, _probs().log(), _matched()))
example(_M + "mode_accuracy")(
    lambda: call(metrics.mode_accuracy, torch.stack([_probs(), _probs()]),
                 torch.stack([_matched(), _matched()])))

_SETS = "torchmm.metrics.sets."
example(_SETS + "gospa")(
    lambda: call(metrics.gospa, torch.tensor([[0.0, 1.0], [9.0, 9.0]]), torch.tensor([[0.0, 0.0], [4.0, 0.0]]),
                 c=3.0, p=2.0, estimate_present=torch.tensor([True, True]),
                 truth_present=torch.tensor([True, False])))
example(_SETS + "gospa_switching")(
    lambda: call(metrics.gospa_switching, torch.tensor([[0, 1], [1, -1], [1, 0]]), penalty=2.0, p=2.0,
                 truth_present=torch.tensor([[True, True], [True, True], [False, True]])))
example(_SETS + "ospa")(
    lambda: call(metrics.ospa, torch.tensor([[0.0, 1.0], [9.0, 9.0]]), torch.tensor([[0.0, 0.0], [4.0, 0.0]]),
                 c=3.0, p=1.0, estimate_present=torch.tensor([True, False]),
                 truth_present=torch.tensor([True, True])))
example("torchmm.assignment.assignment_cost")(
    lambda: call(assignment.assignment_cost, torch.tensor([[4.0, 1.0, 3.0], [2.0, 0.0, 5.0]]), torch.tensor([1, 0])))
example("torchmm.assignment.linear_assignment")(
    lambda: call(assignment.linear_assignment, torch.tensor([[4.0, 1.0, 3.0], [2.0, 0.0, 5.0]])))
example("torchmm.assignment.k_best_assignments")(
    lambda: call(assignment.k_best_assignments, torch.tensor([[4.0, 1.0, 3.0], [2.0, 0.0, 5.0]]), 3))


# -- simulate -------------------------------------------------------------------------------------------
example("torchmm.association.pda.PDA")(
    lambda: call(association.PDA,
                 filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                      models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                 detection_probability=0.9, clutter_density=0.01, gate_probability=0.99))
example("torchmm.association.jpda.JPDA")(
    lambda: call(association.JPDA,
                 filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                      models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                 detection_probability=0.9, clutter_density=0.01, gate_probability=0.99, method="lbp",
                 max_targets=8, iterations=50, tolerance=1e-12))
example("torchmm.association.mht.MHT")(
    lambda: call(association.MHT,
                 filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                      models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                 detection_probability=0.9, clutter_density=0.01, gate_probability=0.99, hypotheses=4, k=6,
                 n_scan=2))
example("torchmm.association.jpda.GNN")(
    lambda: call(association.GNN,
                 filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                      models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                 detection_probability=0.9, clutter_density=0.01, gate_probability=0.99))
example("torchmm.association.ipda.IPDA")(
    lambda: call(association.IPDA,
                 filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                      models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                 detection_probability=0.9, clutter_density=0.01, gate_probability=0.99, survival_probability=0.98,
                 birth_probability=0.01))
example("torchmm.association.ipda.JIPDA")(
    lambda: call(association.JIPDA,
                 filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                      models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                 detection_probability=0.9, clutter_density=0.01, gate_probability=0.99, survival_probability=0.98,
                 birth_probability=0.01, method="lbp", max_targets=8, iterations=50, tolerance=1e-12))
example("torchmm.association.ipda.IPDA.initial_belief")(  # an existence per run
    lambda: call(association.IPDA.initial_belief,
                 association.IPDA(filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                                       models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                                  detection_probability=0.9, clutter_density=0.01),
                 GaussianBelief(torch.zeros(2, 2), torch.eye(2)), existence=torch.tensor([0.5, 0.9])))
example("torchmm.association.ipda.JIPDA.initial_belief")(  # an existence per track: (runs, tracks)
    lambda: call(association.JIPDA.initial_belief,
                 association.JIPDA(filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                                        models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                                   detection_probability=0.9, clutter_density=0.01),
                 GaussianBelief(torch.zeros(2, 3, 2), torch.eye(2)), existence=torch.full((2, 3), 0.4)))
example("torchmm.association.tracks.ManagedTracks")(  # over an IMM of two accelerations (IMM-JIPDA)
    lambda: call(association.ManagedTracks,
                 association.JIPDA(IMM(filters.KalmanFilter(
                     models.ConstantVelocity(1, acceleration=[[0.0], [1.0]], dtype=torch.float64),
                     models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                     torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=torch.float64)),
                     detection_probability=0.9, clutter_density=0.01),
                 capacity=4, initiate=association.position_initiator(2, [0], 1.0, 4.0), birth_existence=0.1,
                 unexplained=0.5, delete=0.01, confirm=0.9, m_of_n=(2, 3), max_misses=3, mode_probs=[0.7, 0.3]))
example("torchmm.association.tracks.ManagedTracks.initial_belief")(  # an empty table of 2 runs
    lambda: call(association.ManagedTracks.initial_belief,
                 association.ManagedTracks(
                     association.JIPDA(filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                                            models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                                       detection_probability=0.9, clutter_density=0.01),
                     capacity=3, initiate=association.position_initiator(2, [0], 1.0, 4.0)),
                 (2,), dtype=torch.float64, device="cpu"))
example("torchmm.association.mht_tracks.ManagedMHT")(  # IMM tracks, score and M-of-N rules
    lambda: call(association.ManagedMHT,
                 IMM(filters.KalmanFilter(models.ConstantVelocity(1, acceleration=[[0.0], [1.0]], dtype=torch.float64),
                                          models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                     torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=torch.float64)),
                 detection_probability=0.9, clutter_density=0.01, capacity=3,
                 initiate=association.position_initiator(2, [0], 1.0, 4.0), birth_density=0.001,
                 gate_probability=0.99, hypotheses=4, k=6, n_scan=2, m_of_n=(2, 3), max_misses=3,
                 mode_probs=[0.7, 0.3], confirm_score=8.0, delete_drop=6.0))
example("torchmm.association.mht_tracks.ManagedMHT.initial_belief")(  # two runs, one known track each
    lambda: call(association.ManagedMHT.initial_belief,
                 association.ManagedMHT(filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                                             models.PositionMeasurement(2, [0], 1.0,
                                                                                        dtype=torch.float64)),
                                        detection_probability=0.9, clutter_density=0.01, capacity=3,
                                        initiate=association.position_initiator(2, [0], 1.0, 4.0),
                                        birth_density=0.001),
                 (2,), tracks=GaussianBelief(torch.zeros(2, 1, 2), torch.eye(2)), dtype=torch.float64,
                 device="cpu"))
example("torchmm.association.sensors.SequentialSensors")(  # a radar and a finer sensor, each its JPDA
    lambda: call(association.SequentialSensors,
                 [association.JPDA(filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                                        models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                                   detection_probability=0.9, clutter_density=0.01),
                  association.JPDA(filters.KalmanFilter(models.ConstantVelocity(1, dtype=torch.float64),
                                                        models.PositionMeasurement(2, [0], 0.1, dtype=torch.float64)),
                                   detection_probability=0.7, clutter_density=0.05)]))
example("torchmm.association.tracks.position_initiator")(
    lambda: call(association.position_initiator, 4, [0, 2], torch.eye(2), 25.0))
example("torchmm.association.particle.ParticleJPDA")(
    lambda: call(association.ParticleJPDA,
                 ParticleFilter(models.ConstantVelocity(1, noise="continuous", dtype=torch.float64),
                                models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                 detection_probability=0.9, clutter_density=0.01, method="lbp", max_targets=4, iterations=50,
                 tolerance=1e-10))
example("torchmm.association.particle.ParticlePDA")(
    lambda: call(association.ParticlePDA,
                 ParticleFilter(models.ConstantVelocity(1, noise="continuous", dtype=torch.float64),
                                models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
                 detection_probability=0.9, clutter_density=0.01))
example("torchmm.association.jpda.jpda_marginals")(
    lambda: call(association.jpda_marginals, torch.tensor([[[0.0, -1.0], [-1.0, 0.0]]], dtype=torch.float64), 0.1,
                 method="exact", iterations=20, tolerance=1e-12))
example("torchmm.association.pda.chi2_gate")(
    lambda: call(association.chi2_gate, 0.99, 2))
_S = "torchmm.simulate.markov."
example("torchmm.simulate.detections.simulate_detections")(
    lambda: call(simulate.simulate_detections, models.PositionMeasurement(4, [0, 2], 1.0, dtype=torch.float64),
                 torch.zeros(3, 2, 2, 4), detection_probability=0.9, clutter_rate=1.0,
                 region=torch.tensor([[-10.0, 10.0], [-10.0, 10.0]]), max_clutter=4, generator=_gen()))
example(_S + "sample_categorical")(lambda: call(simulate.sample_categorical, _probs(), generator=_gen()))
example(_S + "simulate_modes")(
    lambda: call(simulate.simulate_modes, _transition(), 3, (4,), initial_probs=torch.tensor([0.5, 0.5]),
                 generator=_gen()))
example(_S + "simulate_jump_system")(
    lambda: call(simulate.simulate_jump_system, [_cv(0.5), _cv(2.0)], _transition(),
                 GaussianBelief(torch.zeros(2), torch.eye(2)), 3, (4,),
                 initial_mode_probs=torch.tensor([0.5, 0.5]), generator=_gen()))
example(_S + "simulate_measurements")(
    lambda: call(simulate.simulate_measurements, _pos(), torch.zeros(3, 4, 2),
                 modes=torch.zeros(3, 4, dtype=torch.long), available=torch.ones(3, 4, dtype=torch.bool),
                 generator=_gen()))
example(_S + "bernoulli_mask")(
    lambda: call(simulate.bernoulli_mask, 3, (4,), 0.5, generator=_gen(), device="cpu", dtype=torch.float64))
example(_S + "periodic_mask")(lambda: call(simulate.periodic_mask, 5, (4,), 2, offset=1, device="cpu"))
example(_S + "simulate_multirate")(
    lambda: call(simulate.simulate_multirate, _pos(), _pos(), torch.zeros(3, 4, 2), probability=0.5, offset=0,
                 generator=_gen()))


# -- distributions --------------------------------------------------------------------------------------
example("torchmm.distributions.MultivariateStudentT")(
    lambda: call(distributions.MultivariateStudentT, torch.zeros(2), 2 * torch.eye(2), 5.0,
                 validate_args=False))
example("torchmm.distributions.SkewT")(
    lambda: call(distributions.SkewT, torch.zeros(2), torch.full((2,), 4.0), torch.full((2,), 1.0), 10.0,
                 validate_args=False))


# -- learn ----------------------------------------------------------------------------------------------
class _Logger:
    def scalar(self, tag, value, step):
        pass


def _learnable_kf():
    motion = models.learnable_noise(models.ConstantVelocity(1, q=1.0, dtype=torch.float64), "Q", "scale")
    return KalmanFilter(motion, _pos())


def _prior():
    return GaussianBelief(torch.zeros(3, 2), torch.eye(2).expand(3, 2, 2))


def _z():
    return torch.randn(5, 3, 1, generator=_gen())


def _trainer():
    kf = _learnable_kf()
    return learn.Trainer(kf, torch.optim.SGD(kf.parameters(), lr=1e-3))


def _checkpoint() -> Path:
    return Path(tempfile.mkdtemp(prefix="torchmm-contract-")) / "model.pt"


def _saved():
    kf = _learnable_kf()
    opt = torch.optim.SGD(kf.parameters(), lr=1e-3)
    path = learn.save_checkpoint(_checkpoint(), kf, opt)
    return path, kf, opt


_L = "torchmm.learn."
example(_L + "loss.negative_log_likelihood")(
    lambda: call(learn.negative_log_likelihood, KalmanFilter(_cv(), _pos()), _prior(), _z(), controls=None,
                 reduction="sum", return_final=False))
example(_L + "loss.truncated_segments")(lambda: call(learn.truncated_segments, 10, 4))
example(_L + "objective.Objective")(
    lambda: call(learn.Objective, KalmanFilter(_cv(), _pos()), _prior(), _z(), reduction="sum", update_first=False))


def _minimize():
    kf = _learnable_kf()
    objective = learn.Objective(kf, _prior(), _z())
    return call(objective.minimize, parameters=list(kf.parameters()), method="L-BFGS-B", tol=1e-6,
                options={"maxiter": 2})


example(_L + "objective.Objective.minimize")(_minimize)


def _estimation():
    from torchmm.models import LinearMeasurement, LinearMotion

    kf = KalmanFilter(LinearMotion([[1.0]], [[1.0]]), LinearMeasurement([[1.0]], [[1.0]]))
    z = torch.randn(20, 1, generator=_gen()).cumsum(0)
    return call(learn.estimate, kf, GaussianBelief(torch.zeros(1), torch.eye(1)), z, {"motion.Q": "variance"},
                controls=None, update_first=False, burn=0, method="L-BFGS-B", se=True, hessian="differences",
                tol=1e-8, maxiter=20, write=True, progress=False)


example(_L + "estimation.estimate")(_estimation)
example(_L + "entries.Param")(lambda: call(learn.Param, "free", fixed=None, groups=None, lower=0.0, upper=2.0,
                                              label="x"))
example(_L + "entries.stationary")(lambda: call(learn.stationary, _transition()))
def _em():
    from torchmm.models import LinearMeasurement, LinearMotion

    one = torch.ones(1, 1)
    kf = KalmanFilter(LinearMotion(one.clone(), one.clone()), LinearMeasurement(one.clone(), one.clone()))
    z = torch.randn(20, 1, generator=_gen()).cumsum(0)
    return call(learn.em, kf, GaussianBelief(torch.zeros(1), torch.eye(1)), z, ["Q", "R"], iterations=2, tol=None,
                update_first=True, per_series=False, controls=None, present=None, progress=False)


example(_L + "em.em")(_em)


def _em_switching():
    from torchmm.models import LinearMeasurement, LinearMotion

    one = torch.ones(2, 1, 1)
    imm = IMM(KalmanFilter(LinearMotion(one.clone(), 0 * one), LinearMeasurement(torch.tensor([[[0.0]], [[3.0]]]),
                                                                                 one.clone())), _transition())
    b0 = imm.initial_belief(GaussianBelief(torch.ones(1), torch.zeros(1, 1)))
    z = torch.randn(30, 1, generator=_gen())
    return call(learn.em_switching, imm, b0, z, ["transition", "H", "R"], iterations=2, tol=None, update_first=False,
                shared=(), ergodic=False, controls=None, present=None, progress=False)


example(_L + "em_switching.em_switching")(_em_switching)
example(_L + "entries.estimated_entries")(
    lambda: call(learn.estimated_entries, KalmanFilter(_cv(), _pos()), {"measurement.R": "variance"}))

example(_L + "trainer.Trainer")(
    lambda: call(learn.Trainer, _learnable_kf(), torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], 0.1),
                 window=4, clip_grad_norm=10.0, loss_fn=learn.negative_log_likelihood, track=lambda: {},
                 logger=_Logger(), callbacks=[], checkpoint_path=_checkpoint(), checkpoint_every=0,
                 prefix="train"))
example(_L + "trainer.Trainer.fit")(
    lambda: call(_trainer().fit, _prior(), _z(), 1, controls=None, batch_size=2, generator=_gen()))
example(_L + "trainer.save_checkpoint")(
    lambda: call(learn.save_checkpoint, _checkpoint(), _learnable_kf(), torch.optim.SGD(
        [torch.nn.Parameter(torch.zeros(1))], lr=0.1), note="example"))
example(_L + "trainer.load_checkpoint")(lambda: call(learn.load_checkpoint, *_saved()))


def _particles():
    g = _gen()
    return ParticleBelief(torch.randn(4, 50, 2, generator=g), torch.randn(4, 50, generator=g))


example(_L + "resampling.soft_resample")(
    lambda: call(learn.soft_resample, _particles(), 0.5, "systematic", generator=_gen()))
example(_L + "resampling.soft_resample_where_needed")(
    lambda: call(learn.soft_resample_where_needed, _particles(), 0.9, 0.5, "stratified", generator=_gen()))
example(_L + "resampling.SoftResamplingParticleFilter")(
    lambda: call(learn.SoftResamplingParticleFilter, _cv(), _pos(), alpha=0.5, ess_threshold=0.5,
                 generator=_gen()))

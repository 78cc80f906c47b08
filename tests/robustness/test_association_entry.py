"""A fuzz of ``torchmm.association`` after issue 44: each defect refused at entry, naming the argument.

* an association given a filter of the other family (``PDA(ParticleFilter)``, ``ParticlePDA(KalmanFilter)``)
  was accepted and failed inside ``run_filter`` naming ``belief``: now refused at construction naming
  ``filter`` and the class to use;
* ``position_initiator`` with an index outside the state (a raw ``IndexError``) or a covariance that is
  not PSD (every track it started failed later);
* ``ManagedTracks.initial_belief(3)`` (``'int' object is not iterable``) and ``((-1,))`` (a raw
  ``RuntimeError``);
* ``run_filter`` over an association named the step's ``z`` and its internal shapes (an IMM's mode
  axis) for a malformed scan: now ``measurements`` and the shapes the user passed, at entry;
* ``jpda_marginals`` of integer log-weights: a raw ``torch.finfo`` error.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchmm import IMM, GaussianBelief, KalmanFilter, ParticleFilter, UnscentedKalmanFilter, run_filter
from torchmm.association import (
    GNN,
    IPDA,
    JIPDA,
    JPDA,
    PDA,
    ManagedTracks,
    ParticleJPDA,
    ParticlePDA,
    jpda_marginals,
    position_initiator,
)
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.multimodel.particle import MultipleModelParticleFilter

A = {"detection_probability": 0.9, "clutter_density": 0.01}
P2 = [[0.9, 0.1], [0.2, 0.8]]


def _kf():
    return KalmanFilter(ConstantVelocity(2, q=0.5), PositionMeasurement(4, [0, 2], 1.0))


def _bank_kf():
    return KalmanFilter(ConstantVelocity(2, q=0.5, acceleration=[[0.0, 0.0], [1.0, 1.0]]),
                        PositionMeasurement(4, [0, 2], 1.0))


def _pf(bank=False):
    acceleration = [[0.0, 0.0], [1.0, 1.0]] if bank else None
    return ParticleFilter(ConstantVelocity(2, q=0.5, noise="continuous", acceleration=acceleration),
                          PositionMeasurement(4, [0, 2], 1.0), num_particles=16)


def _prior(*batch):
    return GaussianBelief(torch.zeros(*batch, 4), 4 * torch.eye(4).expand(*batch, 4, 4))


def _initiate():
    return position_initiator(4, [0, 2], torch.eye(2), 100.0)


# -- 3. the association's filter: its family, at construction ---------------------------------------
PARTICLE_FILTERS = {
    "ParticleFilter": lambda: _pf(),
    "IMM over particle filters": lambda: IMM(_pf(bank=True), torch.tensor(P2)),
    "MultipleModelParticleFilter": lambda: MultipleModelParticleFilter(
        ConstantVelocity(2, q=0.5, noise="continuous", acceleration=[[0.0, 0.0], [1.0, 1.0]]),
        PositionMeasurement(4, [0, 2], 1.0), torch.tensor(P2), 16),
}


@pytest.mark.parametrize("make", PARTICLE_FILTERS.values(), ids=PARTICLE_FILTERS.keys())
@pytest.mark.parametrize("association, instead", [(PDA, "ParticlePDA"), (IPDA, "ParticlePDA"), (JPDA, "ParticleJPDA"),
                                                  (GNN, "ParticleJPDA"), (JIPDA, "ParticleJPDA")],
                         ids=lambda v: getattr(v, "__name__", v))
def test_a_gaussian_association_refuses_a_particle_filter(association, instead, make):
    with pytest.raises(TypeError, match=rf"^filter: {association.__name__} needs a filter with Gaussian beliefs .*"
                                        rf"draws particles.*{instead}"):
        association(make(), **A)


@pytest.mark.parametrize("association, instead", [(ParticlePDA, "PDA"), (ParticleJPDA, "JPDA")])
@pytest.mark.parametrize("make", [_kf, lambda: UnscentedKalmanFilter(ConstantVelocity(2, q=0.5),
                                                                      PositionMeasurement(4, [0, 2], 1.0))])
def test_a_particle_association_refuses_a_gaussian_filter(association, instead, make):
    with pytest.raises(TypeError, match=rf"^filter: expected a ParticleFilter \(for a Gaussian filter: {instead}\), "
                                        rf"got \w+"):
        association(make(), **A)


# -- 5. position_initiator: indices within the state, a PSD covariance --------------------------------
@pytest.mark.parametrize("indices, message", [([0, 9], r"^indices: entry 9 is outside the state's 4 components"),
                                              ([0, 4], r"^indices: entry 4 is outside"),
                                              ([2, 2], r"^indices: 2 is given twice")])
def test_position_initiator_names_indices_outside_the_state(indices, message):
    with pytest.raises(ValueError, match=message):
        position_initiator(4, indices, torch.eye(2), 100.0)


@pytest.mark.parametrize("noise_cov, error, message", [
    (-torch.eye(2), ValueError, r"^noise_cov: .*positive semi-definite"),
    (-1.0, ValueError, r"^noise_cov: .*positive semi-definite"),
    (torch.tensor([[1.0, 2.0], [0.0, 1.0]]), ValueError, r"^noise_cov: .*symmetric"),
    (torch.eye(3), ValueError, r"^noise_cov: expected a number or a \(2, 2\) matrix .*got shape \(3, 3\)"),
])
def test_position_initiator_refuses_a_covariance_that_is_not_one(noise_cov, error, message):
    """``-I`` was accepted and every track it started failed later (a non-PSD state covariance)."""
    with pytest.raises(error, match=message):
        position_initiator(4, [0, 2], noise_cov, 100.0)


def test_position_initiator_still_takes_what_it_took():
    for noise_cov in (torch.eye(2), 4.0, [[2.0, 0.5], [0.5, 1.0]], torch.zeros(2, 2)):
        belief = position_initiator(4, [0, 2], noise_cov, 25.0)(torch.tensor([[1.0, 2.0]]))
        assert belief.mean.tolist() == [[1.0, 0.0, 2.0, 0.0]]
        assert belief.cov[0, 1, 1] == 25.0


# -- 6. ManagedTracks.initial_belief: a batch shape -----------------------------------------------------
@pytest.mark.parametrize("batch, error, message", [
    (3, TypeError, r"^batch_shape: expected a shape such as \(runs,\), got 3 \(a batch of 3 runs is \(3,\)\)"),
    ((-1,), ValueError, r"^batch_shape: sizes must be >= 0, got -1"),
    ((2.5,), TypeError, r"^batch_shape: "),
    ("3", TypeError, r"^batch_shape: "),
])
def test_managed_tracks_initial_belief_names_the_batch_shape(batch, error, message):
    manager = ManagedTracks(JIPDA(_kf(), **A), capacity=3, initiate=_initiate())
    with pytest.raises(error, match=message):
        manager.initial_belief(batch)
    with pytest.raises(TypeError, match=r"^dtype: "):
        manager.initial_belief((2,), dtype=torch.int64)
    assert manager.initial_belief([2]).log_existence.shape == (2, 3)
    assert manager.initial_belief().log_existence.shape == (3,)


# -- 7. run_filter over an association: the scans named measurements, in the user's shapes ---------------
def _managed():
    return ManagedTracks(JIPDA(_kf(), **A), capacity=3, initiate=_initiate())


CASES = {  # filter, its start belief (3 runs; tracks of a joint association last)
    "PDA": (lambda: PDA(_kf(), **A), lambda f: _prior(3)),
    "IPDA": (lambda: IPDA(_kf(), **A), lambda f: f.initial_belief(_prior(3))),
    "GNN": (lambda: GNN(_kf(), **A), lambda f: _prior(3, 2)),
    "JPDA": (lambda: JPDA(_kf(), **A), lambda f: _prior(3, 2)),
    "JIPDA": (lambda: JIPDA(_kf(), **A), lambda f: f.initial_belief(_prior(3, 2))),
    "ManagedTracks": (_managed, lambda f: f.initial_belief((3,))),
    "ParticlePDA": (lambda: ParticlePDA(_pf(), **A),
                    lambda f: f.initial_belief(_prior(3), 16, generator=torch.Generator().manual_seed(0))),
    "ParticleJPDA": (lambda: ParticleJPDA(_pf(), **A),
                     lambda f: f.initial_belief(_prior(3, 2), 16, generator=torch.Generator().manual_seed(0))),
    "IMM(PDA)": (lambda: IMM(PDA(_bank_kf(), **A), torch.tensor(P2)), lambda f: f.initial_belief(_prior(3))),
    "JPDA(IMM)": (lambda: JPDA(IMM(_bank_kf(), torch.tensor(P2)), **A), lambda f: f.initial_belief(_prior(3, 2))),
    "PDA(IMM)": (lambda: PDA(IMM(_bank_kf(), torch.tensor(P2)), **A), lambda f: f.initial_belief(_prior(3))),
}


def _run(name, z):
    make, start = CASES[name]
    f = make()
    return run_filter(f, start(f), z, generator=torch.Generator().manual_seed(1))


@pytest.mark.parametrize("name", CASES)
def test_run_filter_names_measurements_of_the_wrong_detection_size(name):
    """``(T, *B, D, 1)`` for detections of size 2: ``z: expected a scan of detections (*B, D, 2), got
    (3, 3, 1)`` (an IMM: ``(3, 1, 3, 1)``, its mode axis); now the shape the user passed."""
    with pytest.raises(ValueError, match=r"^measurements: expected scans of detections \(T, \*B, D, 2\), "
                                         r"got \(2, 3, 3, 1\)$"):
        _run(name, torch.zeros(2, 3, 3, 1))
    with pytest.raises(ValueError, match=r"^measurements: expected scans of detections \(T, \*B, D, 2\), "
                                         r"got \(2, 2\)$"):
        _run(name, torch.zeros(2, 2))


@pytest.mark.parametrize("name", CASES)
def test_run_filter_names_measurements_that_enlarge_the_runs(name):
    joint = name in ("GNN", "JPDA", "JIPDA", "ManagedTracks", "ParticleJPDA", "JPDA(IMM)")
    runs = r"the runs \(3,\) of the belief's batch \(3, [23]\) \(tracks last\)" if joint \
        else r"the belief's batch \(3,\)"
    with pytest.raises(ValueError, match=rf"^measurements: the scans' batch \(5, 3\) does not broadcast to {runs}; "
                                         r"measurements \(2, 5, 3, 4, 2\) are \(T, \*B, D, m\)"):
        _run(name, torch.zeros(2, 5, 3, 4, 2))
    with pytest.raises(TypeError, match=r"^measurements: expected real detections, got dtype torch.complex128"):
        _run(name, torch.zeros(2, 3, 4, 2, dtype=torch.complex128))


@pytest.mark.parametrize("name", CASES)
def test_run_filter_takes_the_scans_it_took(name):
    """Shared scans ``(T, D, m)``, per-run scans, empty scans: as before (the check reads shapes only)."""
    for z in (torch.zeros(2, 4, 2), torch.zeros(2, 3, 4, 2), torch.zeros(2, 3, 0, 2), torch.zeros(2, 1, 4, 2)):
        out = _run(name, z)
        assert out.log_likelihood.shape[0] == 2


def test_imm_over_an_association_names_the_step_scan_without_its_mode_axis():
    make, start = CASES["IMM(PDA)"]
    f = make()
    with pytest.raises(ValueError, match=r"^z: expected a scan of detections \(\*B, D, 2\), got \(3, 3, 1\)$"):
        f.step(start(f), torch.zeros(3, 3, 1))


@pytest.mark.parametrize("joint", [lambda: JPDA(_bank_kf(), **A), lambda: GNN(_bank_kf(), **A),
                                   lambda: JIPDA(_bank_kf(), **A), lambda: ParticleJPDA(_pf(bank=True), **A)])
def test_a_joint_association_is_not_a_mode_filter(joint):
    """``IMM(JPDA(...))`` took the IMM's mode axis (the last batch axis) for the JPDA's tracks: each mode
    a track competing for the detections, each track a run (with two identical modes it differed from
    the JPDA by 0.48 in the estimate). The joint IMM form is ``JPDA(IMM(...))``."""
    name = type(joint()).__name__
    with pytest.raises(TypeError, match=rf"^bank: {name} cannot be a mode filter .*{name}\(IMM\(...\), ...\)"):
        IMM(joint(), torch.tensor(P2))
    with pytest.raises(TypeError, match=rf"^bank\[0\]: {name} cannot be a mode filter"):
        IMM([joint(), joint()], torch.tensor(P2))
    with pytest.raises(TypeError, match=r"^bank: ManagedTracks cannot be a mode filter"):
        IMM(_managed(), torch.tensor(P2))


# -- 8. jpda_marginals: floating log-weights --------------------------------------------------------------
def test_jpda_marginals_names_integer_log_weights():
    with pytest.raises(TypeError, match=r"^log_weights: expected floating-point values, got dtype torch.int64"):
        jpda_marginals(torch.zeros(1, 2, 3, dtype=torch.long), 0.1)
    with pytest.raises(TypeError, match=r"^log_weights: expected floating-point values, got dtype torch.bool"):
        jpda_marginals(torch.zeros(1, 2, 3, dtype=torch.bool), 0.1)
    # a list is converted to the default dtype, as before
    log_beta, _ = jpda_marginals([[[0, -math.inf]]], 0.1)
    assert log_beta.dtype == torch.get_default_dtype()

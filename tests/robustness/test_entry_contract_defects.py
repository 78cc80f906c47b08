"""Issue 29's defects 3-5 (entry points that skipped their checks, values coerced silently, absolute
tolerances), each with the input that was measured, and the contract mechanism itself
(torchmm/contract/)."""

from __future__ import annotations

import math

import pytest
import torch

from torchmm import (
    IMM,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    ParticleBelief,
    ParticleFilter,
    PositionMeasurement,
    run_filter,
)
from torchmm.contract import Cov, Flag, Gen, Indices, Int, Of, entry_point, registered, spec_of
from torchmm.multimodel import Embedded, FixedSet, VariableStructureIMM
from torchmm.validation import check_covariance


@pytest.fixture()
def bank_filter():
    bank = ConstantVelocity(1, q=0.5, acceleration=[[0.5], [0.0], [-0.5]], dtype=torch.float64)
    return KalmanFilter(bank, PositionMeasurement(2, [0], 1.0, dtype=torch.float64))


P3 = torch.full((3, 3), 1 / 3, dtype=torch.float64)


def _prior(runs=4):
    return GaussianBelief(torch.zeros(runs, 2, dtype=torch.float64),
                          torch.eye(2, dtype=torch.float64).expand(runs, 2, 2))


def _z(steps=5, runs=4, seed=0):
    return torch.randn(steps, runs, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))


# -- defect 3: VariableStructureIMM's policy, per-step models -------------------------------------------
class _EmptyForRunZero:
    def select(self, belief, generator=None):
        active = torch.ones(belief.mode_log_probs.shape, dtype=torch.bool)
        active[0] = False
        return active, {}


class _WrongShape:
    def select(self, belief, generator=None):
        return torch.ones(5, dtype=torch.bool), {}


class _WrongDtype:
    def select(self, belief, generator=None):
        return torch.ones(belief.mode_log_probs.shape), {}


def test_policy_empty_set_fails_that_run_only(bank_filter, caplog):
    vs = VariableStructureIMM(bank_filter, P3, _EmptyForRunZero())
    traj = run_filter(vs, vs.initial_belief(_prior()), _z())
    total = traj.log_likelihood.sum(0)
    assert math.isnan(total[0])  # before: finite, with model_count 0 and no flag
    assert torch.isfinite(total[1:]).all()
    assert traj.extras["empty_set"][:, 0].all() and not traj.extras["empty_set"][:, 1:].any()
    assert "empty model set" in caplog.text
    # the other runs are those of the same estimator without the faulty run
    reference = VariableStructureIMM(bank_filter, P3, FixedSet([0, 1, 2]))
    ref = run_filter(reference, reference.initial_belief(_prior()), _z())
    torch.testing.assert_close(traj.log_likelihood[:, 1:], ref.log_likelihood[:, 1:], rtol=0, atol=0)


@pytest.mark.parametrize("policy, error, match", [
    (_WrongShape(), ValueError, r"^policy: select returned an active set of shape \(5,\)"),
    (_WrongDtype(), TypeError, r"^policy: select returned an active set of dtype torch.float"),
])
def test_policy_wrong_masks_name_the_policy(bank_filter, policy, error, match):
    vs = VariableStructureIMM(bank_filter, P3, policy)
    with pytest.raises(error, match=match):
        run_filter(vs, vs.initial_belief(_prior()), _z())


def test_policy_class_for_an_instance(bank_filter):
    with pytest.raises(TypeError, match=r"^policy: .*got the class FixedSet; create one"):
        VariableStructureIMM(bank_filter, P3, FixedSet)


def test_per_step_models_of_the_wrong_dtype_or_mode_count(bank_filter):
    imm = IMM(bank_filter, P3)
    b0 = imm.initial_belief(_prior())
    with pytest.raises(TypeError, match=r"^motion: dtype torch.float32 differs"):
        run_filter(imm, b0, _z(), motions=[ConstantVelocity(1, dtype=torch.float32)] * 5)
    two_modes = ConstantVelocity(1, acceleration=[[0.5], [0.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^motion: parameter batch \(2,\) does not broadcast"):
        run_filter(imm, b0, _z(), motions=[two_modes] * 5)
    # a model shared by every mode (parameter batch ()) is legitimate
    shared = ConstantVelocity(1, dtype=torch.float64)
    assert torch.isfinite(run_filter(imm, b0, _z(), motions=[shared] * 5).log_likelihood).all()


# -- defect 4: values coerced silently --------------------------------------------------------------------
def test_sizes_flags_and_generators_are_not_coerced(bank_filter):
    kf = KalmanFilter(ConstantVelocity(2, dtype=torch.float64),
                      PositionMeasurement(4, [0, 2], 1.0, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"^common_dim: expected an integer, got 6.5"):
        Embedded(kf, [0, 1, 3, 4], 6.5)
    with pytest.raises(TypeError, match=r"^members: expected a sequence of integers, got the entry 0.5"):
        FixedSet([0.5])
    with pytest.raises(TypeError, match=r"^feedback: expected True or False, got 'no'"):
        VariableStructureIMM(bank_filter, P3, FixedSet([0]), feedback="no")
    imm = IMM(bank_filter, P3)
    b0 = imm.initial_belief(_prior())
    with pytest.raises(TypeError, match=r"^update_first: expected True or False, got 'yes'"):
        run_filter(imm, b0, _z(), update_first="yes")
    with pytest.raises(TypeError, match=r"^generator: expected a torch.Generator, got 'seed'"):
        run_filter(imm, b0, _z(), generator="seed")
    with pytest.raises(TypeError, match=r"^generator: expected a torch.Generator"):
        imm.initial_belief(_prior(), generator="seed")
    with pytest.raises(TypeError, match=r"^generator: expected a torch.Generator"):
        VariableStructureIMM(bank_filter, P3, FixedSet([0])).initial_belief(_prior(), generator=0)


def test_a_particle_set_without_particles():
    pf = ParticleFilter(ConstantVelocity(1, dtype=torch.float64),
                        PositionMeasurement(2, [0], 1.0, dtype=torch.float64))
    empty = ParticleBelief(torch.zeros(4, 0, 2, dtype=torch.float64), torch.zeros(4, 0, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"^belief0.particles: a particle set needs at least one particle"):
        run_filter(pf, empty, _z())  # before: "ValueError: math domain error"
    with pytest.raises(ValueError, match=r"^num_particles: must be >= 1"):
        pf.initial_belief(_prior(), 0)


# -- defect 5: tolerances relative to the matrix's scale ------------------------------------------------
@pytest.mark.parametrize("scale", [1e-12, 1e-300, 1.0, 1e12])
def test_tiny_and_huge_covariances_are_valid(scale):
    R = scale * torch.eye(1, dtype=torch.float64)
    pf = ParticleFilter(ConstantVelocity(1, dtype=torch.float64), PositionMeasurement(2, [0], R))
    assert pf.measurement.R.item() == scale  # before: "R: covariance is not positive definite" at 1e-12
    check_covariance(scale * torch.tensor([[2.0, 1.0], [1.0, 2.0]], dtype=torch.float64), "Q", definite=True)


@pytest.mark.parametrize("scale", [1e-12, 1e-300, 1.0, 1e12])
def test_indefinite_and_asymmetric_are_refused_at_every_scale(scale):
    indefinite = scale * torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^Q: covariance is not positive semi-definite"):
        check_covariance(indefinite, "Q")
    asymmetric = scale * torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^Q: covariance is not symmetric"):
        check_covariance(asymmetric, "Q")


def test_zero_covariance_is_psd_not_pd():
    zero = torch.zeros(2, 2, dtype=torch.float64)
    check_covariance(zero, "Q")
    with pytest.raises(ValueError, match=r"^Q: covariance is not positive definite"):
        check_covariance(zero, "Q", definite=True)


# -- the mechanism -------------------------------------------------------------------------------------------
def test_an_undeclared_parameter_is_refused_at_decoration():
    with pytest.raises(TypeError, match=r"no kind declared for \['b'\]"):
        @entry_point(a=Int())
        def f(a, b):
            return a, b
    with pytest.raises(TypeError, match=r"\['c'\] are not parameters"):
        @entry_point(a=Int(), c=Flag())
        def g(a):
            return a


def test_the_wrapper_checks_passed_arguments_and_trusts_defaults():
    @entry_point(n=Int(1), flag=Flag(), cov=Cov(optional=True), generator=Gen(), members=Indices(),
                 model=Of(torch.nn.Module, optional=True))
    def f(n, flag=False, cov=None, generator=None, members=(0,), model=None):
        return n

    assert f(3) == 3 and f(n=torch.tensor(2)) == 2  # an integral 0-d tensor becomes an int
    assert spec_of(f) is registered()[
        f"{__name__}.test_the_wrapper_checks_passed_arguments_and_trusts_defaults.<locals>.f"]
    cases = [
        (dict(n=0), ValueError, "^n: must be >= 1"),
        (dict(n=True), TypeError, "^n: expected an integer"),
        (dict(n=1, flag="yes"), TypeError, "^flag: expected True or False"),
        (dict(n=1, cov=[[1.0, 2.0], [2.0, 1.0]]), ValueError,
         "^cov: covariance is not positive semi-definite"),
        (dict(n=1, generator=torch.Generator), TypeError, "^generator: expected a torch.Generator"),
        (dict(n=1, members=[]), ValueError, "^members: must not be empty"),
        (dict(n=1, model=torch.nn.Linear), TypeError, "^model: expected an instance .*got the class Linear"),
    ]
    for kwargs, error, match in cases:
        with pytest.raises(error, match=match):
            f(**kwargs)


def test_every_kind_lists_invalid_inputs_its_check_refuses():
    """The kinds' own invalid inputs fail their own checks (the contract test relies on it)."""
    kinds = [Int(1), Flag(), Gen(), Indices(), Cov(), Of(torch.nn.Module)]
    valids = [2, True, torch.Generator(), [0, 1], torch.eye(2, dtype=torch.float64), torch.nn.Linear(1, 1)]
    for kind, valid in zip(kinds, valids):
        assert kind.check(valid, "x") is not None
        invalid = kind.invalid(valid)
        assert invalid, kind
        for case in invalid:
            with pytest.raises(case.raises, match=r"^x"):
                kind.check(case.value, "x")


# -- found by a probe of common mistakes beside the contract -----------------------------------------------
def test_imm_initial_belief_of_another_state_dimension(bank_filter):
    imm = IMM(bank_filter, P3)
    wrong = GaussianBelief(torch.zeros(4, 3, dtype=torch.float64), torch.eye(3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"^belief: state dimension 3 differs from the filter's state_dim 2"):
        imm.initial_belief(wrong)  # before: accepted, the first step then failed or ran on


def test_metrics_truth_of_another_batch():
    from torchmm import metrics

    with pytest.raises(ValueError, match=r"^truth: shape \(5, 3, 2\) does not broadcast"):
        metrics.rmse(torch.zeros(5, 4, 2), torch.zeros(5, 3, 2))  # before: a raw RuntimeError


def test_minimum_entropy_family_of_non_integers():
    from torchmm import ExactMinimumEntropy

    with pytest.raises(TypeError, match=r"^family\[0\]: expected a sequence of integers"):
        ExactMinimumEntropy([[0.5]])  # before: accepted at construction
    with pytest.raises(TypeError, match=r"^family: expected a \(K, M\) bool mask"):
        ExactMinimumEntropy(torch.ones(2, 3))


def test_progress_is_a_flag_or_a_label():
    kf = KalmanFilter(ConstantVelocity(1, dtype=torch.float64),
                      PositionMeasurement(2, [0], 1.0, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"^progress: expected True, False or the progress bar's description"):
        run_filter(kf, _prior(), _z(), progress=3)

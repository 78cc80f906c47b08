"""Bad input gets a ValueError naming the argument."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmm import (
    IMM,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    LinearMotion,
    ModeTransition,
    PositionMeasurement,
    alpha_transition,
    validate_transition,
)


@pytest.mark.parametrize(
    "matrix,message",
    [
        ([[0.9, 0.2], [0.1, 0.9]], "rows must sum to 1"),
        ([[1.1, -0.1], [0.5, 0.5]], "negative"),
        ([[0.5, 0.5, 0.0], [0.5, 0.5, 0.0]], "square"),
        ([[float("nan"), 1.0], [0.5, 0.5]], "NaN"),
    ],
)
def test_transition_matrix_errors(matrix, message):
    with pytest.raises(ValueError, match=rf"transition: .*{message}"):
        validate_transition(matrix)
    with pytest.raises(ValueError, match=rf"matrix: .*{message}"):
        ModeTransition(matrix)


def test_imm_names_the_transition_argument():
    kf = KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0))
    with pytest.raises(ValueError, match="transition: rows must sum to 1"):
        IMM(kf, torch.tensor([[0.9, 0.2], [0.1, 0.9]]))


def test_bank_mode_count_mismatch():
    motion = ConstantVelocity(1, acceleration=[[0.0], [1.0], [2.0]])
    kf = KalmanFilter(motion, PositionMeasurement(2, [0], 1.0))
    with pytest.raises(ValueError, match="bank: model parameter batch"):
        IMM(kf, torch.eye(2))
    with pytest.raises(ValueError, match="bank: has 2 filters"):
        IMM([kf, kf], torch.eye(3))


@pytest.mark.parametrize(
    "kwargs,name,message",
    [
        ({"F": torch.eye(2), "Q": torch.tensor([[1.0, 0.5], [0.0, 1.0]])}, "Q", "not symmetric"),
        ({"F": torch.eye(2), "Q": torch.tensor([[1.0, 2.0], [2.0, 1.0]])}, "Q", "not positive semi-definite"),
        ({"F": torch.eye(2), "Q": torch.eye(3)}, "Q", "trailing shape"),
        ({"F": torch.ones(2, 3), "Q": torch.eye(2)}, "F", "square"),
        ({"F": torch.eye(2), "Q": torch.eye(2), "offset": torch.zeros(3)}, "offset", "trailing shape"),
        ({"F": torch.eye(2).expand(3, 2, 2), "Q": torch.eye(2).expand(2, 2, 2)}, "LinearMotion", "broadcast"),
    ],
)
def test_linear_motion_errors(kwargs, name, message):
    with pytest.raises(ValueError, match=rf"{name}: .*{message}"):
        LinearMotion(**kwargs)


def test_measurement_errors():
    with pytest.raises(ValueError, match="R: covariance is not positive semi-definite"):
        LinearMeasurement(torch.ones(1, 2), -torch.eye(1))
    with pytest.raises(ValueError, match="R: expected trailing shape"):
        LinearMeasurement(torch.ones(1, 2), torch.eye(2))
    with pytest.raises(ValueError, match="measurement: state_dim 3"):
        KalmanFilter(ConstantVelocity(1), PositionMeasurement(3, [0], 1.0))
    with pytest.raises(ValueError, match="motion: KalmanFilter needs a LinearMotion"):
        from torchmm import NonlinearCoordinatedTurn

        KalmanFilter(NonlinearCoordinatedTurn(), PositionMeasurement(5, [0], 1.0))


def test_model_tensors_of_another_floating_dtype_are_refused_naming_them():
    """A float32 Q (R) next to a float64 F (H) was converted silently while a float32 F (H) was refused
    at the run; each is now a TypeError naming the tensor at the model, as for a network's noise."""
    F, Q, H, R = torch.eye(2), torch.eye(2), torch.ones(1, 2), torch.eye(1)
    with pytest.raises(TypeError, match=r"^Q: dtype torch.float32 differs from F's torch.float64"):
        LinearMotion(F, Q.float())
    with pytest.raises(TypeError, match=r"^Q: dtype torch.float64 differs from F's torch.float32"):
        LinearMotion(F.float(), Q)
    with pytest.raises(TypeError, match=r"^offset: dtype torch.float32"):
        LinearMotion(F, Q, offset=torch.zeros(2, dtype=torch.float32))
    with pytest.raises(TypeError, match=r"^input_matrix: dtype torch.float32"):
        LinearMotion(F, Q, input_matrix=torch.ones(2, 1, dtype=torch.float32))
    with pytest.raises(TypeError, match=r"^R: dtype torch.float32 differs from H's torch.float64"):
        LinearMeasurement(H, R.float())
    with pytest.raises(TypeError, match=r"^R: dtype torch.float64 differs from H's torch.float32"):
        LinearMeasurement(H.float(), R)
    from torchmm.models import LearnedMotion

    with pytest.raises(TypeError, match=r"^Q: dtype torch.float32 differs from the network's torch.float64"):
        LearnedMotion(torch.nn.Linear(2, 2), 2, Q=Q.float())
    # numbers, lists, NumPy arrays and integer tensors take the model's dtype; one dtype throughout is kept
    assert LinearMotion(F, np.eye(2, dtype=np.float32)).Q.dtype == torch.float64
    assert LinearMotion(F, torch.eye(2, dtype=torch.int64)).Q.dtype == torch.float64
    assert LinearMeasurement(H, [[2.0]]).R.dtype == torch.float64
    assert LinearMotion(F.float(), Q.float()).Q.dtype == torch.float32


def test_belief_errors():
    with pytest.raises(ValueError, match="cov: covariance is not symmetric"):
        GaussianBelief.create(torch.zeros(2), torch.tensor([[1.0, 0.3], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="cov: expected trailing shape"):
        GaussianBelief.create(torch.zeros(2), torch.eye(3))
    with pytest.raises(ValueError, match="cov: batch shape"):
        GaussianBelief.create(torch.zeros(3, 2), torch.eye(2).expand(4, 2, 2))


def test_alpha_transition_errors():
    with pytest.raises(ValueError, match="alpha: entries must be non-negative"):
        alpha_transition([0.1, -0.1])
    with pytest.raises(ValueError, match="alpha: sum"):
        alpha_transition([0.6, 0.6, 0.6])


def test_initial_mode_probability_errors():
    kf = KalmanFilter(ConstantVelocity(1, acceleration=[[0.0], [1.0]]), PositionMeasurement(2, [0], 1.0))
    imm = IMM(kf, torch.eye(2))
    prior = GaussianBelief(torch.zeros(2), torch.eye(2))
    with pytest.raises(ValueError, match="mode_probs: must be non-negative and sum to 1"):
        imm.initial_belief(prior, [0.5, 0.6])
    with pytest.raises(ValueError, match="mode_probs: expected 2 modes"):
        imm.initial_belief(prior, [0.2, 0.3, 0.5])


def test_kinematic_argument_errors():
    with pytest.raises(ValueError, match=r"^noise: expected one of \['discrete', 'continuous'\]"):
        ConstantVelocity(1, noise="white")
    with pytest.raises(ValueError, match="dt: must be positive"):
        ConstantVelocity(1, dt=0.0)
    with pytest.raises(ValueError, match=r"acceleration: expected shape \(\*P, 2\)"):
        ConstantVelocity(2, acceleration=[0.1, 0.2, 0.3])


def test_covariance_check_of_broadcast_batches():
    """A prior expanded over the runs is checked once per distinct matrix; a bad matrix is caught
    whether it is repeated by a broadcast axis or stored in a real one."""
    from torchmm.validation import check_covariance

    good = torch.eye(2, dtype=torch.float64)
    bad = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=torch.float64)  # eigenvalues 3 and -1
    check_covariance(good.expand(500, 3, 2, 2), "prior")
    with pytest.raises(ValueError, match="prior: covariance is not positive semi-definite"):
        check_covariance(bad.expand(500, 3, 2, 2), "prior")
    mixed = torch.stack([good, good, bad])  # (3, 2, 2): the bad one in a stored axis
    with pytest.raises(ValueError, match="prior: covariance is not positive semi-definite"):
        check_covariance(mixed.expand(500, 3, 2, 2), "prior")
    with pytest.raises(ValueError, match="prior: covariance is not positive semi-definite"):
        check_covariance(mixed.unsqueeze(1).expand(3, 400, 2, 2), "prior")
    with pytest.raises(ValueError, match="prior: contains NaN"):
        check_covariance(torch.full((2, 2), float("nan"), dtype=torch.float64).expand(7, 2, 2), "prior")


# -- Unchanged: answers kept while their objects are unchanged (the one-shot call's fixed cost, issue 47) --


def test_unchanged_keeps_an_answer_until_a_tensor_changes_or_dies():
    from torchmm.unchanged import Unchanged

    memo = Unchanged(size=4)
    x, y = torch.ones(3), torch.zeros(2)
    assert memo.get((x, y)) is None
    assert memo.put((x, y), "answer") == "answer"
    assert memo.get((x, y)) == "answer"
    assert memo.get((y, x)) is None  # the objects in their order
    y[0] = 1.0  # an in-place change bumps the version
    assert memo.get((x, y)) is None
    memo.put((x, y), "again")
    key_id = id(x)
    del x
    import gc

    gc.collect()
    fresh = torch.ones(3)
    if id(fresh) == key_id:  # (an id reused: the dead object's weak reference tells them apart)
        assert memo.get((fresh, y)) is None
    with torch.inference_mode():
        frozen = torch.ones(2)
    assert memo.put((frozen,), "kept?") == "kept?" and memo.get((frozen,)) is None  # no version: never kept
    for i in range(10):  # bounded: fresh objects every call never hold more than `size`
        memo.put((torch.ones(1),), i)
    assert len(memo._answers) <= 4


def test_unchanged_remember_computes_once_and_keeps_no_failure():
    from torchmm.unchanged import Unchanged

    memo = Unchanged(size=4)
    x = torch.ones(2)
    calls = []

    def compute(answer):
        def run():
            calls.append(answer)
            if isinstance(answer, Exception):
                raise answer
            return answer
        return run

    with pytest.raises(ValueError, match="bad"):  # a failed check keeps nothing: it fails again
        memo.remember((x,), compute(ValueError("bad")))
    with pytest.raises(ValueError, match="bad"):
        memo.remember((x,), compute(ValueError("bad")))
    assert memo.remember((x,), compute(None)) is None and memo.get((x,)) is None  # None is never kept
    assert memo.remember((x,), compute("first")) == "first"
    assert memo.remember((x,), compute("second")) == "first"  # kept: not computed again
    assert calls == [calls[0], calls[1], None, "first"]
    x.add_(1.0)  # a new version: computed again
    assert memo.remember((x,), compute("third")) == "third" and memo.get((x,)) == "third"


def test_broadcast_shape_agrees_with_torch():
    from torchmm.validation import broadcast_shape

    cases = [((3, 2), (3, 2)), ((3, 2), (2,)), ((1, 2), (4, 1)), ((), (5,)), ((2, 3), (2, 3), (2, 3)), ((0,), (1,))]
    for shapes in cases:
        assert broadcast_shape(*map(torch.Size, shapes)) == torch.broadcast_shapes(*shapes)
    assert broadcast_shape() == torch.broadcast_shapes()
    with pytest.raises(RuntimeError):
        broadcast_shape(torch.Size([3]), torch.Size([2]))


def test_a_belief_changed_in_place_after_a_run_is_checked_again():
    from torchmm import GaussianBelief, KalmanFilter, run_filter
    from torchmm.models import ConstantVelocity, PositionMeasurement

    kf = KalmanFilter(ConstantVelocity(1, dtype=torch.float64), PositionMeasurement(2, [0], 1.0, dtype=torch.float64))
    belief = GaussianBelief(torch.zeros(3, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64).repeat(3, 1, 1))
    z = torch.randn(5, 3, 1, dtype=torch.float64)
    first = run_filter(kf, belief, z)
    again = run_filter(kf, belief, z)  # the same unchanged start: its check and the data's fingerprint kept
    assert torch.equal(first.log_likelihood, again.log_likelihood)
    assert first.provenance.data == again.provenance.data
    belief.cov[1, 0, 0] = -1.0  # indefinite now: the version moved, so the check runs again
    with pytest.raises(ValueError, match=r"belief0\.cov.*positive semi-definite"):
        run_filter(kf, belief, z)
    z[2, 1, 0] = z[2, 1, 0] + 1.0  # the data's record follows an in-place change of the data
    belief.cov[1, 0, 0] = 1.0
    assert run_filter(kf, belief, z).provenance.data != first.provenance.data


def test_small_covariances_closed_form_eigenvalues_agree_with_lapack():
    from torchmm.validation import _small_eigvalsh

    rng = np.random.default_rng(1)
    for d in (1, 2):
        for scale in (1e-300, 1e-12, 1.0, 1e300):
            a = rng.standard_normal((200, d, d))
            sym = a @ np.swapaxes(a, -1, -2) - np.eye(d)  # some indefinite
            sym = 0.5 * (sym + np.swapaxes(sym, -1, -2)) * scale
            top = np.abs(sym).max(axis=(-1, -2), keepdims=True)
            got = _small_eigvalsh(sym, top)
            assert np.all(np.isfinite(got))
            np.testing.assert_allclose(got / top[..., 0], np.linalg.eigvalsh(sym) / top[..., 0], atol=1e-14)

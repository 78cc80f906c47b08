"""Defect 2 of the robustness issue: every update checks ``z`` against the sensor and the belief.

For every estimator family: a measurement with the wrong event size, without its event axis, or
with a batch that would enlarge the belief's batch raises a ``ValueError`` naming ``z`` (before,
they were broadcast into finite, wrong answers); documented broadcasting (one measurement shared
by every run), lists and integer tensors are accepted and give the same answer as the full
tensor.
"""

from __future__ import annotations

import pytest
import torch

from tests.robustness.cases import CASES, Case
from torchmm import GaussianBelief, KalmanFilter, PositionMeasurement, RangeBearing, run_filter
from torchmm.filters import ExtendedKalmanFilter
from torchmm.models import ConstantVelocity, NonlinearCoordinatedTurn
from torchmm.multimodel import MultiRate

RUNS = 4


def _step(case: Case, z):
    f = case.make()
    return f.step(case.start(f, RUNS), z)


def _good(case: Case):
    return case.data(1, RUNS)


def _target(case: Case, z):
    """Replace the (target) stream of one step's data."""
    good = _good(case)
    if case.multirate:
        return MultiRate(z, good.source[0])
    return z


def _valid_z(case: Case) -> torch.Tensor:
    good = _good(case)
    return (good.target if case.multirate else good)[0]


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_wrong_event_size_is_an_error_naming_z(case):
    z = _valid_z(case)
    wider = torch.cat([z, z[..., :1]], -1)  # (B, m + 1): one component too many
    with pytest.raises(ValueError, match=r"z(\.target)?: expected shape \(\*B, %d\)" % case.meas_dim):
        _step(case, _target(case, wider))


@pytest.mark.parametrize("case", [c for c in CASES if c.meas_dim == 1], ids=lambda c: c.name)
def test_scalar_sensor_data_without_event_axis_is_an_error(case):
    z = _valid_z(case)[..., 0]  # (B,): read as one B-dimensional measurement before
    with pytest.raises(ValueError, match="z.*unsqueeze"):
        _step(case, _target(case, z))


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_batch_that_would_enlarge_the_belief_is_an_error(case):
    z = _valid_z(case).unsqueeze(-2)  # (B, 1, m): turned B runs into B x B before
    with pytest.raises(ValueError, match=r"z(\.target)?: batch shape \(4, 1\) does not broadcast"):
        _step(case, _target(case, z))


@pytest.mark.parametrize("case", [c for c in CASES if c.multirate], ids=lambda c: c.name)
def test_source_stream_is_checked_against_the_source_sensor(case):
    good = _good(case)
    with pytest.raises(ValueError, match=r"z\.source: expected shape \(\*B, 1\)"):
        _step(case, MultiRate(good.target[0], torch.zeros(RUNS, 2)))
    with pytest.raises(ValueError, match=r"z\.source: batch shape"):
        _step(case, MultiRate(good.target[0], torch.zeros(RUNS, 1, 1)))


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_shared_measurement_list_and_integer_tensor_are_accepted(case):
    z = _valid_z(case).round()
    full = _step(case, _target(case, z))
    shared = _step(case, _target(case, z[0]))  # (m,): one measurement for every run
    as_list = _step(case, _target(case, z.tolist()))
    as_int = _step(case, _target(case, z.to(torch.int64)))
    for out in (as_list, as_int):
        torch.testing.assert_close(out.belief.estimate().mean, full.belief.estimate().mean, rtol=0, atol=0)
    expected = _step(case, _target(case, z[0].expand_as(z)))
    torch.testing.assert_close(shared.belief.estimate().mean, expected.belief.estimate().mean, rtol=0, atol=0)
    assert full.belief.estimate().mean.shape[:1] == (RUNS,)


def test_range_bearing_needs_both_components():
    ekf = ExtendedKalmanFilter(NonlinearCoordinatedTurn(), RangeBearing(5, torch.eye(2)))
    prior = GaussianBelief(torch.tensor([100.0, 1.0, 50.0, 0.0, 0.0]), torch.eye(5))
    with pytest.raises(ValueError, match=r"z: expected shape \(\*B, 2\)"):
        ekf.update(prior, torch.tensor(111.8))  # one number: was used as range *and* bearing
    with pytest.raises(ValueError, match=r"z: expected shape \(\*B, 2\)"):
        ekf.update(prior, torch.tensor([111.8]))


def test_a_run_filter_sequence_of_the_wrong_size_names_measurements():
    """The argument as the caller passed it (issue 29): run_filter checks the sequence's step shape once."""
    kf = KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0))
    prior = GaussianBelief(torch.zeros(3, 2), torch.eye(2).expand(3, 2, 2))
    with pytest.raises(ValueError, match="^measurements: expected shape"):
        run_filter(kf, prior, torch.zeros(5, 3, 2))
    with pytest.raises(ValueError, match="^measurements: batch shape"):
        run_filter(kf, prior, torch.zeros(5, 3, 3, 1))


def test_state_dimension_of_the_belief_is_checked():
    kf = KalmanFilter(ConstantVelocity(2), PositionMeasurement(4, [0, 2], 1.0))
    wrong = GaussianBelief(torch.zeros(3, 2), torch.eye(2))
    with pytest.raises(ValueError, match="belief: state dimension 2 does not match the model's state_dim 4"):
        kf.predict(wrong)
    with pytest.raises(ValueError, match="belief: state dimension"):
        kf.update(wrong, torch.zeros(3, 2))
    with pytest.raises(TypeError, match="belief: expected a GaussianBelief"):
        kf.update(torch.zeros(3, 4), torch.zeros(3, 2))

"""Defects 4 and 5: one policy for non-finite data; one run's numerical trouble stays in that run.

Policy (docs/robustness.md): a measurement component that is not finite - NaN, ``+inf`` or
``-inf`` - is missing and skipped exactly, by every estimator (an infinite datum used to turn
its run NaN for good, or abort every run with a raw ``LinAlgError``). A step with no datum at all
has a log-likelihood of exactly 0. A run whose belief is broken (NaN or indefinite covariance
handed straight to ``step``) or whose innovation covariance is singular never raises and never
changes the other runs; singular innovation covariances are flagged in ``extras["singular"]``.
"""

from __future__ import annotations

import dataclasses
import logging

import pytest
import torch

from tests.robustness.cases import CASES, GAUSSIAN, Case
from torchmm import (
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    LinearMotion,
    ModeBelief,
    ParticleBelief,
    StudentTVBFilter,
    UnscentedKalmanFilter,
    run_filter,
)
from torchmm.beliefs import Belief
from torchmm.multimodel import MultiRate, SourceTrackBelief

RUNS = 5
NAN, INF = float("nan"), float("inf")


def _outputs(out) -> list[torch.Tensor]:
    """What a user reads from a step: estimate, log-likelihood, mode probabilities (if any)."""
    est = out.belief.estimate()
    values = [est.mean, est.cov, out.log_likelihood]
    if hasattr(out.belief, "mode_log_probs"):
        values.append(out.belief.mode_log_probs)
    return values


def _valid(t: torch.Tensor) -> bool:
    """Finite, except that log-probabilities may be -inf (an inactive mode)."""
    return bool((torch.isfinite(t) | (t == -INF)).all())


def _same(a, b):
    for x, y in zip(_outputs(a), _outputs(b)):
        torch.testing.assert_close(x, y, rtol=0, atol=0, equal_nan=True)


def _with(case: Case, z, *, target=None, source=None):
    if not case.multirate:
        return target
    return MultiRate(z.target[0] if target is None else target, z.source[0] if source is None else source)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_infinite_measurement_components_are_missing_data(case):
    data = case.data(1, RUNS, seed=3)
    y = (data.target if case.multirate else data)[0]
    holes = torch.zeros_like(y, dtype=torch.bool)
    holes[1, 0], holes[3] = True, True  # one component of run 1, all of run 3
    source = None
    if case.multirate:  # run 3 without a source datum either
        source = data.source[0].clone()
        source[3] = NAN
    results = []
    for value in (NAN, INF, -INF):
        z = torch.where(holes, value, y)
        f = case.make()
        results.append(f.step(case.start(f, RUNS), _with(case, data, target=z, source=source)))
    _same(results[0], results[1])
    _same(results[0], results[2])
    for out in results:
        for t in _outputs(out):
            assert _valid(t)
    assert results[1].log_likelihood[3] == 0.0  # no datum at all: exactly 0


@pytest.mark.parametrize("case", [c for c in CASES if c.multirate], ids=lambda c: c.name)
def test_infinite_source_datum_is_an_absent_source_datum(case):
    """The multi-rate estimators disagreed: TransferIMM skipped it, IMM-SU / VSIMM went NaN."""
    data = case.data(1, RUNS, seed=4)
    source = data.source[0].clone()
    source[:] = 1.0
    results = []
    for value in (NAN, INF, -INF):
        s = source.clone()
        s[2] = value
        f = case.make()
        results.append(f.step(case.start(f, RUNS), MultiRate(data.target[0], s)))
    _same(results[0], results[1])
    _same(results[0], results[2])
    assert all(_valid(t) for t in _outputs(results[1]))


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_a_step_without_any_datum_has_log_likelihood_exactly_zero(case):
    data = case.data(1, RUNS)
    y = (data.target if case.multirate else data)[0].clone()
    y[0] = NAN
    source = None
    if case.multirate:
        source = data.source[0].clone()
        source[0] = NAN
    f = case.make()
    out = f.step(case.start(f, RUNS), _with(case, data, target=y, source=source))
    assert out.log_likelihood[0].item() == 0.0
    if hasattr(out.belief, "mode_log_probs") and not case.particles and case.name not in ("vsimm", "gpb2"):
        # the posterior mode probabilities are the predicted ones (renormalised: to rounding)
        prior = out.prior.target if isinstance(out.prior, SourceTrackBelief) else out.prior
        torch.testing.assert_close(out.belief.mode_log_probs[0], prior.mode_log_probs[0], rtol=0, atol=1e-14)


def test_run_filter_reports_infinite_measurements(caplog):
    case = next(c for c in CASES if c.name == "kf")
    z = case.data(4, 2)
    z[1, 0, 0] = INF
    z[2, 1, 1] = -INF
    f = case.make()
    with caplog.at_level(logging.WARNING, logger="torchmm"):
        traj = run_filter(f, case.start(f, 2), z)
    assert "2 infinite entries are treated as missing" in caplog.text
    assert torch.isfinite(traj.estimate().mean).all()


# -- one run's numerical trouble ---------------------------------------------------------------------
def _break_run(belief: Belief, how: str) -> Belief:
    """Run 0's covariance (every Gaussian inside) NaN or indefinite; particles NaN."""
    if isinstance(belief, SourceTrackBelief):
        return SourceTrackBelief(_break_run(belief.target, how), _break_run(belief.source, how))
    if isinstance(belief, ModeBelief):
        return dataclasses.replace(belief, components=_break_run(belief.components, how))
    if isinstance(belief, ParticleBelief):
        particles = belief.particles.clone()
        particles[0] = NAN
        return ParticleBelief(particles, belief.log_weights)
    cov = belief.cov.expand(*belief.mean.shape, belief.mean.shape[-1]).clone()
    if how == "nan":
        cov[0] = NAN
    else:
        cov[0] = -cov[0]
    return dataclasses.replace(belief, cov=cov)


@pytest.mark.parametrize("how", ["nan", "indefinite"])
@pytest.mark.parametrize("case", GAUSSIAN, ids=lambda c: c.name)
def test_a_broken_run_never_raises_and_never_changes_the_others(case, how):
    f = case.make()
    start = case.start(f, RUNS)
    data = case.data(1, RUNS, seed=5)
    z = _first(data)
    out = f.step(_break_run(start, how), z)  # no raw torch.linalg error escapes
    alone = f.step(start[1:], _first(data, slice(1, None)))
    for got, want in zip(_outputs(out), _outputs(alone)):
        torch.testing.assert_close(got[1:], want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("case", [c for c in CASES if c.particles], ids=lambda c: c.name)
def test_a_broken_particle_run_never_raises_and_leaves_the_others_finite(case):
    f = case.make()
    out = f.step(_break_run(case.start(f, RUNS), "nan"), _first(case.data(1, RUNS)))
    for t in _outputs(out):
        assert _valid(t[1:])


def _first(data, runs=slice(None)):
    if isinstance(data, MultiRate):
        return MultiRate(data.target[0, runs], data.source[0, runs])
    return data[0, runs]


@pytest.mark.parametrize("m", [1, 2, 3])
def test_singular_innovation_covariance_is_flagged_and_finite(m):
    n = 4
    kf = KalmanFilter(LinearMotion(torch.eye(n), torch.zeros(n, n)), LinearMeasurement(torch.eye(m, n), torch.zeros(m, m)))
    cov = torch.eye(n).expand(3, n, n).clone()
    cov[1, 0, 0] = 0.0  # run 1: a measured component with zero variance and R = 0: S singular
    out = kf.update(GaussianBelief(torch.zeros(3, n), cov), torch.ones(3, m))
    assert out.extras["singular"].tolist() == [False, True, False]
    assert torch.isfinite(out.belief.mean).all() and torch.isfinite(out.belief.cov).all()
    healthy = kf.update(GaussianBelief(torch.zeros(2, n), torch.eye(n).expand(2, n, n)), torch.ones(2, m))
    torch.testing.assert_close(out.belief.mean[[0, 2]], healthy.belief.mean)


def test_vb_and_ukf_with_a_singular_sensor_do_not_raise():
    """A raw LinAlgError used to abort all runs (the UKF, the Student-t VB filter)."""
    from torchmm import ConstantVelocity, PositionMeasurement

    ukf = UnscentedKalmanFilter(ConstantVelocity(1, q=0.0), PositionMeasurement(2, [0], 0.0))
    prior = GaussianBelief(torch.zeros(3, 2), torch.diag(torch.tensor([0.0, 1.0])).expand(3, 2, 2))
    out = ukf.update(prior, torch.tensor([[INF], [1.0], [NAN]]))
    assert out.extras["singular"].tolist() == [False, True, False]
    assert torch.isfinite(out.belief.mean).all()
    vb = StudentTVBFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0), iterations=2)
    out = vb.update(GaussianBelief(torch.zeros(2, 2), torch.zeros(2, 2, 2)), torch.tensor([[1.0], [INF]]))
    assert torch.isfinite(out.belief.mean).all() and out.log_likelihood[1] == 0.0


def test_estimate_reports_infinite_measurements_once_and_skips_them(caplog):
    """estimate's prepared (kernel) evaluations never pass run_filter's entry: its Objective says it once."""
    from torchmm.learn import estimate

    case = next(c for c in CASES if c.name == "kf")
    z = case.data(30, 1)
    z[3, 0, 0] = INF
    f = case.make()
    with caplog.at_level(logging.WARNING, logger="torchmm"):
        fit = estimate(f, case.start(f, 1), z, {"measurement.R": "covariance"}, se=False, write=False)
    assert caplog.text.count("1 infinite entries are treated as missing") == 1
    missing = z.clone()
    missing[3, 0, 0] = NAN
    assert fit.nobs == estimate(f, case.start(f, 1), missing, {"measurement.R": "covariance"}, se=False,
                                write=False).nobs

"""Issue 29, defect 1: a model that outputs NaN is a failure of its run, not missing data.

Missing data are non-finite *measurements* (docs/robustness.md). A non-finite *prediction*,
innovation covariance, gain or likelihood for a present datum used to look like missing data (the
innovation was non-finite, so the datum was skipped): the negative log-likelihood of an EKF over a
network with NaN weights was exactly 0, and ``run_filter`` with a NaN process noise gave NaN
estimates, a finite log-likelihood and no flag. Now such a step's log-likelihood is NaN for that
run only, ``extras["failed"]`` flags it, ``run_filter`` warns, and ``Trainer`` stops with one line
naming the parameter.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import pytest
import torch

import torchmm.kernels.particle as cpu_kernels
from torchmm import kernels
from tests.robustness.cases import CASES, Case
from torchmm import (
    IMM,
    ConstantVelocity,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    LinearMotion,
    ModeBelief,
    ParticleBelief,
    PositionMeasurement,
    run_filter,
)
from torchmm.learn import NonFiniteLossError, Trainer, negative_log_likelihood
from torchmm.models import LearnedMotion, learnable_noise
from torchmm.models.transition import ModeTransition
from torchmm.multimodel import MultipleModelParticleFilter, MultiRate, SourceTrackBelief

NAN = float("nan")
RUNS = 4


def _net(nan: bool) -> torch.nn.Module:
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(2, 4), torch.nn.Tanh(), torch.nn.Linear(4, 2)).double()
    if nan:
        with torch.no_grad():
            net[0].weight[1, 0] = NAN
    return net


def _ekf(nan: bool) -> ExtendedKalmanFilter:
    sensor = PositionMeasurement(2, [0], torch.tensor(1.0, dtype=torch.float64), dtype=torch.float64)
    return ExtendedKalmanFilter(LearnedMotion(_net(nan), 2, Q=0.1), sensor)


def _prior(runs: int = RUNS, n: int = 2) -> GaussianBelief:
    return GaussianBelief(torch.zeros(runs, n, dtype=torch.float64),
                          torch.eye(n, dtype=torch.float64).expand(runs, n, n))


def _data(steps: int = 6, runs: int = RUNS, m: int = 1) -> torch.Tensor:
    return torch.randn(steps, runs, m, generator=torch.Generator().manual_seed(1), dtype=torch.float64)


# -- the reported defect --------------------------------------------------------------------------
def test_nll_of_a_network_with_nan_weights_is_nan_not_zero():
    z = _data()
    loss = negative_log_likelihood(_ekf(nan=True), _prior(), z)
    assert torch.isnan(loss)  # was exactly 0.0: every datum "missing"
    assert torch.isfinite(negative_log_likelihood(_ekf(nan=False), _prior(), z))


def test_run_filter_flags_every_step_of_a_nan_network(caplog):
    with caplog.at_level(logging.WARNING, logger="torchmm"):
        traj = run_filter(_ekf(nan=True), _prior(), _data())
    assert traj.extras["failed"].all()
    assert torch.isnan(traj.log_likelihood).all()
    assert "updates failed" in caplog.text and "extras['failed']" in caplog.text


def _per_run_q(bad_run: int | None) -> KalmanFilter:
    """A Kalman filter whose learnable process noise has one value per run (batch (RUNS,)); the
    parameter of run ``bad_run`` went NaN (as after a diverging optimiser step)."""
    F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=torch.float64)
    Q = torch.diag(torch.tensor([0.1, 0.5], dtype=torch.float64)).expand(RUNS, 2, 2).clone()
    motion = learnable_noise(LinearMotion(F, Q), "Q", "log_diagonal")
    if bad_run is not None:
        with torch.no_grad():
            motion.parametrizations.Q.original[bad_run] = NAN
    return KalmanFilter(motion, PositionMeasurement(2, [0], torch.tensor(1.0, dtype=torch.float64),
                                                     dtype=torch.float64))


def test_run_filter_with_one_runs_q_nan_fails_that_run_only():
    z = _data()
    traj = run_filter(_per_run_q(bad_run=2), _prior(), z)
    good = run_filter(_per_run_q(bad_run=None), _prior(), z)
    failed = traj.extras["failed"]
    assert failed[:, 2].all() and not failed[:, [0, 1, 3]].any()
    assert torch.isnan(traj.log_likelihood[:, 2]).all()
    keep = [0, 1, 3]  # the other runs: bit for bit what they are without the bad one
    torch.testing.assert_close(traj.log_likelihood[:, keep], good.log_likelihood[:, keep], rtol=0, atol=0)
    torch.testing.assert_close(traj.estimate().mean[:, keep], good.estimate().mean[:, keep], rtol=0, atol=0)
    assert not good.extras["failed"].any()


def test_missing_data_still_give_exactly_zero_and_no_flag():
    z = _data()
    z[2] = NAN  # step 2: no datum in any run
    z[4, 1] = float("inf")  # step 4, run 1: an infinite datum is missing too
    traj = run_filter(_per_run_q(bad_run=None), _prior(), z)
    assert (traj.log_likelihood[2] == 0).all() and traj.log_likelihood[4, 1] == 0
    assert not traj.extras["failed"].any()
    # a failed run whose datum is missing: skipped (log-likelihood 0, not flagged) at that step
    bad = run_filter(_per_run_q(bad_run=2), _prior(), z)
    assert bad.log_likelihood[2, 2] == 0 and not bad.extras["failed"][2, 2]
    assert torch.isnan(bad.log_likelihood[3, 2]) and bad.extras["failed"][3, 2]


def _imm(logit_nan: bool) -> IMM:
    bank = ConstantVelocity(1, q=0.5, acceleration=torch.tensor([[0.5], [-0.5]], dtype=torch.float64),
                            dtype=torch.float64)
    sensor = PositionMeasurement(2, [0], torch.tensor(1.0, dtype=torch.float64), dtype=torch.float64)
    transition = ModeTransition(torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=torch.float64), learnable=True)
    if logit_nan:
        with torch.no_grad():
            transition.logits[1, 0] = NAN
    return IMM(KalmanFilter(bank, sensor), transition)


@pytest.mark.parametrize("fast_path", [True, False])
def test_imm_with_a_nan_transition_fails_in_the_fast_path_as_in_the_engine(fast_path):
    imm = _imm(logit_nan=True)
    belief0 = imm.initial_belief(_prior())
    z = _data()
    z[3] = NAN
    traj = run_filter(imm, belief0, z, fast_path=fast_path)
    failed = traj.extras["failed"]
    present = torch.isfinite(z).any(-1)
    assert torch.equal(failed, present)  # every run, wherever it has a datum
    assert torch.isnan(traj.log_likelihood[present]).all() and (traj.log_likelihood[~present] == 0).all()
    estimate = run_filter(imm, belief0, z, fast_path=fast_path, record="estimate")
    torch.testing.assert_close(estimate.log_likelihood, traj.log_likelihood, rtol=0, atol=0, equal_nan=True)
    healthy = run_filter(_imm(logit_nan=False), belief0, z, fast_path=fast_path)
    assert not healthy.extras["failed"].any() and torch.isfinite(healthy.log_likelihood).all()


def test_imm_fast_path_flags_a_failed_mode_like_the_engine():
    """Per-mode flags (``extras["modes"]["failed"]``) agree between the batch-last kernel and the engine."""
    imm = _imm(logit_nan=False)
    belief0 = imm.initial_belief(_prior())
    z = _data(steps=3)
    fast = run_filter(imm, belief0, z, fast_path=True)
    slow = run_filter(imm, belief0, z, fast_path=False)
    assert torch.equal(fast.extras["modes"]["failed"], slow.extras["modes"]["failed"])
    assert not fast.extras["modes"]["failed"].any()


# -- every family: one broken run ------------------------------------------------------------------
def _break(belief, run: int = 0):
    """Run ``run``'s belief NaN (every Gaussian's mean, every particle set), as a model that went NaN
    leaves it; handed straight to ``step`` (which checks shapes only)."""
    if isinstance(belief, SourceTrackBelief):
        return SourceTrackBelief(_break(belief.target, run), belief.source)
    if isinstance(belief, ModeBelief):
        return dataclasses.replace(belief, components=_break(belief.components, run))
    if isinstance(belief, ParticleBelief):
        particles = belief.particles.clone()
        particles[run] = NAN
        return ParticleBelief(particles, belief.log_weights)
    mean = belief.mean.expand(*belief.mean.shape).clone()
    mean[run] = NAN
    return dataclasses.replace(belief, mean=mean)


def _first(case: Case, data, *, missing: bool = False):
    if case.multirate:
        y, ys = data.target[0].clone(), data.source[0].clone()
        if missing:
            y[:], ys[:] = NAN, NAN
        return MultiRate(y, ys)
    z = data[0].clone()
    if missing:
        z[:] = NAN
    return z


def _log_likelihood_and_flag(out):
    failed = out.extras.get("failed") if out.extras else None
    return out.log_likelihood, failed


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_a_nan_prediction_with_a_datum_fails_that_run_only(case):
    f = case.make()
    start = case.start(f, RUNS)
    data = case.data(1, RUNS, seed=11)
    z = _first(case, data)
    ll, failed = _log_likelihood_and_flag(f.step(_break(start), z))
    assert failed is not None and failed.shape == (RUNS,), case.name
    assert failed.tolist() == [True] + [False] * (RUNS - 1), case.name
    assert torch.isnan(ll[0]), case.name  # not 0: the datum was present
    assert torch.isfinite(ll[1:]).all(), case.name
    if not case.particles:  # the other runs are unchanged (particle filters draw per batch)
        ll_good, _ = _log_likelihood_and_flag(case.make().step(start, z))
        torch.testing.assert_close(ll[1:], ll_good[1:], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_missing_data_never_fail_a_run(case):
    f = case.make()
    start = case.start(f, RUNS)
    data = case.data(1, RUNS, seed=11)
    ll, failed = _log_likelihood_and_flag(f.step(start, _first(case, data, missing=True)))
    assert (ll == 0).all() and not failed.any(), case.name
    # a broken run without a datum: skipped as missing data (log-likelihood exactly 0, not flagged)
    ll, failed = _log_likelihood_and_flag(f.step(_break(start), _first(case, data, missing=True)))
    assert (ll == 0).all() and not failed.any(), case.name


def test_multiple_model_pf_kernels_flag_failures_as_the_eager_path(monkeypatch):
    """The fused CPU kernel (complete data, ``innovation_stats=False``) and the eager path agree on a
    run whose particles went NaN."""
    if not cpu_kernels.available():
        pytest.skip("numba not importable")
    calls = []
    original = cpu_kernels.propagate_log_likelihood
    monkeypatch.setattr(cpu_kernels, "propagate_log_likelihood",
                        lambda *a, **k: calls.append(1) or original(*a, **k))
    bank = ConstantVelocity(1, q=0.5, acceleration=torch.tensor([[0.5], [-0.5]], dtype=torch.float64),
                            dtype=torch.float64)
    sensor = PositionMeasurement(2, [0], torch.tensor(1.0, dtype=torch.float64), dtype=torch.float64)
    transition = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=torch.float64)
    z = _data(steps=1)[0]
    outs = []
    previous = kernels.enabled(cpu_kernels.NAME)
    try:
        for flag in (False, True):
            kernels.set_enabled(cpu_kernels.NAME, flag)
            g = torch.Generator().manual_seed(3)
            f = MultipleModelParticleFilter(bank, sensor, transition, 32, innovation_stats=False)
            belief = _break(f.initial_belief(_prior(), generator=g), run=1)
            outs.append(f.step(belief, z, generator=g))
    finally:
        kernels.set_enabled(cpu_kernels.NAME, previous)
    eager, fused = outs
    assert calls == [1]  # the kernel ran once (kernels on), the eager path once (kernels off)
    assert fused.extras["failed"].tolist() == [False, True, False, False]
    assert torch.equal(eager.extras["failed"], fused.extras["failed"])
    torch.testing.assert_close(eager.log_likelihood, fused.log_likelihood, rtol=0, atol=0, equal_nan=True)


# -- Trainer: one line naming the parameter --------------------------------------------------------
def test_trainer_stops_with_one_line_naming_the_nan_parameter():
    f = _ekf(nan=True)
    trainer = Trainer(f, torch.optim.SGD(f.parameters(), lr=0.01))
    with pytest.raises(ValueError) as info:
        trainer.fit(_prior(), _data(), 2)
    assert isinstance(info.value, NonFiniteLossError) and isinstance(info.value, FloatingPointError)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("Trainer: the loss went non-finite (nan) at iteration 1; ")
    assert "parameter 'motion.net.0.weight' is non-finite" in message


def test_trainer_says_when_the_loss_diverged_with_finite_parameters():
    motion = learnable_noise(ConstantVelocity(1, q=1.0, dtype=torch.float64), "Q", "scale")
    kf = KalmanFilter(motion, PositionMeasurement(2, [0], torch.tensor(1.0, dtype=torch.float64),
                                                  dtype=torch.float64))
    z = _data()
    z[3, 0] = 1e200  # the quadratic form overflows: log-likelihood -inf, parameters finite
    trainer = Trainer(kf, torch.optim.SGD(kf.parameters(), lr=0.01))
    with pytest.raises(NonFiniteLossError,
                       match=r"^Trainer: the loss went non-finite \(inf\) at iteration 1; "
                             r"every parameter is finite") as info:
        trainer.fit(_prior(), z, 1)
    assert "\n" not in str(info.value)


def test_trainer_names_a_parameter_an_update_made_non_finite():
    motion = learnable_noise(ConstantVelocity(1, q=1.0, dtype=torch.float64), "Q", "scale")
    kf = KalmanFilter(motion, PositionMeasurement(2, [0], torch.tensor(1.0, dtype=torch.float64),
                                                  dtype=torch.float64))
    trainer = Trainer(kf, torch.optim.SGD(kf.parameters(), lr=math.inf))
    with pytest.raises(NonFiniteLossError,
                       match=r"^Trainer: the parameters went non-finite in the update of "
                             r"iteration 1 .*parameter 'motion.parametrizations.Q.original' "
                             r"is non-finite"):
        trainer.fit(_prior(), _data(), 1)

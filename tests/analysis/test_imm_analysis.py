"""Paper 001: alpha transition matrix, probability bounds, compression ratios, Conclusions 1-5."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from tests.conftest import random_psd
from torchmm import IMM, GaussianBelief, KalmanFilter, ModeBelief, alpha_transition
from torchmm.analysis import (
    matched_model,
    check_conclusions,
    check_probability_bounds,
    delta_ratio,
    interaction_deviations,
    mixed_probability_bounds,
    predicted_mode_probs,
    ratio_bounds,
    zeta_ratio,
)
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.multimodel import transition_alpha

close = partial(torch.testing.assert_close, rtol=1e-10, atol=1e-12)


def test_alpha_transition_is_eq_2_2():
    alpha = torch.tensor([0.1, 0.2, 0.05])
    P = alpha_transition(alpha)
    for i in range(3):
        for j in range(3):
            expected = alpha[j] if i != j else 1 - alpha.sum() + alpha[j]
            close(P[i, j], expected)
    close(P.sum(-1), torch.ones(3))
    close(transition_alpha(P), alpha)
    assert transition_alpha(torch.tensor([[0.9, 0.1, 0.0], [0.0, 0.9, 0.1], [0.1, 0.0, 0.9]])) is None
    # every 2x2 stochastic matrix has the form (2.2): alpha = (pi_21, pi_12)
    close(transition_alpha(torch.tensor([[0.7, 0.3], [0.4, 0.6]])), torch.tensor([0.4, 0.3]))


def _random_mixing_inputs(rng, M, n=2, batch=64):
    probs = torch.tensor(rng.dirichlet(np.ones(M) * 0.5, size=batch))
    means = torch.tensor(rng.normal(scale=5.0, size=(batch, M, n)))
    covs = torch.tensor(np.array([[random_psd(n, rng) for _ in range(M)] for _ in range(batch)]))
    return probs, means, covs


def _imm_for(transition):
    M = transition.shape[-1]
    motion = ConstantVelocity(1, acceleration=torch.zeros(M, 1))
    return IMM(KalmanFilter(motion, PositionMeasurement(2, [0], 1.0)), transition)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), M=st.integers(2, 4), scale=st.floats(0.01, 1.6))
def test_predicted_probabilities_and_bounds(seed, M, scale):
    rng = np.random.default_rng(seed)
    alpha = torch.tensor(rng.dirichlet(np.ones(M)) * scale)
    assume(bool((alpha.sum() - alpha <= 1).all()))
    P = alpha_transition(alpha)
    probs, means, covs = _random_mixing_inputs(rng, M)
    imm = _imm_for(P)
    mixed = imm.mix(ModeBelief(probs.log(), GaussianBelief(means, covs)))
    predicted = mixed.mode_log_probs.exp()
    close(predicted, predicted_mode_probs(alpha, probs))  # eq. (3.1)
    checks = check_probability_bounds(alpha, probs, predicted)
    assert bool(checks["3.2/3.3"].holds.all())  # eqs. (3.2)/(3.3)
    lower, upper = mixed_probability_bounds(alpha)
    assert bool(((predicted >= lower - 1e-12) & (predicted <= upper + 1e-12)).all())
    if alpha.sum() <= 1:
        ratio = checks["3.8"]
        assert bool(ratio.premise.any())
        assert bool(ratio.holds[ratio.premise].all())  # eq. (3.8)


def test_ratio_bound_fails_without_its_premise():
    """(3.8) needs sum(alpha) <= 1: with sum(alpha) > 1 the ratio leaves the interval."""
    alpha = torch.tensor([0.45, 0.7])  # sum 1.15
    probs = torch.tensor([[0.9, 0.1]])
    predicted = predicted_mode_probs(alpha, probs)
    lo, hi = ratio_bounds(alpha, probs)
    ratio = predicted[0, 0] / predicted[0, 1]
    assert not bool((ratio >= lo[0, 0, 1]) & (ratio <= hi[0, 0, 1]))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), M=st.integers(2, 4), scale=st.floats(0.01, 0.99))
def test_delta_formula_4_10_equals_the_imm_interaction(seed, M, scale):
    rng = np.random.default_rng(seed)
    alpha = torch.tensor(rng.dirichlet(np.ones(M)) * scale)
    P = alpha_transition(alpha)
    probs, means, covs = _random_mixing_inputs(rng, M)
    mixed = _imm_for(P).mix(ModeBelief(probs.log(), GaussianBelief(means, covs)))
    matched = torch.tensor(rng.integers(M, size=probs.shape[0]))
    dev = interaction_deviations(probs, means, mixed.components.mean, matched)
    # a ratio of differences: well conditioned only where the deviations exceed rounding
    ok = dev.output > 1e-6 * means.abs().amax((-1, -2))
    empirical = dev.mixed.gather(-1, matched[:, None]).squeeze(-1) / dev.output
    torch.testing.assert_close(empirical[ok], delta_ratio(alpha, probs, matched)[ok], rtol=1e-7, atol=1e-10)
    assert bool((empirical[ok] < 1).all())  # Conclusion 1 (sum alpha < 1)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_zeta_formula_4_14_equals_the_imm_interaction_for_any_2x2(seed):
    rng = np.random.default_rng(seed)
    P = torch.tensor(rng.dirichlet(np.ones(2), size=2))
    probs, means, covs = _random_mixing_inputs(rng, 2)
    mixed = _imm_for(P).mix(ModeBelief(probs.log(), GaussianBelief(means, covs)))
    matched = torch.tensor(rng.integers(2, size=probs.shape[0]))
    dev = interaction_deviations(probs, means, mixed.components.mean, matched)
    other = 1 - matched
    model_j = dev.model.gather(-1, other[:, None]).squeeze(-1)
    ok = model_j > 1e-6 * means.abs().amax((-1, -2))
    empirical = dev.mixed.gather(-1, other[:, None]).squeeze(-1) / model_j
    torch.testing.assert_close(empirical[ok], zeta_ratio(P, probs, matched)[ok], rtol=1e-7, atol=1e-10)
    assert bool((empirical[ok] < 1).all())  # Conclusion 3


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), M=st.sampled_from([2, 3]), alpha_form=st.booleans(),
       scale=st.floats(0.01, 1.4))
def test_conclusions_hold_wherever_their_premises_hold(seed, M, alpha_form, scale):
    rng = np.random.default_rng(seed)
    if alpha_form:
        alpha = torch.tensor(rng.dirichlet(np.ones(M)) * scale)
        assume(bool((alpha.sum() - alpha <= 1).all()))
        P = alpha_transition(alpha)
    else:
        P = torch.tensor(rng.dirichlet(np.ones(M), size=M))
    probs, means, covs = _random_mixing_inputs(rng, M, batch=128)
    mixed = _imm_for(P).mix(ModeBelief(probs.log(), GaussianBelief(means, covs)))
    matched = torch.tensor(rng.integers(M, size=probs.shape[0]))
    checks = check_conclusions(P, probs, means, mixed.components.mean, matched)
    for number, check in checks.items():
        assert bool(check.holds[check.premise].all()), f"Conclusion {number} violated"
    # the premises are not vacuous for the proven conclusions on their model counts
    assert bool(checks[3 if M == 2 else 5].premise.any())


def test_conclusion_1_claim_fails_when_transition_is_not_diagonally_dominant():
    """With sum(alpha) > 1 the interaction pushes the matched model away: delta > 1."""
    alpha = torch.tensor([0.7, 0.6])
    P = alpha_transition(alpha)
    probs = torch.tensor([[0.6, 0.4]])
    means = torch.tensor([[[0.0, 0.0], [1.0, 1.0]]])
    mixed = _imm_for(P).mix(ModeBelief(probs.log(), GaussianBelief(means, torch.eye(2).expand(1, 2, 2, 2))))
    checks = check_conclusions(P, probs, means, mixed.components.mean, torch.tensor([0]))
    assert not bool(checks[1].premise.any())
    assert not bool(checks[1].holds.any())
    assert delta_ratio(alpha, probs, torch.tensor([0])).item() > 1


def test_zeta_needs_two_models():
    with pytest.raises(ValueError, match="two models"):
        zeta_ratio(torch.eye(3), torch.ones(1, 3) / 3, torch.tensor([0]))


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), M=st.sampled_from([2, 3]), alpha=st.floats(0.001, 0.3))
def test_conclusions_hold_on_imm_runs_of_random_scenarios(seed, M, alpha):
    """The checks fed from a real IMM trajectory (mixed start beliefs from ``extras``)."""
    from torchmm import run_filter
    from torchmm.simulate import simulate_jump_system, simulate_measurements

    rng = np.random.default_rng(seed)
    g = torch.Generator().manual_seed(seed)
    acc = torch.tensor(rng.normal(scale=2.0, size=(M, 1)))
    motion = ConstantVelocity(1, q=float(rng.uniform(0.01, 1.0)), acceleration=acc)
    sensor = PositionMeasurement(2, [0], float(rng.uniform(1.0, 100.0)))
    truth_tpm = torch.tensor(rng.dirichlet(np.ones(M) * 0.3, size=M)) * 0.3 + 0.7 * torch.eye(M)
    x0 = GaussianBelief(torch.zeros(2), torch.eye(2) * 10)
    sim = simulate_jump_system(motion, truth_tpm, x0, 30, (16,), generator=g)
    z = simulate_measurements(sensor, sim.states, generator=g)
    P = alpha_transition(torch.full((M,), alpha))
    imm = IMM(KalmanFilter(motion, sensor), P)
    traj = run_filter(imm, imm.initial_belief(x0.expand(16)), z)
    probs = traj.belief.mode_probs[:-1]
    means = traj.belief.components.mean[:-1]
    mixed = traj.extras["mixed"].components.mean[1:]
    close(traj.prior.mode_log_probs[1:].exp(), predicted_mode_probs(torch.full((M,), alpha), probs))
    checks = check_conclusions(P, probs, means, mixed, matched_model(means, sim.states[:-1]))
    for number in (1, 3, 5):
        check = checks[number]
        if number == 1 or (number == 3 and M == 2) or (number == 5 and M == 3):
            assert bool(check.premise.any()), f"Conclusion {number}: premise never held"
        assert bool(check.holds[check.premise].all()), f"Conclusion {number} violated"

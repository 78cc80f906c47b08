"""A model-set policy that does not fit its bank is refused when VariableStructureIMM is built, naming the
policy's argument (before: accepted, then a raw IndexError or a TypeError at the first step); a family of
candidate sets may be any sequence (a config's ListConfig), and a challenge match's threshold must be
reachable."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from torchmm import (
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    LinearMotion,
    PositionMeasurement,
    run_filter,
)
from torchmm.beliefs import ModeBelief
from torchmm.filters.particle import ParticleFilter
from torchmm.multimodel import DropBelow, FixedSet, VariableStructureIMM
from torchmm.multimodel.mevsmm import ChallengeMatch, ExactMinimumEntropy

P3 = torch.full((3, 3), 0.1, dtype=torch.float64) + 0.7 * torch.eye(3, dtype=torch.float64)


def _motion():
    return ConstantVelocity(1, q=1.0, acceleration=[[0.5], [0.0], [-0.5]])


def _kalman():
    return KalmanFilter(_motion(), PositionMeasurement(2, [0], 1.0))


def _particles(num_particles=50):
    return ParticleFilter(_motion(), PositionMeasurement(2, [0], 1.0), num_particles=num_particles)


@pytest.mark.parametrize("policy, match", [
    (lambda: FixedSet([5]),
     r"^policy\.members: \[5\] has model index 5, out of range for the bank's 3 models"),
    (lambda: FixedSet([0, 3]), r"^policy\.members: .* model index 3"),
    (lambda: DropBelow(0.1, [9]), r"^policy\.candidates: \[9\] has model index 9"),
    (lambda: ExactMinimumEntropy([[0, 1], [7]]), r"^policy\.family: entry 1 \(\[7\]\) has model index 7"),
    (lambda: ExactMinimumEntropy(torch.ones(2, 4, dtype=torch.bool)),
     r"^policy\.family: expected a \(K, 3\)"),
], ids=["FixedSet", "FixedSet-one-past", "DropBelow", "family", "family-mask"])
def test_an_index_past_the_bank_is_refused_when_built(policy, match):
    with pytest.raises(ValueError, match=match):
        VariableStructureIMM(_kalman(), P3, policy())


def test_a_challenge_match_over_gaussian_modes_is_refused_when_built():
    with pytest.raises(TypeError, match=r"^policy: ChallengeMatch ranks particles .* got KalmanFilter"):
        VariableStructureIMM(_kalman(), P3, ChallengeMatch(4, 1))


def test_more_winners_than_particles_is_refused_and_the_edge_is_accepted():
    with pytest.raises(ValueError,
                       match=r"^policy\.num_winners: 151 exceeds the bank's 3 x 50 = 150 particles"):
        VariableStructureIMM(_particles(50), P3, ChallengeMatch(151, 5))
    VariableStructureIMM(_particles(50), P3, ChallengeMatch(150, 5))  # every particle a winner: allowed


def test_a_threshold_above_the_winners_is_refused():
    with pytest.raises(ValueError, match=r"^threshold: 11 exceeds num_winners \(10\)"):
        ChallengeMatch(10, 11)
    assert ChallengeMatch(10, 10).threshold == 10  # reachable: one model holding every winner


def test_policies_that_fit_are_accepted_and_run():
    g = torch.Generator().manual_seed(0)
    z = torch.randn(4, 2, 1, generator=g)
    prior = GaussianBelief(torch.zeros(2, 2), torch.eye(2).expand(2, 2, 2))
    for policy in (FixedSet([0, 2]), DropBelow(0.1, [2]), ExactMinimumEntropy([[0, 1], [2]])):
        vs = VariableStructureIMM(_kalman(), P3, policy)
        assert run_filter(vs, vs.initial_belief(prior), z).extras["active"].shape == (4, 2, 3)


@pytest.mark.parametrize("policy, name", [(lambda: FixedSet([5]), "members"),
                                          (lambda: DropBelow(0.1, [9]), "candidates"),
                                          (lambda: ExactMinimumEntropy([[0], [7]]), "family")],
                         ids=["FixedSet", "DropBelow", "family"])
def test_a_policy_used_without_the_estimator_names_its_argument(policy, name):
    """``select`` on a posterior of 3 modes (no VariableStructureIMM to check first): a ValueError naming the
    argument, not a raw IndexError from building the mask."""
    post = ModeBelief(torch.full((2, 3), -math.log(3)), GaussianBelief(torch.zeros(2, 3, 2), torch.eye(2)))
    with pytest.raises(ValueError, match=rf"^{name}: "):
        policy().select(post)


def _brute_force_family(mode_probs: np.ndarray, cov: np.ndarray, family: list[list[int]]) -> np.ndarray:
    """The family member of least joint entropy ``H(p) + sum_j p_j h_j`` (Gaussian ``h_j``), first on ties."""
    h = 0.5 * np.log(np.linalg.det(2 * np.pi * np.e * cov))
    out = np.zeros(mode_probs.shape, dtype=bool)
    for r in range(mode_probs.shape[0]):
        values = []
        for members in family:
            p = mode_probs[r, members] / mode_probs[r, members].sum()
            values.append(-(p * np.log(p)).sum() + (p * h[r, members]).sum())
        out[r, family[int(np.argmin(values))]] = True
    return out


@pytest.mark.parametrize("as_given", [lambda f: OmegaConf.create(f), lambda f: tuple(tuple(m) for m in f)],
                         ids=["ListConfig", "tuples"])
def test_a_family_of_any_sequence_selects_its_minimum_entropy_member(as_given):
    """A config's ``family: [[0,1],[2]]`` arrives as a ListConfig (before: refused, "got ListConfig"): it is
    accepted and selects, every step, the candidate a NumPy enumeration of the family picks."""
    family = [[0, 1], [2], [1, 2]]
    cv = ConstantVelocity(1, q=1.0, acceleration=[[0.5], [0.0], [-0.5]])
    motion = LinearMotion(cv.F, cv.Q * torch.tensor([0.1, 1.0, 4.0]).view(3, 1, 1), offset=cv.offset)
    vs = VariableStructureIMM(KalmanFilter(motion, PositionMeasurement(2, [0], 2.0)), P3,
                              ExactMinimumEntropy(as_given(family)), feedback=False)
    g = torch.Generator().manual_seed(3)
    runs, steps = 5, 12
    trend = 0.4 * torch.arange(steps, dtype=torch.float64) ** 1.5
    z = trend.view(steps, 1, 1) + torch.randn(steps, runs, 1, generator=g)
    belief = vs.initial_belief(GaussianBelief(torch.zeros(runs, 2), 4 * torch.eye(2).expand(runs, 2, 2)))
    chosen = set()
    for k in range(steps):
        out = vs.step(belief, z[k])
        post = out.belief  # feedback=False: the carried probabilities are the posterior over every model
        want = _brute_force_family(post.mode_probs.numpy(), post.components.cov.numpy(), family)
        np.testing.assert_array_equal(out.extras["active"].numpy(), want)
        chosen.update(tuple(row) for row in want.tolist())
        belief = out.belief
    assert len(chosen) >= 2  # (the runs and steps pick different members: not one trivial answer)

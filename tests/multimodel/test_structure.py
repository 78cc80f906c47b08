"""Variable structure as a policy over any bank, and a mode filter defined here getting every combinator."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchmm import GPB1, GPB2, IMM, ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, run_filter
from torchmm.filters import Filter, StepOutput, UnscentedKalmanFilter
from torchmm.filters.particle import ParticleFilter
from torchmm.multimodel import AllModels, FixedSet, StaticMM, VariableStructureIMM
from torchmm.multimodel.mevsmm import ChallengeMatch, ExactMinimumEntropy

ACC = [[1.0], [0.5], [0.0], [-0.5], [-1.0]]


def _setup(runs=4, steps=20, seed=0):
    qs = torch.tensor([0.05, 0.5, 2.0, 0.7, 0.1]).view(5, 1, 1)
    cv = ConstantVelocity(1, q=1.0, acceleration=ACC)
    from torchmm import LinearMotion

    motion = LinearMotion(cv.F, cv.Q * qs, offset=cv.offset)  # modes with different noise levels
    sensor = PositionMeasurement(2, [0], 2.0)
    P = torch.full((5, 5), 0.05) + 0.75 * torch.eye(5)
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(steps, dtype=torch.float64)
    z = (0.3 * t ** 1.5).view(steps, 1, 1) + 1.5 * torch.randn(steps, runs, 1, generator=g)
    prior = GaussianBelief(torch.zeros(runs, 2), 5 * torch.eye(2).expand(runs, 2, 2))
    return motion, sensor, P, prior, z


def _brute_force(mode_probs: np.ndarray, cov: np.ndarray, entropy: str) -> np.ndarray:
    """The minimum-entropy set by enumerating every non-empty subset (ties to the lowest code)."""
    M = mode_probs.shape[-1]
    h = 0.5 * np.log(np.linalg.det(2 * np.pi * np.e * cov))
    out = np.zeros(mode_probs.shape, dtype=bool)
    for r in range(mode_probs.shape[0]):
        best, best_set = math.inf, None
        for code in range(1, 1 << M):
            members = [j for j in range(M) if code >> j & 1]
            W = mode_probs[r, members]
            p = W / W.sum()
            if entropy == "joint":
                value = -(p * np.log(p)).sum() + (p * h[r, members]).sum()
            else:
                value = (p ** 2 * (h[r, members] - 2 * np.log(p))).sum()
            if value < best - 1e-12:
                best, best_set = value, members
        out[r, best_set] = True
    return out


@pytest.mark.parametrize("entropy", ["joint", "literal"])
def test_minimum_entropy_over_a_kalman_bank_equals_brute_force(entropy):
    motion, sensor, P, prior, z = _setup()
    vs = VariableStructureIMM(KalmanFilter(motion, sensor), P, ExactMinimumEntropy(entropy=entropy), feedback=False)
    traj = run_filter(vs, vs.initial_belief(prior), z)
    probs = traj.belief.mode_probs.numpy()
    covs = traj.belief.components.cov.numpy()
    got = traj.extras["active"].numpy()
    for k in range(z.shape[0]):
        np.testing.assert_array_equal(got[k], _brute_force(probs[k], covs[k], entropy))
    if entropy == "joint":  # H(S) >= min_j h_j: always one model, the most concentrated belief
        assert (got.sum(-1) == 1).all()
    # without feedback the recursion is the IMM's
    imm = IMM(KalmanFilter(motion, sensor), P)
    ref = run_filter(imm, imm.initial_belief(prior), z)
    torch.testing.assert_close(traj.belief.mode_probs, ref.belief.mode_probs, rtol=0, atol=1e-13)


def test_minimum_entropy_over_a_family_and_with_feedback():
    motion, sensor, P, prior, z = _setup()
    family = [[0, 1], [1, 2, 3], [3, 4], [0, 1, 2, 3, 4]]
    vs = VariableStructureIMM(KalmanFilter(motion, sensor), P, ExactMinimumEntropy(family))
    traj = run_filter(vs, vs.initial_belief(prior), z)
    active = traj.extras["active"]
    rows = torch.zeros(4, 5, dtype=torch.bool)
    for i, members in enumerate(family):
        rows[i, members] = True
    assert ((active.unsqueeze(-2) == rows).all(-1)).any(-1).all()  # always one of the family
    probs = traj.belief.mode_probs
    assert torch.all(probs[~active] == 0)  # fed back: nothing outside the set
    torch.testing.assert_close(probs.sum(-1), torch.ones(probs.shape[:-1]), rtol=0, atol=1e-12)
    assert torch.isfinite(traj.estimate().mean).all()


def test_all_models_policy_is_the_imm():
    motion, sensor, P, prior, z = _setup()
    vs = VariableStructureIMM(KalmanFilter(motion, sensor), P, AllModels())
    imm = IMM(KalmanFilter(motion, sensor), P)
    a, b = run_filter(vs, vs.initial_belief(prior), z), run_filter(imm, imm.initial_belief(prior), z)
    torch.testing.assert_close(a.estimate().mean, b.estimate().mean, rtol=0, atol=1e-12)  # renormalised: rounding
    assert a.extras["model_count"].eq(5).all()
    fixed = VariableStructureIMM(KalmanFilter(motion, sensor), P, FixedSet([1, 2, 3]))
    f = run_filter(fixed, fixed.initial_belief(prior), z)
    assert torch.all(f.belief.mode_probs[..., [0, 4]] == 0)


def test_minimum_entropy_over_unscented_and_particle_banks():
    motion, sensor, P, prior, z = _setup()
    kf = VariableStructureIMM(KalmanFilter(motion, sensor), P, ExactMinimumEntropy())
    ukf = VariableStructureIMM(UnscentedKalmanFilter(motion, sensor), P, ExactMinimumEntropy())
    a, b = run_filter(kf, kf.initial_belief(prior), z), run_filter(ukf, ukf.initial_belief(prior), z)
    assert torch.equal(a.extras["active"], b.extras["active"])
    torch.testing.assert_close(b.estimate().mean, a.estimate().mean, rtol=0, atol=1e-8)
    pf = VariableStructureIMM(ParticleFilter(motion, sensor, num_particles=300), P, ChallengeMatch(100, 10))
    g = torch.Generator().manual_seed(1)
    c = run_filter(pf, pf.initial_belief(prior, generator=g), z, generator=g)
    assert torch.isfinite(c.estimate().mean).all()
    assert (c.extras["model_count"] >= 1).all()
    with pytest.raises(TypeError, match="^policy: ChallengeMatch ranks particles and needs particle mode"):
        VariableStructureIMM(KalmanFilter(motion, sensor), P, ChallengeMatch(3, 1))  # (refused when built)


# -- a mode filter written here: the information-form Kalman filter --------------------------------
class InformationKalman(Filter):
    """The Kalman filter written in information form (``Y = P^-1``, ``y = Y x``) for the update,
    returning moment-form Gaussian beliefs: a mode filter torchmm has never seen."""

    def __init__(self, motion, measurement):
        super().__init__()
        self.motion, self.measurement = motion, measurement

    def predict(self, belief, *, u=None):
        F = self.motion.F
        return GaussianBelief(self.motion(belief.mean), F @ belief.cov @ F.mT + self.motion.Q)

    def update(self, belief, z):
        H, R = self.measurement.H, self.measurement.R
        Rinv = torch.linalg.inv(R)
        Y = torch.linalg.inv(belief.cov) + H.mT @ Rinv @ H
        cov = torch.linalg.inv(Y)
        y = (torch.linalg.inv(belief.cov) @ belief.mean.unsqueeze(-1) + H.mT @ Rinv @ z.unsqueeze(-1))
        mean = (cov @ y).squeeze(-1)
        S = H @ belief.cov @ H.mT + R
        nu = z - (H @ belief.mean.unsqueeze(-1)).squeeze(-1)
        ll = -0.5 * (nu.unsqueeze(-2) @ torch.linalg.solve(S, nu.unsqueeze(-1))).squeeze(-1).squeeze(-1) \
            - 0.5 * torch.logdet(2 * math.pi * S)
        return StepOutput(GaussianBelief(mean, (cov + cov.mT) / 2), belief, ll, nu, S)


@pytest.mark.parametrize("combinator", ["IMM", "GPB1", "GPB2", "StaticMM", "VSMM"])
def test_a_new_mode_filter_gets_every_combinator(combinator):
    motion, sensor, P, prior, z = _setup(steps=12)
    build = {"IMM": lambda b: IMM(b, P), "GPB1": lambda b: GPB1(b, P), "GPB2": lambda b: GPB2(b, P),
             "StaticMM": lambda b: StaticMM(b, 5),
             "VSMM": lambda b: VariableStructureIMM(b, P, ExactMinimumEntropy(), feedback=True)}[combinator]
    new, ref = build(InformationKalman(motion, sensor)), build(KalmanFilter(motion, sensor))
    a, b = run_filter(new, new.initial_belief(prior), z), run_filter(ref, ref.initial_belief(prior), z)
    torch.testing.assert_close(a.estimate().mean, b.estimate().mean, rtol=0, atol=1e-8)
    torch.testing.assert_close(a.belief.mode_probs, b.belief.mode_probs, rtol=0, atol=1e-8)


def test_active_set_mixing_renormalises_rows_and_drop_below(generator):
    from torchmm.beliefs import ModelSetBelief
    from torchmm.multimodel import ActiveSetMixing, DropBelow, MomentMixing, ModeTransition

    M = 4
    P = torch.softmax(torch.randn(M, M, generator=generator), -1)
    comps = GaussianBelief(torch.randn(3, M, 2, generator=generator), torch.eye(2).expand(3, M, 2, 2))
    mu = torch.softmax(torch.randn(3, M, generator=generator), -1)
    mu[:, 3] = 0.0
    mu = mu / mu.sum(-1, keepdim=True)
    all_active = ModelSetBelief(mu.log(), comps, torch.ones(3, M, dtype=torch.bool))
    a = ActiveSetMixing()(all_active, ModeTransition(P))
    b = MomentMixing()(all_active, ModeTransition(P))
    torch.testing.assert_close(a.mode_log_probs, b.mode_log_probs, rtol=0, atol=1e-14)
    torch.testing.assert_close(a.components.mean, b.components.mean, rtol=0, atol=1e-14)
    active = torch.tensor([True, True, True, False]).expand(3, M)
    c = ActiveSetMixing()(ModelSetBelief(mu.log(), comps, active), P)
    Pr = P[:, :3] / P[:, :3].sum(-1, keepdim=True)  # rows renormalised over the active set
    torch.testing.assert_close(c.mode_log_probs[:, :3].exp(), mu[:, :3] @ Pr[:3], rtol=0, atol=1e-14)
    assert torch.all(c.mode_log_probs[:, 3] == -math.inf)
    lp = torch.log(torch.tensor([[0.5, 0.4999, 0.0001], [0.3, 0.3, 0.4]]))
    from torchmm import ModeBelief

    keep, _ = DropBelow(1e-3, [2]).select(ModeBelief(lp, GaussianBelief(torch.zeros(2, 3, 2), torch.eye(2))))
    assert keep.tolist() == [[True, True, False], [True, True, True]]

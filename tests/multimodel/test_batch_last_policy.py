"""The variable-structure IMM through the batch-last IMM kernel (issue 31): ``VariableStructureIMM``
describes itself as the IMM with its model-set policy as a ``post_update``
(:class:`torchmm.kernels.linear.LinearGaussian`), and the kernel runs the IMM steps batch-last and the
policy after each (batch-first views), continuing from the carried probabilities.

Checked against the batch-first steps on random models (no ties between the candidate sets' entropies:
the modes' covariances differ): every Trajectory field and the extras' order, with and without
feedback, record="estimate", a policy that draws random numbers (the run's generator reaches it), an
empty set (that run's NaN log-likelihood), gradients; the kernels that must decline do, and a subclass
that overrides the policy step leaves the kernel. Also GaussianBelief.entropy's factor-free form for
n <= 2 (the policy's entropy), bit for bit against the factor's diagonal."""

from __future__ import annotations

import math

import pytest
import torch

from tests.multimodel.test_batch_last import D, _random_imm, assert_same_trajectory, count_calls
from torchmm import GaussianBelief, KalmanFilter, LinearMotion, kernels, run_filter
from torchmm.kernels import linear
from torchmm.linalg import cholesky
from torchmm.multimodel import VariableStructureIMM
from torchmm.kernels.batch_last.imm import BATCH_LAST, BatchLastIMM
from torchmm.multimodel.mevsmm import ExactMinimumEntropy
from torchmm.multimodel.structure import ModelSetPolicy


@pytest.fixture(autouse=True)
def kernel_steps(monkeypatch):
    """The small linear kernel declines (as it does for any post-update: tested below); the list of
    the batch-last kernels that stepped."""
    monkeypatch.setattr(linear.LinearKernel, "plan", lambda self, *args: "declined in this test")
    return count_calls(monkeypatch, BatchLastIMM, "step")


def _random_vsimm(n, m, M, batch, steps, seed, policy=None, feedback=True, shared=False):
    imm, belief0, z = _random_imm(n, m, M, batch, steps, seed, shared=shared)
    vs = VariableStructureIMM(imm.bank.filter, imm.transition.matrix(), policy or ExactMinimumEntropy(),
                              feedback=feedback)
    start = GaussianBelief(belief0.components.mean[..., 0, :], belief0.components.cov[..., 0, :, :])
    return vs, vs.initial_belief(start, belief0.mode_log_probs.exp()), z


@pytest.mark.parametrize("n,m,M", [(1, 1, 2), (2, 1, 3), (3, 2, 2), (4, 3, 3), (2, 2, 4)])
@pytest.mark.parametrize("feedback", [True, False])
def test_every_field_equals_the_batch_first_steps(n, m, M, feedback, kernel_steps):
    vs, belief0, z = _random_vsimm(n, m, M, (7,), steps=12, seed=10 * n + 3 * m + M, feedback=feedback)
    got = run_filter(vs, belief0, z)  # the default takes it
    assert len(kernel_steps) == 12 and kernel_steps[0].post_update is not None
    want = run_filter(vs, belief0, z, fast_path=False)
    assert_same_trajectory(got, want)
    assert list(got.extras) == list(want.extras)  # (also in the spec above) "mixed" last, as the steps
    assert not bool(got.extras["active"].all())  # the policy selected: sets smaller than the total
    est = run_filter(vs, belief0, z, record="estimate")
    assert len(kernel_steps) == 24 and kernel_steps[-1].estimate_after
    for a, b in ((est.belief.mean, want.estimate().mean), (est.belief.cov, want.estimate().cov),
                 (est.log_likelihood, want.log_likelihood)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


class _Random(ModelSetPolicy):
    """Keeps each model with probability 0.9 (the run's generator), and none at all in run 0 at step 1."""

    def __init__(self):
        self.calls = 0

    def select(self, belief, generator=None):
        probs = belief.mode_log_probs
        active = torch.rand(probs.shape, generator=generator, dtype=probs.dtype) < 0.9
        if self.calls == 1:
            active[0] = False  # an empty set: run 0's failure, never the others'
        self.calls += 1
        return active, {"kept": active.sum(-1)}


def test_a_random_policy_gets_the_runs_generator_and_an_empty_set_fails_one_run(kernel_steps):
    vs, belief0, z = _random_vsimm(2, 1, 3, (6,), steps=8, seed=3, policy=_Random())
    got = run_filter(vs, belief0, z, generator=torch.Generator().manual_seed(5))
    assert len(kernel_steps) == 8
    vs.policy.calls = 0
    want = run_filter(vs, belief0, z, generator=torch.Generator().manual_seed(5), fast_path=False)
    assert_same_trajectory(got, want)
    assert bool(got.extras["empty_set"][1, 0]) and not bool(got.extras["empty_set"][:, 1:].any())
    assert math.isnan(got.log_likelihood[1, 0]) and bool(torch.isfinite(got.log_likelihood[:, 1:]).all())


def test_gradients_equal_the_batch_first_steps(kernel_steps):
    def grads(fast):  # (symmetric parameters of Q: a raw Q's two triangles take its gradient differently)
        vs, belief0, z = _random_vsimm(2, 1, 3, (5,), steps=8, seed=7)
        kf = vs.bank.filter
        F = kf.motion.F.detach().clone().requires_grad_(True)
        q = torch.tensor(1.3, dtype=D, requires_grad=True)
        vs = VariableStructureIMM(KalmanFilter(LinearMotion(F, q * kf.motion.Q, kf.motion.offset), kf.measurement),
                                  vs.transition.matrix(), ExactMinimumEntropy())
        loss = run_filter(vs, belief0, z, fast_path=fast).log_likelihood.sum()
        return torch.autograd.grad(loss, (F, q))

    fast, slow = grads(True), grads(False)
    assert len(kernel_steps) == 8
    for a, b in zip(fast, slow):
        assert bool(a.ne(0).any())
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


def test_the_kernels_that_must_decline_do(monkeypatch, kernel_steps):
    vs, belief0, z = _random_vsimm(2, 1, 3, (4,), steps=6, seed=2)
    model = vs.linear_gaussian()
    assert model.rule == "mix" and model.post_update == vs.select_models
    monkeypatch.setattr(linear.LinearKernel, "plan", _LINEAR_PLAN)
    small = linear.LinearKernel()
    assert "a post-update" in small.plan(vs, belief0, z, kernels.Request(forced=True))
    traj = run_filter(vs, belief0, z)
    assert "a post-update" in small.plan_smooth(vs, traj, "kim")  # the eager smoother
    assert len(kernel_steps) == 6

    class _Mine(VariableStructureIMM):
        def select_models(self, out, generator=None):
            return super().select_models(out, generator)

    mine = _Mine(vs.bank.filter, vs.transition.matrix(), ExactMinimumEntropy())
    assert "has not joined" in BATCH_LAST.plan(mine, belief0, z, kernels.Request())
    assert_same_trajectory(run_filter(mine, belief0, z), run_filter(vs, belief0, z, fast_path=False))
    assert len(kernel_steps) == 6


_LINEAR_PLAN = linear.LinearKernel.plan


@pytest.mark.parametrize("n", [1, 2, 3])
def test_the_entropy_is_the_factors_bit_for_bit(n):
    g = torch.Generator().manual_seed(n)
    A = torch.randn(500, n, n, generator=g, dtype=D)
    S = A @ A.mT
    S[:10] = 0.0  # singular: the regularised factor's pivots
    S[10:20] *= -1.0
    S[20] = math.nan
    want = cholesky(S).diagonal(dim1=-2, dim2=-1).log().sum(-1) + 0.5 * n * (1.0 + math.log(2 * math.pi))
    got = GaussianBelief(torch.zeros(500, n, dtype=D), S).entropy()
    assert torch.equal(got.isnan(), want.isnan()) and torch.equal(got.nan_to_num(), want.nan_to_num())
    assert int(got.isnan().sum()) == 1

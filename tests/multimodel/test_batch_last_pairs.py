"""GPB2's batch-last kernel (torchmm/kernels/batch_last/pairs.py, the ``"pairs"`` rule of
``BATCH_LAST``): run_filter's GPB2 over linear Kalman modes returns what GPB2's batch-first steps
return - every Trajectory field (the M^2 pair priors, innovations and mode likelihoods included), for
random banks of every small size with per-mode and shared parameters, exact zeros and ones, missing
components, batch shapes (), (B,) and (B1, B2), float32, gradients (transition and model parameters),
record="estimate", traced and compiled - it is taken by default, and not where it does not apply.

The batch-first GPB2 itself is checked against a NumPy reference and FilterPy-style identities in
tests/multimodel/test_imm.py; here the kernel is checked against it."""

from __future__ import annotations

import pytest
import torch
import torch.utils._pytree as pytree

from tests.multimodel.test_batch_last import (
    D,
    _assert_identical,
    _random_imm,
    assert_same_trajectory,
    count_calls,
)
from torchmm import (
    GPB2,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    LinearMotion,
    PositionMeasurement,
    kernels,
    run_filter,
)
from torchmm.kernels import linear
from torchmm.models.transition import ModeTransition
from torchmm.kernels.batch_last.imm import BATCH_LAST
from torchmm.kernels.batch_last.pairs import BatchLastGPB2


@pytest.fixture(autouse=True)
def pair_steps(monkeypatch):
    """The small linear kernel declines (as it does for GPB2 anyway: tested below); the list of the
    :meth:`BatchLastGPB2.step` calls is the fixture's value."""
    monkeypatch.setattr(linear.LinearKernel, "plan", lambda self, *args: "declined in this test")
    return count_calls(monkeypatch, BatchLastGPB2, "step")


def _random_gpb2(n, m, M, batch, steps, seed, dtype=D, shared=False):
    imm, belief0, z = _random_imm(n, m, M, batch, steps, seed, dtype=dtype, shared=shared)
    return GPB2(imm.bank.filter, imm.transition.matrix()), belief0, z


def _plan(filt, belief0, z, **request):
    return BATCH_LAST.plan(filt, belief0, z, kernels.Request(**request))


SIZES = [(1, 1, 1), (1, 1, 2), (2, 1, 3), (2, 2, 2), (3, 1, 2), (3, 2, 3), (4, 3, 3), (4, 2, 4)]


@pytest.mark.parametrize("n,m,M", SIZES)
@pytest.mark.parametrize("shared", [False, True])
def test_every_field_equals_the_batch_first_steps(n, m, M, shared, pair_steps):
    gpb2, belief0, z = _random_gpb2(n, m, M, (7,), steps=12, seed=10 * n + 3 * m + M, shared=shared)
    got = run_filter(gpb2, belief0, z)  # the default takes it
    assert len(pair_steps) == 12
    want = run_filter(gpb2, belief0, z, fast_path=False)
    assert len(pair_steps) == 12
    assert_same_trajectory(got, want)
    assert got.prior.components.mean.shape == (12, 7, M * M, n)
    assert got.innovation_cov.shape == (12, 7, M, M, m, m)
    assert got.extras["mode_log_likelihood"].shape == (12, 7, M, M)


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_batch_shapes(batch, pair_steps):
    gpb2, belief0, z = _random_gpb2(3, 2, 3, batch, steps=10, seed=len(batch))
    got = run_filter(gpb2, belief0, z, fast_path=True)
    assert len(pair_steps) == 10
    assert_same_trajectory(got, run_filter(gpb2, belief0, z, fast_path=False))


def test_the_benchmarks_bank_shares_the_pair_covariances(pair_steps):
    """Paper 000's modes (one F, Q, H, R; per-mode accelerations): the kernel predicts and updates M
    covariances, one per previous mode, broadcast over j - and still gives every field of the M^2 pairs."""
    motion = ConstantVelocity(1, q=1.0, acceleration=torch.tensor([[0.25], [0.0], [-0.25]], dtype=D), dtype=D)
    gpb2 = GPB2(KalmanFilter(motion, PositionMeasurement(2, [0], torch.tensor(100.0, dtype=D), dtype=D)),
                torch.tensor([[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.25, 0.25, 0.5]], dtype=D))
    belief0 = gpb2.initial_belief(GaussianBelief(torch.tensor([10.0, 10.0], dtype=D),
                                                 torch.tensor([[100.0, 1.0], [1.0, 100.0]], dtype=D)).expand(11))
    z = 10 * torch.randn(40, 11, 1, generator=torch.Generator().manual_seed(0), dtype=D)
    run = _plan(gpb2, belief0, z)
    X, C, log_mu, _ = run.kernel.initial_state(belief0)
    out = run.kernel.core(X, C, log_mu, *run.kernel.data[0])
    assert out[1][0][0].shape == (3, 11)  # the collapsed posteriors, (j, *B)
    got = run_filter(gpb2, belief0, z, fast_path=True)
    assert len(pair_steps) == 40
    assert_same_trajectory(got, run_filter(gpb2, belief0, z, fast_path=False))


def test_record_estimate_and_record_functions(pair_steps):
    gpb2, belief0, z = _random_gpb2(3, 2, 3, (8,), steps=10, seed=4)
    want = run_filter(gpb2, belief0, z, fast_path=False)
    got = run_filter(gpb2, belief0, z, record="estimate")
    assert len(pair_steps) == 10 and pair_steps[0].estimate_only
    assert isinstance(got.belief, GaussianBelief) and got.prior is None and got.extras is None
    torch.testing.assert_close(got.belief.mean, want.estimate().mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(got.belief.cov, want.estimate().cov, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=1e-10, atol=1e-10)

    def record(out):  # drops the prior and the extras: the kernel stops building them after step 0
        return out._replace(prior=None, extras=None)

    got = run_filter(gpb2, belief0, z, record=record)
    assert len(pair_steps) == 20 and pair_steps[-1].omitted == {"prior", "extras"}
    assert_same_trajectory(got, run_filter(gpb2, belief0, z, record=record, fast_path=False))


def test_float32(pair_steps):
    g64, b64, z64 = _random_gpb2(2, 1, 3, (9,), steps=15, seed=5)
    g32, b32, z32 = _random_gpb2(2, 1, 3, (9,), steps=15, seed=5, dtype=torch.float32)
    got = run_filter(g32, b32, z32, fast_path=True)
    assert len(pair_steps) == 15 and got.estimate().mean.dtype == torch.float32
    torch.testing.assert_close(got.estimate().mean.double(), run_filter(g64, b64, z64).estimate().mean,
                               rtol=1e-4, atol=1e-4)
    assert_same_trajectory(got, run_filter(g32, b32, z32, fast_path=False), tol=2e-4)


def test_missing_steps_have_zero_log_likelihood(pair_steps):
    gpb2, belief0, z = _random_gpb2(2, 2, 2, (4,), steps=6, seed=6)
    z[2] = float("nan")  # no datum at step 2
    got = run_filter(gpb2, belief0, z, fast_path=True)
    assert len(pair_steps) == 6
    assert torch.equal(got.log_likelihood[2], torch.zeros(4, dtype=D))
    assert_same_trajectory(got, run_filter(gpb2, belief0, z, fast_path=False))


def test_singular_innovations_are_flagged_as_the_engine_does(pair_steps):
    motion = LinearMotion(torch.eye(2, dtype=D), torch.zeros(2, 2, dtype=D))
    sensor = LinearMeasurement(torch.tensor([[1.0, 0.0]], dtype=D), torch.zeros(1, 1, dtype=D))
    gpb2 = GPB2(KalmanFilter(motion, sensor), torch.full((2, 2), 0.5, dtype=D))
    belief0 = gpb2.initial_belief(GaussianBelief(torch.zeros(3, 2, dtype=D),
                                                 torch.diag(torch.tensor([0.0, 1.0], dtype=D))))
    z = torch.zeros(2, 3, 1, dtype=D)
    got = run_filter(gpb2, belief0, z, fast_path=True)
    assert len(pair_steps) == 2 and bool(got.extras["modes"]["singular"].all())
    assert_same_trajectory(got, run_filter(gpb2, belief0, z, fast_path=False))


def test_gradients_equal_the_batch_first_steps(pair_steps):
    """Through the pairs, the logsumexp and the collapse, to the motion matrices (their zero entries
    included) and a learnable transition matrix."""
    def grads(fast):
        F = torch.tensor([[[1.0, 1.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 0.5]]], dtype=D, requires_grad=True)
        q = torch.tensor(0.3, dtype=D, requires_grad=True)
        transition = ModeTransition(torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=D), learnable=True)
        kf = KalmanFilter(LinearMotion(F, q * torch.eye(2, dtype=D)), PositionMeasurement(2, [0], 1.0, dtype=D))
        gpb2 = GPB2(kf, transition)
        belief0 = gpb2.initial_belief(GaussianBelief(torch.zeros(5, 2, dtype=D), torch.eye(2, dtype=D)))
        z = torch.linspace(-1, 2, 40, dtype=D).reshape(8, 5, 1)
        loss = -run_filter(gpb2, belief0, z, fast_path=fast).total_log_likelihood().sum()
        return torch.autograd.grad(loss, (F, q, transition.logits))

    fast, slow = grads(True), grads(False)
    assert len(pair_steps) == 8
    for a, b in zip(fast, slow):
        assert bool(a.ne(0).any())
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


def test_the_traced_step_gives_the_same_numbers_bit_for_bit(monkeypatch):
    from torchmm.kernels.batch_last import traced as batch_last

    monkeypatch.setattr(batch_last, "_TRACED", batch_last.OrderedDict())
    monkeypatch.setattr(batch_last, "_STEPS_SEEN", {})
    gpb2, belief0, z = _random_gpb2(3, 2, 3, (5,), steps=9, seed=21)
    imm = _random_imm(3, 2, 3, (5,), steps=9, seed=21)[0]
    for record in (None, "estimate", lambda out: out._replace(prior=None, innovation_cov=None)):
        monkeypatch.setattr(batch_last, "_TRACE_AFTER", 10**12)
        want = run_filter(gpb2, belief0, z, record=record)
        assert not batch_last._TRACED
        monkeypatch.setattr(batch_last, "_TRACE_AFTER", 0)
        run_filter(imm, belief0, z, record=record)  # the IMM of the same sizes: its own graph
        got = run_filter(gpb2, belief0, z, record=record)
        assert {key[0] for key in batch_last._TRACED} == {"IMM", "GPB2"}  # GPB2's graph is not the IMM's
        _assert_identical(got, want)
        batch_last._TRACED.clear()


def test_the_compiled_step_is_one_graph_and_equals_eager(pair_steps):
    import torch._dynamo

    gpb2, belief0, z = _random_gpb2(2, 1, 3, (6,), steps=3, seed=8)
    kernel = _plan(gpb2, belief0, z).kernel
    torch._dynamo.reset()
    whole = torch.compile(kernel.core, fullgraph=True, backend="eager", dynamic=False)
    X, C, log_mu, _ = kernel.initial_state(belief0)
    want = kernel.core(X, C, log_mu, *kernel.data[0])
    got = whole(X, C, log_mu, *kernel.data[0])  # raises at a graph break
    for a, b in zip(pytree.tree_leaves(got), pytree.tree_leaves(want)):
        assert (a is None and b is None) or torch.equal(a, b)


def test_taken_only_where_it_applies(monkeypatch, pair_steps):
    gpb2, belief0, z = _random_gpb2(2, 2, 2, (3,), steps=4, seed=1)
    kf = gpb2.bank.filter
    full = kf.measurement.R.clone()
    full[:, 0, 1] = full[:, 1, 0] = 0.1

    class _MyGPB2(GPB2):
        def update(self, belief, z, **inputs):
            return super().update(belief, z, **inputs)

    cases = {
        "R is not diagonal": GPB2(KalmanFilter(kf.motion, LinearMeasurement(kf.measurement.H, full)),
                                  gpb2.transition.matrix()),
        "_MyGPB2 has not joined": _MyGPB2(kf, gpb2.transition.matrix()),
        "the Joseph form": GPB2(KalmanFilter(kf.motion, kf.measurement, joseph=True), gpb2.transition.matrix()),
    }
    for reason, filt in cases.items():
        assert reason in _plan(filt, belief0, z)
        assert_same_trajectory(run_filter(filt, belief0, z), run_filter(filt, belief0, z, fast_path=False))
        assert not pair_steps, reason
    with pytest.raises(ValueError, match="fast_path: no fast path .*batch_last: update_first"):
        run_filter(gpb2, belief0, z, fast_path=True, update_first=True)
    # the small Numba kernel has no pair rule: it says so, and the batch-last kernel takes the run
    monkeypatch.setattr(linear.LinearKernel, "plan", _LINEAR_PLAN)
    assert "the 'pairs' rule" in linear.LinearKernel().plan(gpb2, belief0, z, kernels.Request(forced=True))
    run_filter(gpb2, belief0, z, fast_path=True)
    assert len(pair_steps) == 4


_LINEAR_PLAN = linear.LinearKernel.plan

"""IMM-TF's batch-last kernel (torchmm/kernels/batch_last/transfer.py, registered as
``"batch_last_transfer"``): run_filter's TransferIMM (IMM-TF, and IF-TF with its influence gate) over
linear Kalman modes with n <= 6 returns what the eager steps return - every field of the full record
(the extras: influence values, the gate's choices, the smoothed references, the transferred knowledge),
the estimates (record="estimate") and ``Keep`` records - for both smoothing references, both mode
likelihoods, gates of either weight, random banks and source sensors, missing target and source
components, batch shapes, float32 and gradients; it is taken by default, and not where it does not
apply (n > 6 below a large batch, update_first, a non-diagonal R_S, compile=True, a process weight with
a singular Q). The eager TransferIMM is checked against a NumPy reference in tests/multimodel/test_transfer.py."""

from __future__ import annotations

import pytest
import torch

from tests.multimodel.test_batch_last import D, _random_imm, assert_same_trajectory, count_calls
from tests.multimodel.test_transfer import assert_gated_steps, paper_setup
from torchmm import IMM, KalmanFilter, LinearMeasurement, LinearMotion, kernels, run_filter
from torchmm.multimodel import InfluenceGate, MultiRate, TransferIMM
from torchmm.kernels.batch_last.imm import LARGE_BATCH, LARGE_STATE
from torchmm.kernels.batch_last.transfer import TRANSFER, TRANSFER_LARGE, BatchLastTransfer
from torchmm.run import Keep
from torchmm.runtime import no_host_sync

FIELDS = ("belief", "prior", "log_likelihood", "innovation", "innovation_cov")


@pytest.fixture(autouse=True)
def transfer_steps(monkeypatch):
    """The list of the kernel's steps."""
    return count_calls(monkeypatch, BatchLastTransfer, "step")


def _random_transfer(n, m, mS, M, batch, steps, seed, dtype=D, **options):
    imm, belief0, y = _random_imm(n, m, M, batch, steps, seed, dtype=dtype)
    g = torch.Generator().manual_seed(seed + 100)
    H_S = torch.randn(mS, n, generator=g, dtype=D).to(dtype)
    R_S = torch.diag(0.2 + torch.rand(mS, generator=g, dtype=D)).to(dtype)
    ys = (2 * torch.randn(steps, *batch, mS, generator=g, dtype=D)).to(dtype)
    ys[torch.rand(steps, *batch, generator=g) < 0.4] = float("nan")  # gamma_k = 0
    if mS > 1:
        ys[..., 0][torch.rand(steps, *batch, generator=g) < 0.2] = float("nan")  # partly present
    tf = TransferIMM(imm.bank.filter, imm.transition.matrix(), LinearMeasurement(H_S, R_S), **options)
    return tf, belief0, MultiRate(y, ys)


def _close(got, want, tol=1e-9):
    for name in FIELDS:
        a, b = getattr(got, name), getattr(want, name)
        if a is None or b is None:
            assert a is None and b is None, name
            continue
        for x, y in zip(torch.utils._pytree.tree_leaves(a), torch.utils._pytree.tree_leaves(b)):
            assert x.shape == y.shape and x.dtype == y.dtype, name
            torch.testing.assert_close(x, y, rtol=tol, atol=tol, equal_nan=True)


GATES = {"IMM-TF": None, "IF-TF": InfluenceGate(), "IF-TF mode 1": InfluenceGate(threshold=0.5, mode=1),
         "IF-TF process": InfluenceGate(weight="process", mode=1)}


@pytest.mark.parametrize("reference", ["combined", "mixed"])
@pytest.mark.parametrize("likelihood", ["prior", "corrected"])
@pytest.mark.parametrize("n,m,mS,M", [(1, 1, 1, 2), (2, 1, 1, 3), (2, 2, 2, 2), (2, 1, 2, 4), (3, 2, 1, 2),
                                       (4, 2, 2, 3)])
@pytest.mark.parametrize("gate", list(GATES))
def test_equals_the_eager_steps(reference, likelihood, n, m, mS, M, gate, transfer_steps):
    tf, belief0, z = _random_transfer(n, m, mS, M, (6,), steps=14, seed=7 * n + 3 * m + mS + M,
                                      smoothing_reference=reference, mode_likelihood=likelihood, gate=GATES[gate])
    got = run_filter(tf, belief0, z)  # the default takes it, the full record included
    assert len(transfer_steps) == 14
    assert_same_trajectory(got, run_filter(tf, belief0, z, fast_path=False), tol=1e-9)
    if GATES[gate] is not None:  # the gate chose: some present source data not used
        assert bool((got.extras["source_present"] & ~got.extras["transfer_used"]).any())
    _close(run_filter(tf, belief0, z, record="estimate"), run_filter(tf, belief0, z, record="estimate", fast_path=False))
    keep = Keep(*FIELDS)
    _close(run_filter(tf, belief0, z, record=keep), run_filter(tf, belief0, z, record=keep, fast_path=False))
    assert len(transfer_steps) == 42


def test_the_paper_scenario_and_batch_shapes(transfer_steps):
    kf, P, source, prior, z, _ = paper_setup(runs=6, steps=30)
    tf = TransferIMM(kf, P, source)
    belief0 = tf.initial_belief(prior)
    want = run_filter(tf, belief0, z, record="estimate", fast_path=False)
    _close(run_filter(tf, belief0, z, record="estimate"), want)
    for batch in ((), (2, 3)):
        tf, belief0, z = _random_transfer(2, 1, 1, 3, batch, steps=8, seed=len(batch))
        _close(run_filter(tf, belief0, z, record="estimate"),
               run_filter(tf, belief0, z, record="estimate", fast_path=False))
    assert len(transfer_steps) == 30 + 16


@pytest.mark.parametrize("likelihood", ["prior", "corrected"])
@pytest.mark.parametrize("n,m,mS,M", [(2, 1, 1, 3), (3, 2, 2, 2)])
def test_a_rejected_transfer_is_the_imm_step(likelihood, n, m, mS, M, transfer_steps):
    """The kernel's IF-TF: a gate that rejects every transfer gives the plain IMM (the corrected mode
    likelihoods included), and a gate that rejects some gives, step by step, the IMM-TF step where the
    transfer is used and the IMM step elsewhere (tests/multimodel/test_transfer.py)."""
    tf, belief0, z = _random_transfer(n, m, mS, M, (6,), steps=14, seed=5 * n + M, mode_likelihood=likelihood)
    never = TransferIMM(tf.bank.filter, tf.transition.matrix(), tf.source, mode_likelihood=likelihood,
                        gate=InfluenceGate(threshold=-1e300))
    got = run_filter(never, belief0, z)
    assert len(transfer_steps) == 14 and not bool(got.extras["transfer_used"].any())
    imm = IMM(tf.bank.filter, tf.transition.matrix())
    want = run_filter(imm, belief0, z.target, fast_path=False)
    for a, b in [(got.estimate().mean, want.estimate().mean), (got.log_likelihood, want.log_likelihood),
                 (got.belief.mode_log_probs, want.belief.mode_log_probs)]:
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
    gated = TransferIMM(tf.bank.filter, tf.transition.matrix(), tf.source, mode_likelihood=likelihood,
                        gate=InfluenceGate())
    got = run_filter(gated, belief0, z)
    assert len(transfer_steps) == 28
    used, present = got.extras["transfer_used"], got.extras["source_present"]
    assert bool(used.any()) and bool((present & ~used).any())
    assert_gated_steps(got, gated, belief0, z, tol=1e-9)


def test_float32_and_gradients(transfer_steps):
    tf32, b32, z32 = _random_transfer(2, 1, 1, 3, (5,), steps=10, seed=4, dtype=torch.float32)
    got = run_filter(tf32, b32, z32, record="estimate")
    assert got.belief.mean.dtype == torch.float32
    _close(got, run_filter(tf32, b32, z32, record="estimate", fast_path=False), tol=2e-4)

    def grads(fast):
        tf, belief0, z = _random_transfer(2, 1, 1, 3, (5,), steps=10, seed=4)
        y = z.target.clone().requires_grad_(True)
        out = run_filter(tf, belief0, MultiRate(y, z.source), record="estimate", fast_path=fast)
        return torch.autograd.grad(out.log_likelihood.sum() + out.belief.mean.sum(), y)[0]

    fast, slow = grads(True), grads(False)
    assert bool(fast.ne(0).any())
    torch.testing.assert_close(fast, slow, rtol=1e-9, atol=1e-9)


def test_no_host_reads_in_the_steps(transfer_steps):
    tf, belief0, z = _random_transfer(2, 2, 2, 3, (4,), steps=6, seed=3)
    request = kernels.Request(estimate=True, keep=frozenset({"belief", "log_likelihood"}))
    run = TRANSFER.plan(tf, belief0, z, request)
    with no_host_sync("the IMM-TF kernel"):
        fields = run()
    torch.testing.assert_close(fields[2], run_filter(tf, belief0, z, record="estimate").log_likelihood, rtol=0, atol=0)


@pytest.mark.parametrize("n,gate", [(7, "IMM-TF"), (8, "IF-TF")])
def test_larger_states_from_a_large_batch(n, gate, transfer_steps):
    """States of MAX_STATE + 1 to LARGE_STATE components take the kernel (registered apart, as
    ``"batch_last_transfer_large"``, chosen by the batch size: studies switch it off) from LARGE_BATCH
    runs x modes, equal to the eager steps; below that batch, and beyond LARGE_STATE, the eager steps."""
    M = 2
    runs = LARGE_BATCH // M
    tf, belief0, z = _random_transfer(n, 2, 1, M, (runs,), steps=4, seed=n, gate=GATES[gate])
    got = run_filter(tf, belief0, z)
    assert len(transfer_steps) == 4
    assert_same_trajectory(got, run_filter(tf, belief0, z, fast_path=False), tol=1e-9)
    assert "batch_last_transfer_large" in kernels.by_size()
    small, small0, zs = _random_transfer(n, 2, 1, M, (runs - 1,), steps=2, seed=n)
    assert "small batch" in TRANSFER_LARGE.plan(small, small0, zs, kernels.Request())
    big, big0, zbig = _random_transfer(LARGE_STATE + 1, 1, 1, M, (runs,), steps=2, seed=n)
    assert f"a state of {LARGE_STATE + 1} components" in TRANSFER_LARGE.plan(big, big0, zbig, kernels.Request())
    assert "states of" in TRANSFER_LARGE.plan(*_random_transfer(2, 1, 1, M, (runs,), steps=2, seed=n)[:3],
                                              kernels.Request())
    run_filter(small, small0, zs)
    assert len(transfer_steps) == 4


def test_declines_what_it_does_not_compute(transfer_steps):
    tf, belief0, z = _random_transfer(2, 2, 2, 2, (3,), steps=5, seed=1)
    estimate = kernels.Request(estimate=True, keep=frozenset({"belief", "log_likelihood"}))
    kf = tf.bank.filter
    singular = KalmanFilter(LinearMotion(kf.motion.F, torch.zeros_like(kf.motion.Q), kf.motion.offset), kf.measurement)
    with pytest.raises(ValueError, match="gate.weight: process needs a non-singular process noise"):  # at once
        TransferIMM(singular, tf.transition.matrix(), tf.source, gate=InfluenceGate(weight="process"))
    full = tf.source.R.clone()
    full[0, 1] = full[1, 0] = 0.1
    other = TransferIMM(tf.bank.filter, tf.transition.matrix(), LinearMeasurement(tf.source.H, full))
    big, big0, zbig = _random_transfer(7, 1, 1, 2, (3,), steps=5, seed=2)

    class _Mine(TransferIMM):
        def step(self, belief, z, **inputs):
            return super().step(belief, z, **inputs)

    mine = _Mine(tf.bank.filter, tf.transition.matrix(), tf.source)
    cases = [("R is not diagonal", other, belief0, z, estimate),
             ("a state of 7 components", big, big0, zbig, estimate),
             ("_Mine has not joined", mine, belief0, z, estimate),
             ("update_first", tf, belief0, z, kernels.Request(update_first=True, estimate=True)),
             ("no compiled step", tf, belief0, z, kernels.Request(compile_required=True, estimate=True))]
    for reason, filt, b0, data, request in cases:
        assert reason in TRANSFER.plan(filt, b0, data, request)
    run_filter(mine, belief0, z)  # the eager steps
    assert not transfer_steps
    with pytest.raises(ValueError, match="compile: compiles the fast path"):
        run_filter(tf, belief0, z, record="estimate", compile=True)

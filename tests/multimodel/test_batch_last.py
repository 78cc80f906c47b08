"""The batch-last kernel (torchmm/kernels/batch_last/imm.py, ``BATCH_LAST`` behind the seam
:mod:`torchmm.kernels`): run_filter's IMM (and GPB1) over linear Kalman modes in the batch-last layout
returns what the batch-first steps return - every Trajectory field, for random banks of every small
size, per-mode and shared parameters, exact zeros and ones, missing components, batch shapes (),
(B,) and (B1, B2), float32, gradients, record="estimate", compiled - and it is taken only where it
applies.

run_filter tries the small linear-Gaussian kernel (torchmm/kernels/linear.py) first, which takes runs
of these tests' sizes; here it declines (the ``batch_last_steps`` fixture), so that the batch-last
kernel runs, and the tests count its steps to make sure it did."""

from __future__ import annotations

import itertools
import logging

import pytest
import torch
import torch.utils._pytree as pytree

from torchmm import (
    GPB1,
    IMM,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    LinearMotion,
    PositionMeasurement,
    kernels,
    run_filter,
)
from torchmm.filters import ExtendedKalmanFilter
from torchmm.kernels import linear
from torchmm.multimodel import StaticMM
from torchmm.kernels.batch_last.imm import BATCH_LAST, BatchLastIMM

D = torch.float64


def _random_imm(n, m, M, batch, steps, seed, dtype=D, shared=False):
    """A random IMM over linear Kalman modes, its initial belief and measurements with 20 % of the
    components missing. ``shared``: F, H and R the same in every mode (no mode axis), with exact
    zeros and ones in F and H (the kernel's scalar and skipped coefficients)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g, dtype=D)  # noqa: E731
    A = r(M, n, n)
    Q = 0.2 * A @ A.mT + 0.05 * torch.eye(n, dtype=D)
    offset = 0.5 * r(M, n)
    if shared:
        F = torch.eye(n, dtype=D) + torch.triu(torch.full((n, n), 0.5, dtype=D), 1)  # CV-like: 0, 1, 0.5
        H = torch.zeros(m, n, dtype=D)
        H[torch.arange(m), torch.arange(m)] = 1.0
        R = torch.diag(0.5 + torch.rand(m, generator=g, dtype=D))
    else:
        F = torch.eye(n, dtype=D) + 0.3 * r(M, n, n)
        H = r(M, m, n)
        R = torch.diag_embed(0.5 + torch.rand(M, m, generator=g, dtype=D))
    stay = 0.6 + 0.3 * torch.rand(M, generator=g, dtype=D)
    P = (1 - stay).unsqueeze(-1) / max(M - 1, 1) * (1 - torch.eye(M, dtype=D)) + torch.diag(stay) if M > 1 \
        else torch.ones(1, 1, dtype=D)
    imm = IMM(KalmanFilter(LinearMotion(F.to(dtype), Q.to(dtype), offset.to(dtype)),
                           LinearMeasurement(H.to(dtype), R.to(dtype))), P.to(dtype))
    B0 = r(*batch, n, n)
    prior = GaussianBelief(r(*batch, n).to(dtype), (B0 @ B0.mT + torch.eye(n, dtype=D)).to(dtype))
    mode_probs = torch.softmax(r(M), 0).to(dtype)
    z = (2 * r(steps, *batch, m)).to(dtype)
    z[torch.rand(steps, *batch, m, generator=g) < 0.2] = float("nan")  # missing components, some whole steps
    return imm, imm.initial_belief(prior, mode_probs), z


def _fields(traj):
    return [traj.belief, traj.prior, traj.log_likelihood, traj.innovation, traj.innovation_cov, traj.extras]


def assert_same_trajectory(got, want, tol=1e-10):
    """Every field of two trajectories: the same structure, shapes and dtypes, equal values (NaN
    where NaN: the innovations of missing components), equal flags."""
    got_leaves, got_spec = pytree.tree_flatten(_fields(got))
    want_leaves, want_spec = pytree.tree_flatten(_fields(want))
    assert got_spec == want_spec
    for a, b in zip(got_leaves, want_leaves):
        if a is None or b is None:
            assert a is None and b is None
            continue
        assert a.shape == b.shape and a.dtype == b.dtype
        if a.dtype == torch.bool:
            assert torch.equal(a, b)
        else:
            torch.testing.assert_close(a, b, rtol=tol, atol=tol, equal_nan=True)


_LINEAR_PLAN = linear.LinearKernel.plan


@pytest.fixture(autouse=True)
def batch_last_steps(monkeypatch):
    """Every test here runs the batch-last kernel: the small linear kernel, which run_filter tries
    first (and which ``fast_path=True`` takes at any size), declines; the list of the
    :meth:`BatchLastIMM.step` calls (one per step the kernel ran) is the fixture's value."""
    monkeypatch.setattr(linear.LinearKernel, "plan",
                        lambda self, *args: "declined in tests/multimodel/test_batch_last.py")
    return count_calls(monkeypatch, BatchLastIMM, "step")


def count_calls(monkeypatch, cls: type, name: str) -> list:
    """Wrap the method ``cls.name`` (for the test) so that every call appends its instance to the
    returned list."""
    calls = []
    original = getattr(cls, name)

    def counted(self, *args, **kwargs):
        calls.append(self)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(cls, name, counted)
    return calls


def _plan(filt, belief0, z, **request):
    """The batch-last kernel's plan for this run (a callable with ``.kernel``, or the reason)."""
    return BATCH_LAST.plan(filt, belief0, z, kernels.Request(**request))


@pytest.fixture(params=["broadcast", "entries"])
def layout(request, monkeypatch):
    """Both layouts of the kernel's state: every entry in one broadcast operation (small batches,
    as these tests' own) and one operation per stored entry (large batches)."""
    from torchmm.kernels.batch_last import imm as batch_last

    monkeypatch.setattr(batch_last, "_BROADCAST_BYTES", 1 << 62 if request.param == "broadcast" else 0)
    return request.param


SIZES = [(n, m, M) for n, m, M in itertools.product([1, 2, 3, 4], [1, 2, 3], [1, 2, 3]) if m <= n]


@pytest.mark.parametrize("n,m,M", SIZES)
def test_every_field_equals_the_batch_first_steps(n, m, M, layout, batch_last_steps):
    imm, belief0, z = _random_imm(n, m, M, (7,), steps=12, seed=10 * n + 3 * m + M)
    assert run_filter(imm, belief0, z, fast_path=True) is not None  # the fast path applies
    assert len(batch_last_steps) == 12
    got = run_filter(imm, belief0, z)  # the default takes it
    assert len(batch_last_steps) == 24
    assert_same_trajectory(got, run_filter(imm, belief0, z, fast_path=False))
    assert len(batch_last_steps) == 24


@pytest.mark.parametrize("n,m,M", [(1, 1, 2), (2, 1, 3), (3, 2, 2), (4, 2, 3)])
@pytest.mark.parametrize("shared", [False, True])
def test_gpb1_every_field_equals_the_batch_first_steps(n, m, M, shared, layout, batch_last_steps):
    """GPB1 (every mode starts from the one collapsed posterior) takes the same kernel."""
    imm, belief0, z = _random_imm(n, m, M, (6,), steps=10, seed=5 * n + m + M, shared=shared)
    gpb1 = GPB1(imm.bank.filter, imm.transition.matrix())
    run = _plan(gpb1, belief0, z)
    assert callable(run) and run.kernel.collapse
    got = run_filter(gpb1, belief0, z, fast_path=True)
    assert len(batch_last_steps) == 10 and all(k.collapse for k in batch_last_steps)
    assert_same_trajectory(got, run_filter(gpb1, belief0, z, fast_path=False))
    assert got.extras["mixed"].components.mean.shape == (10, 6, M, n)


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
@pytest.mark.parametrize("shared", [False, True])
def test_batch_shapes_and_structured_models(batch, shared, layout, batch_last_steps):
    imm, belief0, z = _random_imm(3, 2, 3, batch, steps=10, seed=len(batch) + 7 * shared, shared=shared)
    got = run_filter(imm, belief0, z, fast_path=True)
    assert len(batch_last_steps) == 10
    assert_same_trajectory(got, run_filter(imm, belief0, z, fast_path=False))


def test_the_default_takes_it_and_record_sees_the_same_outputs(batch_last_steps):
    imm, belief0, z = _random_imm(2, 1, 3, (6,), steps=9, seed=3)
    seen = []

    def record(out):  # drops the prior and the extras: the kernel stops building them after step 0
        seen.append(out)
        return out._replace(prior=None, extras=None)

    got = run_filter(imm, belief0, z, record=record)
    assert len(batch_last_steps) == 9
    want = run_filter(imm, belief0, z, record=record, fast_path=False)
    assert_same_trajectory(got, want)
    assert got.prior is None and got.extras is None
    assert seen[0].belief.components.mean.stride()[-1] != 1  # the fast path ran: batch-last memory


def _memory_order_view(t) -> bool:
    """``t`` is a permuted view of contiguous memory (no gaps, no broadcast axes)."""
    order = sorted(range(t.dim()), key=lambda i: -t.stride()[i])
    return t.permute(order).is_contiguous()


def test_the_plan_runs_the_whole_trajectory_as_batch_first_views_in_memory_order(layout, batch_last_steps):
    """``BATCH_LAST.plan(...)()`` (what run_filter stacks into its Trajectory) gives the six fields,
    batch-first (time, *B, ...), each stacked in its memory order (no transposing copy: the full record
    costs what the estimates cost), and equal to the eager steps'."""
    imm, belief0, z = _random_imm(3, 2, 3, (2, 3), steps=5, seed=12)
    fields = _plan(imm, belief0, z)()
    assert len(fields) == 6 and len(batch_last_steps) == 5
    want = run_filter(imm, belief0, z, fast_path=False)
    for got, ref in zip(pytree.tree_leaves(fields), pytree.tree_leaves(_fields(want)), strict=True):
        assert got.shape == ref.shape and _memory_order_view(got)
    got = run_filter(imm, belief0, z)
    assert len(batch_last_steps) == 10
    assert_same_trajectory(got, want)
    assert any(not t.is_contiguous() for t in pytree.tree_leaves(_fields(got)))  # batch-last memory


def test_record_estimate(layout, batch_last_steps):
    imm, belief0, z = _random_imm(3, 2, 3, (8,), steps=10, seed=4)
    want = run_filter(imm, belief0, z, fast_path=False)
    for fast in (True, False):
        got = run_filter(imm, belief0, z, record="estimate", fast_path=fast)
        assert len(batch_last_steps) == 10 and all(k.estimate_only for k in batch_last_steps)
        assert isinstance(got.belief, GaussianBelief) and got.prior is None and got.extras is None
        torch.testing.assert_close(got.belief.mean, want.estimate().mean, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(got.belief.cov, want.estimate().cov, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=1e-10, atol=1e-10)
    with pytest.raises(ValueError, match="record: expected a callable, None or 'estimate'"):
        run_filter(imm, belief0, z, record="means")


def test_float32(batch_last_steps):
    imm64, b64, z64 = _random_imm(2, 1, 3, (9,), steps=15, seed=5)
    imm32, b32, z32 = _random_imm(2, 1, 3, (9,), steps=15, seed=5, dtype=torch.float32)
    got = run_filter(imm32, b32, z32, fast_path=True)
    assert len(batch_last_steps) == 15
    assert got.estimate().mean.dtype == torch.float32
    torch.testing.assert_close(got.estimate().mean.double(), run_filter(imm64, b64, z64).estimate().mean,
                               rtol=1e-4, atol=1e-4)
    assert_same_trajectory(got, run_filter(imm32, b32, z32, fast_path=False), tol=2e-4)


def test_missing_steps_have_zero_log_likelihood_and_keep_the_prediction(layout, batch_last_steps):
    imm, belief0, z = _random_imm(2, 2, 2, (4,), steps=6, seed=6)
    z[2] = float("nan")  # no datum at step 2
    got = run_filter(imm, belief0, z, fast_path=True)
    assert len(batch_last_steps) == 6
    assert torch.equal(got.log_likelihood[2], torch.zeros(4, dtype=D))
    torch.testing.assert_close(got.belief.components.mean[2], got.prior.components.mean[2], rtol=0, atol=0)


def test_singular_innovation_is_flagged_as_the_engine_does(caplog, batch_last_steps):
    motion = LinearMotion(torch.eye(2, dtype=D), torch.zeros(2, 2, dtype=D))
    sensor = LinearMeasurement(torch.tensor([[1.0, 0.0]], dtype=D), torch.zeros(1, 1, dtype=D))
    imm = IMM(KalmanFilter(motion, sensor), torch.full((2, 2), 0.5, dtype=D))
    belief0 = imm.initial_belief(GaussianBelief(torch.zeros(3, 2, dtype=D), torch.diag(torch.tensor([0.0, 1.0],
                                                                                                    dtype=D))))
    z = torch.zeros(2, 3, 1, dtype=D)  # (z = 1 gives log-likelihoods near -1e307, where the batch-first
    # steps' logsumexp absorbs the log 2 of two equal modes: probabilities (1, 1) there, (0.5, 0.5) here)
    with caplog.at_level(logging.WARNING, logger="torchmm"):
        got = run_filter(imm, belief0, z, fast_path=True)
    assert len(batch_last_steps) == 2
    want = run_filter(imm, belief0, z, fast_path=False)
    assert bool(got.extras["modes"]["singular"].all())
    assert_same_trajectory(got, want)
    assert "not numerically positive definite" in caplog.text


def test_gradients_equal_the_batch_first_steps(layout, batch_last_steps):
    def loss(fast, F, q):
        kf = KalmanFilter(LinearMotion(F, q * torch.eye(2, dtype=D)), PositionMeasurement(2, [0], 1.0, dtype=D))
        imm = IMM(kf, torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=D))
        belief0 = imm.initial_belief(GaussianBelief(torch.zeros(5, 2, dtype=D), torch.eye(2, dtype=D)))
        z = torch.linspace(-1, 2, 40, dtype=D).reshape(8, 5, 1)
        return -run_filter(imm, belief0, z, fast_path=fast).total_log_likelihood().sum()

    grads = []
    for fast in (True, False):
        F = torch.tensor([[[1.0, 1.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 0.5]]], dtype=D, requires_grad=True)
        q = torch.tensor(0.3, dtype=D, requires_grad=True)
        grads.append(torch.autograd.grad(loss(fast, F, q), (F, q)))
        assert len(batch_last_steps) == 8  # (the fast run's steps only)
    for a, b in zip(*grads):  # the zero entries of F keep their gradients (no skipped terms under autograd)
        assert bool(a.ne(0).any())
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


def test_compiled_equals_eager(layout, batch_last_steps):
    imm, belief0, z = _random_imm(2, 1, 3, (6,), steps=8, seed=8)
    got = run_filter(imm, belief0, z, compile=True)
    assert len(batch_last_steps) == 8 and batch_last_steps[0]._compiled
    assert_same_trajectory(got, run_filter(imm, belief0, z, fast_path=False), tol=1e-9)
    est = run_filter(imm, belief0, z, compile=True, record="estimate")
    torch.testing.assert_close(est.belief.mean, got.estimate().mean, rtol=1e-9, atol=1e-9)


def _list_bank(imm):
    """A list bank of two Kalman filters with different (non-stackable) options: not the vectorised bank."""
    kf = imm.bank.filter
    return [KalmanFilter(LinearMotion(kf.motion.F[j], kf.motion.Q[j], kf.motion.offset[j]),
                         LinearMeasurement(kf.measurement.H[j], kf.measurement.R[j]), joseph=bool(j))
            for j in range(2)]


class _MyIMM(IMM):
    """A subclass that overrides a step has left the kernel family: it runs the batch-first steps."""

    def step(self, belief, z, **inputs):
        return super().step(belief, z, **inputs)


class _PlainIMM(IMM):
    """A subclass that keeps the steps stays in the family: it takes the kernel."""


class _Shifted(LinearMotion):
    def forward(self, x, *, u=None):  # not F x + b: the fast path must not take it
        return super().forward(x, u=u) + 1.0


def test_taken_only_where_it_applies(batch_last_steps):
    imm, belief0, z = _random_imm(2, 2, 2, (3,), steps=4, seed=1)
    kf = imm.bank.filter
    full = kf.measurement.R.clone()
    full[:, 0, 1] = full[:, 1, 0] = 0.1
    cases = {
        "R is not diagonal": IMM(KalmanFilter(kf.motion, LinearMeasurement(kf.measurement.H, full)),
                                 imm.transition.matrix()),
        "_MyIMM has not joined the linear_gaussian kernels": _MyIMM(kf, imm.transition.matrix()),
        "the 'static' rule": StaticMM(kf, 2),
        "mode 1: the Joseph form": IMM(_list_bank(imm), imm.transition.matrix()),
        "the Joseph form": IMM(KalmanFilter(kf.motion, kf.measurement, joseph=True), imm.transition.matrix()),
        "not a LinearMotion": IMM(KalmanFilter(_Shifted(kf.motion.F, kf.motion.Q, kf.motion.offset), kf.measurement),
                                  imm.transition.matrix()),
    }
    for reason, filt in cases.items():
        assert reason in _plan(filt, belief0, z)  # the batch-last kernel's own reason
        with pytest.raises(ValueError, match=f"fast_path: no fast path for this run .*batch_last: .*{reason}"):
            run_filter(filt, belief0, z, fast_path=True)
        with pytest.raises(ValueError, match="compile: compiles the fast path"):
            run_filter(filt, belief0, z, compile=True)
        assert_same_trajectory(run_filter(filt, belief0, z), run_filter(filt, belief0, z, fast_path=False))
        assert not batch_last_steps, reason  # the batch-first steps ran
    # an extended bank: not this kernel's (the nonlinear banks' kernel takes it, batch_last_nonlinear.py)
    extended = IMM(ExtendedKalmanFilter(kf.motion, kf.measurement), imm.transition.matrix())
    assert "ExtendedKalmanFilter is not linear-Gaussian" in _plan(extended, belief0, z)
    assert_same_trajectory(run_filter(extended, belief0, z, fast_path=True),
                           run_filter(extended, belief0, z, fast_path=False))
    assert batch_last_steps and all(type(k).__name__ == "BatchLastNonlinear" for k in batch_last_steps)
    batch_last_steps.clear()
    plain = _PlainIMM(kf, imm.transition.matrix())
    assert_same_trajectory(run_filter(plain, belief0, z, fast_path=True), run_filter(imm, belief0, z, fast_path=False))
    assert len(batch_last_steps) == 4
    with pytest.raises(ValueError, match="fast_path: no fast path .*batch_last: update_first"):
        run_filter(imm, belief0, z, fast_path=True, update_first=True)
    with pytest.raises(ValueError, match="fast_path: no fast path .*per-step models"):
        run_filter(imm, belief0, z, fast_path=True, motions=[kf.motion] * 4)
    with pytest.raises(ValueError, match="measurements' dtype"):
        run_filter(imm, belief0, z.float(), fast_path=True)
    assert _plan(imm, belief0, z.to("meta")) == "the measurements' device differs from belief0's"
    assert len(batch_last_steps) == 4
    with pytest.raises(ValueError, match="compile: compiles the fast path, and fast_path=False"):
        run_filter(imm, belief0, z, fast_path=False, compile=True)
    with pytest.raises(TypeError, match="fast_path: expected None, True or False"):
        run_filter(imm, belief0, z, fast_path="yes")


def test_constant_velocity_bank_of_the_benchmarks(batch_last_steps):
    """Paper 000's IMM (ConstantVelocity acceleration modes: shared F, per-mode offsets)."""
    motion = ConstantVelocity(1, q=1.0, acceleration=torch.tensor([[0.25], [0.0], [-0.25]], dtype=D), dtype=D)
    imm = IMM(KalmanFilter(motion, PositionMeasurement(2, [0], torch.tensor(100.0, dtype=D), dtype=D)),
              torch.tensor([[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.25, 0.25, 0.5]], dtype=D))
    belief0 = imm.initial_belief(GaussianBelief(torch.tensor([10.0, 10.0], dtype=D),
                                                torch.tensor([[100.0, 1.0], [1.0, 100.0]], dtype=D)).expand(11))
    z = 10 * torch.randn(40, 11, 1, generator=torch.Generator().manual_seed(0), dtype=D)
    got = run_filter(imm, belief0, z, fast_path=True)
    assert len(batch_last_steps) == 40
    assert_same_trajectory(got, run_filter(imm, belief0, z, fast_path=False))


def test_process_default_of_compile():
    from torchmm.runtime import compile_fast_paths, fast_paths_compiled

    imm, belief0, z = _random_imm(2, 1, 2, (3,), steps=4, seed=2)
    previous = compile_fast_paths(True)
    try:
        assert fast_paths_compiled()
        gpb = StaticMM(imm.bank.filter, 2)  # no fast path: runs its steps, no error
        assert_same_trajectory(run_filter(gpb, belief0, z), run_filter(gpb, belief0, z, compile=False))
        with pytest.raises(ValueError, match="compile: compiles the fast path, which this run has not"):
            run_filter(gpb, belief0, z, compile=True)  # asked for explicitly: an error
    finally:
        compile_fast_paths(previous)
    with pytest.raises(TypeError, match="enabled: expected True or False"):
        compile_fast_paths("yes")
    with pytest.raises(TypeError, match="compile: expected None, True or False"):
        run_filter(imm, belief0, z, compile="yes")


def test_a_compiler_failure_runs_eagerly_with_a_warning(monkeypatch, caplog, batch_last_steps):
    """A machine without a working compiler (inductor needs a C++ compiler on the CPU): compile=True
    warns once and gives the eager numbers instead of aborting the run."""
    def broken(fn, **kwargs):
        def fail(*args, **kw):
            raise RuntimeError("no C++ compiler found")
        return fail

    monkeypatch.setattr(torch, "compile", broken)
    imm, belief0, z = _random_imm(2, 1, 2, (4,), steps=5, seed=9)
    with caplog.at_level(logging.WARNING, logger="torchmm"):
        got = run_filter(imm, belief0, z, compile=True)
    assert len(batch_last_steps) == 5 and not batch_last_steps[0]._compiled  # the kernel ran, eagerly
    assert caplog.text.count("torch.compile failed for the IMM fast path (RuntimeError: no C++ compiler") == 1
    assert_same_trajectory(got, run_filter(imm, belief0, z))


def test_the_layout_follows_the_batch_size(monkeypatch, batch_last_steps):
    """Broadcast operations over every entry while the mixing's temporaries stay small (dispatch
    bound), one operation per entry beyond (memory bound); both give the same numbers. Runs beyond
    the small linear kernel's size take the batch-last kernel by default."""
    monkeypatch.setattr(linear.LinearKernel, "plan", _LINEAR_PLAN)  # (the real one: it declines by size)
    imm, belief0, z = _random_imm(2, 1, 3, (400,), steps=3, seed=11)
    assert _plan(imm, belief0, z).kernel.broadcast
    big, big0, zbig = _random_imm(2, 1, 3, (4000,), steps=3, seed=11)
    assert not _plan(big, big0, zbig).kernel.broadcast
    assert 4000 > linear.MAX_RUNS
    got = run_filter(big, big0, zbig)
    assert len(batch_last_steps) == 3 and not batch_last_steps[0].broadcast
    assert_same_trajectory(got, run_filter(big, big0, zbig, fast_path=False))


@pytest.fixture
def trace_cache(monkeypatch):
    """An empty cache of traced steps for the test, and a way to set the tracing threshold."""
    from torchmm.kernels.batch_last import traced as batch_last

    monkeypatch.setattr(batch_last, "_TRACED", batch_last.OrderedDict())
    monkeypatch.setattr(batch_last, "_STEPS_SEEN", {})

    def after(steps):
        monkeypatch.setattr(batch_last, "_TRACE_AFTER", steps)

    return batch_last, after


def _leaves(traj):
    return pytree.tree_leaves(_fields(traj))


def _assert_identical(got, want):
    """Bit for bit: the same leaves, shapes, dtypes and values (NaN where NaN)."""
    a, b = _leaves(got), _leaves(want)
    assert len(a) == len(b)
    for x, y in zip(a, b):
        if x is None or y is None:
            assert x is None and y is None
            continue
        assert x.shape == y.shape and x.dtype == y.dtype
        assert torch.equal(x, y) or (x.is_floating_point() and torch.equal(x.isnan(), y.isnan())
                                     and torch.equal(x.nan_to_num(0.0), y.nan_to_num(0.0)))


@pytest.mark.parametrize("n,m,M,gpb", [(2, 1, 3, False), (3, 2, 2, False), (1, 1, 1, False), (4, 3, 3, False),
                                       (2, 2, 3, True)])
def test_the_traced_step_gives_the_same_numbers_bit_for_bit(n, m, M, gpb, layout, trace_cache):
    batch_last, after = trace_cache
    imm, belief0, z = _random_imm(n, m, M, (5,), steps=9, seed=20 + n + m + M, shared=n == 2)
    if gpb:
        imm = GPB1(imm.bank.filter, imm.transition.matrix())
    for record in (None, "estimate", lambda out: out._replace(prior=None, innovation_cov=None)):
        after(10**12)
        want = run_filter(imm, belief0, z, record=record)
        assert not batch_last._TRACED
        after(0)
        got = run_filter(imm, belief0, z, record=record)
        assert batch_last._TRACED  # traced, and run
        _assert_identical(got, want)
        batch_last._TRACED.clear()


def test_a_cached_graph_reads_each_kernels_own_constants(trace_cache):
    """Two IMMs of one structure (the same kinds of entries) but other numbers share the graph; each
    gets its own numbers (a graph with the first one's constants baked in would give the first's)."""
    batch_last, after = trace_cache
    after(0)
    first, belief0, z = _random_imm(2, 1, 3, (4,), steps=6, seed=1)
    second, belief1, z1 = _random_imm(2, 1, 3, (4,), steps=6, seed=2)
    run_filter(first, belief0, z)
    assert len(batch_last._TRACED) == 1
    got = run_filter(second, belief1, z1)
    assert len(batch_last._TRACED) == 1  # the same structure: the cached graph
    assert_same_trajectory(got, run_filter(second, belief1, z1, fast_path=False))
    with pytest.raises(AssertionError):
        assert_same_trajectory(got, run_filter(first, belief0, z1, fast_path=False))


def test_steps_are_traced_after_the_threshold_and_the_cache_is_bounded(trace_cache, monkeypatch):
    batch_last, after = trace_cache
    after(25)
    imm, belief0, z = _random_imm(2, 1, 2, (3,), steps=10, seed=4)
    for calls in (1, 2):  # untraced until 25 steps of the structure have run
        run_filter(imm, belief0, z)
        assert not batch_last._TRACED, calls
    run_filter(imm, belief0, z)  # 30 steps of this structure
    assert len(batch_last._TRACED) == 1
    kernel = _plan(imm, belief0, z).kernel
    assert kernel._core != kernel.core  # the next kernel starts traced
    monkeypatch.setattr(batch_last, "_TRACED_MAX", 2)
    after(0)
    for M in (1, 3, 4):
        other, b, zz = _random_imm(2, 1, M, (3,), steps=3, seed=M)
        run_filter(other, b, zz)
    assert len(batch_last._TRACED) == 2  # the least recently used dropped


def test_gradients_through_the_traced_step(trace_cache):
    batch_last, after = trace_cache

    def grads():
        F = torch.tensor([[[1.0, 1.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 0.5]]], dtype=D, requires_grad=True)
        kf = KalmanFilter(LinearMotion(F, 0.3 * torch.eye(2, dtype=D)), PositionMeasurement(2, [0], 1.0, dtype=D))
        imm = IMM(kf, torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=D))
        belief0 = imm.initial_belief(GaussianBelief(torch.zeros(5, 2, dtype=D), torch.eye(2, dtype=D)))
        z = torch.linspace(-1, 2, 40, dtype=D).reshape(8, 5, 1)
        return torch.autograd.grad(run_filter(imm, belief0, z).total_log_likelihood().sum(), F)[0]

    after(10**12)
    want = grads()
    after(0)
    got = grads()
    assert batch_last._TRACED
    assert bool(got.ne(0).any()) and torch.equal(got, want)


def test_a_constant_left_out_of_the_graphs_inputs_is_caught(trace_cache, monkeypatch):
    """A tensor the step reads besides its inputs would be baked into a cached graph (and silently
    used by every other kernel of the structure): tracing refuses it."""
    batch_last, _ = trace_cache
    monkeypatch.setattr(batch_last, "_CONSTANTS", tuple(c for c in batch_last._CONSTANTS if c != "zero"))
    imm, belief0, z = _random_imm(2, 1, 2, (3,), steps=3, seed=4)
    kernel = _plan(imm, belief0, z).kernel
    with pytest.raises(RuntimeError, match="holds tensors"):
        batch_last.trace(kernel)


@pytest.mark.parametrize("gpb,record", [(False, None), (False, "estimate"), (True, None)])
def test_the_compiled_step_is_one_graph(gpb, record, layout):
    """compile=True compiles the whole step, without a graph break (a `del` of a name that a
    comprehension reads once split it into eager-glued pieces: the compiled step ran slower than eager)."""
    import torch._dynamo

    imm, belief0, z = _random_imm(2, 1, 3, (6,), steps=3, seed=8)
    if gpb:
        imm = GPB1(imm.bank.filter, imm.transition.matrix())
    estimate = record == "estimate"  # (as run_filter asks for record="estimate")
    kernel = _plan(imm, belief0, z, estimate=estimate,
                   keep=frozenset({"belief", "log_likelihood"}) if estimate else None).kernel
    assert kernel.estimate_only == estimate
    assert kernel.omitted == (frozenset(["prior", "innovation", "innovation_cov", "extras"]) if estimate
                              else frozenset())
    torch._dynamo.reset()
    whole = torch.compile(kernel.core, fullgraph=True, backend="eager", dynamic=False)
    X, P, mu, _ = kernel.initial_state(belief0)
    want = kernel.core(X, P, mu, *kernel.data[0])
    got = whole(X, P, mu, *kernel.data[0])  # raises at a graph break
    for a, b in zip(pytree.tree_leaves(got), pytree.tree_leaves(want)):
        assert (a is None and b is None) or torch.equal(a, b)

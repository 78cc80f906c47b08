"""The batch-last kernel of the IMM, GPB1 and variable-structure IMM over extended and unscented Kalman
banks (torchmm/kernels/batch_last/nonlinear.py, registered as ``"batch_last_nonlinear"``): run_filter returns
what the eager steps return - every field of the full record, the estimates and ``Keep`` records - for the
coordinated turn with a range-bearing sensor (models that declare their Jacobians' exact zeros), for
learned models through the default entry hooks (autograd Jacobians, m = 1 and m = 3), with missing
components and whole steps, batch shapes, sigma-point factors that fail (the eigen-factor on the CPU, the
pivot-clamped factor in the device form) and gradients; without a host read inside a step; it is taken
by default from ``MIN_BATCH`` runs x modes and declines where it does not apply."""

from __future__ import annotations

import pytest
import torch

from tests.multimodel.test_batch_last import assert_same_trajectory, count_calls
from tests.multimodel.test_batch_last_transfer import _close
from torchmm import (
    GPB1,
    IMM,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    NonlinearCoordinatedTurn,
    RangeBearing,
    UnscentedKalmanFilter,
    kernels,
    run_filter,
)
from torchmm.models import LearnedMeasurement, LearnedMotion
from torchmm.multimodel import VariableStructureIMM
from torchmm.kernels.batch_last.nonlinear import MIN_BATCH, NONLINEAR, BatchLastNonlinear
from torchmm.multimodel.mevsmm import ExactMinimumEntropy
from torchmm.run import Keep
from torchmm.runtime import no_host_sync

D = torch.float64
TRANSITION = [[0.9, 0.05, 0.05], [0.05, 0.9, 0.05], [0.05, 0.05, 0.9]]


@pytest.fixture(autouse=True)
def kernel_steps(monkeypatch):
    """The list of the kernel's steps."""
    return count_calls(monkeypatch, BatchLastNonlinear, "step")


def _filter(kind, motion, sensor):
    return ExtendedKalmanFilter(motion, sensor) if kind == "ekf" else UnscentedKalmanFilter(motion, sensor)


def _turn(kind, combinator=IMM, batch=(6,), steps=10, seed=0, dtype=D):
    """IMM (GPB1) over a coordinated-turn bank (three process noises) with a range-bearing sensor; data
    with missing components and whole steps."""
    g = torch.Generator().manual_seed(seed)
    modes = [NonlinearCoordinatedTurn(1.0, q, qw, dtype=dtype) for q, qw in ((0.01, 1e-8), (0.1, 1e-5), (1.0, 1e-3))]
    bank = NonlinearCoordinatedTurn(1.0, 0.01, 1e-8, dtype=dtype)
    bank.Q = torch.stack([m.Q for m in modes])
    sensor = RangeBearing(5, torch.diag(torch.tensor([100.0, 1e-4], dtype=dtype)), origin=(-2000.0, 0.0), dtype=dtype)
    mm = combinator(_filter(kind, bank, sensor), torch.tensor(TRANSITION, dtype=dtype))
    noise = lambda *shape: torch.randn(*shape, generator=g, dtype=D).to(dtype)  # noqa: E731
    mean = torch.tensor([1000.0, 10.0, 500.0, 5.0, 0.05], dtype=dtype) + noise(*batch, 5)
    prior = GaussianBelief(mean, torch.diag(torch.tensor([100.0, 4.0, 100.0, 4.0, 1e-3], dtype=dtype)))
    x = mean.clone()
    z = []
    for _ in range(steps):
        x = bank.forward_entries(list(x.unbind(-1)))
        x = torch.stack(x, -1) + 0.3 * noise(*batch, 5) * torch.tensor([1, 1, 1, 1, 0.01], dtype=dtype)
        z.append(sensor(x) + noise(*batch, 2) * torch.tensor([10.0, 1e-2], dtype=dtype))
    z = torch.stack(z)
    z[torch.rand(steps, *batch, 2, generator=g) < 0.15] = float("nan")  # missing components
    z[1, ..., 0, :] = float("nan")  # and whole steps
    return mm, mm.initial_belief(prior), z


def _learned(kind, m, batch=(5,), steps=8, seed=1):
    """IMM over a learned mode bank (a small network, learnable per-mode noise) and a learned sensor:
    the default entry hooks (autograd Jacobians, stacked calls)."""
    torch.manual_seed(seed)
    n = 3
    net = torch.nn.Sequential(torch.nn.Linear(n, 6), torch.nn.Tanh(), torch.nn.Linear(6, n)).to(D)
    Q = torch.stack([0.1 * torch.eye(n, dtype=D), 0.5 * torch.eye(n, dtype=D), torch.eye(n, dtype=D) + 0.2])
    motion = LearnedMotion(net, n, Q, noise="cholesky", residual=True)
    head = torch.nn.Sequential(torch.nn.Linear(n, m), torch.nn.Tanh()).to(D)
    sensor = LearnedMeasurement(head, n, m, R=0.05 * torch.eye(m, dtype=D) + 0.01, noise="cholesky")
    imm = IMM(_filter(kind, motion, sensor), torch.tensor(TRANSITION, dtype=D))
    g = torch.Generator().manual_seed(seed)
    prior = GaussianBelief(torch.randn(*batch, n, generator=g, dtype=D), 0.5 * torch.eye(n, dtype=D))
    z = 0.5 * torch.randn(steps, *batch, m, generator=g, dtype=D)
    z[torch.rand(steps, *batch, m, generator=g) < 0.2] = float("nan")
    return imm, imm.initial_belief(prior), z


@pytest.mark.parametrize("combinator", [IMM, GPB1], ids=["IMM", "GPB1"])
@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_the_turn_model_equals_the_eager_steps(kind, combinator, kernel_steps):
    mm, belief0, z = _turn(kind, combinator)
    assert torch.isnan(z).all(-1).any() and (torch.isnan(z).any(-1) & ~torch.isnan(z).all(-1)).any()
    got = run_filter(mm, belief0, z, fast_path=True)
    assert len(kernel_steps) == 10
    assert_same_trajectory(got, run_filter(mm, belief0, z, fast_path=False), tol=1e-8)
    _close(run_filter(mm, belief0, z, record="estimate", fast_path=True),
           run_filter(mm, belief0, z, record="estimate", fast_path=False))
    keep = Keep("belief", "log_likelihood", "innovation")
    _close(run_filter(mm, belief0, z, record=keep, fast_path=True),
           run_filter(mm, belief0, z, record=keep, fast_path=False))
    assert len(kernel_steps) == 30


@pytest.mark.parametrize("feedback", [True, False])
@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_the_variable_structure_imm_equals_the_eager_steps(kind, feedback, kernel_steps):
    """``VariableStructureIMM`` over extended and unscented modes: the kernel's IMM steps and the model-set
    policy after each (paper 003's minimum-entropy set; the modes' process noises differ, so no two
    candidate sets tie), every field, the extras in their order, and the estimate over the set."""
    imm, belief0, z = _turn(kind, steps=8, seed=6)
    vs = VariableStructureIMM(imm.bank.filter, imm.transition.matrix(), ExactMinimumEntropy(), feedback=feedback)
    start = GaussianBelief(belief0.components.mean[..., 0, :], belief0.components.cov[..., 0, :, :])
    belief0 = vs.initial_belief(start, belief0.mode_log_probs.exp())
    got, want = run_filter(vs, belief0, z, fast_path=True), run_filter(vs, belief0, z, fast_path=False)
    assert len(kernel_steps) == 8 and kernel_steps[0].post_update is not None
    assert_same_trajectory(got, want, tol=1e-8)
    assert list(got.extras) == list(want.extras)
    assert not bool(got.extras["active"].all())  # the policy selected
    est = run_filter(vs, belief0, z, record="estimate", fast_path=True)
    assert len(kernel_steps) == 16 and kernel_steps[-1].estimate_after
    _close(est, run_filter(vs, belief0, z, record="estimate", fast_path=False))


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_batch_shapes_and_the_default(kind, kernel_steps):
    mm, belief0, z = _turn(kind, batch=(2, 3), steps=6, seed=3)
    assert_same_trajectory(run_filter(mm, belief0, z, fast_path=True), run_filter(mm, belief0, z, fast_path=False),
                           tol=1e-8)
    runs = MIN_BATCH // 3 + 1  # the default takes it from MIN_BATCH runs x modes
    mm, belief0, z = _turn(kind, batch=(runs,), steps=3, seed=4)
    kernel_steps.clear()
    _close(run_filter(mm, belief0, z, record="estimate"),
           run_filter(mm, belief0, z, record="estimate", fast_path=False))
    assert len(kernel_steps) == 3
    small, belief0, z = _turn(kind, batch=(runs - 2,), steps=3, seed=4)
    run_filter(small, belief0, z, record="estimate")
    assert len(kernel_steps) == 3  # below it, the eager steps
    run = NONLINEAR.plan(small, belief0, z, kernels.Request())
    assert isinstance(run, str) and "small batch" in run


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_compiled_equals_the_eager_steps(kind, kernel_steps):
    """``compile=True`` takes the kernel at any size and compiles its step, the models' calls included."""
    mm, belief0, z = _turn(kind, steps=4)
    got = run_filter(mm, belief0, z, record="estimate", compile=True)
    assert len(kernel_steps) == 4 and kernel_steps[0]._compiled
    _close(got, run_filter(mm, belief0, z, record="estimate", fast_path=False), tol=1e-8)


@pytest.mark.parametrize("m", [1, 3])
@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_learned_models_through_the_default_hooks_and_their_gradients(kind, m, kernel_steps):
    imm, belief0, z = _learned(kind, m)
    with torch.no_grad():
        assert_same_trajectory(run_filter(imm, belief0, z, fast_path=True),
                               run_filter(imm, belief0, z, fast_path=False), tol=1e-9)
    assert len(kernel_steps) == 8
    params = [p for p in imm.parameters() if p.requires_grad]
    assert len(params) >= 6  # the network's, the motion's and the sensor's noise
    grads = []
    for fast in (True, False):
        total = run_filter(imm, belief0, z, fast_path=fast, record="estimate").log_likelihood.sum()
        grads.append(torch.autograd.grad(total, params))
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("device_form", [False, True])
def test_sigma_points_of_a_singular_covariance(device_form, kernel_steps, monkeypatch):
    """A start covariance without turn-rate variance and with x and y fully correlated: the mixed
    covariances' Cholesky factor fails, and the sigma points come from psd_sqrt's square root (the
    eigen-factor, a full matrix, on the CPU; the pivot-clamped factor in the device form, taken here as
    where the host may not read), as in the eager steps."""
    if device_form:
        from torchmm import linalg
        from torchmm.kernels.batch_last import nonlinear as batch_last_nonlinear

        for module in (linalg, batch_last_nonlinear):
            monkeypatch.setattr(module, "host_reads_ok", lambda tensor: False)
    mm, belief0, z = _turn("ukf", steps=5, seed=5)
    cov = belief0.components.cov.clone()
    cov[..., 4, :] = 0.0
    cov[..., :, 4] = 0.0
    cov[..., 0, 2] = cov[..., 2, 0] = 100.0  # x and y fully correlated: rank 3
    belief0 = type(belief0)(belief0.mode_log_probs, GaussianBelief(belief0.components.mean, cov))
    assert (torch.linalg.cholesky_ex(cov)[1] != 0).all()
    got, want = run_filter(mm, belief0, z, fast_path=True), run_filter(mm, belief0, z, fast_path=False)
    assert len(kernel_steps) == 5
    assert torch.isfinite(got.log_likelihood).all()
    assert_same_trajectory(got, want, tol=1e-8)


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_steps_never_read_values_on_the_host(kind, kernel_steps):
    mm, belief0, z = _turn(kind, steps=4)
    run = NONLINEAR.plan(mm, belief0, z, kernels.Request(forced=True))
    assert callable(run), run
    with no_host_sync("the nonlinear IMM kernel's whole run"):
        fields = run()
    assert len(kernel_steps) == 4 and torch.isfinite(fields[2]).all()


def test_where_it_declines():
    mm, belief0, z = _turn("ukf", steps=3)
    request = kernels.Request(forced=True)

    def why(filt, b0=belief0, data=z):
        out = NONLINEAR.plan(filt, b0, data, request)
        assert isinstance(out, str)
        return out

    f = mm.bank.filter
    f32 = IMM(UnscentedKalmanFilter(f.motion.to(torch.float32), f.measurement.to(torch.float32)),
              torch.tensor(TRANSITION, dtype=torch.float32))
    b32 = f32.initial_belief(GaussianBelief(belief0.components.mean[:, 0].float(), torch.eye(5)))
    assert "Joseph" in why(f32, b32, z.float())  # float32's default form
    joseph_off = IMM(UnscentedKalmanFilter(f32.bank.filter.motion, f32.bank.filter.measurement, joseph=False),
                     torch.tensor(TRANSITION, dtype=torch.float32))
    assert callable(NONLINEAR.plan(joseph_off, b32, z.float(), request))
    assert "Joseph" in why(IMM(ExtendedKalmanFilter(f.motion, f.measurement, joseph=True), mm.transition.matrix()))
    assert "update_first" in NONLINEAR.plan(mm, belief0, z, kernels.Request(update_first=True))

    class OwnUpdate(ExtendedKalmanFilter):
        def update(self, belief, z, *, sensor=None):
            return super().update(belief, z, sensor=sensor)

    assert "overrides" in why(IMM(OwnUpdate(f.motion, f.measurement), mm.transition.matrix()))
    members = [ExtendedKalmanFilter(NonlinearCoordinatedTurn(1.0, q, dtype=D), f.measurement) for q in (0.1, 1, 10)]
    assert "not nonlinear-Gaussian" in why(IMM(members, mm.transition.matrix()))
    assert "differs" in why(mm, belief0, z[:, :3])
    # a linear Kalman filter is the linear kernels' (it overrides the linearisation)
    from torchmm import ConstantVelocity, PositionMeasurement

    kf = IMM(KalmanFilter(ConstantVelocity(1, dtype=D), PositionMeasurement(2, [0], 1.0, dtype=D)),
             mm.transition.matrix())
    assert "not nonlinear-Gaussian" in why(kf) or "overrides" in why(kf)


def test_the_models_entry_hooks_are_their_forward_and_jacobian():
    """The entry forms the kernel calls are the models' own arithmetic: bit for bit for the turn model and
    the range-bearing sensor (which declare their exact zeros and ones), and for the default hooks."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(4, 3, 5, generator=g, dtype=D)
    x[0, :, 4] = 0.0  # the turn terms' series at omega = 0
    parts = list(x.unbind(-1))
    turn = NonlinearCoordinatedTurn(1.0, 0.1, 1e-3, dtype=D)
    sensor = RangeBearing(5, torch.eye(2, dtype=D), origin=(-3.0, 1.0), dtype=D)
    net = torch.nn.Sequential(torch.nn.Linear(5, 5), torch.nn.Tanh()).to(D)
    learned = LearnedMotion(net, 5, 0.1 * torch.eye(5, dtype=D))
    for model in (turn, sensor, learned):
        extra = {} if model is sensor else {"u": None}
        assert torch.equal(torch.stack(model.forward_entries(parts, **extra), -1), model(x))
        J = model.jacobian(x)
        rows = model.jacobian_entries(parts, **extra)
        for a, row in enumerate(rows):
            for e, entry in enumerate(row):
                if isinstance(entry, torch.Tensor):
                    assert torch.equal(entry.expand(x.shape[:-1]), J[..., a, e])
                else:  # a declared exact entry: that number at every state
                    assert entry in (0.0, 1.0) and bool((J[..., a, e] == entry).all())
    exact = sum(not isinstance(e, torch.Tensor) for row in turn.jacobian_entries(parts) for e in row)
    assert exact == 13

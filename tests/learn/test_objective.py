"""torchmm.learn.Objective: the likelihood checked once and evaluated many times (issue 31).

Its values and gradients are those of :func:`torchmm.learn.negative_log_likelihood` (the eager steps),
for the Kalman filter (Nile, exact diffuse start built from the parameters at every call) and an IMM;
it falls back to the eager steps where no kernel applies; ``minimize`` reaches statsmodels' optimum
of the Nile local level (an independent implementation).
"""

from __future__ import annotations

import pytest
import torch
from torch.nn.utils import parametrize

from experiments.realdata import load_nile, local_level, local_level_start
from torchmm import IMM, ExtendedKalmanFilter, GaussianBelief, KalmanFilter, run_filter
from torchmm.learn import Objective, negative_log_likelihood
from torchmm.models import (
    ConstantVelocity,
    LinearMeasurement,
    LinearMotion,
    PositionMeasurement,
    learnable_noise,
)


def _eager_loss(filter, belief0, z, **kwargs):
    """negative_log_likelihood on the eager steps (every kernel switched off): the reference."""
    import torchmm.kernels as kernels

    with kernels.switched_off("linear_gaussian"), kernels.switched_off("batch_last"):
        return negative_log_likelihood(filter, belief0, z, **kwargs)


def _grads(loss, params):
    return torch.autograd.grad(loss, params)


def test_nile_value_and_gradient_equal_the_eager_likelihood():
    y = load_nile()
    kf, _ = local_level(1400.0, 15000.0, learnable=True)
    params = list(kf.parameters())
    objective = Objective(kf, lambda f: local_level_start(f, y[0]), y[1:])
    loss = objective()
    assert objective.kernel == "linear_gaussian"
    with parametrize.cached():
        reference = _eager_loss(kf, local_level_start(kf, y[0]), y[1:], reduction="sum")
    torch.testing.assert_close(loss, reference, rtol=1e-12, atol=0)
    for got, want in zip(_grads(loss, params), _grads(reference, params)):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-14)
    # a parameter change is seen by the next call
    with torch.no_grad():
        params[0].add_(0.3)
    moved = objective()
    with parametrize.cached():
        torch.testing.assert_close(moved, _eager_loss(kf, local_level_start(kf, y[0]), y[1:], reduction="sum"),
                                   rtol=1e-12, atol=0)
    assert float(moved.detach()) != float(loss.detach())


@pytest.mark.parametrize("reduction", ["sum", "mean", "none"])
def test_imm_objective_equals_negative_log_likelihood(reduction):
    g = torch.Generator().manual_seed(3)
    motion = ConstantVelocity(1, q=1.0, acceleration=[[0.5], [0.0], [-0.5]], dtype=torch.float64)
    sensor = PositionMeasurement(2, [0], 4.0, dtype=torch.float64)
    learnable_noise(sensor, "R", "log_diagonal")
    imm = IMM(KalmanFilter(motion, sensor), torch.tensor([[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]],
                                                         dtype=torch.float64))
    belief0 = GaussianBelief(torch.zeros(3, 2, dtype=torch.float64), 10 * torch.eye(2, dtype=torch.float64))
    z = torch.randn(40, 3, 1, generator=g, dtype=torch.float64) * 3
    z[5, 1] = float("nan")
    objective = Objective(imm, belief0, z, reduction=reduction)
    loss = objective()
    assert objective.kernel == "linear_gaussian"
    reference = _eager_loss(imm, belief0, z, reduction=reduction)
    torch.testing.assert_close(loss, reference, rtol=1e-12, atol=1e-12)
    params = list(imm.parameters())
    for got, want in zip(_grads(loss.sum(), params), _grads(reference.sum(), params)):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-14)


def test_a_filter_without_a_kernel_runs_the_eager_steps():
    cv = ConstantVelocity(1, q=0.5, dtype=torch.float64)
    ekf = ExtendedKalmanFilter(cv, PositionMeasurement(2, [0], 1.0, dtype=torch.float64))
    belief0 = GaussianBelief(torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))
    z = torch.randn(20, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    objective = Objective(ekf, belief0, z)
    assert objective.why  # why no kernel
    torch.testing.assert_close(objective(), negative_log_likelihood(ekf, belief0, z, reduction="sum"))
    assert objective.kernel == "eager"


def test_checks_once_with_named_errors():
    kf, belief0 = local_level(1.0, 1.0, first=torch.zeros(1, dtype=torch.float64))
    with pytest.raises(ValueError, match="^measurements"):
        Objective(kf, belief0, torch.zeros(5, 2, dtype=torch.float64))  # m = 2 for a one-sensor filter
    with pytest.raises(ValueError, match="^belief0"):
        Objective(kf, GaussianBelief(torch.zeros(1, dtype=torch.float64), -torch.ones(1, 1, dtype=torch.float64)),
                  torch.zeros(5, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="^reduction"):
        Objective(kf, belief0, torch.zeros(5, 1, dtype=torch.float64), reduction="max")
    with pytest.raises(ValueError, match="^parameters"):
        Objective(kf, belief0, torch.zeros(5, 1, dtype=torch.float64)).minimize()  # nothing learnable


def test_minimize_reaches_statsmodels_optimum_of_the_nile():
    sm = pytest.importorskip("statsmodels.api")
    y = load_nile()
    model = sm.tsa.UnobservedComponents(y[:, 0].numpy(), "llevel", use_exact_diffuse=True)
    optimum = model.fit(method="bfgs", gtol=1e-10, maxiter=2000, disp=False)
    r, q = (float(v) for v in optimum.params)
    kf, _ = local_level(1000.0, 10000.0, learnable=True)
    objective = Objective(kf, lambda f: local_level_start(f, y[0]), y[1:])
    result = objective.minimize(options={"gtol": 1e-10, "ftol": 1e-15})
    assert result.success, result.message
    with parametrize.cached():
        learned_q, learned_r = float(kf.motion.Q.reshape(())), float(kf.measurement.R.reshape(()))
    assert learned_q == pytest.approx(q, rel=1e-4) and learned_r == pytest.approx(r, rel=1e-4)
    # the maximised log-likelihood is statsmodels' (which keeps the diffuse observation's constant)
    import math

    assert -float(objective()) - 0.5 * math.log(2 * math.pi) == pytest.approx(optimum.llf, abs=1e-6)


# -- issue 44: the objective's and minimize's arguments, checked at entry ------------------------------
def _learnable(steps=30):
    """A learnable local level (log q, log r) and its data (seeded, float64)."""
    kf, belief0 = local_level(2.0, 3.0, learnable=True, known=(0.0, 10.0))
    z = torch.randn(steps, 1, generator=torch.Generator().manual_seed(5), dtype=torch.float64).cumsum(0)
    return kf, belief0, z


def test_minimize_steps_back_from_a_non_finite_loss():
    """A raw variance as the parameter: L-BFGS-B's first step from R = 4 goes negative (the loss NaN).
    Passed to scipy, that ended the search at R = 3 with "CONVERGENCE" (loss 377.1 against the optimum's
    283.0); answered as a failed step (torchmm.learn.search.Guarded) the search backtracks and reaches
    the optimum a bounded scalar search of the same loss finds, and the message counts the failed steps."""
    from scipy.optimize import minimize_scalar

    g = torch.Generator().manual_seed(0)
    T = 200
    walk = torch.cumsum(torch.randn(T, generator=g, dtype=torch.float64), 0)
    z = (walk + 0.1 * torch.randn(T, generator=g, dtype=torch.float64)).reshape(T, 1)
    R = torch.tensor([[4.0]], dtype=torch.float64, requires_grad=True)
    one = torch.eye(1, dtype=torch.float64)
    kf = KalmanFilter(LinearMotion(one, one.clone()), LinearMeasurement(one.clone(), R))
    obj = Objective(kf, GaussianBelief(torch.zeros(1, dtype=torch.float64), 10 * one), z)
    result = obj.minimize(parameters=[kf.measurement.R])
    found = float(kf.measurement.R.detach())

    def loss(r):
        with torch.no_grad():
            kf.measurement.R.copy_(torch.tensor([[r]], dtype=torch.float64))
            return float(obj())

    ref = minimize_scalar(loss, bounds=(1e-6, 10.0), method="bounded", options={"xatol": 1e-12})
    assert found == pytest.approx(ref.x, rel=1e-4) and result.fun == pytest.approx(ref.fun, rel=1e-10)
    assert "not finite, answered as failed steps" in result.message


def test_minimize_refuses_a_tensor_the_loss_does_not_depend_on():
    """A tensor that is not a parameter of the filter (nor read by the start) was 'optimised' to
    success after 0 iterations."""
    kf, belief0, z = _learnable()
    objective = Objective(kf, belief0, z, update_first=True)
    stray = torch.nn.Parameter(torch.zeros(2, dtype=torch.float64))
    before = [p.detach().clone() for p in kf.parameters()]
    with pytest.raises(ValueError, match=r"^parameters\[0\]: the loss does not depend on it"):
        objective.minimize(parameters=[stray])
    own = list(kf.parameters())
    with pytest.raises(ValueError, match=rf"^parameters\[{len(own)}\]: the loss does not depend on it"):
        objective.minimize(parameters=[*own, stray])
    for p, b in zip(kf.parameters(), before):  # left as they were
        torch.testing.assert_close(p.detach(), b, rtol=0, atol=0)


@pytest.mark.parametrize("bad, message", [
    (lambda kf: [next(kf.parameters()), torch.zeros(1, dtype=torch.float64)], r"^parameters\[1\]: .*require"),
    (lambda kf: [next(kf.parameters()), next(kf.parameters())], r"^parameters\[1\]: .*parameters\[0\]"),
    (lambda kf: [next(kf.parameters()) * 2], r"^parameters\[0\]: .*leaf"),
    (lambda kf: next(kf.parameters()), r"^parameters: expected"),
    (lambda kf: "log_r", r"^parameters: expected"),
    (lambda kf: [], r"^parameters: "),
    (lambda kf: [next(kf.parameters()), "x"], r"^parameters\[1\]: expected a tensor"),
])
def test_minimize_refuses_malformed_parameters(bad, message):
    """A tensor without grad among them was dropped silently, the same tensor twice was optimised as
    two (the last copy won), a single tensor was iterated row by row."""
    kf, belief0, z = _learnable()
    with pytest.raises((TypeError, ValueError), match=message):
        Objective(kf, belief0, z, update_first=True).minimize(parameters=bad(kf))


def test_minimize_over_a_tensor_of_the_start_belief():
    """A tensor the loss depends on through the start function, not the filter, is a parameter."""
    kf, _, z = _learnable()
    for p in kf.parameters():
        p.requires_grad_(False)
    mean = torch.nn.Parameter(torch.tensor([5.0], dtype=torch.float64))
    objective = Objective(kf, lambda f: GaussianBelief(mean, torch.eye(1, dtype=torch.float64)), z,
                          update_first=True)
    result = objective.minimize(parameters=[mean])
    assert result.success and result.nit > 0 and float(mean) != 5.0


@pytest.mark.parametrize("kwargs, error, message", [
    (dict(method="bogus"), ValueError, r"^method: expected one of \[.*'L-BFGS-B'"),
    (dict(method="Nelder-Mead"), ValueError, r"^method: "),  # not a gradient method
    (dict(method=1), ValueError, r"^method: "),
    (dict(tol="small"), TypeError, r"^tol: "),
    (dict(tol=-1.0), ValueError, r"^tol: "),
    (dict(tol=float("nan")), ValueError, r"^tol: "),
    (dict(options="fast"), TypeError, r"^options: "),
])
def test_minimize_refuses_a_bad_method_tol_or_options(kwargs, error, message):
    kf, belief0, z = _learnable()
    with pytest.raises(error, match=message):
        Objective(kf, belief0, z, update_first=True).minimize(**kwargs)


def test_an_objective_over_no_steps_names_the_measurements():
    kf, belief0, _ = _learnable()
    with pytest.raises(ValueError, match=r"^measurements: .*no time steps"):
        Objective(kf, belief0, torch.zeros(0, 1, dtype=torch.float64), update_first=True)


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_a_parameter_turned_non_finite_is_named_at_the_evaluation(value):
    """A filter parameter set to NaN after the objective was built gave a NaN loss without a word."""
    kf, belief0, z = _learnable()
    objective = Objective(kf, belief0, z, update_first=True)
    assert torch.isfinite(objective())
    name, parameter = list(kf.named_parameters())[-1]
    with torch.no_grad():
        parameter.fill_(value)
    with pytest.raises(ValueError, match=rf"^filter\.{name.replace('.', chr(92) + '.')}: .*not finite"):
        objective()
    with pytest.raises(ValueError, match=rf"^filter\.{name.replace('.', chr(92) + '.')}: "):
        objective.minimize()


# -- a fuzz after issue 44: data with no datum, a misspelt option ---------------------------------------
def _position_kf():
    kf = KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0))
    learnable_noise(kf.measurement, "R", "log_diagonal")
    return kf, GaussianBelief(torch.zeros(2), torch.eye(2))


@pytest.mark.parametrize("shape", [(10, 1), (4, 3, 1)])
def test_an_objective_over_measurements_that_are_all_missing_names_them(shape):
    """Every entry missing gave a zero gradient (not None), so minimize returned success after 0
    iterations with R unchanged: nothing informs the parameters."""
    kf, belief0 = _position_kf()
    if len(shape) == 3:
        belief0 = belief0.expand(shape[1])
    for missing in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"^measurements: every entry is missing"):
            Objective(kf, belief0, torch.full(shape, missing))
    # burn: the steps left out of the likelihood do not count (data only there inform no term)
    z = torch.full(shape, float("nan"))
    z[0] = 1.0
    with pytest.raises(ValueError, match=r"^measurements: every entry after the burn \(1 steps\) is missing"):
        Objective(kf, belief0, z, burn=1)
    # one datum is enough to build it (and its gradient is not zero)
    z = torch.full(shape, float("nan"))
    z.view(-1)[-1] = 0.5
    objective = Objective(kf, belief0, z)
    objective().backward()
    assert float(next(kf.parameters()).grad.abs().sum()) > 0


@pytest.mark.parametrize("method", ["L-BFGS-B", "BFGS", "trust-constr"])
def test_minimize_refuses_an_unknown_option(method):
    """``options={'max_iter': 1}`` (for ``maxiter``) only warned (scipy's OptimizeWarning) and ran on."""
    kf, belief0, z = _learnable()
    before = [p.detach().clone() for p in kf.parameters()]
    with pytest.raises(ValueError, match=r"^options: unknown option 'max_iter' of .*" + method):
        Objective(kf, belief0, z, update_first=True).minimize(method=method, options={"max_iter": 1})
    with pytest.raises(ValueError, match=r"^options: unknown options 'max_iter', 'tolerance'"):
        Objective(kf, belief0, z, update_first=True).minimize(method=method,
                                                                options={"max_iter": 1, "tolerance": 1.0})
    for p, b in zip(kf.parameters(), before):  # left as they were
        torch.testing.assert_close(p.detach(), b, rtol=0, atol=0)
    result = Objective(kf, belief0, z, update_first=True).minimize(method=method, options={"maxiter": 1})
    assert result.nit <= 1


def test_smoothed_is_the_filter_and_smoother_at_the_current_parameters():
    """Objective.smoothed() (issue 47): Kim's smoother of an IMM through the prepared compiled loops equals
    run_filter + smooth(method="kim") (1e-12), follows a parameter change, and the RTS smoother of a Kalman
    filter likewise; a filter without the loops (per-step models) takes run_filter + smooth."""
    from experiments.realdata import fedfunds_imm, load_fedfunds
    from torchmm import smooth

    y = load_fedfunds()
    imm, b0 = fedfunds_imm([3.7, 9.6], [4.0, 16.0], [[0.98, 0.02], [0.05, 0.95]])
    objective = Objective(imm, b0, y)
    for _ in range(2):
        with torch.no_grad():
            ref = smooth(run_filter(imm, b0, y), method="kim").belief
        out = objective.smoothed()
        assert objective.why == ""  # (the objective has the compiled loops' plan)
        assert torch.allclose(out.mode_probs, ref.mode_probs, rtol=1e-12, atol=1e-12)
        assert torch.allclose(out.components.mean, ref.components.mean, rtol=1e-12, atol=1e-12)
        assert torch.allclose(out.components.cov, ref.components.cov, rtol=1e-12, atol=1e-12)
        with torch.no_grad():
            imm.bank.filter.measurement.H.mul_(1.1)  # (the next round: other parameters)
            imm.bank.filter.measurement.R.mul_(0.9)  # (the kernel's own copies of them refreshed: versions)
    # a new start belief (another object) is read, not the last call's arrays
    b1 = b0.__class__(torch.tensor([0.3, 0.7], dtype=torch.float64).log(), b0.components)
    objective = Objective(imm, b1, y)
    objective.smoothed()
    with torch.no_grad():
        ref = smooth(run_filter(imm, b1, y), method="kim").belief
    assert torch.allclose(objective.smoothed().mode_probs, ref.mode_probs, rtol=1e-12, atol=1e-12)
    kf = KalmanFilter(LinearMotion(torch.eye(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64)),
                      LinearMeasurement(torch.eye(1, dtype=torch.float64), 4 * torch.eye(1, dtype=torch.float64)))
    z = torch.randn(30, 2, 1, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    start = GaussianBelief(torch.zeros(2, 1, dtype=torch.float64), torch.eye(1, dtype=torch.float64))
    with torch.no_grad():
        ref = smooth(run_filter(kf, start, z)).belief
    for objective in (Objective(kf, start, z), Objective(kf, start, z, motions=[kf.motion] * 30)):
        out = objective.smoothed()
        assert torch.allclose(out.mean, ref.mean, rtol=1e-12, atol=1e-12)
        assert torch.allclose(out.cov, ref.cov, rtol=1e-12, atol=1e-12)

"""gradcheck (float64) of the negative log-likelihood w.r.t. every learnable parameter.

Each test builds a filter whose parameters are all learnable (transition logits, parametrised
noise covariances, network weights), then checks ``torch.autograd.gradcheck`` on the map from the
full list of ``named_parameters()`` to the loss (through ``torch.func.functional_call``).
"""

from __future__ import annotations

import pytest
import torch
from torch import nn
from torch.autograd import gradcheck
from torch.func import functional_call

from torchmm import (
    GPB1,
    GPB2,
    IMM,
    CoordinatedTurn,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    LinearMotion,
    ModeTransition,
    UnscentedKalmanFilter,
)
from torchmm.learn import negative_log_likelihood
from torchmm.models import LearnedMeasurement, LearnedMotion, learnable_noise

D = torch.float64


def _measurements(steps: int, runs: int, m: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    z = torch.cumsum(torch.randn(steps, runs, m, generator=g, dtype=D), 0)
    z[2, 0] = float("nan")  # a missing step in one run
    if m > 1:
        z[3, 1, 0] = float("nan")  # one missing component
    return z


def _check_every_parameter(module: nn.Module, loss_of_module, expected: set[str]) -> None:
    names = [n for n, p in module.named_parameters() if p.requires_grad]
    assert set(names) == expected, names
    values = tuple(p.detach().clone().requires_grad_() for _, p in module.named_parameters())

    def loss(*params):
        return functional_call(module, dict(zip(names, params)), args=(), kwargs={"_loss": loss_of_module})

    # functional_call calls module.forward; route it to the loss instead
    original_forward = module.forward
    module.forward = lambda _loss: _loss(module)  # type: ignore[method-assign]
    try:
        # every parameter really enters the loss (a parameter functional_call did not substitute
        # would have zero analytical *and* numerical gradient and pass gradcheck vacuously)
        grads = torch.autograd.grad(loss(*values), values)
        for name, grad in zip(names, grads):
            assert grad.abs().sum() > 0, f"{name} gets no gradient"
        assert gradcheck(loss, values, eps=1e-6, atol=1e-5, rtol=1e-4)
    finally:
        module.forward = original_forward  # type: ignore[method-assign]


def _mlp(n_in: int, n_out: int, seed: int) -> nn.Module:
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(n_in, 3), nn.Tanh(), nn.Linear(3, n_out)).to(D)
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(0.3)
    return net


F2 = [[1.0, 1.0], [0.0, 1.0]]


def test_kalman_nll_gradcheck_every_parameter():
    Q = torch.tensor([[0.3, 0.1], [0.1, 0.4]], dtype=D)
    motion = LinearMotion(nn.Parameter(torch.tensor(F2, dtype=D)), Q)
    learnable_noise(motion, "Q", "cholesky")
    sensor = LinearMeasurement(torch.tensor([[1.0, 0.0]], dtype=D), torch.tensor([[0.7]], dtype=D))
    learnable_noise(sensor, "R", "log_diagonal")
    kf = KalmanFilter(motion, sensor)
    prior = GaussianBelief(torch.zeros(2, 2, dtype=D), 2 * torch.eye(2, dtype=D))
    z = _measurements(6, 2, 1)
    _check_every_parameter(kf, lambda f: negative_log_likelihood(f, prior, z),
                           {"motion.F", "motion.parametrizations.Q.original",
                            "measurement.parametrizations.R.original"})


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter], ids=lambda c: c.__name__)
def test_nonlinear_filter_nll_gradcheck_learned_models(cls):
    motion = LearnedMotion(_mlp(2, 2, 0), 2, Q=torch.tensor([[0.3, 0.1], [0.1, 0.4]], dtype=D),
                           noise="cholesky", residual=True)
    sensor = LearnedMeasurement(_mlp(2, 2, 1), 2, 2, R=torch.diag(torch.tensor([0.5, 0.8], dtype=D)),
                                noise="log_diagonal")
    filt = cls(motion, sensor)
    prior = GaussianBelief(torch.zeros(2, 2, dtype=D), torch.eye(2, dtype=D))
    z = 0.3 * _measurements(5, 2, 2)
    expected = {f"{part}.net.{i}.{w}" for part in ("motion", "measurement") for i in (0, 2)
                for w in ("weight", "bias")}
    expected |= {"motion.parametrizations.Q.original", "measurement.parametrizations.R.original"}
    _check_every_parameter(filt, lambda f: negative_log_likelihood(f, prior, z), expected)


@pytest.mark.parametrize("combinator", [IMM, GPB1, GPB2], ids=lambda c: c.__name__)
def test_multiple_model_nll_gradcheck_transition_noise_and_network(combinator):
    """A bank mixing a learned mode (EKF through an MLP) with two analytic Kalman modes."""
    sensor = LinearMeasurement(torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]], dtype=D),
                               4 * torch.eye(2, dtype=D))
    learnable_noise(sensor, "R", "cholesky")
    left = learnable_noise(CoordinatedTurn(torch.tensor(0.2, dtype=D), q=0.5, dtype=D), "Q", "scale")
    right = learnable_noise(CoordinatedTurn(torch.tensor(-0.2, dtype=D), q=0.5, dtype=D), "Q", "scale")
    learned = LearnedMotion(_mlp(4, 4, 2), 4, Q=0.3 * torch.eye(4, dtype=D), noise="log_diagonal",
                            residual=True)
    bank = [ExtendedKalmanFilter(learned, sensor), KalmanFilter(left, sensor), KalmanFilter(right, sensor)]
    transition = ModeTransition(torch.tensor([[0.8, 0.1, 0.1], [0.2, 0.7, 0.1], [0.25, 0.25, 0.5]], dtype=D),
                                learnable=True)
    mm = combinator(bank, transition)
    assert type(mm.bank).__name__ == "ListBank"  # learnable KFs are not fused into a frozen copy
    prior = GaussianBelief(torch.zeros(2, 4, dtype=D), 3 * torch.eye(4, dtype=D))
    z = _measurements(4, 2, 2)
    expected = {"transition.logits", "bank.filters.0.measurement.parametrizations.R.original",
                "bank.filters.0.motion.parametrizations.Q.original",
                "bank.filters.1.motion.parametrizations.Q.original",
                "bank.filters.2.motion.parametrizations.Q.original"}
    expected |= {f"bank.filters.0.motion.net.{i}.{w}" for i in (0, 2) for w in ("weight", "bias")}
    _check_every_parameter(mm, lambda f: negative_log_likelihood(f, prior, z), expected)


def test_variational_filter_elbo_loss_gradcheck():
    """VB filters report the ELBO as their log-likelihood: the loss is its negative (a bound)."""
    from torchmm.filters.variational import StudentTVBFilter

    motion = LinearMotion(torch.tensor(F2, dtype=D), 0.3 * torch.eye(2, dtype=D))
    learnable_noise(motion, "Q", "scale")
    sensor = LinearMeasurement(torch.tensor([[1.0, 0.0]], dtype=D), torch.tensor([[0.7]], dtype=D))
    learnable_noise(sensor, "R", "log_diagonal")
    vb = StudentTVBFilter(motion, sensor, df=4.0, iterations=3)
    prior = GaussianBelief(torch.zeros(2, 2, dtype=D), 2 * torch.eye(2, dtype=D))
    z = _measurements(5, 2, 1)
    _check_every_parameter(vb, lambda f: negative_log_likelihood(f, prior, z),
                           {"kalman.motion.parametrizations.Q.original",
                            "kalman.measurement.parametrizations.R.original"})

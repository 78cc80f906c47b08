"""Adapters: PSD-by-construction noise, user networks as models, learned modes in IMM banks."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from tests.conftest import assert_symmetric_psd
from torchmm import (
    IMM,
    ConstantVelocity,
    CoordinatedTurn,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    LinearMotion,
    PositionMeasurement,
    UnscentedKalmanFilter,
    run_filter,
)
from torchmm.models import (
    CholeskyCovariance,
    LearnedMeasurement,
    LearnedMotion,
    LogDiagonalCovariance,
    LogScaleCovariance,
    learnable_noise,
)

close = torch.testing.assert_close


@pytest.mark.parametrize("batch", [(), (3,), (2, 4)], ids=str)
@pytest.mark.parametrize("d", [1, 2, 4])
def test_parametrisations_are_psd_for_any_unconstrained_value(batch, d, generator):
    for scale in (0.1, 1.0, 5.0):  # includes large raw values (exp of big log-diagonals)
        theta = scale * torch.randn(*batch, d, d, generator=generator)
        cov = CholeskyCovariance()(theta)
        assert_symmetric_psd(cov)
        assert bool((torch.linalg.eigvalsh(cov) > 0).all())  # positive definite
        diag = LogDiagonalCovariance()(scale * torch.randn(*batch, d, generator=generator))
        assert_symmetric_psd(diag)
        assert bool((diag.diagonal(dim1=-2, dim2=-1) > 0).all())
        structure = ConstantVelocity(1, q=1.0).Q  # singular G G^T
        scaled = LogScaleCovariance(structure)(scale * torch.randn(batch, generator=generator))
        assert_symmetric_psd(scaled, tol=1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("d", [2, 4, 6])
def test_cholesky_covariance_is_positive_definite_to_working_precision(d, dtype):
    """What CholeskyCovariance promises in floating point: for *any* finite theta - here the
    adversarial ones, large negative log-diagonals under large off-diagonal entries, where the
    bare L L^T came out with eigenvalues like -1.6e-15 - the covariance's computed eigenvalues
    are positive and its Cholesky factorisation succeeds. Deterministic values: nothing depends
    on a generator's output on one processor."""
    grid = torch.linspace(-1.0, 1.0, d * d, dtype=torch.float64).reshape(d, d)
    for log_diag in (-60.0, -30.0, -12.0, 0.0, 5.0):
        for off in (1e-3, 1.0, 1e3, 1e6):
            theta = (off * grid).tril(-1) + torch.diag(torch.full((d,), log_diag) + grid.diagonal())
            cov = CholeskyCovariance()(theta.to(dtype))
            assert bool((torch.linalg.eigvalsh(cov) > 0).all()), (log_diag, off)
            assert int(torch.linalg.cholesky_ex(cov).info) == 0, (log_diag, off)
            # the floor is a relative change of 16 d eps of the trace, nothing more
            lower = torch.tril(theta, -1) + torch.diag(theta.diagonal().exp())
            exact = lower @ lower.mT
            bound = 20 * d * torch.finfo(dtype).eps * exact.diagonal().sum()
            assert float((cov.double() - exact).abs().max()) <= float(bound) + 1e-300


@pytest.mark.parametrize("kind", ["cholesky", "log_diagonal", "scale"])
def test_learnable_noise_keeps_the_initial_value_and_is_learnable(kind):
    R = torch.tensor([[2.0, 0.3], [0.3, 0.5]])
    if kind == "log_diagonal":
        R = torch.diag(R.diagonal())
    sensor = LinearMeasurement(torch.eye(2), R)
    learnable_noise(sensor, "R", kind)
    close(sensor.R, R)
    close(sensor.noise_cov(), R)
    params = dict(sensor.named_parameters())
    assert list(params) == ["parametrizations.R.original"]
    # assigning a new covariance goes through the parametrisation's inverse
    new = 3 * R
    sensor.R = new
    close(sensor.R, new)


def test_scale_noise_on_a_mode_bank_with_per_mode_levels():
    bank = CoordinatedTurn(torch.tensor([0.0, 0.1, -0.1]), q=0.5)
    Q0 = bank.Q.clone()
    learnable_noise(bank, "Q", "scale", scale_shape=(3,))
    theta = bank.parametrizations.Q.original
    assert theta.shape == (3,)
    with torch.no_grad():
        theta.copy_(torch.log(torch.tensor([1.0, 2.0, 4.0])))
    close(bank.Q, torch.tensor([1.0, 2.0, 4.0])[:, None, None] * Q0)


def test_bad_arguments_raise_value_errors_naming_them():
    with pytest.raises(ValueError, match="kind"):
        learnable_noise(ConstantVelocity(1), "Q", "softplus")
    with pytest.raises(ValueError, match="name"):
        learnable_noise(ConstantVelocity(1), "R")
    with pytest.raises(ValueError, match="cov"):
        learnable_noise(ConstantVelocity(1), "Q", "cholesky")  # G G^T is singular
    with pytest.raises(ValueError, match="cov"):
        correlated = LinearMeasurement(torch.eye(2), torch.tensor([[1.0, 0.5], [0.5, 1.0]]))
        learnable_noise(correlated, "R", "log_diagonal")
    with pytest.raises(ValueError, match="name"):
        learnable_noise(learnable_noise(ConstantVelocity(1), "Q", "scale"), "Q", "scale")
    with pytest.raises(ValueError, match="scale_shape"):
        two_modes = LinearMotion(torch.eye(2), torch.eye(2).repeat(2, 1, 1))
        learnable_noise(two_modes, "Q", "scale", scale_shape=(3,))
    with pytest.raises(ValueError, match="Q"):
        LearnedMotion(nn.Linear(2, 2), 2, Q=-torch.eye(2))
    with pytest.raises(ValueError, match="net"):
        LearnedMotion(nn.Linear(2, 3), 2, Q=1.0)(torch.zeros(2))
    with pytest.raises(ValueError, match="net"):
        LearnedMeasurement(nn.Linear(2, 3), 2, 1, R=1.0)(torch.zeros(2))
    with pytest.raises(TypeError, match="^net: expected a callable"):  # a wrong type (issue 29's contract)
        LearnedMotion(3, 2, Q=1.0)


def _linear_net(F: torch.Tensor, offset: torch.Tensor | None = None) -> nn.Linear:
    net = nn.Linear(F.shape[1], F.shape[0], bias=offset is not None)
    with torch.no_grad():
        net.weight.copy_(F)
        if offset is not None:
            net.bias.copy_(offset)
    return net


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter], ids=lambda c: c.__name__)
def test_learned_linear_network_matches_the_kalman_filter(cls, generator):
    F = torch.tensor([[1.0, 1.0, 0.0], [0.0, 0.9, 0.2], [0.0, 0.0, 0.95]])
    b = torch.tensor([0.1, -0.2, 0.3])
    Q = torch.tensor([[0.5, 0.1, 0.0], [0.1, 0.4, 0.05], [0.0, 0.05, 0.3]])
    H = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R = torch.tensor([[2.0, 0.2], [0.2, 1.0]])
    kf = KalmanFilter(LinearMotion(F, Q, offset=b), LinearMeasurement(H, R))
    learned = cls(LearnedMotion(_linear_net(F, b), 3, Q=Q, noise="cholesky"),
                  LearnedMeasurement(_linear_net(H), 3, 2, R=R, noise="cholesky"))
    prior = GaussianBelief(torch.randn(5, 3, generator=generator), 2 * torch.eye(3))
    z = torch.randn(8, 5, 2, generator=generator)
    z[3, 2] = float("nan")
    a, c = run_filter(kf, prior, z), run_filter(learned, prior, z)
    close(c.belief.mean, a.belief.mean)
    close(c.belief.cov, a.belief.cov)
    close(c.log_likelihood, a.log_likelihood)
    # the autograd Jacobian of the wrapped network is the matrix
    close(learned.motion.jacobian(prior.mean), F.expand(5, 3, 3))


def test_imm_with_a_learned_mode_equals_the_analytic_imm(generator):
    """A learned mode that reproduces an analytic one gives the analytic IMM exactly (ListBank)."""
    turns = CoordinatedTurn(torch.tensor([0.0, 0.1, -0.1]), q=0.2)
    sensor = PositionMeasurement(4, [0, 2], 9.0)
    P = torch.full((3, 3), 0.05) + 0.85 * torch.eye(3)
    analytic = IMM(KalmanFilter(turns, sensor), P)
    learned_ct = LearnedMotion(_linear_net(turns.F[1]), 4, Q=turns.Q, noise="fixed")
    mixed = IMM([KalmanFilter(turns.select_mode(0), sensor), ExtendedKalmanFilter(learned_ct, sensor),
                 KalmanFilter(turns.select_mode(2), sensor)], P)
    assert type(mixed.bank).__name__ == "ListBank"
    prior = GaussianBelief(torch.tensor([0.0, 10.0, 0.0, 0.0]).expand(6, 4),
                           torch.diag(torch.tensor([50.0, 4, 50, 4])))
    z = 10 * torch.randn(12, 6, 2, generator=generator).cumsum(0)
    a = run_filter(analytic, analytic.initial_belief(prior), z)
    b = run_filter(mixed, mixed.initial_belief(prior), z)
    close(b.belief.mode_log_probs, a.belief.mode_log_probs)
    close(b.estimate().mean, a.estimate().mean)
    close(b.log_likelihood, a.log_likelihood)


def test_learnable_kalman_filters_are_not_frozen_into_a_fused_bank():
    sensor = PositionMeasurement(2, [0], 1.0)
    modes = [learnable_noise(ConstantVelocity(1, q=q), "Q", "scale") for q in (0.1, 1.0)]
    imm = IMM([KalmanFilter(m, sensor) for m in modes], torch.tensor([[0.9, 0.1], [0.1, 0.9]]))
    prior = GaussianBelief(torch.zeros(3, 2), torch.eye(2))
    loss = -run_filter(imm, imm.initial_belief(prior), torch.randn(10, 3, 1)).total_log_likelihood().sum()
    loss.backward()
    for m in modes:
        grad = m.parametrizations.Q.original.grad
        assert grad is not None and bool(torch.isfinite(grad)) and grad != 0
    # analytic (parameter-free) Kalman filters are still fused into one vectorised bank
    fused = IMM([KalmanFilter(ConstantVelocity(1, q=q), sensor) for q in (0.1, 1.0)], torch.eye(2))
    assert type(fused.bank).__name__ == "VectorizedBank"


def test_learned_measurement_log_likelihood_for_particle_filters(generator):
    R = torch.tensor([[2.0, 0.3], [0.3, 1.0]])
    sensor = LearnedMeasurement(nn.Sequential(nn.Linear(3, 4), nn.Tanh(), nn.Linear(4, 2)), 3, 2, R=R)
    particles = torch.randn(50, 7, 3, generator=generator)  # (Np, *B, n)
    z = torch.randn(7, 2, generator=generator)
    got = sensor.log_likelihood(z, particles)
    want = torch.distributions.MultivariateNormal(sensor(particles).detach(), covariance_matrix=R).log_prob(z)
    close(got.detach(), want)
    got.sum().backward()
    assert sensor.parametrizations.R.original.grad is not None


def test_float32_learned_imm_runs_finite():
    torch.manual_seed(0)
    sensor = PositionMeasurement(4, [0, 2], torch.tensor(9.0, dtype=torch.float32), dtype=torch.float32)
    net = nn.Sequential(nn.Linear(4, 8), nn.Tanh(), nn.Linear(8, 4)).float()
    learned = LearnedMotion(net, 4, Q=torch.eye(4, dtype=torch.float32), residual=True)
    cv = learnable_noise(CoordinatedTurn(torch.tensor(0.0), q=0.1, dtype=torch.float32), "Q", "scale")
    imm = IMM([KalmanFilter(cv, sensor), UnscentedKalmanFilter(learned, sensor)],
              torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=torch.float32))
    prior = GaussianBelief(torch.zeros(4, 4, dtype=torch.float32), 10 * torch.eye(4, dtype=torch.float32))
    traj = run_filter(imm, imm.initial_belief(prior), torch.randn(30, 4, 2, dtype=torch.float32) * 5)
    loss = -traj.total_log_likelihood().mean()
    loss.backward()
    assert traj.estimate().mean.dtype == torch.float32
    assert bool(torch.isfinite(traj.estimate().mean).all()) and bool(torch.isfinite(loss))
    assert all(bool(torch.isfinite(p.grad).all()) for p in imm.parameters())


class _Controlled(nn.Module):
    """x_k = A x + B u (a user network taking the control as a second argument)."""

    def __init__(self, A, B):
        super().__init__()
        self.A, self.B = nn.Parameter(A.clone()), nn.Parameter(B.clone())

    def forward(self, x, u):
        return x @ self.A.mT + u @ self.B.mT


def test_learned_motion_with_controls_matches_the_linear_model(generator):
    A = torch.tensor([[1.0, 0.5], [0.0, 0.9]])
    B = torch.tensor([[0.1], [1.0]])
    Q = torch.tensor([[0.2, 0.0], [0.0, 0.3]])
    sensor = PositionMeasurement(2, [0], 1.0)
    kf = KalmanFilter(LinearMotion(A, Q, input_matrix=B), sensor)
    learned = LearnedMotion(_Controlled(A, B), 2, Q=Q, noise="log_diagonal", uses_input=True)
    ekf = ExtendedKalmanFilter(learned, sensor)
    prior = GaussianBelief(torch.zeros(4, 2), torch.eye(2))
    z = torch.randn(6, 4, 1, generator=generator)
    u = torch.randn(6, 4, 1, generator=generator)
    a, b = run_filter(kf, prior, z, controls=u), run_filter(ekf, prior, z, controls=u)
    close(b.belief.mean, a.belief.mean)
    close(b.log_likelihood, a.log_likelihood)
    b.total_log_likelihood().sum().backward()
    assert learned.net.B.grad is not None and learned.net.B.grad.abs().sum() > 0

"""A transition matrix with entries held at exactly 0 (a cyclic chain 0 -> 1 -> 2 -> 0), parametrised by a
softmax over each row's free entries (logits of ``-inf`` at the zeros): the gradient of the log-likelihood
in those logits must equal central finite differences on every path. GPB2 works with ``log pi_ij``; at a
zero entry ``log``'s derivative ``1 / 0`` met a zero adjoint (NaN), which the softmax's backward carried into
the row's free logits (``ModeTransition.log_matrix`` and the batch-last pairs kernel now pass no gradient
through a zero entry: ``torchmm.beliefs.ops.live_log``). IMM and GPB1 work with the matrix itself."""

from __future__ import annotations

import pytest
import torch

from torchmm import GPB1, GPB2, IMM, GaussianBelief, KalmanFilter, kernels, run_filter, smooth
from torchmm.kernels import linear
from torchmm.models import LinearMeasurement, LinearMotion

D = torch.float64
PATHS = {"linear_gaussian": dict(record="estimate"),  # (the Numba kernel: no full record under autograd)
         "batch_last": dict(record=None),
         "eager steps": dict(record="estimate", fast_path=False)}
CASES = [(path, comb) for path in PATHS for comb in (IMM, GPB1, GPB2)
         if not (path == "linear_gaussian" and comb is GPB2)]  # (the Numba kernel takes no GPB2)


def _cyclic(comb, theta):
    """``comb`` over three random walks of different noise, the transition a softmax over each row's free
    entries (``theta (4,)``; 0 -> 2, 1 -> 0 and 2 -> 1 held at exactly 0): ``(filter, belief0, z (20, 1))``."""
    zero, out = torch.zeros((), dtype=D), torch.tensor(-torch.inf, dtype=D)
    logits = torch.stack([torch.stack([theta[0], theta[1], out]),
                          torch.stack([out, theta[2], zero]),
                          torch.stack([theta[3], out, zero])])
    Q = torch.tensor([0.01, 1.0, 10.0], dtype=D).reshape(3, 1, 1)
    one = torch.ones(1, 1, dtype=D)
    f = comb(KalmanFilter(LinearMotion(one, Q), LinearMeasurement(one, one)), torch.softmax(logits, -1))
    b0 = f.initial_belief(GaussianBelief(torch.zeros(1, dtype=D), torch.eye(1, dtype=D)),
                          torch.full((3,), 1 / 3, dtype=D))
    return f, b0, torch.sin(torch.arange(20, dtype=D)).cumsum(0).reshape(-1, 1)


def _log_likelihood(comb, theta, **options):
    f, b0, z = _cyclic(comb, theta)
    traj = run_filter(f, b0, z, **options)
    return traj.log_likelihood.sum(), traj.provenance.kernel


@pytest.fixture(autouse=True)
def _short_runs_take_the_kernel(monkeypatch):
    monkeypatch.setattr(linear, "LONG_RUN", 0)  # (as tests/kernels/test_linear_kernel.py)


@pytest.mark.parametrize("path, comb", CASES, ids=[f"{p}-{c.__name__}" for p, c in CASES])
def test_gradient_through_a_transition_with_zero_entries(path, comb):
    theta = torch.tensor([1.0, 0.5, 2.0, -1.0], dtype=D, requires_grad=True)
    with kernels.switched_off(*[k for k in ("linear_gaussian",) if path == "batch_last"]):
        ll, kernel = _log_likelihood(comb, theta, **PATHS[path])
    assert kernel == path
    (grad,) = torch.autograd.grad(ll, theta)
    h, fd = 1e-6, []
    for i in range(4):
        e = torch.zeros(4, dtype=D)
        e[i] = h
        with torch.no_grad():
            up = _log_likelihood(comb, theta + e, fast_path=False)[0]
            down = _log_likelihood(comb, theta - e, fast_path=False)[0]
        fd.append(((up - down) / (2 * h)).item())
    assert min(abs(v) for v in fd) > 0.05  # (every logit matters)
    torch.testing.assert_close(grad, torch.tensor(fd, dtype=D), rtol=1e-6, atol=1e-8)


def _smoothed(comb, theta, method, off=()):
    """The smoothed mixture means and mode-0 probabilities, summed (one number that reads every step)."""
    f, b0, z = _cyclic(comb, theta)
    with kernels.switched_off(*off):
        s = smooth(f, run_filter(f, b0, z), z, method=method).belief
    mu = s.mode_log_probs.exp()
    return (s.components.mean.squeeze(-1) * mu).sum() + mu[..., 0].sum()


SMOOTHERS = [(comb, method, off) for comb in (IMM, GPB2) for method in ("kim", "two_filter", "two_filter_info")
             for off in ((), ("batch_last", "linear_gaussian"))]


@pytest.mark.parametrize("comb, method, off", SMOOTHERS,
                         ids=[f"{c.__name__}-{m}-{'eager' if o else 'kernels'}" for c, m, o in SMOOTHERS])
def test_smoother_gradient_through_a_transition_with_zero_entries(comb, method, off):
    """Every smoother reads ``log pi`` (``ModeTransition.log_matrix``; the batch-last two-filter kernel its own
    log): NaN in every logit before."""
    theta = torch.tensor([1.0, 0.5, 2.0, -1.0], dtype=D, requires_grad=True)
    (grad,) = torch.autograd.grad(_smoothed(comb, theta, method, off), theta)
    h, fd = 1e-6, []
    for i in range(4):
        e = torch.zeros(4, dtype=D)
        e[i] = h
        with torch.no_grad():
            fd.append(((_smoothed(comb, theta + e, method, off) - _smoothed(comb, theta - e, method, off))
                       / (2 * h)).item())
    assert min(abs(v) for v in fd) > 0.05
    # (the two-filter smoother's flat start amplifies rounding about 1e7-fold: finite differences to ~1e-6)
    rtol = 1e-4 if method == "two_filter" else 1e-6
    torch.testing.assert_close(grad, torch.tensor(fd, dtype=D), rtol=rtol, atol=1e-8)


@pytest.mark.parametrize("comb", [IMM, GPB1, GPB2], ids=lambda c: c.__name__)
def test_gradient_through_start_probabilities_with_a_zero(comb):
    """``initial_belief(mode_probs=)`` with a probability that is exactly 0 (a softmax with a ``-inf`` logit):
    ``probs.log()``'s NaN reached both free logits."""
    one = torch.ones(1, 1, dtype=D)
    z = torch.sin(torch.arange(20, dtype=D)).cumsum(0).reshape(-1, 1)

    def ll(theta):
        p0 = torch.softmax(torch.cat([theta, torch.tensor([-torch.inf], dtype=D)]), -1)
        kf = KalmanFilter(LinearMotion(one, torch.tensor([0.01, 1.0, 10.0], dtype=D).reshape(3, 1, 1)),
                          LinearMeasurement(one, one))
        f = comb(kf, torch.tensor([[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]], dtype=D))
        b0 = f.initial_belief(GaussianBelief(torch.zeros(1, dtype=D), torch.eye(1, dtype=D)), p0)
        return run_filter(f, b0, z, fast_path=False).log_likelihood.sum()

    theta = torch.tensor([1.0, 0.2], dtype=D, requires_grad=True)
    (grad,) = torch.autograd.grad(ll(theta), theta)
    e = torch.tensor([1e-6, 0.0], dtype=D)
    with torch.no_grad():
        fd = (ll(theta + e) - ll(theta - e)) / 2e-6
    assert abs(fd) > 0.05
    torch.testing.assert_close(grad, torch.stack([fd, -fd]), rtol=1e-6, atol=1e-8)

"""Defect 1: the coordinated-turn model is exact in value and derivative at and near omega = 0.

References: ``s = sin(w T) / w``, ``c = (1 - cos(w T)) / w`` and their derivatives in 50-digit
arithmetic (mpmath); the branch that returned constants below 1e-9 gave ``dc/dw = 0`` (exact:
``T^2 / 2``) and ``1 - cos`` cancelled just above it.
"""

from __future__ import annotations

import math

import mpmath
import pytest
import torch

from torchmm import (
    CoordinatedTurn,
    ExtendedKalmanFilter,
    GaussianBelief,
    NonlinearCoordinatedTurn,
    PositionMeasurement,
)
from torchmm.models.motion import turn_matrix

mpmath.mp.dps = 50
OMEGAS = [0.0] + [10.0**e for e in range(-15, 1)] + [0.03, 0.0499, 0.05, 0.0501, 0.3, 0.7]


def _exact(omega: float, T: float) -> dict[str, float]:
    w, t = mpmath.mpf(omega), mpmath.mpf(T)

    def s(x):
        return t * mpmath.sinc(x * t)

    def c(x):
        return x * t * t / 2 * mpmath.sinc(x * t / 2) ** 2  # (1 - cos(x t)) / x, exact at 0

    return {"s": float(s(w)), "c": float(c(w)), "ds": float(mpmath.diff(s, w)), "dc": float(mpmath.diff(c, w)),
            "cos": float(mpmath.cos(w * t)), "sin": float(mpmath.sin(w * t))}


@pytest.mark.parametrize("T", [1.0, 2.5])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_turn_terms_and_derivatives_match_the_analytic_values(T, sign):
    for omega in OMEGAS:
        w = torch.tensor(sign * omega, requires_grad=True)
        F = turn_matrix(w, T)
        s, c = F[0, 1], F[2, 1]
        ds, = torch.autograd.grad(s, w, retain_graph=True)
        dc, = torch.autograd.grad(c, w)
        ref = _exact(sign * omega, T)
        scale = T * T  # the Jacobian entries are of the order of T^2
        assert abs(s.item() - ref["s"]) <= 4e-16 * T, (omega, s.item(), ref["s"])
        assert abs(c.item() - ref["c"]) <= 4e-16 * max(abs(ref["c"]), T * 1e-16), (omega, c.item(), ref["c"])
        assert abs(ds.item() - ref["ds"]) <= 1e-13 * scale, (omega, ds.item(), ref["ds"])
        assert abs(dc.item() - ref["dc"]) <= 1e-15 * scale, (omega, dc.item(), ref["dc"])
        # the other entries are the plain cos / sin
        assert F[1, 1].item() == pytest.approx(ref["cos"], abs=4e-16)
        assert F[3, 1].item() == pytest.approx(ref["sin"], abs=4e-16)


def test_issue_reproducer_jacobian_at_zero_turn_rate():
    """``jacobian(...)[[0, 2], 4]`` was ``[0, 0]``; exact ``[-vy T^2/2, vx T^2/2] = [2.5, 5.0]``."""
    model = NonlinearCoordinatedTurn(dt=1.0)
    J = model.jacobian(torch.tensor([100.0, 10.0, 50.0, -5.0, 0.0]))
    torch.testing.assert_close(J[[0, 2], 4], torch.tensor([2.5, 5.0]), rtol=0, atol=1e-15)


class _AnalyticTurn(NonlinearCoordinatedTurn):
    """The same model with the Jacobian written out by hand (the reference)."""

    def jacobian(self, x, *, u=None):
        T = self.dt
        w = x[..., 4]
        vx, vy = x[..., 1], x[..., 3]
        ref = [_exact(float(v), T) for v in w.flatten()]
        J = torch.zeros(*x.shape, 5, dtype=x.dtype)
        flat = J.view(-1, 5, 5)
        for k, (r, a, b) in enumerate(zip(ref, vx.flatten(), vy.flatten())):
            flat[k, 0, 0] = flat[k, 2, 2] = flat[k, 4, 4] = 1.0
            flat[k, 0, 1], flat[k, 0, 3] = r["s"], -r["c"]
            flat[k, 1, 1], flat[k, 1, 3] = r["cos"], -r["sin"]
            flat[k, 2, 1], flat[k, 2, 3] = r["c"], r["s"]
            flat[k, 3, 1], flat[k, 3, 3] = r["sin"], r["cos"]
            dcos, dsin = -T * r["sin"], T * r["cos"]
            flat[k, 0, 4] = a * r["ds"] - b * r["dc"]
            flat[k, 1, 4] = a * dcos - b * dsin
            flat[k, 2, 4] = a * r["dc"] + b * r["ds"]
            flat[k, 3, 4] = a * dsin + b * dcos
        return J


def test_ekf_started_at_zero_turn_rate_equals_the_exact_jacobian_ekf():
    """Up to 87 % covariance differences before the fix."""
    sensor = PositionMeasurement(5, [0, 2], 4.0)
    prior = GaussianBelief(torch.tensor([[100.0, 10.0, 50.0, -5.0, 0.0], [0.0, 3.0, 0.0, 4.0, 1e-8]]),
                           torch.diag(torch.tensor([4.0, 1.0, 4.0, 1.0, 0.01])).expand(2, 5, 5))
    auto = ExtendedKalmanFilter(NonlinearCoordinatedTurn(dt=1.0, q=0.1, q_omega=1e-4), sensor)
    exact = ExtendedKalmanFilter(_AnalyticTurn(dt=1.0, q=0.1, q_omega=1e-4), sensor)
    z = torch.tensor([[110.0, 45.0], [3.0, 4.0]])
    a, b = auto.step(prior, z), exact.step(prior, z)
    torch.testing.assert_close(a.belief.cov, b.belief.cov, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(a.belief.mean, b.belief.mean, rtol=1e-12, atol=1e-12)


def test_gradcheck_at_zero_turn_rate():
    def known_rate(w):
        return CoordinatedTurn(w, dt=1.5).F

    def in_state(w):
        x = torch.cat([torch.tensor([1.0, 2.0, 3.0, -1.0], dtype=w.dtype), w.reshape(1)])
        return NonlinearCoordinatedTurn(dt=1.5)(x)

    for w0 in (0.0, 1e-9, 1e-5, 0.1):
        w = torch.tensor(w0, requires_grad=True)
        assert torch.autograd.gradcheck(known_rate, (w,), eps=1e-7, atol=1e-7)
        assert torch.autograd.gradcheck(in_state, (w,), eps=1e-7, atol=1e-7)
        assert torch.autograd.gradgradcheck(in_state, (w,), eps=1e-6, atol=1e-5)


def test_zero_turn_rate_is_exactly_constant_velocity_and_float32_is_accurate():
    from torchmm import ConstantVelocity

    torch.testing.assert_close(CoordinatedTurn(0.0, dt=2.0).F, ConstantVelocity(2, dt=2.0).F, rtol=0, atol=0)
    w = torch.tensor([0.0, 1e-6, 1e-3, 0.2], dtype=torch.float32, requires_grad=True)
    F = turn_matrix(w, 1.0)
    dc = torch.autograd.grad(F[:, 2, 1].sum(), w)[0]
    ref = torch.tensor([_exact(float(v), 1.0)["dc"] for v in w.detach()], dtype=torch.float32)
    torch.testing.assert_close(dc, ref, rtol=1e-6, atol=1e-7)
    assert math.isfinite(F.sum().item())


@pytest.mark.parametrize("T", [1.0, 2.5])
def test_closed_form_jacobian_matches_the_50_digit_jacobian_and_autograd(T):
    """``NonlinearCoordinatedTurn.jacobian`` is written out (issue 31: no forward-mode autograd per
    step); against the mpmath Jacobian at every turn rate of OMEGAS, both signs, around the series
    switch ``|omega T| = 0.1``, and against forward-mode autograd of the model."""
    from torchmm.models.base import forward_jacobian

    omegas = [sign * w for w in OMEGAS for sign in (1.0, -1.0)] + [0.1 / T * (1 + d) for d in (-1e-12, 0, 1e-12)]
    x = torch.tensor([[100.0, 10.0 + k % 3, 50.0, -5.0 + k % 2, w] for k, w in enumerate(omegas)],
                     dtype=torch.float64)
    model = NonlinearCoordinatedTurn(dt=T, q=0.1, q_omega=1e-4)
    J = model.jacobian(x)
    assert J.shape == (len(omegas), 5, 5) and J.dtype == torch.float64
    exact = _AnalyticTurn(dt=T, q=0.1, q_omega=1e-4).jacobian(x)
    # entries of order |v| T^2 (the omega column) or 1: the series and closed forms to a few ulps
    torch.testing.assert_close(J, exact, rtol=0, atol=2e-14 * T * T * 15)
    torch.testing.assert_close(J, forward_jacobian(model, x), rtol=0, atol=2e-14 * T * T * 15)


def test_closed_form_jacobian_is_differentiable():
    """Training through an EKF differentiates the Jacobian: its derivatives in the state, in both
    branches and at omega = 0, by finite differences."""
    model = NonlinearCoordinatedTurn(dt=1.5)
    for w0 in (0.0, 1e-7, 0.05, 0.0666, 0.07, 0.4, -0.3):
        x = torch.tensor([1.0, 2.0, 3.0, -1.0, w0], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(model.jacobian, (x,), eps=1e-7, atol=1e-7)

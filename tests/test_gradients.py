"""Gradients through filters: gradcheck of the negative log-likelihood (float64)."""

from __future__ import annotations

import torch
from torch import nn
from torch.autograd import gradcheck

from torchmm import (
    GPB1,
    IMM,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    LinearMotion,
    UnscentedKalmanFilter,
    run_filter,
)
from torchmm.models import ConstantVelocity

D = torch.float64  # module constants are built before the float64 fixture runs
F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=D)
H = torch.tensor([[1.0, 0.0]], dtype=D)
ZS = torch.tensor([[0.3], [1.1], [2.4], [3.2], [float("nan")], [5.9]], dtype=D).unsqueeze(1).expand(6, 2, 1).clone()
ZS[2, 1] = float("nan")  # missing data: one whole step, and one run at another step
PRIOR = GaussianBelief(torch.zeros(2, 2, dtype=D), torch.eye(2, dtype=D) * 2.0)


def _sym(A):
    return 0.5 * (A + A.mT)


def test_kalman_log_likelihood_gradcheck_q_r_f():
    def nll(A_q, r, F_):
        kf = KalmanFilter(LinearMotion(F_, _sym(A_q)), LinearMeasurement(H, r))
        return -run_filter(kf, PRIOR, ZS).total_log_likelihood()

    inputs = (torch.tensor([[0.5, 0.1], [0.1, 0.3]], requires_grad=True),
              torch.tensor([[0.8]], requires_grad=True), F.clone().requires_grad_())
    assert gradcheck(nll, inputs)


def test_ekf_ukf_log_likelihood_gradcheck():
    for cls in (ExtendedKalmanFilter, UnscentedKalmanFilter):
        def nll(A_q, r, cls=cls):
            f = cls(LinearMotion(F, _sym(A_q)), LinearMeasurement(H, r))
            return -run_filter(f, PRIOR, ZS).total_log_likelihood()

        inputs = (torch.tensor([[0.5, 0.1], [0.1, 0.3]], requires_grad=True),
                  torch.tensor([[0.8]], requires_grad=True))
        assert gradcheck(nll, inputs), cls.__name__


def test_imm_log_likelihood_gradcheck_q_r_transition():
    offsets = torch.tensor([[0.5, 1.0], [0.0, 0.0], [-0.5, -1.0]], dtype=D)

    def nll(A_q, r, transition):
        motion = LinearMotion(F, _sym(A_q), offset=offsets)
        imm = IMM(KalmanFilter(motion, LinearMeasurement(H, r)), transition)
        return -run_filter(imm, imm.initial_belief(PRIOR), ZS).total_log_likelihood()

    transition = torch.tensor([[0.8, 0.1, 0.1], [0.2, 0.7, 0.1], [0.25, 0.25, 0.5]], requires_grad=True)
    inputs = (torch.tensor([[0.5, 0.1], [0.1, 0.3]], requires_grad=True),
              torch.tensor([[0.8]], requires_grad=True), transition)
    assert gradcheck(nll, inputs)


def test_gpb1_log_likelihood_gradcheck_transition():
    motion = ConstantVelocity(1, q=0.5, acceleration=[[0.5], [-0.5]])

    def nll(transition):
        gpb = GPB1(KalmanFilter(motion, LinearMeasurement(H, torch.tensor([[0.8]]))), transition)
        return -run_filter(gpb, gpb.initial_belief(PRIOR), ZS).total_log_likelihood()

    assert gradcheck(nll, (torch.tensor([[0.9, 0.1], [0.3, 0.7]], requires_grad=True),))


def test_learnable_parameters_receive_gradients_through_run_filter():
    motion = LinearMotion(nn.Parameter(F.clone()), torch.eye(2) * 0.1)
    kf = KalmanFilter(motion, LinearMeasurement(H, torch.tensor([[1.0]])))
    assert [name for name, _ in kf.named_parameters()] == ["motion.F"]
    loss = -run_filter(kf, PRIOR, ZS).total_log_likelihood().sum()
    loss.backward()
    assert motion.F.grad is not None and bool(torch.isfinite(motion.F.grad).all())
    assert motion.F.grad.abs().sum() > 0

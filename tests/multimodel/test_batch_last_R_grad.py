"""The batch-last kernels' diagonal ``R`` under autograd (torchmm/kernels/batch_last/plan.py, ``why_not``):
the kernels update one measurement component after the other and read only ``R``'s (and IMM-TF's
``R_S``'s) diagonal, so an ``R`` that requires grad would get a zero gradient for its off-diagonal
entries. A run whose diagonal ``R`` (or ``R_S``) of ``m > 1`` components requires grad declines them
(``provenance.declined`` says why) and its gradient equals the eager steps' and central finite
differences of the log-likelihood; a ``torch.diag_embed`` output (``learnable_noise(..., "log_diagonal")``),
whose own backward drops the off-diagonal adjoint, keeps the kernel with the eager gradient."""

from __future__ import annotations

import pytest
import torch

from torchmm import (GPB2, IMM, GaussianBelief, KalmanFilter, LinearMeasurement, LinearMotion, kernels,
                     run_filter)
from torchmm.models.adapters import learnable_noise
from torchmm.multimodel import MultiRate, TransferIMM

D = torch.float64
_P = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=D)


def _data():
    g = torch.Generator().manual_seed(0)
    return torch.randn(4, 2, dtype=D, generator=g), torch.randn(4, 2, dtype=D, generator=g)


def _filter(kind, R, R_S):
    """``kind`` in imm / gpb2 / transfer over two constant-position modes, and its measurements."""
    F = torch.eye(2, dtype=D).expand(2, 2, 2).clone()
    Q = torch.stack([0.1 * torch.eye(2, dtype=D), torch.eye(2, dtype=D)])
    kf = KalmanFilter(LinearMotion(F, Q), LinearMeasurement(torch.eye(2, dtype=D), R))
    y, ys = _data()
    if kind == "imm":
        f, z = IMM(kf, _P), y
    elif kind == "gpb2":
        f, z = GPB2(kf, _P), y
    else:
        H_S = torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=D)
        f, z = TransferIMM(kf, _P, LinearMeasurement(H_S, R_S)), MultiRate(y, ys)
    b0 = f.initial_belief(GaussianBelief(torch.zeros(2, dtype=D), torch.eye(2, dtype=D)),
                          torch.tensor([0.5, 0.5], dtype=D))
    return f, b0, z


def _R(off=0.0):
    return torch.tensor([[1.0, off], [off, 1.0]], dtype=D)


def _RS(off=0.0):
    return torch.tensor([[0.5, off], [off, 0.5]], dtype=D)


@pytest.mark.parametrize("kind, target",
                         [("imm", "R"), ("gpb2", "R"), ("transfer", "R"), ("transfer", "R_S")])
def test_off_diagonal_gradient_of_a_diagonal_R(kind, target):
    R, R_S = _R().requires_grad_(True), _RS().requires_grad_(True)
    leaf = R if target == "R" else R_S
    grads = {}
    for fast_path in (None, False):
        f, b0, z = _filter(kind, R, R_S)
        traj = run_filter(f, b0, z, fast_path=fast_path)
        (grads[fast_path],) = torch.autograd.grad(traj.log_likelihood.sum(), leaf)
        if fast_path is None:
            assert not traj.provenance.kernel.startswith("batch_last"), traj.provenance.kernel
            assert "requires grad" in traj.provenance.declined
    torch.testing.assert_close(grads[None], grads[False], rtol=1e-10, atol=1e-12)

    # the symmetric off-diagonal direction, by central differences of the log-likelihood (float64)
    def ll(off):
        with torch.no_grad():
            Rv, RSv = (_R(off), _RS()) if target == "R" else (_R(), _RS(off))
            f, b0, z = _filter(kind, Rv, RSv)
            return run_filter(f, b0, z, fast_path=False).log_likelihood.sum().item()

    h = 1e-6
    fd = (ll(h) - ll(-h)) / (2 * h)
    assert abs(fd) > 1e-3  # (a real off-diagonal gradient, which the diagonal update dropped)
    torch.testing.assert_close(grads[None][0, 1] + grads[None][1, 0], torch.tensor(fd, dtype=D),
                               rtol=1e-6, atol=1e-8)


def test_no_grad_and_diag_embedded_R_keep_the_kernel():
    f, b0, z = _filter("imm", _R().requires_grad_(True), _RS())
    with torch.no_grad(), kernels.switched_off("linear_gaussian"):  # (the small Numba kernel takes it first)
        assert run_filter(f, b0, z).provenance.kernel == "batch_last"
    grads = {}
    for fast_path in (None, False):
        f, b0, z = _filter("imm", _R(), _RS())
        learnable_noise(f.bank.filter.measurement, "R", "log_diagonal")
        theta = f.bank.filter.measurement.parametrizations.R.original
        traj = run_filter(f, b0, z, fast_path=fast_path)
        assert traj.provenance.kernel == ("batch_last" if fast_path is None else "eager steps")
        (grads[fast_path],) = torch.autograd.grad(traj.log_likelihood.sum(), theta)
    torch.testing.assert_close(grads[None], grads[False], rtol=1e-10, atol=1e-12)

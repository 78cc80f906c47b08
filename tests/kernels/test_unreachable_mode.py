"""A mode that no run can reach (a zero start probability and a zero transition into it): its predicted
probability ``c_j`` is exactly 0. The log-likelihood is finite and smooth in the other modes' models, and
its gradient must be too - through the Numba kernel's reverse pass (torchmm/kernels/linear_reverse.py:
it divided by the raw ``c_j``, a ZeroDivisionError), the batch-last kernel and the eager steps (NaN:
``log``'s derivative ``1 / c_j`` times a zero adjoint, carried into every mode by the mixing). Each path's
gradient is checked against central finite differences of the eager log-likelihood."""

from __future__ import annotations

import pytest
import torch

from torchmm import GPB1, GPB2, IMM, GaussianBelief, KalmanFilter, kernels, run_filter
from torchmm.kernels import linear
from torchmm.models import LinearMeasurement, LinearMotion

D = torch.float64
PATHS = {"linear_gaussian": dict(record="estimate"),  # (the Numba kernel: no full record under autograd)
         "batch_last": dict(record=None),
         "eager steps": dict(record="estimate", fast_path=False)}


@pytest.fixture(autouse=True)
def _short_runs_take_the_kernel(monkeypatch):
    monkeypatch.setattr(linear, "LONG_RUN", 0)  # (as tests/kernels/test_linear_kernel.py)


def _log_likelihood(comb, Q, update_first, **options):
    kf = KalmanFilter(LinearMotion(torch.ones(1, 1, dtype=D), Q),
                      LinearMeasurement(torch.ones(1, 1, dtype=D), torch.eye(1, dtype=D)))
    f = comb(kf, torch.tensor([[0.9, 0.1], [0.0, 1.0]], dtype=D))  # mode 0 unreachable from mode 1
    b0 = f.initial_belief(GaussianBelief(torch.zeros(1, dtype=D), torch.eye(1, dtype=D)),
                          torch.tensor([0.0, 1.0], dtype=D))
    z = torch.tensor([[0.3], [-0.5], [1.2]], dtype=D)
    traj = run_filter(f, b0, z, update_first=update_first, **options)
    return traj.log_likelihood.sum(), traj.provenance.kernel


# (path, combinator, update_first): the batch-last kernel takes no update_first, the Numba one no GPB2
CASES = [(path, comb, first) for path in PATHS for comb in (IMM, GPB1, GPB2) for first in (True, False)
         if not (path == "batch_last" and first) and not (path == "linear_gaussian" and comb is GPB2)]


@pytest.mark.parametrize("path, comb, update_first", CASES,
                         ids=[f"{p}-{c.__name__}-{'update_first' if f else 'predict_first'}" for p, c, f in CASES])
def test_gradient_with_an_unreachable_mode(path, comb, update_first):
    """GPB2: logsumexp over a dead mode's pairs (all -inf) had a NaN backward, reaching every parameter
    (torchmm.beliefs.ops.dead_safe_logsumexp, eager and batch-last)."""
    q = torch.tensor([0.1, 1.0], dtype=D)
    Q = q.reshape(2, 1, 1).clone().requires_grad_(True)
    off = [k for k in ("linear_gaussian",) if path == "batch_last"]
    with kernels.switched_off(*off):
        ll, kernel = _log_likelihood(comb, Q, update_first, **PATHS[path])
    assert kernel == path
    assert torch.isfinite(ll)
    (grad,) = torch.autograd.grad(ll, Q)

    h = 1e-6
    fd = []
    for i in range(2):
        e = torch.zeros(2, dtype=D)
        e[i] = h
        with torch.no_grad():
            up = _log_likelihood(comb, (q + e).reshape(2, 1, 1), update_first, fast_path=False)[0]
            down = _log_likelihood(comb, (q - e).reshape(2, 1, 1), update_first, fast_path=False)[0]
        fd.append(((up - down) / (2 * h)).item())
    assert abs(fd[1]) > 0.1 and fd[0] == 0.0  # (the unreachable mode's Q is irrelevant, the live one's not)
    torch.testing.assert_close(grad.flatten(), torch.tensor(fd, dtype=D), rtol=1e-6, atol=1e-8)

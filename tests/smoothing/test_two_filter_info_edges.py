"""``smooth(..., method="two_filter_info")`` (torchmm/two_filter_info.py) where its divisions and fusions can
break, against the float64 NumPy exact smoother of tests/reference/jump_numpy.py (every mode sequence, no
inverse of F, Q or P): a filtered covariance that is singular (a state component known exactly: the
reference density of the mixture's collapse), a singular measurement covariance (refused), fusions that
must stay proper (the floor at 0 of the divided-out information; a wrong-signed determinant gives NaN,
not a number), and padded runs whose controls are NaN after their end (docs/smoothing.md, "The
information-form backward filter")."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmm import (GPB2, IMM, GaussianBelief, KalmanFilter, LinearMeasurement, LinearMotion, run_filter,
                     smooth)
from torchmm.two_filter_info import info_fuse, info_predict

from tests.reference.jump_numpy import exact

D = torch.float64
INFO = "two_filter_info"


def _t(a):
    return torch.as_tensor(np.asarray(a, dtype=np.float64))


def _model(F, b, Q, H, R, Pi, combinator=IMM, B=None):
    motion = LinearMotion(_t(F), _t(Q), _t(b), None if B is None else _t(B))
    return combinator(KalmanFilter(motion, LinearMeasurement(_t(H), _t(R))), _t(Pi))


def _filter(mm, mu0, m0, P0, z, u=None):
    runs, n = z.shape[1], len(m0)
    b0 = GaussianBelief(_t(m0).expand(runs, n), _t(P0).expand(runs, n, n))
    return run_filter(mm, mm.initial_belief(b0, _t(mu0)), _t(z), **({} if u is None else {"controls": _t(u)}))


def _exact(F, b, Q, H, R, Pi, mu0, m0, P0, z):
    refs = [exact(F, b, Q, H, R, Pi, mu0, m0, P0, z[:, r]) for r in range(z.shape[1])]
    return tuple(np.stack(parts, 1) for parts in zip(*refs))  # mean (T, runs, n), cov, probs (T, runs, M)


def _intercept(Pi):
    """x = [level, 1] (the constant 1 known exactly: P0 = diag(4, 0), no noise on it), modes drifting 0
    and +1 a step; 3 runs of 8 steps."""
    F = [[[1.0, 0.0], [0.0, 1.0]], [[1.0, 1.0], [0.0, 1.0]]]
    Q = [np.diag([0.1, 0.0])] * 2
    g = torch.Generator().manual_seed(2)
    steps = torch.randint(0, 2, (8, 3), generator=g).cumsum(0)
    z = (steps + torch.randn(8, 3, generator=g, dtype=D)).unsqueeze(-1)
    return dict(F=F, b=np.zeros((2, 2)), Q=Q, H=[[[1.0, 0.0]]] * 2, R=[[[1.0]]] * 2, Pi=Pi, mu0=[0.5, 0.5],
                m0=[0.0, 1.0], P0=np.diag([4.0, 0.0]), z=z.numpy())


@pytest.mark.parametrize("combinator", [IMM, GPB2])
def test_a_state_component_known_exactly_static_modes_are_exact(combinator):
    """Every filtered covariance singular (the constant's direction): static modes are exact for IMM and
    GPB2 (as the default reading, tests/smoothing/test_two_filter.py). Before, the singular reference was
    regularised silently: the level off by 0.97, mode probabilities by 0.66, the constant 0.74 .. 0.97."""
    case = _intercept(np.eye(2))
    mean, _, probs = _exact(**case)
    traj = _filter(_model(*(case[k] for k in "F b Q H R Pi".split()), combinator),
                   case["mu0"], case["m0"], case["P0"], case["z"])
    out = smooth(traj, method=INFO)
    np.testing.assert_allclose(out.belief.estimate().mean.numpy(), mean, atol=1e-10, rtol=0)
    np.testing.assert_allclose(out.belief.mode_probs.numpy(), probs, atol=1e-10, rtol=0)
    assert not out.extras["failed"].any()


def test_a_state_component_known_exactly_switching_modes():
    """Switching modes: the constant stays 1, and the level is closer to the exact smoother than Kim's."""
    case = _intercept([[0.9, 0.1], [0.1, 0.9]])
    mean, _, _ = _exact(**case)
    traj = _filter(_model(*(case[k] for k in "F b Q H R Pi".split())), case["mu0"], case["m0"], case["P0"],
                   case["z"])
    info, kim = (smooth(traj, method=m).belief.estimate().mean.numpy() for m in (INFO, "kim"))
    np.testing.assert_allclose(info[..., 1], 1.0, atol=1e-10, rtol=0)
    err = {m: np.abs(e[:-1, :, 0] - mean[:-1, :, 0]).max() for m, e in (("info", info), ("kim", kim))}
    assert err["info"] < err["kim"], err


@pytest.mark.parametrize("combinator", [IMM, GPB2])
def test_a_mode_that_forgets_the_state_takes_all_probability(combinator):
    """A mode with a zero row of F and Q = 0 (its filtered covariance singular) takes all the probability,
    static modes: exact. Before: GPB2 mode probabilities off by 1 (NaN in the audit's case), IMM 1e-9."""
    case = dict(F=[[[1.2, 0.15], [0.05, 1.2]], [[0.0, 0.0], [-0.2, 1.0]]], b=[[-0.2, -0.6], [0.5, 0.1]],
                Q=np.zeros((2, 2, 2)), H=[[[1.6, -1.1]], [[0.4, 0.45]]], R=[[[0.25]], [[0.9]]], Pi=np.eye(2),
                mu0=[0.5, 0.5], m0=[-1.4, 2.1], P0=[[2.8, 2.5], [2.5, 2.8]],
                z=np.array([[-0.77, 0.32], [0.11, 2.2], [-0.64, -5.93], [-1.52, 0.37], [-0.88, 1.54],
                            [2.03, -0.3]])[..., None])
    mean, _, probs = _exact(**case)
    traj = _filter(_model(*(case[k] for k in "F b Q H R Pi".split()), combinator),
                   case["mu0"], case["m0"], case["P0"], case["z"])
    out = smooth(traj, method=INFO).belief
    np.testing.assert_allclose(out.estimate().mean.numpy(), mean, atol=1e-10, rtol=0)
    np.testing.assert_allclose(out.mode_probs.numpy(), probs, atol=1e-10, rtol=0)


def test_a_singular_measurement_covariance_is_refused():
    """A noise-free measurement component (R = diag(1, 0), which LinearMeasurement accepts) has infinite
    information: refused naming ``method`` (before: regularised silently, mode probabilities off by 0.18)."""
    F = [[[1.0, 1.0], [0.0, 1.0]], [[0.9, 0.5], [0.0, 0.8]]]
    mm = _model(F, np.zeros((2, 2)), [0.1 * np.eye(2), 0.5 * np.eye(2)], [np.eye(2)] * 2,
                [np.diag([1.0, 0.0])] * 2, np.eye(2))
    z = torch.randn(6, 2, 2, generator=torch.Generator().manual_seed(3), dtype=D).numpy()
    traj = _filter(mm, [0.5, 0.5], np.zeros(2), np.eye(2), z)
    with pytest.raises(ValueError, match="method: 'two_filter_info' needs a positive definite measurement"):
        smooth(traj, method=INFO)
    assert torch.isfinite(smooth(traj, method="kim").belief.estimate().mean).all()  # the alternative named


def test_the_divided_out_information_keeps_every_fusion_proper():
    """The audit's random case (IMM, a mode with a zero row of F; inputs rounded to 3 digits) where the old
    guard (eigenvalues floored at -0.5 relative to the reference) let indefinite pair fusions through:
    errors up to 6.1 posterior sd; now 0.28, and every smoothed covariance positive definite."""
    case = dict(F=[[[0.664, 0.345], [-0.115, 1.048]], [[0.0, 0.0], [-0.096, 0.11]]],
                b=[[1.083, -0.299], [2.108, -0.349]],
                Q=[[[0.081, 0.048], [0.048, 0.099]], [[0.501, -0.687], [-0.687, 1.734]]],
                H=[[[-1.137, -0.156]], [[1.078, -0.937]]], R=[[[3.907]], [[1.808]]],
                Pi=[[0.839, 0.161], [0.164, 0.836]], mu0=[0.5, 0.5], m0=[-1.5, 1.358],
                P0=[[0.498, -0.623], [-0.623, 1.885]],
                z=np.array([[0.77, 2.0, 1.081], [2.053, 1.46, 1.187], [2.616, 1.442, 1.489],
                            [3.042, 2.286, 1.387], [2.693, 1.458, 0.496], [3.865, 1.373, 1.282],
                            [2.568, -0.565, 0.233]])[..., None])
    mean, cov, _ = _exact(**case)
    traj = _filter(_model(*(case[k] for k in "F b Q H R Pi".split())), case["mu0"], case["m0"], case["P0"],
                   case["z"])
    out = smooth(traj, method=INFO)
    sd = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))
    err = np.abs(out.belief.estimate().mean.numpy() - mean)[:-1] / sd[:-1]
    assert err.max() < 1.0, err.max()
    assert torch.linalg.eigvalsh(out.belief.components.cov).min() > 0
    assert not out.extras["failed"].any()


def test_an_improper_fusion_is_nan_not_a_number():
    """``I + S Omega`` or ``I + Omega Q`` with a negative determinant (an indefinite ``Omega``: the
    integral diverges) gives NaN; before, ``log |det|`` returned a finite log-likelihood."""
    Omega = torch.tensor([[-2.0, 0.0], [0.0, 1.0]], dtype=D)  # S = Q = I: det(I + Omega) = -2
    omega, lam, eye = torch.zeros(2, dtype=D), torch.zeros((), dtype=D), torch.eye(2, dtype=D)
    assert torch.isnan(info_fuse(torch.zeros(2, dtype=D), eye, Omega, omega, lam)[0])
    assert torch.isnan(info_predict(Omega, omega, lam, eye, eye, torch.zeros(2, dtype=D))[2])
    proper = info_fuse(torch.zeros(2, dtype=D), eye, Omega.abs(), omega, lam)[0]  # det 6: log 6 / -2
    torch.testing.assert_close(proper, torch.tensor(-0.5 * np.log(6.0), dtype=D))


@pytest.mark.parametrize("with_present", [True, False])
def test_nan_controls_after_a_run_ends(with_present):
    """Runs of 8, 5 and 3 steps whose controls are NaN after their end (``present=``, or the runs' trailing
    missing data) smooth as each alone; before, NaN over their real steps."""
    F, Q = [[[1.0, 1.0], [0.0, 1.0]]] * 2, [0.05 * np.eye(2), np.eye(2)]
    B, Pi = [[[0.5], [1.0]]] * 2, [[0.9, 0.1], [0.2, 0.8]]
    mm = _model(F, np.zeros((2, 2)), Q, [[[1.0, 0.0]]] * 2, [[[1.0]]] * 2, Pi, B=B)
    g = torch.Generator().manual_seed(5)
    z, u = 3 * torch.randn(8, 3, 1, generator=g, dtype=D), torch.randn(8, 3, 1, generator=g, dtype=D)
    lengths = [8, 5, 3]
    present = torch.arange(8).unsqueeze(-1) < torch.tensor(lengths)
    zp, up = (torch.where(present.unsqueeze(-1), x, torch.nan).numpy() for x in (z, u))
    traj = _filter(mm, [0.6, 0.4], np.zeros(2), np.eye(2), zp, up)
    out = smooth(traj, method=INFO, **({"present": present} if with_present else {})).belief
    for r, length in enumerate(lengths):
        alone = smooth(_filter(mm, [0.6, 0.4], np.zeros(2), np.eye(2), z[:length, r:r + 1].numpy(),
                               u[:length, r:r + 1].numpy()), method=INFO).belief
        torch.testing.assert_close(out.estimate().mean[:length, r], alone.estimate().mean[:, 0],
                                   rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(out.mode_probs[:length, r], alone.mode_probs[:, 0], rtol=1e-10, atol=1e-12)

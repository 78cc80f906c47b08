"""A user's MotionModel / MeasurementModel outputs are checked where the filters call the model.

Before, nothing checked them: a one-output sensor returning ``(*B,)`` instead of ``(*B, 1)`` (``x[..., 0]``)
was filtered silently into garbage (EKF log-likelihood -7e15 for 2 runs, the IMM's fast path -13.50 where
-13.55 is right: ``z (B, 1) - h (B,)`` broadcast to ``(B, B)``); a motion returning ``(*B, 3)`` for
``state_dim`` 2 raised a raw RuntimeError deep in a step; a float32 forward or ``noise_cov`` next to a float64
belief ran at float32 precision (UKF, PF) or raised a raw RuntimeError. Now each is a ValueError /
TypeError naming the model's slot, on the eager steps, the particle filter and the batch-last kernel of the
IMM over an extended bank; models that keep the contract give the numbers of a float64 NumPy Kalman filter.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmm import (
    IMM,
    ExtendedKalmanFilter,
    GaussianBelief,
    ParticleFilter,
    UnscentedKalmanFilter,
    run_filter,
)
from torchmm.models import MeasurementModel, MotionModel

D = torch.float64
DT = 0.5
Q = [[0.05, 0.0], [0.0, 0.3]]


class CV(MotionModel):
    state_dim = 2

    def forward(self, x, *, u=None):
        return torch.stack([x[..., 0] + DT * x[..., 1], x[..., 1]], -1)

    def noise_cov(self, x=None):
        return torch.tensor(Q, dtype=D)


class Pos(MeasurementModel):
    state_dim, meas_dim = 2, 1

    def forward(self, x):
        return x[..., :1]

    def noise_cov(self, x=None):
        return torch.tensor([[4.0]], dtype=D)


class PosNoEventAxis(Pos):
    """The common slip: ``(*B,)`` instead of ``(*B, 1)``."""

    def forward(self, x):
        return x[..., 0]


class WrongDim(CV):
    def forward(self, x, *, u=None):
        return torch.cat([x, x[..., :1]], -1)  # (*B, 3) for state_dim 2


class Float32Out(CV):
    def forward(self, x, *, u=None):
        return super().forward(x).float()


class Float32Q(CV):
    def noise_cov(self, x=None):
        return torch.tensor(Q, dtype=torch.float32)


class Float32R(Pos):
    def noise_cov(self, x=None):
        return torch.tensor([[4.0]], dtype=torch.float32)


class SharedNoise(CV):
    """Legitimate broadcasting: a noise covariance with a unit batch axis ``(1, n, n)``."""

    def noise_cov(self, x=None):
        return super().noise_cov().unsqueeze(0)


class CVBank(CV):
    """Two modes through a noise bank ``(M, n, n)``."""

    def noise_cov(self, x=None):
        return torch.diag_embed(torch.tensor([[0.05, 0.3], [0.5, 3.0]], dtype=D))


class OwnEntries(Pos):
    """A sensor whose own ``forward_entries`` (the batch-last kernel's call) returns two entries for
    ``meas_dim`` 1."""

    def forward_entries(self, x):
        return [x[0], x[1]]


def _data(B: int) -> tuple[GaussianBelief, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    z = 2 * torch.randn(6, B, 1, dtype=D, generator=g)
    z[2, 0] = float("nan")
    return GaussianBelief(torch.zeros(B, 2, dtype=D), torch.eye(2, dtype=D).expand(B, 2, 2).clone()), z


def _run(kind: str, motion, sensor, B: int):
    b0, z = _data(B)
    if kind == "pf":
        pf = ParticleFilter(motion, sensor, num_particles=64)
        g = torch.Generator().manual_seed(0)
        return run_filter(pf, pf.initial_belief(b0, generator=g), z, generator=g)
    filt = (ExtendedKalmanFilter if kind == "ekf" else UnscentedKalmanFilter)(motion, sensor)
    return run_filter(filt, b0, z)


def _numpy_kalman(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A float64 NumPy Kalman filter of CV + Pos for one run ``z (T,)``: log-likelihoods, means."""
    F, H = np.array([[1.0, DT], [0.0, 1.0]]), np.array([[1.0, 0.0]])
    m, P, lls, means = np.zeros(2), np.eye(2), [], []
    for zk in z:
        m, P = F @ m, F @ P @ F.T + np.array(Q)
        if np.isfinite(zk):
            S = (H @ P @ H.T)[0, 0] + 4.0
            nu = zk - m[0]
            K = P @ H.T[:, 0] / S
            m, P = m + K * nu, P - np.outer(K, K) * S
            lls.append(-0.5 * (nu * nu / S + np.log(2 * np.pi * S)))
        else:
            lls.append(0.0)
        means.append(m)
    return np.array(lls), np.array(means)


@pytest.mark.parametrize("kind", ["ekf", "ukf", "pf"])
@pytest.mark.parametrize("B", [2, 3])
def test_a_sensor_without_its_event_axis_is_refused_naming_measurement(kind, B):
    with pytest.raises(ValueError, match=r"^measurement: returned shape .*expected \(.*1\) - \(\*B, m\) "
                                         r"with meas_dim 1.*event axis is missing"):
        _run(kind, CV(), PosNoEventAxis(), B)


@pytest.mark.parametrize("fast_path", [False, True])
@pytest.mark.parametrize("B", [1, 4])
def test_an_imm_over_a_sensor_without_its_event_axis_is_refused_on_both_paths(fast_path, B):
    """Old code: B = 1 gave -1.98e11 (eager) and -13.5033 (the kernel; right: -13.5506), silently."""
    b0, z = _data(B)
    imm = IMM(ExtendedKalmanFilter(CVBank(), PosNoEventAxis()), torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=D))
    with pytest.raises(ValueError, match=r"^measurement(\.jacobian)?: returned shape"):
        run_filter(imm, imm.initial_belief(b0), z, fast_path=fast_path)


def test_the_kernel_checks_a_models_own_entries():
    b0, z = _data(4)
    imm = IMM(ExtendedKalmanFilter(CVBank(), OwnEntries()), torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=D))
    good = run_filter(imm, imm.initial_belief(b0), z, fast_path=False)  # (the eager steps call forward)
    assert torch.isfinite(good.log_likelihood).all()
    with pytest.raises(ValueError, match=r"^measurement\.forward_entries: returned 2 items, expected 1"):
        run_filter(imm, imm.initial_belief(b0), z, fast_path=True)


@pytest.mark.parametrize("kind", ["ekf", "ukf", "pf"])
def test_a_motion_of_another_width_is_refused_naming_motion(kind):
    with pytest.raises(ValueError, match=r"^motion: returned shape \(.*3\) .*\(\*B, n\) with state_dim 2"):
        _run(kind, WrongDim(), Pos(), 2)


@pytest.mark.parametrize("kind", ["ekf", "ukf", "pf"])
@pytest.mark.parametrize("motion, sensor, name", [(Float32Out(), Pos(), "motion"),
                                                  (Float32Q(), Pos(), "motion.noise_cov"),
                                                  (CV(), Float32R(), "measurement.noise_cov")])
def test_a_float32_output_next_to_a_float64_belief_is_refused(kind, motion, sensor, name):
    with pytest.raises(TypeError, match=rf"^{name}: returned dtype torch.float32 for states of dtype torch.float64"):
        _run(kind, motion, sensor, 2)


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
@pytest.mark.parametrize("motion", [CV(), SharedNoise()], ids=["plain", "shared-noise"])
def test_models_that_keep_the_contract_give_the_numpy_kalman_filter(kind, motion):
    """CV + Pos are linear: the EKF and UKF are the Kalman filter (reference in float64 NumPy); a noise
    covariance with a unit batch axis broadcasts as before."""
    traj = _run(kind, motion, Pos(), 3)
    _, z = _data(3)
    for r in range(3):
        lls, means = _numpy_kalman(z[:, r, 0].numpy())
        np.testing.assert_allclose(traj.log_likelihood[:, r].numpy(), lls, rtol=1e-10)
        np.testing.assert_allclose(traj.belief.mean[:, r].numpy(), means, rtol=1e-10, atol=1e-12)


def test_the_particle_filter_of_a_shared_noise_equals_the_plain_one():
    plain, shared = _run("pf", CV(), Pos(), 3), _run("pf", SharedNoise(), Pos(), 3)
    torch.testing.assert_close(shared.log_likelihood, plain.log_likelihood, rtol=0, atol=0)


def test_the_imm_kernel_of_good_models_equals_its_eager_steps():
    b0, z = _data(4)
    imm = IMM(ExtendedKalmanFilter(CVBank(), Pos()), torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=D))
    fast = run_filter(imm, imm.initial_belief(b0), z, fast_path=True)
    slow = run_filter(imm, imm.initial_belief(b0), z, fast_path=False)
    assert fast.provenance.kernel == "batch_last_nonlinear"
    torch.testing.assert_close(fast.log_likelihood, slow.log_likelihood, rtol=1e-10, atol=1e-12)


def test_check_output_accepts_what_broadcasts_without_adding_runs():
    from torchmm.models.base import check_output

    sensor, x = Pos(), torch.zeros(3, 2, dtype=D)
    for shape in [(3, 1), (1,), (1, 1), (1, 3, 1)]:  # full, shared, shared with a unit batch, a unit axis
        check_output(sensor, torch.zeros(shape, dtype=D), x, "measurement")
    for shape in [(3,), (2, 3, 1), (3, 2), (4, 1), ()]:  # no event axis, added runs, wrong width, mixed runs
        with pytest.raises(ValueError, match=r"^measurement: returned shape"):
            check_output(sensor, torch.zeros(shape, dtype=D), x, "measurement")
    check_output(CV(), torch.zeros(1, 2, 2, dtype=D), x, "motion", "noise_cov")
    with pytest.raises(ValueError, match=r"^motion\.noise_cov: returned shape \(2, 2, 2\)"):
        check_output(CV(), torch.zeros(2, 2, 2, dtype=D), x, "motion", "noise_cov")
    with pytest.raises(TypeError, match=r"^measurement: returned list"):
        check_output(sensor, [0.0], x, "measurement")

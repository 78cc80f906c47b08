"""Kalman filter: FilterPy cross-check, exact-likelihood oracle, missing data, shapes, properties."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import multivariate_normal

from tests.conftest import BATCH_SHAPES, assert_symmetric_psd, random_system
from torchmm import GaussianBelief, KalmanFilter, LinearMeasurement, LinearMotion, run_filter

close = partial(torch.testing.assert_close, rtol=1e-9, atol=1e-9)


def _filterpy_kf(system):
    from filterpy.kalman import KalmanFilter as FPKalmanFilter

    n, m = system.F.shape[0], system.H.shape[0]
    kf = FPKalmanFilter(dim_x=n, dim_z=m, dim_u=1)
    kf.F, kf.Q, kf.H, kf.R = system.F, system.Q, system.H, system.R
    kf.B = system.offset.reshape(n, 1)
    kf.x, kf.P = system.x0.reshape(n, 1).copy(), system.P0.copy()
    return kf


@pytest.mark.parametrize("n,m", [(1, 1), (2, 1), (3, 2), (4, 3), (2, 4)], ids=str)
@pytest.mark.parametrize("joseph", [False, True], ids=["standard", "joseph"])
def test_kalman_matches_filterpy(n, m, joseph):
    pytest.importorskip("filterpy")
    rng = np.random.default_rng(10 * n + m)
    system = random_system(n, m, rng)
    _, zs = system.simulate(25, rng)
    kf = KalmanFilter(system.motion(), system.measurement(), joseph=joseph)
    traj = run_filter(kf, system.prior(), torch.tensor(zs))

    ref = _filterpy_kf(system)
    for k, z in enumerate(zs):
        ref.predict(u=np.ones((1, 1)))
        close(traj.prior.mean[k], torch.tensor(ref.x.ravel()))
        close(traj.prior.cov[k], torch.tensor(ref.P))
        ref.update(z.reshape(m, 1))
        close(traj.belief.mean[k], torch.tensor(ref.x.ravel()))
        close(traj.belief.cov[k], torch.tensor(ref.P))
        close(traj.log_likelihood[k], torch.tensor(float(ref.log_likelihood)))
        close(traj.innovation_cov[k], torch.tensor(ref.S))


def _stacked_measurement_distribution(system, steps):
    """Exact joint mean and covariance of z_1..z_T of the linear system (independent oracle)."""
    mean_x, cov_x = system.joint_state_moments(steps)
    H = np.kron(np.eye(steps), system.H)
    return H @ mean_x, H @ cov_x @ H.T + np.kron(np.eye(steps), system.R)


@pytest.mark.parametrize("n,m", [(1, 1), (2, 2), (3, 1)], ids=str)
def test_log_likelihood_equals_joint_gaussian_density(n, m):
    rng = np.random.default_rng(7 + n)
    system = random_system(n, m, rng)
    steps = 6
    _, zs = system.simulate(steps, rng)
    kf = KalmanFilter(system.motion(), system.measurement())
    traj = run_filter(kf, system.prior(), torch.tensor(zs))
    mean, cov = _stacked_measurement_distribution(system, steps)
    expected = multivariate_normal(mean, cov).logpdf(zs.ravel())
    close(traj.total_log_likelihood(), torch.tensor(expected))


def test_joseph_equals_standard_form_in_float64():
    rng = np.random.default_rng(3)
    system = random_system(3, 2, rng)
    _, zs = system.simulate(30, rng)
    a = run_filter(KalmanFilter(system.motion(), system.measurement()), system.prior(), torch.tensor(zs))
    b = run_filter(
        KalmanFilter(system.motion(), system.measurement(), joseph=True), system.prior(), torch.tensor(zs)
    )
    close(a.belief.mean, b.belief.mean)
    close(a.belief.cov, b.belief.cov)


@pytest.mark.parametrize("batch_shape", BATCH_SHAPES, ids=str)
@pytest.mark.parametrize("n,m", [(1, 1), (2, 1), (3, 2), (3, 3)], ids=str)
def test_shapes_and_dtypes(batch_shape, n, m):
    rng = np.random.default_rng(0)
    system = random_system(n, m, rng)
    kf = KalmanFilter(system.motion(), system.measurement())
    prior = GaussianBelief(torch.zeros(*batch_shape, n), torch.eye(n).expand(*batch_shape, n, n))
    z = torch.randn(5, *batch_shape, m)
    traj = run_filter(kf, prior, z)
    assert traj.belief.mean.shape == (5, *batch_shape, n)
    assert traj.belief.cov.shape == (5, *batch_shape, n, n)
    assert traj.prior.mean.shape == (5, *batch_shape, n)
    assert traj.log_likelihood.shape == (5, *batch_shape)
    assert traj.innovation.shape == (5, *batch_shape, m)
    assert traj.innovation_cov.shape == (5, *batch_shape, m, m)
    assert traj.belief.mean.dtype == torch.float64
    out32 = kf.to(torch.float32).step(prior.to(torch.float32), z[0].float())
    assert out32.belief.mean.dtype == torch.float32
    assert out32.log_likelihood.dtype == torch.float32


def test_batched_runs_equal_individual_runs():
    rng = np.random.default_rng(5)
    system = random_system(2, 1, rng)
    kf = KalmanFilter(system.motion(), system.measurement())
    zs = torch.randn(8, 3, 1)
    batched = run_filter(kf, system.prior().expand(3), zs)
    for r in range(3):
        single = run_filter(kf, system.prior(), zs[:, r])
        close(batched.belief.mean[:, r], single.belief.mean)
        close(batched.log_likelihood[:, r], single.log_likelihood)


class TestMissingData:
    def setup_method(self):
        rng = np.random.default_rng(11)
        self.system = random_system(3, 2, rng)
        self.kf = KalmanFilter(self.system.motion(), self.system.measurement())

    def test_whole_measurement_missing_skips_update(self):
        prior = self.kf.predict(self.system.prior().expand(4))
        z = torch.randn(4, 2)
        z[1] = torch.nan
        out = self.kf.update(prior, z)
        close(out.belief.mean[1], prior.mean[1])
        close(out.belief.cov[1], prior.cov[1])
        assert out.log_likelihood[1].item() == 0.0
        assert bool(torch.isfinite(out.belief.mean).all())
        # the other runs are untouched by run 1's missing datum
        full = self.kf.update(prior, torch.where(torch.isnan(z), 0.0, z))
        close(out.belief.mean[[0, 2, 3]], full.belief.mean[[0, 2, 3]])

    def test_partial_measurement_equals_reduced_sensor(self):
        prior = self.kf.predict(self.system.prior())
        z = torch.tensor([0.7, torch.nan])
        out = self.kf.update(prior, z)
        reduced = KalmanFilter(
            self.system.motion(),
            LinearMeasurement(torch.tensor(self.system.H[:1]), torch.tensor(self.system.R[:1, :1])),
        )
        ref = reduced.update(prior, z[:1])
        close(out.belief.mean, ref.belief.mean)
        close(out.belief.cov, ref.belief.cov)
        close(out.log_likelihood, ref.log_likelihood)

    def test_all_missing_sequence_is_pure_prediction(self):
        zs = torch.full((6, 2), torch.nan)
        traj = run_filter(self.kf, self.system.prior(), zs)
        close(traj.belief.mean, traj.prior.mean)
        assert bool((traj.log_likelihood == 0).all())


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 4), m=st.integers(1, 3), joseph=st.booleans())
def test_covariances_stay_symmetric_psd(seed, n, m, joseph):
    rng = np.random.default_rng(seed)
    system = random_system(n, m, rng)
    _, zs = system.simulate(15, rng)
    kf = KalmanFilter(system.motion(), system.measurement(), joseph=joseph)
    traj = run_filter(kf, system.prior(), torch.tensor(zs))
    for cov in (traj.belief.cov, traj.prior.cov, traj.innovation_cov):
        assert_symmetric_psd(cov)


def test_float32_stays_finite_over_long_runs():
    rng = np.random.default_rng(2)
    system = random_system(4, 2, rng)
    _, zs = system.simulate(500, rng)
    kf = KalmanFilter(system.motion(), system.measurement(), joseph=True).to(torch.float32)
    traj = run_filter(kf, system.prior().to(torch.float32), torch.tensor(zs, dtype=torch.float32))
    assert bool(torch.isfinite(traj.belief.cov).all())
    assert bool(torch.isfinite(traj.log_likelihood).all())


def test_stack_builds_a_mode_bank():
    rng = np.random.default_rng(4)
    systems = [random_system(2, 1, rng) for _ in range(3)]
    filters = [KalmanFilter(s.motion(), s.measurement()) for s in systems]
    bank = KalmanFilter.stack(filters)
    assert tuple(bank.param_batch_shape) == (3,)
    prior = GaussianBelief(torch.zeros(5, 3, 2), torch.eye(2).expand(5, 3, 2, 2))
    z = torch.randn(5, 1, 1)
    out = bank.step(prior, z)
    for j, f in enumerate(filters):
        ref = f.step(prior.select(-1, j), z[:, 0])
        close(out.belief.mean[:, j], ref.belief.mean)
        close(out.log_likelihood[:, j], ref.log_likelihood)


def test_linear_motion_with_input_matrix():
    motion = LinearMotion(torch.eye(2), torch.eye(2), input_matrix=torch.tensor([[1.0], [2.0]]))
    x = torch.zeros(3, 2)
    out = motion(x, u=torch.ones(3, 1))
    close(out, torch.tensor([[1.0, 2.0]]).expand(3, 2))

"""torchmm.parallel: the associative-scan Kalman filter and RTS smoother equal the sequential ones
(1e-9, float64) on random systems of dimensions 1-6 with missing data, gradients included."""

from __future__ import annotations

import pytest
import torch

from torchmm import GaussianBelief, KalmanFilter, LinearMeasurement, LinearMotion, parallel, run_filter, smooth
from torchmm.parallel import associative_scan


def _random_system(n, m, steps, runs, seed, missing=0.2):
    g = torch.Generator().manual_seed(seed)

    def spd(k):
        A = torch.randn(k, k, generator=g, dtype=torch.float64)
        return A @ A.mT / k + 0.1 * torch.eye(k, dtype=torch.float64)

    F = torch.eye(n, dtype=torch.float64) + 0.3 * torch.randn(n, n, generator=g, dtype=torch.float64) / n**0.5
    motion = LinearMotion(F, spd(n))
    sensor = LinearMeasurement(torch.randn(m, n, generator=g, dtype=torch.float64), spd(m))
    kf = KalmanFilter(motion, sensor)
    belief0 = GaussianBelief(torch.randn(runs, n, generator=g, dtype=torch.float64), spd(n).expand(runs, n, n))
    z = 2 * torch.randn(steps, runs, m, generator=g, dtype=torch.float64)
    z[torch.rand(steps, runs, m, generator=g, dtype=torch.float64) < missing] = float("nan")  # missing components
    if steps > 1:
        z[1] = float("nan")  # a step with no datum at all
    return kf, belief0, z


def test_the_scan_is_an_inclusive_prefix_scan():
    x = torch.randn(37, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    (out,) = associative_scan(lambda a, b: (a[0] + b[0],), (x,))
    torch.testing.assert_close(out, x.cumsum(0))
    M = torch.randn(13, 2, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    (prod,) = associative_scan(lambda a, b: (b[0] @ a[0],), (M,))  # non-commutative: order matters
    want = [M[0]]
    for k in range(1, 13):
        want.append(M[k] @ want[-1])
    torch.testing.assert_close(prod, torch.stack(want))


@pytest.mark.parametrize("n,m,steps", [(1, 1, 1), (1, 1, 9), (2, 1, 16), (3, 2, 33), (4, 3, 50), (6, 2, 64)])
def test_parallel_filter_and_smoother_equal_the_sequential_ones(n, m, steps):
    kf, belief0, z = _random_system(n, m, steps, runs=3, seed=10 * n + m)
    seq = run_filter(kf, belief0, z)
    par = parallel.filter(kf, belief0, z)
    for field in ("mean", "cov"):
        torch.testing.assert_close(getattr(par.belief, field), getattr(seq.belief, field), rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(getattr(par.prior, field), getattr(seq.prior, field), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(par.log_likelihood, seq.log_likelihood, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(par.innovation, seq.innovation, rtol=1e-9, atol=1e-9, equal_nan=True)
    want = smooth(kf, seq).belief
    got = parallel.smooth(kf, belief0, z).belief
    torch.testing.assert_close(got.mean, want.mean, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(got.cov, want.cov, rtol=1e-9, atol=1e-9)


def test_gradients_equal_the_sequential_ones():
    kf, belief0, z = _random_system(3, 2, 20, runs=2, seed=3)
    scale = torch.tensor(1.3, dtype=torch.float64, requires_grad=True)
    zz = torch.nan_to_num(z, nan=0.5).requires_grad_(True)

    def loss(fn):
        motion = LinearMotion(kf.motion.F, kf.motion.Q * scale)
        model = KalmanFilter(motion, kf.measurement)
        if fn == "parallel":
            traj, smoothed = parallel.filter(model, belief0, zz), parallel.smooth(model, belief0, zz)
        else:
            traj = run_filter(model, belief0, zz)
            smoothed = smooth(model, traj)
        return traj.log_likelihood.sum() + smoothed.belief.mean.square().sum()

    grads = {fn: torch.autograd.grad(loss(fn), (scale, zz)) for fn in ("parallel", "sequential")}
    for a, b in zip(grads["parallel"], grads["sequential"]):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-9)


def test_clear_errors():
    kf, belief0, z = _random_system(2, 1, 5, runs=2, seed=0)
    with pytest.raises(ValueError, match=r"z: expected shape \(T, \*B, 1\)"):
        parallel.filter(kf, belief0, z[..., [0, 0]])
    from torchmm import UnscentedKalmanFilter

    with pytest.raises(TypeError, match="kf: the parallel filter needs a KalmanFilter"):
        parallel.filter(UnscentedKalmanFilter(kf.motion, kf.measurement), belief0, z)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (runs where a GPU is present)")
def test_smoothers_on_cuda_equal_the_cpu_ones():
    kf, belief0, z = _random_system(3, 2, 40, runs=4, seed=8)
    cpu_seq = smooth(kf, run_filter(kf, belief0, z)).belief
    dev = torch.device("cuda")
    kf_d = KalmanFilter(LinearMotion(kf.motion.F.to(dev), kf.motion.Q.to(dev)),
                        LinearMeasurement(kf.measurement.H.to(dev), kf.measurement.R.to(dev)))
    b0 = GaussianBelief(belief0.mean.to(dev), belief0.cov.to(dev))
    for got in (smooth(kf_d, run_filter(kf_d, b0, z.to(dev))).belief, parallel.smooth(kf_d, b0, z.to(dev)).belief):
        torch.testing.assert_close(got.mean.cpu(), cpu_seq.mean, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(got.cov.cpu(), cpu_seq.cov, rtol=1e-9, atol=1e-9)

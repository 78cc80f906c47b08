"""torchmm.soa.filter: the batch-last IMM kernel equals run_filter's IMM (random linear banks of
every small size, per-mode models, missing components), in float32 too, compiled too; clear errors."""

from __future__ import annotations

import itertools

import pytest
import torch

from torchmm import GPB2, IMM, GaussianBelief, KalmanFilter, LinearMeasurement, LinearMotion, run_filter, soa

D = torch.float64


def _random_imm(n, m, M, runs, steps, seed, dtype=D):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g, dtype=D)  # noqa: E731
    F = torch.eye(n, dtype=D) + 0.3 * r(M, n, n)
    A = r(M, n, n)
    Q = 0.2 * A @ A.mT + 0.05 * torch.eye(n, dtype=D)
    offset = 0.5 * r(M, n)
    H = r(M, m, n)
    R = torch.diag_embed(0.5 + torch.rand(M, m, generator=g, dtype=D))
    stay = 0.6 + 0.3 * torch.rand(M, generator=g, dtype=D)
    P = (1 - stay).unsqueeze(-1) / max(M - 1, 1) * (1 - torch.eye(M, dtype=D)) + torch.diag(stay) if M > 1 \
        else torch.ones(1, 1, dtype=D)
    imm = IMM(KalmanFilter(LinearMotion(F.to(dtype), Q.to(dtype), offset.to(dtype)),
                           LinearMeasurement(H.to(dtype), R.to(dtype))), P.to(dtype))
    B0 = r(runs, n, n)
    prior = GaussianBelief(r(runs, n).to(dtype), (B0 @ B0.mT + torch.eye(n, dtype=D)).to(dtype))
    mode_probs = torch.softmax(r(M), 0).to(dtype)
    z = (2 * r(steps, runs, m)).to(dtype)
    z[torch.rand(steps, runs, m, generator=g) < 0.2] = float("nan")  # missing components, some whole steps
    return imm, imm.initial_belief(prior, mode_probs), z


@pytest.mark.parametrize("n,m,M", [(n, m, M) for n, m, M in itertools.product([1, 2, 3, 4], [1, 2], [1, 2, 3])
                                   if m <= n])
def test_equals_run_filter(n, m, M):
    imm, belief0, z = _random_imm(n, m, M, runs=7, steps=12, seed=10 * n + 3 * m + M)
    want, got = run_filter(imm, belief0, z), soa.filter(imm, belief0, z)
    torch.testing.assert_close(got.belief.components.mean, want.belief.components.mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(got.belief.components.cov, want.belief.components.cov, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(got.belief.mode_log_probs, want.belief.mode_log_probs, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(got.estimate().mean, want.estimate().mean, rtol=1e-10, atol=1e-10)
    est = soa.filter(imm, belief0, z, output="estimate")  # the collapsed estimate only
    torch.testing.assert_close(est.belief.mean, want.estimate().mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(est.belief.cov, want.estimate().cov, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(est.log_likelihood, want.log_likelihood, rtol=1e-10, atol=1e-10)


def test_float32_and_compiled():
    imm64, b64, z64 = _random_imm(2, 1, 3, runs=9, steps=15, seed=5)
    imm32, b32, z32 = _random_imm(2, 1, 3, runs=9, steps=15, seed=5, dtype=torch.float32)
    want = run_filter(imm64, b64, z64).estimate().mean
    got = soa.filter(imm32, b32, z32)
    assert got.estimate().mean.dtype == torch.float32
    torch.testing.assert_close(got.estimate().mean.double(), want, rtol=1e-4, atol=1e-4)
    compiled = soa.filter(imm64, b64, z64, compile=True)  # the loops unroll when traced: same numbers
    torch.testing.assert_close(compiled.estimate().mean, want, rtol=1e-10, atol=1e-10)


def test_clear_errors():
    imm, belief0, z = _random_imm(2, 2, 2, runs=3, steps=4, seed=1)
    with pytest.raises(TypeError, match="imm: torchmm.soa.filter runs an IMM"):
        soa.filter(GPB2(imm.bank.filter, imm.transition.matrix()), belief0, z)
    with pytest.raises(TypeError, match="imm: torchmm.soa.filter needs a bank of one KalmanFilter"):
        soa.filter(IMM(_list_bank(imm), imm.transition.matrix()), belief0, z)
    full = imm.bank.filter.measurement.R.clone()
    full[:, 0, 1] = full[:, 1, 0] = 0.1
    dense = IMM(KalmanFilter(imm.bank.filter.motion, LinearMeasurement(imm.bank.filter.measurement.H, full)),
                imm.transition.matrix())
    with pytest.raises(ValueError, match="diagonal R"):
        soa.filter(dense, belief0, z)
    with pytest.raises(ValueError, match="output: expected 'beliefs' or 'estimate'"):
        soa.filter(imm, belief0, z, output="means")
    with pytest.raises(TypeError, match="z: dtype"):
        soa.filter(imm, belief0, z.float())
    with pytest.raises(ValueError, match=r"z: expected shape \(T, 3, 2\)"):
        soa.filter(imm, belief0, z[..., :1])
    with pytest.raises(ValueError, match="belief0: torchmm.soa.filter takes one batch axis"):
        two = imm.initial_belief(GaussianBelief(torch.zeros(2, 3, 2, dtype=D), torch.eye(2, dtype=D)))
        soa.filter(imm, two, z)


def _list_bank(imm):
    """A list bank of two Kalman filters with different (non-stackable) options: not the vectorised bank."""
    kf = imm.bank.filter
    return [KalmanFilter(LinearMotion(kf.motion.F[j], kf.motion.Q[j], kf.motion.offset[j]),
                         LinearMeasurement(kf.measurement.H[j], kf.measurement.R[j]), joseph=bool(j))
            for j in range(2)]

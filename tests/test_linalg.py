"""torchmm.linalg's reductions over short axes (issue 31): the same values as torch's, and gradients."""

from __future__ import annotations

import pytest
import torch

from torchmm.linalg import cholesky, half_log_det, not_psd, sum_last


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("k", [1, 2, 3, 5])
def test_sum_last_equals_sum(dtype, k):
    x = torch.randn(7, 3, k, generator=torch.Generator().manual_seed(k), dtype=dtype)
    got = sum_last(x)
    assert got.shape == (7, 3) and got.dtype == dtype
    if k <= 2:  # one rounding: bit for bit
        assert torch.equal(got, x.sum(-1))
    # the summation order may differ: within the bound of any order, k eps sum |x_i|
    bound = k * torch.finfo(dtype).eps * x.abs().sum(-1)
    assert ((got.double() - x.double().sum(-1)).abs() <= bound).all()
    # infinities and NaN propagate as in a sum
    x[0, 0, 0], x[1, 1, 0] = float("inf"), float("nan")
    assert sum_last(x)[0, 0] == float("inf") and sum_last(x)[1, 1].isnan()


@pytest.mark.parametrize("m", [1, 2, 4])
def test_half_log_det_is_half_the_log_determinant(m):
    gen = torch.Generator().manual_seed(m)
    A = torch.randn(5, 2, m, m, generator=gen, dtype=torch.float64)
    S = A @ A.mT + 0.1 * torch.eye(m, dtype=torch.float64)
    L = cholesky(S)
    torch.testing.assert_close(half_log_det(L), 0.5 * torch.logdet(S), rtol=1e-13, atol=1e-13)
    S.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda s: half_log_det(cholesky(s @ s.mT + torch.eye(m, dtype=s.dtype))),
                                    (A[0, 0].clone().requires_grad_(True),))


@pytest.mark.parametrize("n", [1, 2, 4])
def test_not_psd_matches_the_eigenvalues(n):
    """Against numpy's eigenvalues: PSD, singular PSD, zero, rounding-level negative and any scale pass;
    an eigenvalue of -1e-6 x the scale and below, and a NaN entry, fail."""
    import numpy as np

    g = torch.Generator().manual_seed(n)
    Q = torch.linalg.qr(torch.randn(n, n, generator=g, dtype=torch.float64))[0]
    cases = []
    for low in (1.0, 0.0, -1e-14, -1e-6, -0.3, -5.0):
        eig = torch.linspace(1.0, 2.0, n, dtype=torch.float64)
        eig[0] = low
        for scale in (1e-200, 1.0, 1e24):
            cases.append(scale * (Q * eig) @ Q.T)
    S = torch.stack(cases + [torch.zeros(n, n, dtype=torch.float64)])
    S = 0.5 * (S + S.mT)
    lo = np.linalg.eigvalsh(S.numpy()).min(-1)
    big = np.abs(S.numpy()).max((-2, -1))
    expected = lo < -1e-9 * big
    assert expected.any() and not expected.all()
    assert not_psd(S).tolist() == expected.tolist()
    nan = S[:1].clone()
    nan[0, 0, -1] = float("nan")
    assert bool(not_psd(nan)[0])

"""The two-filter smoother's batch-last kernel (torchmm/kernels/batch_last/smooth.py, the
``plan_smooth`` of ``BATCH_LAST``): ``smooth`` of a run of an IMM, GPB1 or GPB2 over linear Kalman
modes with ``n <= 6`` and a diagonal ``R`` runs there, and equals the eager passes (the kernel switched
off) for random banks, per-mode and shared parameters, exact zeros and ones, missing data, batch
shapes, float32 and gradients; it declines what it does not compute. (tests/smoothing/test_two_filter.py
checks the smoother itself - through this kernel where it applies - against an independent NumPy
implementation, RTS and the exact smoother.)

The tolerance: the backward filter starts from the last estimate with its covariance times
``eps^{-1/2}`` (6.7e7), which amplifies rounding about 1e7-fold: the eager smoother itself moves by
~5e-8 when its inputs move by 3e-15 (``test_the_difference_is_the_methods_own_rounding``)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tests.multimodel.test_batch_last import _random_imm, count_calls
from torchmm import (
    GPB1,
    GPB2,
    IMM,
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    kernels,
    run_filter,
    smooth,
)
from torchmm.beliefs import ModeBelief
from torchmm.filters import ExtendedKalmanFilter
from torchmm.multimodel import VariableStructureIMM
from torchmm.kernels.batch_last.algebra import factor
from torchmm.kernels.batch_last.imm import LARGE_BATCH, LARGE_STATE, MAX_STATE
from torchmm.kernels.batch_last.smooth import LARGE_SMOOTHER, BatchLastTwoFilter
from torchmm.multimodel.mevsmm import ExactMinimumEntropy
from torchmm.runtime import no_host_sync
from torchmm.smooth_checks import unobserved_tail

TOL = 1e-6


@pytest.fixture(autouse=True)
def kernel_runs(monkeypatch):
    """The list of the kernel's runs (one per smooth call it took)."""
    return count_calls(monkeypatch, BatchLastTwoFilter, "run")


def _eager(filt, traj, z, **kwargs):
    with kernels.switched_off("batch_last", "batch_last_smooth_large"):
        return smooth(filt, traj, z, **kwargs)


def _fields(out):
    return out.belief.mode_log_probs.exp(), out.belief.components.mean, out.belief.components.cov


def assert_same(filt, belief0, z, traj, got, want):
    """``got`` (the kernel's) equals ``want`` (the eager passes') to the smoother's own rounding: at most
    20 times what the eager passes change by between the trajectories of the kernel and the eager
    filter (equal to rounding, ~1e-15; the diffuse start amplifies it, the module docstring), and at
    least TOL."""
    runs = [_eager(filt, run_filter(filt, belief0, z, fast_path=fast), z) for fast in (True, False)]
    for a, b, c, e in zip(_fields(got), _fields(want), *map(_fields, runs)):
        assert a.shape == b.shape and a.dtype == b.dtype
        tol = max(TOL, 20 * float((c - e).abs().max()))
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)
    assert torch.equal(got.log_likelihood, want.log_likelihood)


COMBINATORS = {"IMM": lambda imm: imm, "GPB1": lambda imm: GPB1(imm.bank.filter, imm.transition.matrix()),
               "GPB2": lambda imm: GPB2(imm.bank.filter, imm.transition.matrix())}


@pytest.mark.parametrize("n,m,M", [(1, 1, 1), (1, 1, 2), (2, 1, 3), (2, 2, 2), (2, 2, 4), (3, 2, 2), (4, 2, 3)])
@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("combinator", list(COMBINATORS))
def test_equals_the_eager_passes(n, m, M, shared, combinator, kernel_runs):
    imm, belief0, z = _random_imm(n, m, M, (7,), steps=12, seed=10 * n + 3 * m + M, shared=shared)
    filt = COMBINATORS[combinator](imm)
    traj = run_filter(filt, belief0, z)
    got = smooth(filt, traj, z)
    assert len(kernel_runs) == 1
    assert_same(filt, belief0, z, traj, got, _eager(filt, traj, z))
    assert len(kernel_runs) == 1
    # at the last step the smoothed belief is the filtered one, exactly
    assert torch.equal(got.belief.components.cov[-1], traj.belief.components.cov[-1])
    assert torch.equal(got.belief.mode_log_probs[-1], traj.belief.mode_log_probs[-1])


@pytest.mark.parametrize("n,combinator", [(7, "IMM"), (8, "GPB2"), (10, "GPB1")])
def test_larger_states_from_a_large_batch(n, combinator, kernel_runs):
    """States of MAX_STATE + 1 to LARGE_STATE components take the kernel (registered apart, as
    ``"batch_last_smooth_large"``, chosen by the batch size: studies switch it off) from LARGE_BATCH runs
    x modes, and equal the eager passes; below that batch, and beyond LARGE_STATE, the eager passes run."""
    M = 2
    runs = LARGE_BATCH // M
    imm, belief0, z = _random_imm(n, 2, M, (runs,), steps=5, seed=n)
    filt = COMBINATORS[combinator](imm)
    traj = run_filter(filt, belief0, z)
    got = smooth(filt, traj, z)
    assert len(kernel_runs) == 1
    assert_same(filt, belief0, z, traj, got, _eager(filt, traj, z))
    assert "batch_last_smooth_large" in kernels.by_size()
    imm, belief0, z = _random_imm(n, 2, M, (runs - 1,), steps=3, seed=n)  # one run fewer: the eager passes
    filt = COMBINATORS[combinator](imm)
    traj = run_filter(filt, belief0, z)
    assert "small batch" in LARGE_SMOOTHER.plan_smooth(filt, traj, "two_filter", measurements=z, prior_log=None)
    smooth(filt, traj, z)
    assert len(kernel_runs) == 1


def test_larger_states_decline_outside_their_range():
    for n, reason in ((MAX_STATE, "states of"), (LARGE_STATE + 1, "states of")):
        imm, belief0, z = _random_imm(n, 1, 2, (LARGE_BATCH,), steps=2, seed=n)
        traj = run_filter(imm, belief0, z)
        assert reason in LARGE_SMOOTHER.plan_smooth(imm, traj, "two_filter", measurements=z, prior_log=None)
    assert "a smoother's kernel only" == LARGE_SMOOTHER.plan(imm, belief0, z, kernels.Request())


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_batch_shapes_and_a_batch_first_trajectory(batch, kernel_runs):
    imm, belief0, z = _random_imm(2, 1, 3, batch, steps=9, seed=len(batch))
    for fast in (True, False):  # the kernel's batch-last record, and the eager steps' batch-first one
        traj = run_filter(imm, belief0, z, fast_path=fast)
        assert_same(imm, belief0, z, traj, smooth(imm, traj, z), _eager(imm, traj, z))
    assert len(kernel_runs) == 2


def test_the_difference_is_the_methods_own_rounding(kernel_runs):
    """The kernel differs from the eager passes by no more than the eager passes differ from themselves
    when the filtered means move by one part in 1e15."""
    imm, belief0, z = _random_imm(2, 1, 3, (7,), steps=12, seed=26)
    filt = GPB1(imm.bank.filter, imm.transition.matrix())
    traj = run_filter(filt, belief0, z)
    want = _eager(filt, traj, z)
    c = traj.belief.components
    moved = dataclasses.replace(traj, belief=ModeBelief(traj.belief.mode_log_probs,
                                                        GaussianBelief(c.mean * (1 + 1e-15), c.cov)), provenance=None)
    own = (_eager(filt, moved, z).belief.components.mean - want.belief.components.mean).abs().max()
    diff = (smooth(filt, traj, z).belief.components.mean - want.belief.components.mean).abs().max()
    assert 0 < diff <= 20 * own and own > 1e-10


def test_float32_and_gradients(kernel_runs):
    imm, belief0, z = _random_imm(2, 1, 2, (4,), steps=8, seed=3)
    i32, b32, z32 = _random_imm(2, 1, 2, (4,), steps=8, seed=3, dtype=torch.float32)
    t32 = run_filter(i32, b32, z32)
    got, want = smooth(i32, t32, z32), _eager(i32, t32, z32)
    assert got.belief.components.mean.dtype == torch.float32
    # float32: the diffuse factor is 2.9e3 and the eager float32 passes are ~2e-2 from float64 here
    for a, b in zip(_fields(got), _fields(want)):
        torch.testing.assert_close(a, b, rtol=5e-3, atol=5e-3)

    def grad(fast):
        data = z.clone().requires_grad_(True)
        traj = run_filter(imm, belief0, data)
        out = smooth(imm, traj, data) if fast else _eager(imm, traj, data)
        return torch.autograd.grad(out.estimate().mean[0].sum() + out.belief.mode_probs[1].sum(), data)[0]

    fast, slow = grad(True), grad(False)
    assert bool(fast.ne(0).any())
    torch.testing.assert_close(fast, slow, rtol=1e-4, atol=1e-4)


def test_no_host_reads_in_the_run(kernel_runs):
    imm, belief0, z = _random_imm(2, 2, 3, (5,), steps=6, seed=9)
    traj = run_filter(imm, belief0, z)
    from torchmm.two_filter import prior_mode_log_probs as _prior_mode_log_probs  # noqa: PLC0415 (what smooth hands the kernel)

    prior_log = _prior_mode_log_probs(imm, traj, 6, traj.belief.mode_log_probs)
    # runs whose last steps hold no datum end at their last datum (smooth's padding): the restarts inside too
    padding = unobserved_tail(z, traj)
    ends = set(torch.nonzero(padding[1:] & ~padding[:-1])[:, 0].tolist())
    assert ends
    run, why = kernels.plan_smooth(imm, traj, "two_filter", measurements=z, prior_log=prior_log,
                                   padding=padding, ends=ends)
    assert run is not None, why
    with no_host_sync("the two-filter kernel"):
        out = run()
    torch.testing.assert_close(out.components.mean, smooth(imm, traj, z).belief.components.mean, rtol=0, atol=0)


def test_declines_what_it_does_not_compute(kernel_runs):
    imm, belief0, z = _random_imm(2, 2, 2, (3,), steps=5, seed=1)
    kf = imm.bank.filter
    full = kf.measurement.R.clone()
    full[:, 0, 1] = full[:, 1, 0] = 0.1
    big, big0, zbig = _random_imm(7, 1, 2, (3,), steps=5, seed=2)
    cases = {
        "R is not diagonal": (IMM(KalmanFilter(kf.motion, LinearMeasurement(kf.measurement.H, full)),
                                  imm.transition.matrix()), belief0, z),
        "a state of 7 components": (big, big0, zbig),
        "ExtendedKalmanFilter is not linear-Gaussian": (IMM(ExtendedKalmanFilter(kf.motion, kf.measurement),
                                                            imm.transition.matrix()), belief0, z),
    }
    for reason, (filt, b0, data) in cases.items():
        traj = run_filter(filt, b0, data)
        from torchmm.two_filter import prior_mode_log_probs as _prior_mode_log_probs  # noqa: PLC0415

        prior_log = _prior_mode_log_probs(filt, traj, 5, traj.belief.mode_log_probs)
        run, why = kernels.plan_smooth(filt, traj, "two_filter", measurements=data, prior_log=prior_log)
        assert run is None and reason in why, why
        assert smooth(filt, traj, data).belief.mode_probs.shape[0] == 5  # the eager passes
    traj = run_filter(imm, belief0, z)
    smooth(imm, traj, method="kim")  # Kim's smoother: not this kernel
    assert not kernel_runs
    vs = VariableStructureIMM(kf, imm.transition.matrix(), ExactMinimumEntropy())
    with pytest.raises(TypeError, match="no smoother for VariableStructureIMM"):  # as without the kernel
        smooth(vs, run_filter(vs, vs.initial_belief(GaussianBelief(belief0.components.mean[:, 0],
                                                                   belief0.components.cov[:, 0])), z), z)
    smooth(imm, traj, z)
    assert len(kernel_runs) == 1


@pytest.mark.parametrize("n", [1, 2, 3, 4, 6])
def test_the_factor_is_torchmms_regularised_one(n):
    """Entry by entry, the closed form for n <= 2 and beyond with cholesky_ex's retry: positive
    definite, singular (the jittered factor), indefinite (the clamped pivots, the diagonal fallback) and
    NaN matrices."""
    from torchmm.linalg import cholesky  # noqa: PLC0415

    g = torch.Generator().manual_seed(n)
    A = torch.randn(40, n, n, generator=g, dtype=torch.float64)
    S = A @ A.mT
    S[5:10] = (A[5:10, :, :1] @ A[5:10, :, :1].mT)  # rank one: the jittered retry
    S[10:15] = -S[10:15]  # negative definite: the diagonal fallback
    S[15] = float("nan")
    L = factor([[S[:, a, c] if c >= a else None for c in range(n)] for a in range(n)])
    got = torch.stack([torch.stack([L[a][c] if c <= a else torch.zeros(40, dtype=torch.float64)
                                    for c in range(n)], -1) for a in range(n)], -2)
    want = cholesky(S)
    # (the jittered factors' last pivots are ~1e-4 of the matrix's scale: rounding of 1e-12 absolute)
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10, equal_nan=True)
    assert bool(torch.isfinite(got[:15]).all()) and bool(got[15].isnan().any())

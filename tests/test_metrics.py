"""Metrics against hand computations."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch

from torchmm import GaussianBelief
from torchmm.metrics import armse, mode_accuracy, nees, nis, rmse, squared_error

close = partial(torch.testing.assert_close, rtol=1e-12, atol=1e-12)


def test_rmse_per_step_over_runs_then_time_average():
    est = torch.tensor([[[1.0, 0.0], [3.0, 0.0]], [[0.0, 0.0], [0.0, 2.0]]])  # (T=2, runs=2, n=2)
    truth = torch.zeros(2, 2, 2)
    close(rmse(est, truth, [0]), torch.tensor([(5.0) ** 0.5, 0.0]))  # sqrt((1 + 9) / 2)
    close(rmse(est, truth), torch.tensor([5.0**0.5, 2.0**0.5]))
    close(armse(est, truth, [0]), torch.tensor(5.0**0.5 / 2))
    close(squared_error(est, truth, [1]), torch.tensor([[0.0, 0.0], [0.0, 4.0]]))


def test_rmse_over_multiple_batch_dims():
    est = torch.randn(3, 4, 5, 2)
    truth = torch.randn(3, 4, 5, 2)
    close(rmse(est, truth), rmse(est.reshape(3, 20, 2), truth.reshape(3, 20, 2)))


def test_nees_and_nis():
    cov = torch.tensor([[4.0, 1.0], [1.0, 2.0]])
    est = GaussianBelief(torch.tensor([[1.0, 2.0]]), cov.expand(1, 2, 2))
    truth = torch.tensor([[0.0, 0.0]])
    e = torch.tensor([1.0, 2.0])
    close(nees(est, truth), (e @ torch.linalg.solve(cov, e)).reshape(1))
    nu = torch.tensor([[1.0, 2.0], [torch.nan, 1.0], [torch.nan, torch.nan]])
    out = nis(nu, cov.expand(3, 2, 2))
    close(out[0], e @ torch.linalg.solve(cov, e))
    close(out[1], torch.tensor(1.0 / 2.0))  # only the second component observed
    assert torch.isnan(out[2])


def test_mode_accuracy():
    probs = torch.tensor([[[0.7, 0.3], [0.2, 0.8]], [[0.6, 0.4], [0.9, 0.1]]])
    truth = torch.tensor([[0, 0], [0, 0]])
    close(mode_accuracy(probs, truth), torch.tensor([0.5, 1.0]))


def test_mode_hits_score_ties_the_same_whatever_the_rounding():
    """A tie of k modes that includes the true one scores 1/k, also when rounding has split the tie
    (the learn_dynamics chunking test flipped an argmax between batch sizes on an AVX-512 CPU)."""
    from torchmm.metrics import mode_hits

    log_half = torch.tensor(0.5, dtype=torch.float64).log()
    split = log_half * (1 + 1e-15)  # the same probability, rounded differently
    scores = torch.stack([torch.stack([log_half, split]), torch.stack([split, log_half]),
                          torch.tensor([-0.1, -2.4], dtype=torch.float64),
                          torch.tensor([-2.4, -0.1], dtype=torch.float64)])
    truth = torch.tensor([1, 1, 1, 1])
    close(mode_hits(scores, truth), torch.tensor([0.5, 0.5, 0.0, 1.0], dtype=torch.float64))
    three = torch.full((2, 3), 1 / 3, dtype=torch.float64)  # probabilities, not logs
    close(mode_hits(three, torch.tensor([0, 2])), torch.full((2,), 1 / 3, dtype=torch.float64))
    close(mode_accuracy(torch.stack([scores, scores]), torch.stack([truth, truth])),
          torch.tensor([0.5, 0.5], dtype=torch.float64))


def test_nees_scores_a_covariance_that_is_not_positive_definite_nan_and_refuses_an_asymmetric_one():
    """An indefinite, a zero and a non-symmetric covariance gave 4.5e15, 8.99e307 and 2.0 (the lower
    triangle's) through the regularised Cholesky factor. Not positive definite is a run's numerical trouble
    (a collapsed particle cloud): NaN for that run only, the others e^T P^-1 e by NumPy; not symmetric is a
    mistake in the argument: refused, naming it (as nis refuses all three)."""
    good = np.array([[4.0, 1.0], [1.0, 2.0]])
    cov = torch.tensor([[[1.0, 2.0], [2.0, 1.0]], [[0.0, 0.0], [0.0, 0.0]], good.tolist()],
                       dtype=torch.float64)
    mean = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.5, -1.0]], dtype=torch.float64)
    out = nees(GaussianBelief(mean, cov), torch.ones(3, 2, dtype=torch.float64))
    assert bool(out[:2].isnan().all())
    e = np.array([0.5, -1.0]) - 1.0
    close(out[2], torch.tensor(e @ np.linalg.solve(good, e)))
    e1 = torch.ones(1, 1, 2)
    with pytest.raises(ValueError, match=r"^estimate\.cov: covariance is not symmetric"):
        nees(GaussianBelief(torch.zeros(1, 1, 2), torch.tensor([[1.0, 0.5], [0.0, 1.0]]).expand(1, 1, 2, 2)),
             e1)
    for C, problem in (([[1.0, 2.0], [2.0, 1.0]], "positive definite"),
                       ([[0.0, 0.0], [0.0, 0.0]], "positive definite"), ([[1.0, 0.5], [0.0, 1.0]], "symmetric")):
        with pytest.raises(ValueError, match=rf"^innovation_cov: covariance is not {problem}"):
            nis(e1, torch.tensor(C).expand(1, 1, 2, 2))


def test_nees_of_a_diverged_run_is_nan_and_the_others_are_exact():
    """A NaN mean component was skipped as if missing (NEES over the other component: 1.0) and an
    infinite variance gave 0; a run with a non-finite estimate is now NaN (its covariance not checked),
    the others e^T P^-1 e by NumPy."""
    nan, inf = float("nan"), float("inf")
    good = np.array([[4.0, 1.0], [1.0, 2.0]])
    mean = torch.tensor([[nan, 0.0], [0.0, 0.0], [0.5, -1.0]])
    cov = torch.stack([torch.tensor([[1.0, 2.0], [2.0, 1.0]]), torch.tensor([[inf, 0.0], [0.0, 1.0]]),
                       torch.as_tensor(good)])
    truth = torch.ones(3, 2)
    out = nees(GaussianBelief(mean, cov), truth)
    assert bool(out[:2].isnan().all())
    e = np.array([0.5, -1.0]) - 1.0
    close(out[2], torch.tensor(e @ np.linalg.solve(good, e)))


def test_metric_shapes_that_do_not_fit_are_refused_naming_the_argument():
    est = GaussianBelief(torch.zeros(3, 4, 2), torch.eye(2).expand(3, 4, 2, 2))
    for shape in ((3, 5, 2), (3, 4, 1, 2)):  # another batch, or one that enlarges the estimate's
        with pytest.raises(ValueError, match=r"^truth: shape .* does not broadcast to the estimate's"):
            nees(est, torch.ones(shape))
    assert nees(est, torch.ones(3, 1, 2)).shape == (3, 4)  # one truth shared by the runs
    with pytest.raises(ValueError, match=r"^innovation_cov: batch \(3, 5\) does not broadcast"):
        nis(torch.ones(3, 4, 2), torch.eye(2).expand(3, 5, 2, 2))


def test_error_metrics_take_numpy_arrays_as_gospa_does():
    """rmse, armse, squared_error (an AttributeError before), nees and nis on NumPy arrays: the same
    numbers as on tensors, and as NumPy's own."""
    rng = np.random.default_rng(0)
    est, truth = rng.normal(size=(4, 6, 2)), rng.normal(size=(4, 6, 2))
    want = np.sqrt(((est - truth) ** 2).sum(-1).mean(-1))
    close(rmse(est, truth), torch.as_tensor(want))
    close(armse(est, truth), torch.as_tensor(want.mean()))
    close(squared_error(est, truth.tolist()), torch.as_tensor(((est - truth) ** 2).sum(-1)))
    cov = np.array([[4.0, 1.0], [1.0, 2.0]])
    e = est - truth
    quad = torch.as_tensor(np.einsum("...i,ij,...j->...", e, np.linalg.inv(cov), e))
    close(nis(e, cov), quad)
    close(nees(GaussianBelief(torch.as_tensor(est), torch.as_tensor(cov).expand(4, 6, 2, 2)), truth), quad)

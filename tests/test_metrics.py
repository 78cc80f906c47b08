"""Metrics against hand computations."""

from __future__ import annotations

from functools import partial

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

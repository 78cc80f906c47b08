"""The invariants torchmm held before the robustness work, kept in tests for every estimator family.

* same seed -> same bits (two fresh builds of a filter give identical trajectories);
* a run alone is the same run in a batch (deterministic filters, to rounding);
* a step without data leaves a Gaussian belief at its prediction, exactly where the filter is
  linear-Gaussian (missing = skipped exactly);
* the particle filters' all-underflow guard (``tests/filters/test_particle.py``) and the
  bit-identical resume of interrupted studies (``tests/experiments/test_studies.py``) are tested
  where those features live.
"""

from __future__ import annotations

import pytest
import torch

from tests.robustness.cases import CASES, GAUSSIAN
from torchmm import run_filter
from torchmm.multimodel import MultiRate

RUNS, STEPS = 5, 6


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_same_seed_gives_the_same_bits(case):
    z = case.data(STEPS, RUNS, seed=11)
    results = []
    for _ in range(2):
        f = case.make()
        results.append(run_filter(f, case.start(f, RUNS), z))
    a, b = (r.estimate() for r in results)
    assert torch.equal(a.mean, b.mean) and torch.equal(a.cov, b.cov)
    assert torch.equal(results[0].log_likelihood, results[1].log_likelihood)


def _runs(data, index):
    if isinstance(data, MultiRate):
        return MultiRate(data.target[:, index], data.source[:, index])
    return data[:, index]


@pytest.mark.parametrize("case", GAUSSIAN, ids=lambda c: c.name)
def test_a_run_alone_is_the_same_run_in_a_batch(case):
    f = case.make()
    z = case.data(STEPS, RUNS, seed=12)
    batch = run_filter(f, case.start(f, RUNS), z)
    for k in (0, RUNS - 1):
        alone = run_filter(f, case.start(f, 1), _runs(z, slice(k, k + 1)))
        torch.testing.assert_close(alone.estimate().mean[:, 0], batch.estimate().mean[:, k], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(alone.estimate().cov[:, 0], batch.estimate().cov[:, k], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(alone.log_likelihood[:, 0], batch.log_likelihood[:, k], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("case", [c for c in GAUSSIAN if c.name in ("kf", "kf_joseph", "ekf", "ukf", "student_t",
                                                                     "skew_t", "skew_t_iw")], ids=lambda c: c.name)
def test_a_step_without_data_keeps_the_prediction(case):
    f = case.make()
    prior = f.predict(case.start(f, RUNS))
    z = case.data(1, RUNS)[0]
    z[2] = float("nan")
    out = f.update(prior, z)
    torch.testing.assert_close(out.belief.mean[2], prior.mean[2], rtol=0, atol=0)
    torch.testing.assert_close(out.belief.cov[2], prior.cov[2], rtol=1e-15, atol=1e-15)
    assert out.log_likelihood[2].item() == 0.0

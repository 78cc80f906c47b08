"""``learn.method: em_then_mle`` (experiments/learning_em.py): the maximum-likelihood stage estimates what
EM did - the whole of a multivariate Q and R (kind covariance; before, kind variance forced on them
refitted their diagonals only), the start's mean and covariance (before, dropped from k, AIC, BIC, the
learned table and the errors) - so its table, k and AIC are those of method mle with the same entries."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from experiments import study
from experiments.config import ConfigError


@pytest.fixture(scope="module")
def two_dim(tmp_path_factory):
    """A 2-D AR(1) state with correlated noise, measured with correlated noise (100 steps)."""
    g = np.random.default_rng(0)
    F, Q, R = np.diag([0.9, 0.7]), np.array([[1.0, 0.6], [0.6, 1.0]]), np.array([[1.0, 0.5], [0.5, 1.0]])
    x, rows = np.zeros(2), []
    for _ in range(100):
        x = F @ x + g.multivariate_normal(np.zeros(2), Q)
        rows.append(x + g.multivariate_normal(np.zeros(2), R))
    folder = tmp_path_factory.mktemp("two_dim")
    pd.DataFrame(rows, columns=["a", "b"]).to_csv(folder / "two.csv", index=False)
    return folder


def _overrides(folder, entries):
    return dict(scenario__data__path=str(folder / "two.csv"), scenario__data__measurements=["a", "b"],
                scenario__modes=[{"_target_": "torchmm.LinearMotion", "F": [[0.9, 0.0], [0.0, 0.7]],
                                  "Q": [[1.0, 0.0], [0.0, 1.0]]}],
                scenario__sensors=[{"_target_": "torchmm.LinearMeasurement", "H": [[1.0, 0.0], [0.0, 1.0]],
                                    "R": [[1.0, 0.0], [0.0, 1.0]]}],
                scenario__initial_mean=[0.0, 0.0], scenario__initial_cov=[[4.0, 0.0], [0.0, 4.0]],
                update_first=True, burn=0, learn__parameters=entries, learn__iterations=50,
                progress=False, logger="none", figures=False)


def _fit(result):
    learned = result.table("learned").set_index("parameter")
    fit = result.table("fit").iloc[0]
    return learned, fit


def test_em_then_mle_is_mle_of_what_em_estimated(two_dim):
    """Q, R (2x2, estimated whole by EM) and the start's mean: em_then_mle's table, k, AIC and errors are
    mle's with kind covariance (k = 3 + 3 + 2 = 8; before: 4, the diagonals only, and no start)."""
    entries = [{"model": "modes[0]", "name": "Q"}, {"model": "sensors[0]", "name": "R"},
               {"name": "initial_mean"}]
    both = study("nile", out=two_dim / "em_then_mle", learn__method="em_then_mle",
                 **_overrides(two_dim, entries))
    full = [{"model": "modes[0]", "name": "Q", "kind": "covariance"},
            {"model": "sensors[0]", "name": "R", "kind": "covariance"}, {"name": "initial_mean"}]
    mle = study("nile", out=two_dim / "mle", learn__method="mle", **_overrides(two_dim, full))
    (a, fa), (b, fb) = _fit(both), _fit(mle)
    assert list(a.index) == list(b.index)
    assert {"modes[0].Q[1,0]", "sensors[0].R[1,0]", "initial_mean[0,1]"} <= set(a.index)
    assert fa["k"] == fb["k"] == 8 and fa["converged"] and fb["converged"]
    assert fa["loglik"] == pytest.approx(fb["loglik"], abs=1e-6)
    assert fa["aic"] == pytest.approx(fb["aic"], abs=1e-5)
    np.testing.assert_allclose(a["estimate"].astype(float), b["estimate"].astype(float), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(a["se"].astype(float), b["se"].astype(float), rtol=1e-3)


def test_em_then_mle_refuses_a_kind_em_does_not_estimate(two_dim):
    """kind variance on a Q that EM estimates whole: one ConfigError naming the entry's kind, before EM
    runs (a diagonal Q for both stages: fixed, its off-diagonal entries)."""
    entries = [{"model": "modes[0]", "name": "Q", "kind": "variance"}, {"model": "sensors[0]", "name": "R"}]
    with pytest.raises(ConfigError, match=r"learn.parameters\[0\].kind.*whole matrix"):
        study("nile", out=two_dim / "refused", learn__method="em_then_mle", **_overrides(two_dim, entries))
    assert not (two_dim / "refused").exists()
    diagonal = [{"model": "modes[0]", "name": "Q", "fixed": [[False, True], [True, False]]},
                {"model": "sensors[0]", "name": "R"}]
    res = study("nile", out=two_dim / "diagonal", learn__method="em_then_mle",
                **_overrides(two_dim, diagonal))
    learned, fit = _fit(res)
    assert "modes[0].Q[1,0]" not in learned.index and fit["k"] == 2 + 3

"""A transition matrix with fixed entries estimated by maximum likelihood (``Param("stochastic",
fixed=...)``, docs/studies.md "Learning"): the held entries stay, the row's other entries share the rest
of its mass, and the optimum is the one a hand-written float64 Hamilton filter maximised by scipy's SLSQP
(on the raw probabilities, the rows' sums as constraints: no softmax) reaches with the same entry held."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import minimize
from scipy.stats import norm

from experiments.realdata import fedfunds_imm
from torchmm.learn import Param, estimate

MEANS, VARIANCES = (0.0, 3.0, -2.5), (1.0, 2.0, 0.5)


def _data(steps=300, seed=5):
    """A 3-regime Markov-switching mean and variance, simulated in NumPy."""
    rng = np.random.default_rng(seed)
    P = np.array([[0.85, 0.1, 0.05], [0.1, 0.8, 0.1], [0.15, 0.05, 0.8]])
    s, regimes = 0, []
    for _ in range(steps):
        s = rng.choice(3, p=P[s])
        regimes.append(s)
    regimes = np.array(regimes)
    return np.array(MEANS)[regimes] + np.sqrt(np.array(VARIANCES))[regimes] * rng.standard_normal(steps)


def _hamilton_loglik(P: np.ndarray, y: np.ndarray) -> float:
    """Hamilton's filter: the regime one step before the first datum uniform, each step predicts with P."""
    probs = np.full(3, 1 / 3)
    dens = norm.pdf(y[:, None], np.array(MEANS), np.sqrt(np.array(VARIANCES)))
    total = 0.0
    for t in range(len(y)):
        joint = (probs @ P) * dens[t]
        total += np.log(joint.sum())
        probs = joint / joint.sum()
    return total


def test_fixed_transition_entry_is_held_at_the_constrained_maximum():
    y = _data()
    start = [[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]]
    hold = torch.tensor([[False, True, False], [False] * 3, [False] * 3])  # P[0, 1] held at 0.1
    imm, b0 = fedfunds_imm(list(MEANS), list(VARIANCES), start)
    est = estimate(imm, b0, torch.as_tensor(y).reshape(-1, 1),
                   {"transition.value": Param("stochastic", fixed=hold)}, progress=False)
    P = imm.transition.matrix().detach().numpy()
    assert P[0, 1] == 0.1
    np.testing.assert_allclose(P.sum(-1), 1.0, atol=1e-12)
    assert est.k == 1 + 2 + 2  # row 0: two free entries (one value); rows 1, 2: three (two values)
    assert "transition.value[0,1]" not in est.names and len(est.names) == 8

    # the reference: the raw probabilities, P[0, 1] = 0.1 held, each row summing to one
    def full(x):
        return np.array([[x[0], 0.1, x[1]], [x[2], x[3], x[4]], [x[5], x[6], x[7]]])
    rows = [lambda x: x[0] + x[1] - 0.9, lambda x: x[2] + x[3] + x[4] - 1, lambda x: x[5] + x[6] + x[7] - 1]
    x0 = np.array([0.8, 0.1, 0.1, 0.8, 0.1, 0.1, 0.1, 0.8])
    constraints = [{"type": "eq", "fun": f} for f in rows]
    ref = minimize(lambda x: -_hamilton_loglik(full(x), y), x0, method="SLSQP", bounds=[(1e-9, 1.0)] * 8,
                   constraints=constraints, options={"ftol": 1e-14, "maxiter": 1000})
    assert ref.success
    assert P.min() > 0.03  # (an interior maximum)
    np.testing.assert_allclose(P, full(ref.x), atol=1e-5)
    assert est.loglik == pytest.approx(-ref.fun, abs=1e-6)
    assert est.loglik == pytest.approx(_hamilton_loglik(P.astype(np.float64), y), abs=1e-9)


def test_a_row_left_with_one_free_entry_is_held_and_not_reported():
    """Two regimes, P[0, 0] fixed: row 0's other entry is its rest (1 - P[0, 0]), not an estimate."""
    y = _data()[:120]
    imm, b0 = fedfunds_imm([0.0, 3.0], [1.0, 2.0], [[0.7, 0.3], [0.2, 0.8]])
    est = estimate(imm, b0, torch.as_tensor(y).reshape(-1, 1),
                   {"transition.value": Param("stochastic", fixed=[[True, False], [False, False]])},
                   progress=False)
    P = imm.transition.matrix()
    assert float(P[0, 0]) == 0.7 and float(P[0, 1]) == pytest.approx(0.3, abs=1e-15)
    assert est.k == 1 and est.names == ["transition.value[1,0]", "transition.value[1,1]"]

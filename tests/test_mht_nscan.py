"""N-scan pruning of the MHT (torchmm.association.MHT, ManagedMHT; docs/tracking.md): ``n_scan = N >= 1``
fixes the decisions ``N`` scans back (the surviving hypotheses may differ on the last ``N`` scans), as in the
literature's N-scan-back pruning; against a NumPy hypothesis tree with full histories, and ``n_scan = 1`` is
not GNN."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from torchmm import GaussianBelief, KalmanFilter
from torchmm.association import MHT
from torchmm.models import ConstantVelocity, PositionMeasurement

PD, PG, LAM = 0.8, 0.99, 0.02


def _models():
    motion = ConstantVelocity(2, q=0.1, dtype=torch.float64)
    return motion, PositionMeasurement(4, [0, 2], 1.0, dtype=torch.float64)


def _tree(x0, P0, scans, F, Q, Hm, Rm, hypotheses, n_scan):
    """Hypothesis-oriented MHT by hand, each hypothesis with its whole history: children of every hypothesis's
    joint events (each track at most one detection in its gate, each detection at most one track), the
    ``hypotheses`` best kept, then those whose assignment ``n_scan`` scans back differs from the best one's
    dropped, and the rest normalised."""
    gamma = chi2.ppf(PG, 2)
    hyps = [(0.0, x0.copy(), P0.copy(), [])]
    for z in scans:
        kids = []
        for lw, x, P, hist in hyps:
            x, P = x @ F.T, F @ P @ F.T + Q
            N, D = len(x), len(z)
            post, w = {}, np.zeros((N, D))
            for i in range(N):
                S = Hm @ P[i] @ Hm.T + Rm
                K = P[i] @ Hm.T @ np.linalg.inv(S)
                for j in range(D):
                    nu = z[j] - Hm @ x[i]
                    d2 = nu @ np.linalg.solve(S, nu)
                    if d2 <= gamma:
                        w[i, j] = PD * math.exp(-0.5 * d2) / math.sqrt(np.linalg.det(2 * np.pi * S)) / LAM
                    post[i, j] = (x[i] + K @ nu, P[i] - K @ S @ K.T)
            for event in itertools.product(range(D + 1), repeat=N):
                used = [j for j in event if j]
                if len(used) != len(set(used)):
                    continue
                v = math.prod(w[i, j - 1] if j else 1 - PD * PG for i, j in enumerate(event))
                if v > 0:
                    nx = np.array([post[i, j - 1][0] if j else x[i] for i, j in enumerate(event)])
                    nP = np.array([post[i, j - 1][1] if j else P[i] for i, j in enumerate(event)])
                    kids.append((lw + math.log(v), nx, nP, hist + [event]))
        kids.sort(key=lambda c: -c[0])
        kids = kids[:hypotheses]
        if n_scan and len(kids[0][3]) > n_scan:
            fixed = kids[0][3][-1 - n_scan]
            kids = [c for c in kids if c[3][-1 - n_scan] == fixed]
        total = np.logaddexp.reduce([c[0] for c in kids])
        hyps = [(c[0] - total, *c[1:]) for c in kids]
    return hyps


def _scans(seed, T=5):
    rng = np.random.default_rng(seed)
    x0 = np.array([[0, 1, 0, 0.2], [1.2, 1, 0.6, -0.2]])
    scans = []
    for t in range(T):
        pos = x0[:, [0, 2]] + (t + 1) * x0[:, [1, 3]]
        scans.append(np.concatenate([pos + rng.normal(size=pos.shape), rng.uniform(-2, 7, size=(2, 2))]))
    return x0, scans


@pytest.mark.parametrize("n_scan", [1, 2])
def test_n_scan_pruning_against_a_hypothesis_tree_with_whole_histories(n_scan):
    motion, sensor = _models()
    F, Q = motion.F.numpy(), motion.Q.numpy()
    Hm, Rm = np.array([[1, 0, 0, 0], [0, 0, 1, 0.0]]), np.eye(2)
    for seed in range(3):
        x0, scans = _scans(seed)
        P0 = np.tile(np.eye(4), (2, 1, 1))
        hyps = _tree(x0, P0, scans, F, Q, Hm, Rm, 8, n_scan)
        mht = MHT(KalmanFilter(motion, sensor), detection_probability=PD, clutter_density=LAM,
                  gate_probability=PG, hypotheses=8, k=8, n_scan=n_scan)
        b = mht.initial_belief(GaussianBelief(torch.tensor(x0), torch.tensor(P0)))
        for z in scans:
            b = mht.update(mht.predict(b), torch.tensor(z)).belief
        lw = b.log_weights.numpy()
        alive = np.isfinite(lw)
        assert alive.sum() == len(hyps), (seed, alive.sum(), len(hyps))
        order = np.argsort(-lw)[:len(hyps)]
        np.testing.assert_allclose(lw[order], [h[0] for h in hyps], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(b.by_hypothesis().mean.numpy()[order], [h[1] for h in hyps], rtol=1e-9,
                                   atol=1e-9)
        kept = b.history.numpy()[order]  # (H, n_scan + 1, N): the last n_scan + 1 scans
        assert kept.shape[1] == n_scan + 1
        np.testing.assert_array_equal(kept, [h[3][-1 - n_scan:] for h in hyps])


def test_one_scan_pruning_keeps_hypotheses_that_differ_on_the_last_scan():
    """n_scan = 1 fixes the previous scan's decisions, not the current one's: after the first scan every
    hypothesis survives (they differ only there), and later some run keeps hypotheses that differ on the
    last scan (with the old off-by-one n_scan = 1 kept the best one alone: GNN)."""
    motion, sensor = _models()
    x0, scans = _scans(0, T=4)
    mht = MHT(KalmanFilter(motion, sensor), detection_probability=PD, clutter_density=LAM,
              gate_probability=PG, hypotheses=8, k=8, n_scan=1)
    P0 = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
    b = mht.initial_belief(GaussianBelief(torch.tensor(x0), P0))
    b = mht.update(mht.predict(b), torch.tensor(scans[0])).belief
    assert bool(torch.isfinite(b.log_weights).all())
    differ = False
    for z in scans[1:]:
        b = mht.update(mht.predict(b), torch.tensor(z)).belief
        alive = torch.isfinite(b.log_weights)
        last, previous = b.history[alive][:, -1], b.history[alive][:, 0]
        assert bool((previous == previous[0]).all())  # the previous scan: one decision
        differ |= bool((last != last[0]).any())
    assert differ

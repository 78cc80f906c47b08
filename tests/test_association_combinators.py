"""Association over the other multiple-model combinators (docs/tracking.md, "Over any multiple-model
combinator"): GPB2 under PDA / JPDA against a NumPy computation of the GPB2-PDA over every (mode
pair, detection) hypothesis; a variable-structure IMM is refused with a message."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2, multivariate_normal

from torchmm import GaussianBelief, KalmanFilter, run_filter
from torchmm.association import JIPDA, JPDA, PDA
from torchmm.beliefs import ModeBelief
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.multimodel import GPB2, VariableStructureIMM
from torchmm.multimodel.mevsmm import ExactMinimumEntropy

DT = torch.float64
ACC = [[0.0, 0.0], [3.0, 0.0], [0.0, -3.0]]
PI = torch.tensor([[0.8, 0.1, 0.1], [0.2, 0.7, 0.1], [0.15, 0.15, 0.7]], dtype=DT)
OPTS = {"detection_probability": 0.85, "clutter_density": 3e-3, "gate_probability": 0.97}


def _models():
    bank = ConstantVelocity(2, dt=1.0, q=0.4, acceleration=ACC, dtype=DT)
    sensor = PositionMeasurement(4, [0, 2], torch.tensor([[2.0, 0.3], [0.3, 1.5]], dtype=DT))
    return bank, sensor


def _gpb2_pda_reference(mu, means, covs, scan, bank, sensor):
    """One GPB2-PDA scan in float64 NumPy: every pair (i, j) predicted from mode i's posterior with
    model j, every validated detection k; weights mu_i pi_ij (1 - P_D P_G) and mu_i pi_ij P_D N_ijk /
    lambda; mode j's posterior the moment match over (i, k)."""
    M = len(mu)
    F, Q, off = bank.F.numpy(), bank.Q.numpy(), bank.offset.numpy()
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    R = sensor.R.numpy()
    pd, lam, pg = OPTS["detection_probability"], OPTS["clutter_density"], OPTS["gate_probability"]
    gamma = chi2.ppf(pg, 2)
    pi = PI.numpy()
    dets = [z for z in scan if np.isfinite(z).all()]
    pred, upd, dens, inside = {}, {}, {}, np.zeros(len(dets), bool)
    for i in range(M):
        for j in range(M):
            x, P = F @ means[i] + off[j], F @ covs[i] @ F.T + Q
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            pred[i, j] = (x, P)
            for k, z in enumerate(dets):
                nu = z - H @ x
                inside[k] |= nu @ np.linalg.solve(S, nu) <= gamma
                upd[i, j, k] = (x + K @ nu, P - K @ S @ K.T)
                dens[i, j, k] = multivariate_normal(np.zeros(2), S).pdf(nu)
    weights = {}
    for i in range(M):
        for j in range(M):
            weights[i, j, None] = mu[i] * pi[i, j] * (1 - pd * pg)
            for k in range(len(dets)):
                weights[i, j, k] = mu[i] * pi[i, j] * pd * dens[i, j, k] / lam if inside[k] else 0.0
    total = sum(weights.values())
    modes, out_means, out_covs = np.zeros(M), [], []
    for j in range(M):
        items = [(w, pred[i, j] if k is None else upd[i, j, k]) for (i, jj, k), w in weights.items() if jj == j]
        wj = sum(w for w, _ in items)
        modes[j] = wj / total
        m = sum(w * x for w, (x, _) in items) / wj
        C = sum(w * (P + np.outer(x - m, x - m)) for w, (x, P) in items) / wj
        out_means.append(m)
        out_covs.append(C)
    return modes, np.array(out_means), np.array(out_covs), math.log(total)


def test_gpb2_under_pda_equals_a_numpy_computation_over_every_pair_and_detection():
    bank, sensor = _models()
    pda = PDA(GPB2(KalmanFilter(bank, sensor), PI), **OPTS)
    gen = torch.Generator().manual_seed(3)
    mu = torch.tensor([0.5, 0.3, 0.2], dtype=DT)
    means = torch.randn(3, 4, generator=gen, dtype=DT)
    covs = torch.eye(4, dtype=DT) * torch.tensor([1.0, 2.0, 1.5], dtype=DT)[:, None, None]
    belief = ModeBelief(mu.log(), GaussianBelief(means, covs))
    scan = torch.tensor([[1.5, 0.8], [4.0, -1.0], [-2.0, -4.0], [30.0, 30.0], [math.nan, math.nan]], dtype=DT)
    out = pda.step(belief, scan)
    modes, m, C, loglik = _gpb2_pda_reference(mu.numpy(), means.numpy(), covs.numpy(), scan.numpy(), bank, sensor)
    np.testing.assert_allclose(out.belief.mode_log_probs.exp().numpy(), modes, atol=1e-12)
    np.testing.assert_allclose(out.belief.components.mean.numpy(), m, atol=1e-10)
    np.testing.assert_allclose(out.belief.components.cov.numpy(), C, atol=1e-10)
    assert float(out.log_likelihood) == pytest.approx(loglik, abs=1e-10)
    assert out.extras["validated"].tolist() == [True, True, True, False, False]


def test_gpb2_under_jpda_with_one_track_is_the_gpb2_pda_and_runs_over_scans():
    bank, sensor = _models()
    gpb2 = GPB2(KalmanFilter(bank, sensor), PI)
    pda, jpda = PDA(gpb2, **OPTS), JPDA(gpb2, **OPTS)
    prior = GaussianBelief(torch.zeros(3, 4, dtype=DT), torch.eye(4, dtype=DT) * 10)
    z = torch.randn(6, 3, 4, 2, generator=torch.Generator().manual_seed(4), dtype=DT) * 4
    z[..., 3, :] = math.nan
    a = run_filter(pda, gpb2.initial_belief(prior), z, record=None)
    b = run_filter(jpda, gpb2.initial_belief(prior.unsqueeze(-1)), z, record=None)
    torch.testing.assert_close(b.belief.mode_log_probs[..., 0, :], a.belief.mode_log_probs, rtol=0, atol=1e-12)
    torch.testing.assert_close(b.belief.components.mean[..., 0, :, :], a.belief.components.mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(b.log_likelihood[..., 0], a.log_likelihood, rtol=0, atol=1e-12)
    jipda = JIPDA(gpb2, survival_probability=0.95, **OPTS)  # with existence too
    c = run_filter(jipda, jipda.initial_belief(prior.unsqueeze(-1), 0.5), z, record=None)
    assert torch.isfinite(c.belief.existence).all() and torch.isfinite(c.log_likelihood).all()


def test_a_variable_structure_imm_is_refused_with_the_reason():
    bank, sensor = _models()
    vs = VariableStructureIMM(KalmanFilter(bank, sensor), PI, ExactMinimumEntropy())
    pda = PDA(vs, **OPTS)
    belief = vs.initial_belief(GaussianBelief(torch.zeros(2, 4, dtype=DT), torch.eye(4, dtype=DT)))
    with pytest.raises(TypeError, match="filter: PDA over a variable-structure IMM is not supported"):
        pda.step(belief, torch.zeros(2, 3, 2, dtype=DT))

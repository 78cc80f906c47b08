"""IMM-IPDA and IMM-JIPDA: IPDA / JIPDA over an IMM (torchmm.association; docs/tracking.md). A NumPy
computation of the existence and mode update from the IMM's prediction, an IMM of identical modes is
the single filter's IPDA / JIPDA, one track is the IMM-IPDA, sure targets are the IMM-JPDAF."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2, multivariate_normal

from torchmm import IMM, GaussianBelief, KalmanFilter, run_filter
from torchmm.association import IPDA, JIPDA, JPDA
from torchmm.beliefs import ModeExistenceBelief
from torchmm.models import ConstantVelocity, PositionMeasurement

DT = torch.float64
SENSOR = PositionMeasurement(4, [0, 2], torch.tensor([[4.0, 0.5], [0.5, 2.0]], dtype=DT))
PI = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=DT)
OPTS = {"detection_probability": 0.9, "clutter_density": 2e-3, "survival_probability": 0.97, "birth_probability": 0.01}


def _scans(T, runs, D, seed, spread=8.0):
    gen = torch.Generator().manual_seed(seed)
    z = torch.randn(T, runs, D, 2, generator=gen, dtype=DT) * spread
    z[..., D - 2:, :] = math.nan  # padding
    return z


def test_existence_and_modes_equal_a_numpy_computation_from_the_imm_prediction():
    """One scan: ``1 - delta = 1 - P_D P_G + sum_k P_D p(z_k) / lambda`` with ``p`` the mode mixture
    (a detection weighs when some mode's gate holds it); ``chi = (1 - delta) chi^- / (1 - delta chi^-)``;
    the modes given existence ``mu_r ~ mu_r^- (1 - P_D P_G + sum_k P_D N_r(z_k) / lambda)``."""
    bank = ConstantVelocity(2, dt=1.0, q=0.5, acceleration=[[0.0, 0.0], [0.0, 8.0]], dtype=DT)
    imm = IMM(KalmanFilter(bank, SENSOR), PI)
    ipda = IPDA(imm, gate_probability=0.95, **OPTS)
    runs = 5
    gen = torch.Generator().manual_seed(4)
    prior = GaussianBelief(torch.randn(runs, 4, generator=gen, dtype=DT), torch.eye(4, dtype=DT) * 6)
    track = ipda.initial_belief(prior, existence=torch.tensor([0.2, 0.5, 0.9, 1.0, 0.05], dtype=DT))
    assert isinstance(track, ModeExistenceBelief)
    z = _scans(1, runs, 6, seed=5, spread=4.0)[0]
    out = ipda.step(track, z)
    pred = imm.predict(track.state)  # the IMM's own prediction (tested elsewhere)
    mu = pred.mode_log_probs.exp().numpy()  # (runs, M)
    means, covs = pred.components.mean.numpy(), pred.components.cov.numpy()
    chi_pred = OPTS["survival_probability"] * track.existence.numpy() + OPTS["birth_probability"] * (
        1 - track.existence.numpy())
    H, Rm = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]]), SENSOR.R.numpy()
    pd, lam, pg = OPTS["detection_probability"], OPTS["clutter_density"], 0.95
    gamma = chi2.ppf(pg, 2)
    for b in range(runs):
        per_mode = np.zeros(2)  # sum_k P_D N_r(z_k) / lambda
        for zk in z[b].numpy():
            if not np.isfinite(zk).all():
                continue
            S = [H @ covs[b, r] @ H.T + Rm for r in range(2)]
            nu = [zk - H @ means[b, r] for r in range(2)]
            if min(v @ np.linalg.solve(s, v) for v, s in zip(nu, S)) > gamma:
                continue
            per_mode += [pd * multivariate_normal(np.zeros(2), S[r]).pdf(nu[r]) / lam for r in range(2)]
        L_r = 1 - pd * pg + per_mode
        L = float(mu[b] @ L_r)  # 1 - delta
        chi = L * chi_pred[b] / (1 - (1 - L) * chi_pred[b])
        assert float(out.belief.existence[b]) == pytest.approx(chi, abs=1e-10, rel=1e-10)
        assert float(out.log_likelihood[b]) == pytest.approx(math.log(1 - (1 - L) * chi_pred[b]), abs=1e-10)
        modes = mu[b] * L_r / L
        np.testing.assert_allclose(out.belief.mode_log_probs[b].exp().numpy(), modes, atol=1e-10)


def _identical_bank():
    return ConstantVelocity(2, dt=1.0, q=0.3, acceleration=[[0.0, 0.0], [0.0, 0.0]], dtype=DT)


@pytest.mark.parametrize("joint", [False, True])
def test_an_imm_of_identical_modes_is_the_single_filter(joint):
    """Two identical modes mix to the one model: existence, estimates and log-likelihoods equal the
    IPDA's (JIPDA's) of the single Kalman filter."""
    cv = ConstantVelocity(2, dt=1.0, q=0.3, dtype=DT)
    kind, extra = (JIPDA, {"method": "exact"}) if joint else (IPDA, {})
    single = kind(KalmanFilter(cv, SENSOR), **OPTS, **extra)
    mixed = kind(IMM(KalmanFilter(_identical_bank(), SENSOR), PI), **OPTS, **extra)
    shape = (3, 2) if joint else (3,)
    gen = torch.Generator().manual_seed(7)
    prior = GaussianBelief(torch.randn(*shape, 4, generator=gen, dtype=DT) * 3, torch.eye(4, dtype=DT) * 20)
    z = _scans(10, 3, 5, seed=8)
    a = run_filter(single, single.initial_belief(prior, 0.6), z, record=None)
    b = run_filter(mixed, mixed.initial_belief(prior, 0.6), z, record=None)
    assert torch.allclose(a.belief.existence, b.belief.existence, atol=1e-12, rtol=0)
    assert torch.allclose(a.belief.mean, b.belief.estimate().mean, atol=1e-10, rtol=0)
    assert torch.allclose(a.log_likelihood, b.log_likelihood, atol=1e-12, rtol=0)


def _imm():
    bank = ConstantVelocity(2, dt=1.0, q=0.3, acceleration=[[0.0, 0.0], [0.0, 1.0], [0.0, -1.0]], dtype=DT)
    Pi = torch.full((3, 3), 0.05, dtype=DT) + 0.85 * torch.eye(3, dtype=DT)
    return IMM(KalmanFilter(bank, SENSOR), Pi)


def test_imm_jipda_with_one_track_is_the_imm_ipda():
    imm = _imm()
    joint = JIPDA(imm, method="exact", **OPTS)
    alone = IPDA(imm, **OPTS)
    prior = GaussianBelief(torch.zeros(4, 1, 4, dtype=DT), torch.eye(4, dtype=DT) * 20)
    z = _scans(8, 4, 5, seed=11)
    a = run_filter(joint, joint.initial_belief(prior, 0.4), z, record=None)
    b = run_filter(alone, alone.initial_belief(prior[:, 0], 0.4), z, record=None)
    assert torch.allclose(a.belief.existence[..., 0], b.belief.existence, atol=1e-12, rtol=0)
    assert torch.allclose(a.belief.mode_log_probs[..., 0, :].exp(), b.belief.mode_log_probs.exp(), atol=1e-12)
    assert torch.allclose(a.belief.components.mean[..., 0, :, :], b.belief.components.mean, atol=1e-10, rtol=0)
    assert torch.allclose(a.log_likelihood[..., 0], b.log_likelihood, atol=1e-12, rtol=0)


@pytest.mark.parametrize("method", ["exact", "lbp"])
def test_imm_jipda_with_sure_targets_is_the_imm_jpdaf(method):
    imm = _imm()
    sure = {**OPTS, "survival_probability": 1.0, "birth_probability": 0.0}
    joint = JIPDA(imm, method=method, **sure)
    jpda = JPDA(imm, method=method, **{k: sure[k] for k in ("detection_probability", "clutter_density")})
    prior = GaussianBelief(torch.tensor([[0.0, 1.0, 0.0, 0.0], [6.0, 0.0, 4.0, -1.0]], dtype=DT).expand(3, 2, 4),
                           torch.eye(4, dtype=DT) * 9)
    z = _scans(6, 3, 6, seed=12, spread=5.0)
    a = run_filter(joint, joint.initial_belief(prior, 1.0), z, record=None)
    b = run_filter(jpda, imm.initial_belief(prior), z, record=None)
    assert torch.allclose(a.belief.existence, torch.ones((), dtype=DT), atol=1e-12)
    assert torch.allclose(a.belief.estimate().mean, b.belief.estimate().mean, atol=1e-9, rtol=0)
    assert torch.allclose(a.belief.mode_log_probs.exp(), b.belief.mode_log_probs.exp(), atol=1e-10)


def test_errors_name_the_argument():
    imm = _imm()
    ipda = IPDA(imm, **OPTS)
    prior = GaussianBelief(torch.zeros(2, 4, dtype=DT), torch.eye(4, dtype=DT))
    with pytest.raises(TypeError, match="belief: IPDA needs an ExistenceBelief or a ModeExistenceBelief"):
        ipda.step(imm.initial_belief(prior), _scans(1, 2, 4, 0)[0])
    single = IPDA(KalmanFilter(ConstantVelocity(2, dtype=DT), SENSOR), **OPTS)
    with pytest.raises(ValueError, match="belief: a ModeBelief of 3 modes needs an IMM"):
        single.initial_belief(imm.initial_belief(prior))
    track = ipda.initial_belief(imm.initial_belief(prior), 0.5)  # a ready mode belief is taken as it is
    assert isinstance(track, ModeExistenceBelief) and track.batch_shape == (2,)
    with pytest.raises(ValueError, match="log_existence"):
        ModeExistenceBelief(track.mode_log_probs, track.components, torch.full((2,), 0.5, dtype=DT)).validate()

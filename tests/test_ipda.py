"""Integrated PDA (torchmm.association.IPDA): a float64 NumPy reference of Mušicki, Evans &
Stanković's recursion (existence Markov chain, delta, the PDA state), PDA when the target surely
exists, and track existence telling a target from clutter through run_filter."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2, multivariate_normal

from torchmm import GaussianBelief, KalmanFilter, run_filter
from torchmm.association import IPDA, JIPDA, PDA
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.simulate import simulate_detections

R = torch.tensor([[4.0, 0.5], [0.5, 2.0]], dtype=torch.float64)


def _models():
    return ConstantVelocity(2, dt=1.0, q=0.5, dtype=torch.float64), PositionMeasurement(4, [0, 2], R)


def _reference(x, P, chi, scans, *, pd, density, pg, ps, pb, F, Q, H, Rm):
    """IPDA in float64 NumPy, scan by scan: (means, existence, log-likelihoods)."""
    gamma = chi2.ppf(pg, 2) if pg < 1 else math.inf
    means, exist, logliks = [], [], []
    for scan in scans:
        x, P = F @ x, F @ P @ F.T + Q
        chi = ps * chi + pb * (1 - chi)
        S = H @ P @ H.T + Rm
        K = P @ H.T @ np.linalg.inv(S)
        dets = [z for z in scan if np.isfinite(z).all()]
        nus = [z - H @ x for z in dets]
        valid = [nu for nu in nus if nu @ np.linalg.solve(S, nu) <= gamma]
        g = [multivariate_normal(np.zeros(2), S).pdf(nu) for nu in valid]
        delta = pd * pg - pd * sum(g) / density
        beta = [pd * gi / density / (1 - delta) for gi in g]
        beta0 = (1 - pd * pg) / (1 - delta)
        nu = sum((b * v for b, v in zip(beta, valid)), np.zeros(2))
        spread = sum((b * np.outer(v, v) for b, v in zip(beta, valid)), np.zeros((2, 2))) - np.outer(nu, nu)
        x = x + K @ nu
        P = beta0 * P + (1 - beta0) * (P - K @ S @ K.T) + K @ spread @ K.T
        logliks.append(math.log(1 - delta * chi))
        chi = (1 - delta) * chi / (1 - delta * chi)
        means.append(x.copy())
        exist.append(chi)
    return np.array(means), np.array(exist), np.array(logliks)


@pytest.mark.parametrize("pd, pg, ps, pb", [(0.9, 0.99, 0.98, 0.0), (0.7, 0.95, 0.9, 0.05)])
def test_equals_a_numpy_reference_of_the_recursion(pd, pg, ps, pb):
    motion, sensor = _models()
    density = 1e-3
    gen = torch.Generator().manual_seed(int(100 * pd))
    truth = torch.tensor([0.0, 1.0, 0.0, 0.5], dtype=torch.float64) + torch.cumsum(
        torch.randn(12, 4, generator=gen, dtype=torch.float64) * 0.3, 0)
    det = simulate_detections(sensor, truth.unsqueeze(-2), detection_probability=pd, clutter_rate=3.0,
                              region=torch.tensor([[-30.0, 30.0], [-30.0, 30.0]]), generator=gen)
    ipda = IPDA(KalmanFilter(motion, sensor), detection_probability=pd, clutter_density=density,
                gate_probability=pg, survival_probability=ps, birth_probability=pb)
    x0 = GaussianBelief(torch.zeros(4, dtype=torch.float64), 5 * torch.eye(4, dtype=torch.float64))
    out = run_filter(ipda, ipda.initial_belief(x0, existence=0.4), det.z)
    H = sensor.H.numpy()
    means, exist, logliks = _reference(x0.mean.numpy(), x0.cov.numpy(), 0.4, det.z.numpy(), pd=pd, density=density,
                                       pg=pg, ps=ps, pb=pb, F=motion.F.numpy(), Q=motion.Q.numpy(), H=H,
                                       Rm=R.numpy())
    np.testing.assert_allclose(out.belief.mean.numpy(), means, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.belief.existence.numpy(), exist, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(out.log_likelihood.numpy(), logliks, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out.extras["existence"].numpy(), exist, rtol=1e-10, atol=1e-14)


def test_a_sure_target_is_the_pda():
    motion, sensor = _models()
    options = {"detection_probability": 0.9, "clutter_density": 1e-3, "gate_probability": 0.99}
    ipda = IPDA(KalmanFilter(motion, sensor), survival_probability=1.0, **options)
    pda = PDA(KalmanFilter(motion, sensor), **options)
    x0 = GaussianBelief(torch.zeros(3, 4, dtype=torch.float64), 5 * torch.eye(4, dtype=torch.float64))
    z = torch.randn(6, 3, 4, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 3
    a = run_filter(ipda, ipda.initial_belief(x0, existence=1.0), z)
    b = run_filter(pda, x0, z)
    torch.testing.assert_close(a.belief.mean, b.belief.mean, rtol=1e-13, atol=1e-12)
    torch.testing.assert_close(a.log_likelihood, b.log_likelihood, rtol=1e-13, atol=1e-12)
    assert torch.equal(a.belief.existence, torch.ones(6, 3, dtype=torch.float64))


def test_existence_tells_a_target_from_clutter():
    """Runs 0-9 hold a target where the track starts, runs 10-19 clutter only: over the second half of
    the scans, every target run's mean existence is above 0.8 and every clutter run's below 0.05
    (a missed detection costs an existing target some existence for a scan or two)."""
    motion, sensor = _models()
    gen = torch.Generator().manual_seed(5)
    runs = 20
    truth = torch.tensor([0.0, 1.0, 0.0, 0.5], dtype=torch.float64) + torch.cumsum(
        torch.randn(15, runs, 4, generator=gen, dtype=torch.float64) * 0.3, 0)
    truth[:, 10:] = math.nan  # no target in the second half
    det = simulate_detections(sensor, truth.unsqueeze(-2), detection_probability=0.9, clutter_rate=5.0,
                              region=torch.tensor([[-40.0, 40.0], [-40.0, 40.0]]), generator=gen)
    ipda = IPDA(KalmanFilter(motion, sensor), detection_probability=0.9, clutter_density=5.0 / 6400)
    x0 = GaussianBelief(torch.zeros(runs, 4, dtype=torch.float64), 4 * torch.eye(4, dtype=torch.float64))
    out = run_filter(ipda, ipda.initial_belief(x0, existence=0.5), det.z)
    late = out.belief.existence[8:].mean(0)
    assert (late[:10] > 0.8).all() and (late[10:] < 0.05).all(), late
    from torchmm.runtime import no_host_sync

    b = ipda.initial_belief(x0, existence=0.5)
    with no_host_sync("the IPDA step"):
        b = ipda.step(b, det.z[0]).belief
    assert torch.isfinite(b.log_existence).all()


def test_errors_name_the_argument():
    motion, sensor = _models()
    ipda = IPDA(KalmanFilter(motion, sensor), detection_probability=0.9, clutter_density=1e-3)
    x0 = GaussianBelief(torch.zeros(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="existence"):
        ipda.initial_belief(x0, existence=1.5)
    # issue 44: a wrong size and a string were raw errors of torch
    runs = x0.expand(3)
    for bad, error in ((torch.full((2,), 0.5), ValueError), (torch.full((3, 3), 0.5), ValueError),
                       ("0.5", TypeError), (True, TypeError), (torch.tensor([0.5, math.nan, 0.5]), ValueError),
                       (torch.tensor([0.5, -0.1, 0.5]), ValueError)):
        for assoc in (ipda, JIPDA(KalmanFilter(motion, sensor), detection_probability=0.9, clutter_density=1e-3)):
            with pytest.raises(error, match=r"^existence\b"):
                assoc.initial_belief(runs, existence=bad)
    track = ipda.initial_belief(runs, existence=torch.tensor([0.1, 0.5, 1.0]))  # one per run: accepted
    torch.testing.assert_close(track.existence, torch.tensor([0.1, 0.5, 1.0], dtype=torch.float64))
    with pytest.raises(TypeError, match="belief: IPDA needs an ExistenceBelief"):
        ipda.step(x0, torch.zeros(3, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="survival_probability"):
        IPDA(KalmanFilter(motion, sensor), detection_probability=0.9, clutter_density=1e-3, survival_probability=2.0)


def test_jipda_equals_enumeration_of_every_joint_event_with_existence():
    """JIPDA against a NumPy enumeration of every joint event (each track at most one detection, each
    detection at most one track) with weights chi_i P_D N / lambda and 1 - P_D P_G chi_i: the posterior
    existence, and the state given existence collapsed with beta_i0 (1 - P_D P_G) chi_i / m_i and
    beta_ij, divided by chi_i."""
    import itertools

    from torchmm.association import JIPDA

    motion, sensor = _models()
    pd, pg, density = 0.85, 0.99, 2e-3
    gen = torch.Generator().manual_seed(21)
    for method in ("exact", "lbp", "kbest"):  # (kbest with k above the 125 events: every event, exactly)
        jipda = JIPDA(KalmanFilter(motion, sensor), detection_probability=pd, clutter_density=density,
                      gate_probability=pg, survival_probability=1.0, method=method, k=1000)
        for trial in range(3):
            mean = torch.randn(3, 4, generator=gen, dtype=torch.float64) * (40.0 if method == "lbp" else 2.0)
            prior = GaussianBelief(mean, 6 * torch.eye(4, dtype=torch.float64))
            chi = torch.tensor([0.9, 0.4, 0.7], dtype=torch.float64)
            belief = jipda.initial_belief(prior, existence=chi)
            z = torch.cat([mean[:, [0, 2]] + 2 * torch.randn(3, 2, generator=gen, dtype=torch.float64),
                           mean[:1, [0, 2]] + 5 * torch.randn(1, 2, generator=gen, dtype=torch.float64)])
            out = jipda.update(belief, z)
            kf = KalmanFilter(motion, sensor)
            upd = [[kf.update(prior[i], z[j]) for j in range(4)] for i in range(3)]
            gamma = chi2.ppf(pg, 2)
            w = np.zeros((3, 4))
            for i in range(3):
                for j in range(4):
                    nu, S = upd[i][j].innovation.numpy(), upd[i][j].innovation_cov.numpy()
                    if nu @ np.linalg.solve(S, nu) <= gamma:
                        w[i, j] = chi[i].item() * pd * multivariate_normal(np.zeros(2), S).pdf(nu) / density
            m = 1 - pd * pg * chi.numpy()
            beta, Z = np.zeros((3, 5)), 0.0
            for event in itertools.product(range(5), repeat=3):
                used = [j for j in event if j]
                if len(used) != len(set(used)):
                    continue
                weight = math.prod(w[i, j - 1] if j else m[i] for i, j in enumerate(event))
                Z += weight
                for i, j in enumerate(event):
                    beta[i, j] += weight
            beta /= Z
            missed_exists = beta[:, 0] * (1 - pd * pg) * chi.numpy() / m
            existence = missed_exists + beta[:, 1:].sum(-1)
            tol = 1e-7 if method == "lbp" else 1e-10
            np.testing.assert_allclose(out.belief.existence.numpy(), existence, rtol=tol, atol=tol)
            if method != "lbp":
                assert float(out.log_likelihood[0]) == pytest.approx(math.log(Z), rel=1e-10)
            for i in range(3):
                weights = np.concatenate([[missed_exists[i]], beta[i, 1:]]) / existence[i]
                means = [prior.mean[i].numpy()] + [upd[i][j].belief.mean.numpy() for j in range(4)]
                covs = [prior[i].cov.numpy()] + [upd[i][j].belief.cov.numpy() for j in range(4)]
                mu = sum(wk * mk for wk, mk in zip(weights, means))
                cov = sum(wk * (ck + np.outer(mk - mu, mk - mu)) for wk, mk, ck in zip(weights, means, covs))
                np.testing.assert_allclose(out.belief.mean[i].numpy(), mu, rtol=tol, atol=tol)
                np.testing.assert_allclose(out.belief.cov[i].numpy(), cov, rtol=tol, atol=tol)


def test_jipda_with_one_track_is_the_ipda_and_with_sure_targets_the_jpda():
    from torchmm.association import JIPDA, JPDA

    motion, sensor = _models()
    options = {"detection_probability": 0.9, "clutter_density": 1e-3, "gate_probability": 0.99}
    z = torch.randn(5, 2, 4, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 3
    x0 = GaussianBelief(torch.zeros(2, 1, 4, dtype=torch.float64), 5 * torch.eye(4, dtype=torch.float64))
    jipda = JIPDA(KalmanFilter(motion, sensor), survival_probability=0.95, **options)
    ipda = IPDA(KalmanFilter(motion, sensor), survival_probability=0.95, **options)
    a = run_filter(jipda, jipda.initial_belief(x0, existence=0.6), z)
    b = run_filter(ipda, ipda.initial_belief(x0[:, 0], existence=0.6), z)
    torch.testing.assert_close(a.belief.mean[:, :, 0], b.belief.mean, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(a.belief.existence[:, :, 0], b.belief.existence, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(a.log_likelihood[:, :, 0], b.log_likelihood, rtol=1e-12, atol=1e-12)
    x3 = GaussianBelief(torch.tensor([[0.0, 0, 0, 0], [3.0, 0, 1, 0], [-2.0, 0, 2, 0]], dtype=torch.float64)
                        .expand(2, 3, 4), 5 * torch.eye(4, dtype=torch.float64))
    sure = JIPDA(KalmanFilter(motion, sensor), survival_probability=1.0, **options)
    got = run_filter(sure, sure.initial_belief(x3, existence=1.0), z)
    want = run_filter(JPDA(KalmanFilter(motion, sensor), **options), x3, z)
    torch.testing.assert_close(got.belief.mean, want.belief.mean, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=1e-12, atol=1e-10)

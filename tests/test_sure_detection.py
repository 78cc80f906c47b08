"""P_D P_G = 1 (detection_probability=1, gate_probability=1): the missed weight m = 0, every track must take a
detection. The loopy-belief-propagation JPDA against brute-force enumeration and against a hand-written
NumPy Williams & Lau iteration at small m > 0 (its m -> 0 limit); JIPDA with sure targets (existence 1)
against JPDA for every method, and JIPDA near P_D P_G = 1 against a float64 enumeration."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from torchmm import GaussianBelief, KalmanFilter
from torchmm.association import JIPDA, JPDA, jpda_marginals
from torchmm.models import ConstantVelocity, PositionMeasurement

from tests.test_jpda import _brute  # (every joint event, a missed weight per track)


def _williams_lau(w: np.ndarray, m: float, iterations: int = 20000) -> np.ndarray:
    """Williams & Lau (IEEE TAES 50(4), 2014) as printed, m > 0, every sum over the others written out."""
    N, D = w.shape
    nu = np.ones((N, D))
    for _ in range(iterations):
        mu = np.array([[w[i, j] / (m + sum(w[i, k] * nu[i, k] for k in range(D) if k != j)) for j in range(D)]
                       for i in range(N)])
        nu = np.array([[1.0 / (1.0 + sum(mu[k, j] for k in range(N) if k != i)) for j in range(D)]
                       for i in range(N)])
    num = np.concatenate([np.full((N, 1), m), w * nu], -1)
    return num / num.sum(-1, keepdims=True)


def test_lbp_with_no_missed_weight_is_finite_and_exact_without_shared_detections():
    # disjoint gates and a padding column (-inf everywhere): loopy BP is exact, here as for m > 0
    log_w = torch.tensor([[[0.0, -math.inf, -math.inf, -math.inf], [-math.inf, -0.7, 0.4, -math.inf]]],
                         dtype=torch.float64)
    lbp, _ = jpda_marginals(log_w, 0.0, method="lbp")
    beta, _ = _brute(log_w[0].exp().numpy(), np.zeros(2))
    np.testing.assert_allclose(lbp[0].exp().numpy(), beta, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("log_w", [[[0.0, -5.0], [-5.0, 0.0]], [[0.0, math.log(0.5)], [math.log(0.5), 0.0]],
                                   [[0.0, -1.0, -0.5], [-0.3, 0.0, -2.0]]])
def test_lbp_with_no_missed_weight_is_the_limit_of_small_missed_weights(log_w):
    """Shared detections: m = 0 gives the messages' m -> 0 limit (the reference at m = 1e-9, converged). For
    [[0, -5], [-5, 0]] that is [[0, 1, 0], [0, 0, 1]] (exact: 0.99995); loopy BP on the one loop of two tracks
    sharing two detections is more confident than exact as m -> 0 (docs/tracking.md)."""
    log_w = torch.tensor([log_w], dtype=torch.float64)
    lbp, _ = jpda_marginals(log_w, 0.0, method="lbp", iterations=5000)
    ref = _williams_lau(log_w[0].exp().numpy(), 1e-9, iterations=3000)
    assert torch.isfinite(lbp).logical_or(torch.isneginf(lbp)).all()
    np.testing.assert_allclose(lbp[0].exp().numpy(), ref, atol=1e-6)


def test_lbp_messages_match_the_printed_iteration_for_a_positive_missed_weight():
    gen = torch.Generator().manual_seed(2)
    log_w = torch.randn(1, 3, 4, generator=gen, dtype=torch.float64)
    log_w[0, 0, 3] = -math.inf
    for m in (0.5, 1e-3):
        lbp, _ = jpda_marginals(log_w, m, method="lbp", iterations=3000, tolerance=0.0)
        ref = _williams_lau(log_w[0].exp().numpy(), m, iterations=3000)
        np.testing.assert_allclose(lbp[0].exp().numpy(), ref, rtol=1e-10, atol=1e-13)


def _kf():
    return KalmanFilter(ConstantVelocity(2, q=0.1, dtype=torch.float64), PositionMeasurement(4, [0, 2], 1.0))


def _prior(N=2):
    mean = torch.tensor([[[0, 0, 0, 0.0], [10, 0, 0, 0], [4, 0, 6, 0]]], dtype=torch.float64)[:, :N]
    return GaussianBelief(mean, torch.eye(4, dtype=torch.float64).expand(1, N, 4, 4).clone())


SURE = dict(detection_probability=1.0, clutter_density=1e-4, gate_probability=1.0)


def test_lbp_jpda_with_sure_detection_and_a_padding_row_matches_exact():
    z = torch.tensor([[[0.5, 0.2], [9.0, 0.5], [math.nan, math.nan]]], dtype=torch.float64)
    exact = JPDA(_kf(), **SURE).update(_prior(), z)
    lbp = JPDA(_kf(), method="lbp", **SURE).update(_prior(), z)
    assert not lbp.extras["failed"].any()
    torch.testing.assert_close(lbp.extras["association"], exact.extras["association"], rtol=0, atol=1e-12)
    torch.testing.assert_close(lbp.belief.mean, exact.belief.mean, rtol=0, atol=1e-9)


def test_the_sums_over_the_others_keep_small_terms_beside_a_dominant_or_infinite_one():
    from torchmm.association.jpda import others_sum

    gen = torch.Generator().manual_seed(1)
    for shape, dim in (((3, 4, 5), -1), ((3, 4, 5), -2), ((2, 1, 3), -2)):
        x = torch.rand(shape, generator=gen, dtype=torch.float64)
        x[0].view(-1)[0] = math.inf
        x[1].view(-1)[:2] = 1e30  # two equal dominant terms
        x[-1].view(-1)[-1] = 1e20
        ref = torch.stack([sum(x.select(dim, k) for k in range(x.shape[dim]) if k != i) if x.shape[dim] > 1
                           else torch.zeros_like(x.select(dim, i)) for i in range(x.shape[dim])], dim)
        torch.testing.assert_close(others_sum(x, dim), ref, rtol=1e-14, atol=0)


@pytest.mark.parametrize("method", ["exact", "kbest", "lbp"])
def test_jipda_with_sure_targets_and_sure_detection_is_the_jpda(method):
    """docs/tracking.md: a JIPDA whose tracks exist for sure is the JPDA; with P_D = P_G = 1 too (m = 0), over
    scans with clutter, padding and one impossible scan (fewer detections than tracks: priors kept)."""
    gen = torch.Generator().manual_seed(5)
    prior = GaussianBelief(torch.tensor([[0, 1, 0, 0.0], [10, 0, 0, 1], [4, 0, 6, 0]], dtype=torch.float64)
                           .expand(2, 3, 4).clone(), 2 * torch.eye(4, dtype=torch.float64))
    z = torch.randn(4, 2, 5, 2, generator=gen, dtype=torch.float64) * 8
    z[:, :, 3:] = math.nan  # padding
    z[2, 0, 1:] = math.nan  # one detection for three sure tracks: no joint event
    jpda = JPDA(_kf(), method=method, k=1000, **SURE)
    jipda = JIPDA(_kf(), method=method, k=1000, survival_probability=1.0, **SURE)
    b_jpda, b_jipda = prior, jipda.initial_belief(prior, existence=1.0)
    for t in range(4):
        want = jpda.update(jpda.predict(b_jpda), z[t])
        predicted = jipda.predict(b_jipda)
        got = jipda.update(predicted, z[t])
        if t == 2:  # run 0's impossible scan: likelihood 0, every track keeps its prediction
            assert torch.isneginf(got.log_likelihood[0]).all()
            assert torch.isneginf(want.log_likelihood[0]).all()
            torch.testing.assert_close(got.belief.state.mean[0], predicted.state.mean[0], rtol=0, atol=0)
        assert not got.extras["failed"].any() and not want.extras["failed"].any()
        assert torch.equal(got.extras["existence"], torch.ones(2, 3, dtype=torch.float64))
        torch.testing.assert_close(got.belief.state.mean, want.belief.mean, rtol=1e-12, atol=1e-10)
        torch.testing.assert_close(got.belief.state.cov, want.belief.cov, rtol=1e-12, atol=1e-10)
        torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=1e-12, atol=1e-10)
        b_jpda, b_jipda = want.belief, got.belief


@pytest.mark.parametrize("detection_probability", [1.0, 1.0 - 1e-9])
def test_jipda_near_sure_detection_against_an_enumeration_in_50_digits(detection_probability):
    """P_D P_G at or within 1e-9 of 1, existences 1, 1 - 1e-9 and 0.3: the posterior existence, marginals and
    means against every joint event summed in 50-digit arithmetic (mpmath) from the same float64 weights
    (track 1 lies far from every detection: its existence given a miss is (1 - P_D P_G) chi / m, 0.5 here,
    0 at P_D = 1)."""
    import mpmath

    with mpmath.workdps(50):
        _near_sure(detection_probability, mpmath)


def _near_sure(detection_probability, mpmath):
    pd = detection_probability
    kf = _kf()
    prior = GaussianBelief(torch.tensor([[0, 0, 0, 0.0], [60, 0, 60, 0], [10, 0, 0, 0]], dtype=torch.float64),
                           torch.eye(4, dtype=torch.float64))
    z = torch.tensor([[0.5, 0.2], [9.0, 0.5], [3.0, 3.0]], dtype=torch.float64)
    density = 1e-3
    jipda = JIPDA(kf, detection_probability=pd, clutter_density=density, gate_probability=1.0, method="exact")
    belief = jipda.initial_belief(prior, existence=torch.tensor([1.0, 1.0 - 1e-9, 0.3], dtype=torch.float64))
    out = jipda.update(belief, z)
    upd = [[kf.update(prior[i], z[j]) for j in range(3)] for i in range(3)]
    chi = [mpmath.exp(mpmath.mpf(float(v))) for v in belief.log_existence]
    pdpg = mpmath.mpf(pd)
    w = [[chi[i] * pdpg * mpmath.mpf(float(torch.distributions.MultivariateNormal(
        torch.zeros(2, dtype=torch.float64), upd[i][j].innovation_cov).log_prob(upd[i][j].innovation).exp()))
        / mpmath.mpf(density) for j in range(3)] for i in range(3)]
    m = [1 - pdpg * c for c in chi]
    beta, Z = [[mpmath.mpf(0)] * 4 for _ in range(3)], mpmath.mpf(0)
    for event in itertools.product(range(4), repeat=3):
        used = [j for j in event if j]
        if len(used) != len(set(used)):
            continue
        weight = mpmath.fprod(w[i][j - 1] if j else m[i] for i, j in enumerate(event))
        Z += weight
        for i, j in enumerate(event):
            beta[i][j] += weight
    beta = [[b / Z for b in row] for row in beta]
    missed_exists = [beta[i][0] * ((1 - pdpg) * chi[i] / m[i] if m[i] != 0 else 1) for i in range(3)]
    existence = [missed_exists[i] + sum(beta[i][1:]) for i in range(3)]
    assert not out.extras["failed"].any()
    np.testing.assert_allclose(out.extras["existence"].numpy(), np.array(existence, dtype=float), rtol=1e-12,
                               atol=0)
    np.testing.assert_allclose(out.extras["association"].numpy(), np.array(beta, dtype=float), rtol=1e-10,
                               atol=1e-300)
    for i in range(3):
        weights = [missed_exists[i]] + beta[i][1:]
        weights = ([float(v / existence[i]) for v in weights] if existence[i] > 0
                   else [1.0, 0.0, 0.0, 0.0])  # (no chance of existing: the prior kept)
        means = [prior.mean[i]] + [upd[i][j].belief.mean for j in range(3)]
        mean = sum(wk * mk for wk, mk in zip(weights, means))
        torch.testing.assert_close(out.belief.state.mean[i], mean, rtol=1e-10, atol=1e-10)
    assert abs(float(existence[1]) - (0.5 if pd < 1 else 0.0)) < 1e-6

"""GOSPA and OSPA (torchmm.metrics.sets) at any order p, where c^p and d^p leave the float range: against
every partial assignment (every pairing for OSPA) summed in 2000-digit arithmetic (mpmath: every u^p kept beside
c^p), p in {1, 2, 150, 250}, with sets whose points all pair far within c (the sum of u^p far below 1)."""

from __future__ import annotations

import itertools

import mpmath
import numpy as np
import pytest
import torch

from torchmm.metrics import gospa, ospa

DIGITS = 2000  # (the sums span up to p log10(c / d) digits: every term kept beside c^p)
BIG = float(np.finfo(np.float64).max)


def _reference_gospa(X, Y, c, p):
    """(distance, localisation, missed, false) of the best partial assignment, in DIGITS digits."""
    with mpmath.workdps(DIGITS):
        return _gospa_digits(X, Y, c, p)


def _gospa_digits(X, Y, c, p):
    c, p = mpmath.mpf(c), mpmath.mpf(p)
    D = [[min(mpmath.mpf(float(np.linalg.norm(x - y))), c) for y in Y] for x in X]
    best = None
    for k in range(min(len(X), len(Y)) + 1):
        for rows in itertools.combinations(range(len(X)), k):
            for cols in itertools.permutations(range(len(Y)), k):
                close = [D[i][j] for i, j in zip(rows, cols) if D[i][j] < c]
                loc = mpmath.fsum(d**p for d in close)
                missed, false = c**p / 2 * (len(X) - len(close)), c**p / 2 * (len(Y) - len(close))
                total = loc + missed + false
                if best is None or total < best[0]:
                    best = (total, loc, missed, false)
    total, *parts = best
    return (total ** (1 / p), *parts)


def _reference_ospa(X, Y, c, p):
    with mpmath.workdps(DIGITS):
        return _ospa_digits(X, Y, c, p)


def _ospa_digits(X, Y, c, p):
    if not len(X) and not len(Y):
        return mpmath.mpf(0)
    if not len(X) or not len(Y):
        return mpmath.mpf(c)
    if len(X) > len(Y):
        X, Y = Y, X
    c, p = mpmath.mpf(c), mpmath.mpf(p)
    D = [[min(mpmath.mpf(float(np.linalg.norm(x - y))), c) for y in Y] for x in X]
    best = min(mpmath.fsum(D[i][j] ** p for i, j in enumerate(cols))
               for cols in itertools.permutations(range(len(Y)), len(X)))
    return ((best + c**p * (len(Y) - len(X))) / len(Y)) ** (1 / p)


def _as_float(v):
    """A reference part as float64: inf beyond the float range (what gospa reports there)."""
    return float(v) if v <= BIG else np.inf


@pytest.mark.parametrize("p", [1.0, 2.0, 150.0, 250.0])
def test_gospa_and_ospa_against_an_enumeration_in_2000_digits(p):
    rng = np.random.default_rng(int(p))
    c = 30.0
    for trial in range(40):
        N, K = int(rng.integers(0, 5)), int(rng.integers(0, 5))
        truth = rng.normal(size=(N, 2)) * 20
        if trial % 2 and N and K:  # every truth with an estimate close by: the sum of u^p far below 1
            K = N
            scale = rng.choice([1e-3, 0.1, 3.0])
            est = truth[rng.permutation(N)] + rng.normal(size=(N, 2)) * scale
        else:
            est = rng.normal(size=(K, 2)) * 20
        out = gospa(torch.tensor(est).reshape(K, 2), torch.tensor(truth).reshape(N, 2), c=c, p=p)
        want = _reference_gospa(list(truth), list(est), c, p)
        assert float(out["distance"]) == pytest.approx(float(want[0]), rel=1e-9, abs=1e-12), (trial, N, K)
        for key, ref in zip(("localisation", "missed", "false"), want[1:]):
            got, ref = float(out[key]), _as_float(ref)
            assert got == pytest.approx(ref, rel=1e-9, abs=1e-300) or got == ref, (trial, key, got, ref)
        o = ospa(torch.tensor(est).reshape(K, 2), torch.tensor(truth).reshape(N, 2), c=c, p=p)
        assert float(o) == pytest.approx(float(_reference_ospa(list(truth), list(est), c, p)), rel=1e-9,
                                         abs=1e-12), (trial, N, K)


def test_gospa_at_p_250_is_a_number_and_batched_equals_alone():
    """c^p = 30^250 is beyond float64 (an OverflowError before): the distance is the enumeration's, the
    parts in units of distance^p are inf where they pass the float range (missed, false) and exact where
    not; a batch of set pairs gives each pair's own figures."""
    truth = torch.tensor([[0.0, 0.0], [10.0, 0.0], [50.0, 50.0]], dtype=torch.float64)
    est = torch.tensor([[1.0, 0.0], [10.0, 2.0]], dtype=torch.float64)
    out = gospa(est, truth, c=30.0, p=250.0)
    want = _reference_gospa(list(truth.numpy()), list(est.numpy()), 30.0, 250.0)
    assert float(out["distance"]) == pytest.approx(float(want[0]), rel=1e-12)
    assert out["assigned"].tolist() == [0, 1, -1]
    assert float(out["localisation"]) == pytest.approx(float(want[1]), rel=1e-12)
    assert float(out["missed"]) == np.inf and float(out["false"]) == 0.0
    gen = torch.Generator().manual_seed(0)
    T = torch.randn(6, 4, 2, generator=gen, dtype=torch.float64) * 15
    E = T[:, torch.tensor([2, 0, 3, 1])] + torch.randn(6, 4, 2, generator=gen, dtype=torch.float64) * 0.01
    batched = gospa(E, T, c=30.0, p=250.0)
    for b in range(6):
        alone = gospa(E[b], T[b], c=30.0, p=250.0)
        assert float(batched["distance"][b]) == float(alone["distance"])
        assert batched["assigned"][b].tolist() == alone["assigned"].tolist() == [1, 3, 0, 2]


def test_the_device_form_reads_nothing_on_the_host_and_gives_the_same_figures():
    """Without host reads (a GPU's form, tried on the CPU) every set pair is also assigned on the rescaled
    costs and the better kept where needed: the same figures as the CPU's form, at p = 2 and 250."""
    from torchmm.runtime import no_host_sync

    gen = torch.Generator().manual_seed(4)
    T = torch.randn(5, 4, 2, generator=gen, dtype=torch.float64) * 15
    E = torch.cat([T[:, torch.tensor([2, 0, 3, 1])] + torch.randn(5, 4, 2, generator=gen, dtype=torch.float64)
                   * torch.tensor([1e-3, 0.1, 1.0, 5.0, 30.0], dtype=torch.float64).view(5, 1, 1),
                   torch.randn(5, 1, 2, generator=gen, dtype=torch.float64) * 40], 1)
    for p in (2.0, 250.0):
        want, want_ospa = gospa(E, T, c=30.0, p=p), ospa(E, T, c=30.0, p=p)
        with no_host_sync("set metrics"):
            got, got_ospa = gospa(E, T, c=30.0, p=p), ospa(E, T, c=30.0, p=p)
        for key in want:
            assert torch.equal(got[key], want[key]), (p, key)
        assert torch.equal(got_ospa, want_ospa)

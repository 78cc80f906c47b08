"""The batched assignment (torchmm.assignment) and the set metrics GOSPA and OSPA (torchmm.metrics.sets),
issue 32: against brute-force enumeration, scipy's linear_sum_assignment and Stone Soup 1.9."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from torchmm.assignment import assignment_cost, linear_assignment
from torchmm.metrics import gospa, ospa


def _brute_assignment(C: np.ndarray) -> float:
    n, m = C.shape
    if n <= m:
        return min(sum(C[i, cols[i]] for i in range(n)) for cols in itertools.permutations(range(m), n))
    return _brute_assignment(C.T)


@pytest.mark.parametrize("n, m", [(1, 1), (2, 3), (3, 2), (4, 4), (5, 7), (7, 5), (9, 9)])
def test_assignment_is_optimal_against_scipy_and_enumeration(n, m):
    gen = torch.Generator().manual_seed(10 * n + m)
    C = torch.rand(40, n, m, generator=gen, dtype=torch.float64) * 10
    C[::4] = C[::4].round()  # ties
    C[1::4] = C[1::4] - 100.0  # negative costs
    assigned = linear_assignment(C)
    assert assigned.shape == (40, n) and assigned.dtype == torch.long
    for b in range(40):
        cols = assigned[b][assigned[b] >= 0].tolist()
        assert len(cols) == len(set(cols)) == min(n, m) and all(0 <= j < m for j in cols)
    got = assignment_cost(C, assigned).numpy()
    rows, cols = zip(*(linear_sum_assignment(c) for c in C.numpy()))
    want = np.array([c[r, k].sum() for c, r, k in zip(C.numpy(), rows, cols)])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    if n * m <= 30:  # and by enumeration of every assignment
        np.testing.assert_allclose(got, [_brute_assignment(c) for c in C.numpy()], rtol=0, atol=1e-12)


def test_assignment_batch_shapes_float32_and_empty():
    gen = torch.Generator().manual_seed(1)
    C = torch.rand(2, 3, 4, 4, generator=gen, dtype=torch.float32)
    out = linear_assignment(C)
    assert out.shape == (2, 3, 4)
    flat = linear_assignment(C.reshape(6, 4, 4)).reshape(2, 3, 4)
    assert torch.equal(out, flat)
    torch.testing.assert_close(assignment_cost(C, out), assignment_cost(C.double(), linear_assignment(C.double())).float())
    assert linear_assignment(torch.zeros(5, 0, 3)).shape == (5, 0)
    assert (linear_assignment(torch.zeros(5, 2, 0)) == -1).all()
    with pytest.raises(ValueError, match="cost"):
        linear_assignment(torch.tensor([[math.inf, 1.0]]))


# -- GOSPA and OSPA against the definitions, enumerated -------------------------------------------

def _brute_gospa(X: np.ndarray, Y: np.ndarray, c: float, p: float) -> tuple[float, float, float, float]:
    """Every partial assignment of truths X to estimates Y: (distance, localisation, missed, false) of
    the best, the pairs at distance >= c counted as a missed and a false point."""
    best = None
    half = c**p / 2
    for k in range(min(len(X), len(Y)) + 1):
        for rows in itertools.combinations(range(len(X)), k):
            for cols in itertools.permutations(range(len(Y)), k):
                d = [min(float(np.linalg.norm(X[i] - Y[j])), c) for i, j in zip(rows, cols)]
                close = [x for x in d if x < c]
                loc = sum(x**p for x in close)
                missed, false = half * (len(X) - len(close)), half * (len(Y) - len(close))
                total = loc + missed + false
                if best is None or total < best[0]:
                    best = (total, loc, missed, false)
    total, loc, missed, false = best
    return total ** (1 / p), loc, missed, false


def _brute_ospa(X: np.ndarray, Y: np.ndarray, c: float, p: float) -> float:
    if len(X) > len(Y):
        X, Y = Y, X
    m, n = len(X), len(Y)
    if n == 0:
        return 0.0
    best = min(sum(min(float(np.linalg.norm(X[i] - Y[pi[i]])), c) ** p for i in range(m))
               for pi in itertools.permutations(range(n), m))
    return ((best + c**p * (n - m)) / n) ** (1 / p)


def _random_sets(gen, batch: int, N: int, K: int, d: int = 2):
    truth = torch.rand(batch, N, d, generator=gen, dtype=torch.float64) * 20
    est = truth[:, torch.randint(0, N, (K,), generator=gen)] if N else torch.zeros(batch, K, d, dtype=torch.float64)
    est = est + torch.randn(batch, K, d, generator=gen, dtype=torch.float64) * 3
    tp = torch.rand(batch, N, generator=gen) < 0.8
    ep = torch.rand(batch, K, generator=gen) < 0.8
    return est, truth, ep, tp


@pytest.mark.parametrize("p", [1.0, 2.0, 3.5])
def test_gospa_and_ospa_equal_enumeration_over_all_assignments(p):
    gen = torch.Generator().manual_seed(int(10 * p))
    for N, K in ((0, 3), (3, 0), (1, 1), (3, 4), (4, 2), (4, 4)):
        est, truth, ep, tp = _random_sets(gen, 12, N, K)
        c = 5.0
        out = gospa(est, truth, c=c, p=p, estimate_present=ep, truth_present=tp)
        dist = ospa(est, truth, c=c, p=p, estimate_present=ep, truth_present=tp)
        assert out["distance"].shape == (12,) and out["assigned"].shape == (12, N) and dist.shape == (12,)
        for b in range(12):
            X, Y = truth[b][tp[b]].numpy(), est[b][ep[b]].numpy()
            want = _brute_gospa(X, Y, c, p)
            got = [float(out[k][b]) for k in ("distance", "localisation", "missed", "false")]
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(float(dist[b]), _brute_ospa(X, Y, c, p), rtol=1e-12, atol=1e-12)
            # the reported assignment: present points, closer than c, each estimate once
            a = out["assigned"][b]
            kept = a[a >= 0]
            assert len(set(kept.tolist())) == len(kept) and bool(ep[b][kept].all()) and bool(tp[b][a >= 0].all())


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_a_non_finite_true_point_is_a_target_that_does_not_exist(p):
    """Issue 44: a truth row with a NaN or infinite coordinate (simulate_detections' states: a target not
    yet born or dead) was a present point at distance c from everything, so every such row counted as a
    missed target. It is absent: GOSPA and OSPA equal the enumeration over the sets without those rows
    (and without the rows truth_present masks), and the row is never assigned."""
    gen = torch.Generator().manual_seed(7)
    for N, K in ((3, 3), (4, 2), (2, 4)):
        est, truth, ep, tp = _random_sets(gen, 10, N, K)
        truth = truth.clone()
        gone = torch.rand(10, N, generator=gen) < 0.4
        coordinate = torch.randint(0, 2, (10, N), generator=gen)
        bad = torch.where(torch.rand(10, N, generator=gen) < 0.5, math.nan, math.inf)
        truth[gone, coordinate[gone]] = bad[gone]  # one coordinate NaN or inf: the target does not exist
        for masks in ({}, {"estimate_present": ep, "truth_present": tp}):
            out = gospa(est, truth, c=5.0, p=p, **masks)
            dist = ospa(est, truth, c=5.0, p=p, **masks)
            for b in range(10):
                keep = ~gone[b] & (tp[b] if masks else torch.ones(N, dtype=torch.bool))
                X = truth[b][keep].numpy()
                Y = est[b][ep[b]].numpy() if masks else est[b].numpy()
                got = [float(out[k][b]) for k in ("distance", "localisation", "missed", "false")]
                np.testing.assert_allclose(got, _brute_gospa(X, Y, 5.0, p), rtol=1e-12, atol=1e-12)
                np.testing.assert_allclose(float(dist[b]), _brute_ospa(X, Y, 5.0, p), rtol=1e-12, atol=1e-12)
                assert (out["assigned"][b][gone[b]] == -1).all()
    # a diverged *estimate* is still scored: a false point and a missed target
    out = gospa(torch.tensor([[math.nan, 0.0]]), torch.tensor([[0.0, 0.0]]), c=4.0)
    assert float(out["missed"]) == 8.0 and float(out["false"]) == 8.0


def test_masks_broadcasting_and_diverged_estimates():
    truth = torch.tensor([[0.0, 0.0], [10.0, 0.0], [float("nan"), float("nan")]])  # the last row: padding
    est = torch.tensor([[[0.0, 1.0], [float("nan"), 3.0]], [[10.0, 0.0], [0.0, 0.0]]])  # (2 runs, 2, 2)
    present = torch.tensor([True, True, False])
    out = gospa(est, truth, c=4.0, truth_present=present)
    assert out["distance"].shape == (2,)
    # run 0: (0,0)-(0,1) at 1; the diverged estimate is false, truth (10, 0) missed
    torch.testing.assert_close(out["localisation"], torch.tensor([1.0, 0.0]))
    torch.testing.assert_close(out["missed"], torch.tensor([8.0, 0.0]))
    torch.testing.assert_close(out["false"], torch.tensor([8.0, 0.0]))
    assert out["assigned"].tolist() == [[0, -1, -1], [1, 0, -1]]
    torch.testing.assert_close(ospa(est, truth, c=4.0, truth_present=present), torch.tensor([((1 + 16) / 2) ** 0.5, 0.0]))
    with pytest.raises(ValueError, match="truth"):
        gospa(est, torch.zeros(3, 3), c=4.0)
    with pytest.raises(ValueError, match="truth_present"):
        gospa(est, truth, c=4.0, truth_present=torch.ones(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="c"):
        gospa(est, truth, c=0.0)
    with pytest.raises(ValueError, match="p"):
        ospa(est, truth, c=1.0, p=0.5)


# -- Stone Soup 1.9 -------------------------------------------------------------------------------

def _stone_soup_states(points: np.ndarray, when):
    from stonesoup.types.state import State

    return [State(np.asarray(x, dtype=float).reshape(-1, 1), timestamp=when) for x in points]


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_gospa_and_ospa_equal_stone_soup(p):
    """Stone Soup's GOSPAMetric (``compute_gospa_metric``) on the same sets gives the same four figures;
    its OSPAMetric too for p = 1 (it assigns on distances, not on distances to the p: for p != 1 its
    assignment can miss the optimum, and torchmm's OSPA is then at most its)."""
    import datetime

    from stonesoup.measures import Euclidean
    from stonesoup.metricgenerator.ospametric import GOSPAMetric, OSPAMetric

    when = datetime.datetime(2026, 12, 4)
    c = 6.0
    g_ss = GOSPAMetric(c=c, p=p, measure=Euclidean())
    o_ss = OSPAMetric(c=c, p=p, measure=Euclidean())
    gen = torch.Generator().manual_seed(7)
    for N, K in ((1, 3), (4, 4), (5, 3), (6, 8)):
        est, truth, _, _ = _random_sets(gen, 10, N, K)
        out = gospa(est, truth, c=c, p=p)
        dist = ospa(est, truth, c=c, p=p)
        for b in range(10):
            X, Y = _stone_soup_states(truth[b].numpy(), when), _stone_soup_states(est[b].numpy(), when)
            metric, _ = g_ss.compute_gospa_metric(Y, X)
            for key in ("distance", "localisation", "missed", "false"):
                assert float(out[key][b]) == pytest.approx(metric.value[key], rel=1e-9, abs=1e-9), key
            theirs = o_ss.compute_OSPA_distance(Y, X).value
            if p == 1.0:
                assert float(dist[b]) == pytest.approx(theirs, rel=1e-9, abs=1e-9)
            else:
                assert float(dist[b]) <= theirs + 1e-9


def test_the_device_form_reads_nothing_and_equals_the_early_stopping_cpu_form():
    """On the CPU the scans stop when every matrix is done (a host read); the device form runs them
    all without a read (checked under no_host_sync) and gives the same assignments."""
    from torchmm.assignment import _hungarian  # the solver behind the entry point's value check
    from torchmm.runtime import no_host_sync

    C = torch.rand(30, 5, 8, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    cpu = _hungarian(C)
    with no_host_sync("the batched assignment"):
        device = _hungarian(C)
    assert torch.equal(cpu, device)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (runs where a GPU is present)")
def test_on_cuda_equal_the_cpu_and_do_not_synchronise():
    """The assignment and GOSPA on CUDA: the same assignments and figures as on the CPU, with no
    host synchronisation (``torch.cuda.set_sync_debug_mode("error")``)."""
    gen = torch.Generator().manual_seed(11)
    C = torch.rand(64, 6, 9, generator=gen, dtype=torch.float64)
    est, truth, ep, tp = _random_sets(gen, 64, 5, 7)
    cpu_assigned, cpu_gospa = linear_assignment(C), gospa(est, truth, c=4.0, estimate_present=ep, truth_present=tp)
    Cd, estd, truthd, epd, tpd = (t.cuda() for t in (C, est, truth, ep, tp))
    from torchmm.assignment import _hungarian  # past the entry point's one value check
    from torchmm.contract import unchecked

    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        assigned = _hungarian(Cd)
        out = unchecked(gospa)(estd, truthd, c=4.0, estimate_present=epd, truth_present=tpd)  # past its checks
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert torch.equal(assigned.cpu(), cpu_assigned)
    for key in ("distance", "localisation", "missed", "false", "assigned"):
        torch.testing.assert_close(out[key].cpu(), cpu_gospa[key], rtol=1e-12, atol=1e-12)


def test_gospa_switching_equals_stone_soup_over_time():
    """GOSPA's track-switching term (issue 46) against Stone Soup's ``GOSPAMetric(switching_penalty=...)``
    over time: tracks that wander between targets, targets that appear and vanish, p = 1 and 2; the
    switching term and the combined distance at every step (1e-9)."""
    import datetime

    from stonesoup.measures import Euclidean
    from stonesoup.metricgenerator.ospametric import GOSPAMetric

    from torchmm.metrics import gospa_switching

    gen = torch.Generator().manual_seed(5)
    T, N, K, c = 12, 3, 3, 4.0
    base = datetime.datetime(2026, 12, 7)
    for p in (1.0, 2.0):
        for trial in range(4):
            truth = torch.randn(T, N, 2, generator=gen, dtype=torch.float64).cumsum(0) * 2
            present = torch.rand(T, N, generator=gen) > 0.2
            # each track follows a random target each step (plus noise): switches, losses and gains
            follow = torch.randint(0, N, (T, K), generator=gen)
            est = truth.gather(1, follow.unsqueeze(-1).expand(T, K, 2)) + torch.randn(T, K, 2, generator=gen,
                                                                                      dtype=torch.float64) * 1.5
            out = gospa(est, torch.where(present.unsqueeze(-1), truth, math.nan), c=c, p=p)
            term = gospa_switching(out["assigned"], penalty=3.0, p=p, truth_present=present)
            combined = (out["distance"] ** 2 + term ** 2).sqrt()
            from stonesoup.types.state import State
            meas, meas_ids, tru, tru_ids = [], [], [], []
            for k in range(T):
                when = base + datetime.timedelta(seconds=k)
                for j in range(K):
                    meas.append(State(est[k, j].numpy().reshape(-1, 1), timestamp=when))
                    meas_ids.append(j)
                for i in range(N):
                    if present[k, i]:
                        tru.append(State(truth[k, i].numpy().reshape(-1, 1), timestamp=when))
                        tru_ids.append(i)
            metric = GOSPAMetric(c=c, p=p, measure=Euclidean(), switching_penalty=3.0)
            theirs = metric.compute_over_time(meas, meas_ids, tru, tru_ids).value
            assert len(theirs) == T
            for k in range(T):
                assert float(term[k]) == pytest.approx(theirs[k].value["switching"], abs=1e-9), (p, trial, k)
                assert float(combined[k]) == pytest.approx(theirs[k].value["distance"], abs=1e-9), (p, trial, k)
            assert float(term.sum()) > 0  # (the case exercises switches)


def test_gospa_switching_cases_by_hand():
    from torchmm.metrics import gospa_switching

    # never tracked, then tracked: no cost; a track lost: half; another track: full; absent: nothing
    labels = torch.tensor([[-1], [-1], [2], [-1], [-1], [3], [4], [4]])
    present = torch.tensor([[True], [True], [True], [True], [False], [True], [True], [True]])
    out = gospa_switching(labels, penalty=1.0, p=1.0, truth_present=present)
    assert out.tolist() == [0.0, 0.0, 0.0, 0.5, 0.0, 0.5, 1.0, 0.0]
    two = gospa_switching(torch.tensor([[0, 1], [1, 0]]), penalty=2.0, p=2.0)  # a swap: two full switches
    assert two.tolist() == pytest.approx([0.0, 2.0 * 2 ** 0.5])
    with pytest.raises(ValueError, match="penalty"):
        gospa_switching(labels, penalty=-1.0)
    with pytest.raises(ValueError, match="labels"):
        gospa_switching(torch.tensor([[-2]]), penalty=1.0)

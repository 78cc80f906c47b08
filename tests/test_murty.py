"""k_best_assignments (Murty's k best assignments, issue 46) against an enumeration of every assignment:
random batched cost matrices up to 6 x 6, square and rectangular both ways, with forbidden pairs and ties."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

import torchmm.kernels as kernels
from torchmm.assignment import k_best_assignments, linear_assignment


@pytest.fixture(autouse=True, params=["compiled loop", "tensors"])
def path(request):
    """Every test on both paths: the compiled CPU loop (the default on the CPU) and the batched tensor
    form (a device's; here with the loop switched off)."""
    if request.param == "tensors":
        with kernels.switched_off("assignment_loops"):
            yield request.param
    else:
        yield request.param


def enumerate_costs(cost: np.ndarray) -> list[tuple[float, tuple]]:
    """Every assignment of ``cost (n, m)`` (each of the min(n, m) rows / columns matched) with its cost,
    sorted; forbidden pairs (inf) left out."""
    n, m = cost.shape
    out = []
    if n <= m:
        for cols in itertools.permutations(range(m), n):
            total = sum(cost[i, j] for i, j in enumerate(cols))
            if math.isfinite(total):
                out.append((total, tuple(cols)))
    else:
        for rows in itertools.permutations(range(n), m):
            assigned = [-1] * n
            for j, i in enumerate(rows):
                assigned[i] = j
            total = sum(cost[i, j] for j, i in enumerate(rows))
            if math.isfinite(total):
                out.append((total, tuple(assigned)))
    return sorted(out, key=lambda t: t[0])


def check_against_enumeration(cost: torch.Tensor, k: int) -> None:
    assign, costs = k_best_assignments(cost, k)
    flat_c = cost.reshape(-1, *cost.shape[-2:]).numpy()
    flat_a = assign.reshape(-1, k, cost.shape[-2]).numpy()
    flat_k = costs.reshape(-1, k).numpy()
    for c, a, kk in zip(flat_c, flat_a, flat_k):
        ref = enumerate_costs(c)
        want = [t for t, _ in ref[:k]] + [math.inf] * (k - min(k, len(ref)))
        np.testing.assert_allclose(kk, want, rtol=1e-12, atol=1e-12)
        seen = set()
        for row, total in zip(a, kk):
            if not math.isfinite(total):
                assert (row == -1).all()
                continue
            used = [j for j in row if j >= 0]
            assert len(used) == len(set(used)) == min(c.shape)  # a valid assignment
            assert sum(c[i, j] for i, j in enumerate(row) if j >= 0) == pytest.approx(total, rel=1e-12, abs=1e-12)
            assert tuple(row) not in seen  # each once
            seen.add(tuple(row))


@pytest.mark.parametrize("n, m", [(1, 1), (2, 3), (3, 3), (4, 4), (3, 5), (5, 3), (4, 6), (6, 6), (6, 2)])
def test_k_best_equal_an_enumeration(n, m):
    g = torch.Generator().manual_seed(10 * n + m)
    cost = torch.randn(5, n, m, dtype=torch.float64, generator=g)
    total = math.perm(max(n, m), min(n, m))
    for k in (1, 3, min(total, 12), total + 2):
        check_against_enumeration(cost, k)


@pytest.mark.parametrize("n, m", [(3, 3), (4, 5), (5, 4), (6, 6)])
def test_ties_and_forbidden_pairs(n, m):
    """Integer costs (many ties) and forbidden pairs (+inf), some matrices with no assignment at all."""
    g = torch.Generator().manual_seed(n * m)
    cost = torch.randint(0, 3, (2, 3, n, m), generator=g).to(torch.float64)
    forbid = torch.rand(2, 3, n, m, generator=g) < 0.3
    cost = torch.where(forbid, math.inf, cost)
    cost[0, 0, 0] = math.inf  # row 0 forbidden everywhere: no assignment when n <= m
    check_against_enumeration(cost, 25)


def test_the_first_is_the_optimal_assignment():
    g = torch.Generator().manual_seed(1)
    cost = torch.rand(64, 7, 9, dtype=torch.float64, generator=g)
    assign, costs = k_best_assignments(cost, 4)
    best = linear_assignment(cost)
    torch.testing.assert_close(costs[:, 0], cost.gather(-1, best.unsqueeze(-1)).squeeze(-1).sum(-1), rtol=1e-12,
                               atol=1e-12)
    assert bool((costs[:, 1:] >= costs[:, :-1]).all())


def test_shapes_empty_and_errors():
    a, c = k_best_assignments(torch.zeros(2, 0, 3), 2)
    assert a.shape == (2, 2, 0) and c.tolist() == [[0.0, math.inf]] * 2
    a, c = k_best_assignments(torch.zeros(0, 3, 3), 2)
    assert a.shape == (0, 2, 3) and c.shape == (0, 2)
    with pytest.raises(ValueError, match="^cost: NaN or -inf"):
        k_best_assignments(torch.tensor([[float("nan")]]), 1)
    with pytest.raises(ValueError, match="^cost: entries up to 1e\\+308"):
        k_best_assignments(torch.tensor([[1e308, 1.0], [math.inf, 1e308]], dtype=torch.float64), 2)
    with pytest.raises(ValueError, match="^k"):
        k_best_assignments(torch.zeros(2, 2), 0)


def test_both_paths_give_the_same_costs():
    g = torch.Generator().manual_seed(5)
    cost = torch.rand(40, 6, 8, dtype=torch.float64, generator=g)
    cost[cost > 0.9] = math.inf
    _, loop = k_best_assignments(cost, 15)
    with kernels.switched_off("assignment_loops"):
        _, tensors = k_best_assignments(cost, 15)
    torch.testing.assert_close(loop, tensors, rtol=1e-12, atol=1e-12)

"""The Numba loops of :func:`torchmm.assignment.k_best_assignments` on the CPU (imported on first use).

The same algorithm as the batched tensor form in torchmm/assignment.py, one run after another in one
compiled call: the cost matrix made square with rows of zeros (so that a child's only free column is
the one its row gave up), solved by the shortest-augmenting-path Hungarian method (Jonker & Volgenant's
potentials), then Murty's partition (Murty, Oper. Res. 16(3), 1968), each child solved by one augmenting
path from its parent's optimal potentials (Miller, Stone & Cox, IEEE TAES 33(3), 1997). Results equal
the tensor form's (tests/test_murty.py runs both against an enumeration of every assignment).

Array layouts (C-contiguous float64 / int64): ``base (R, m, m)`` the square costs with forbidden pairs
already ``big``, ``c (R, n, m)`` the true costs (``inf``: forbidden), outputs ``assign (R, k, n)`` and
``costs (R, k)``.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def _augment(a, u, v, p, row, minv, way, used):
    """Assign the unassigned ``row`` (1-based) of the square ``a (m + 1, m + 1)`` (index 0 virtual) by one
    shortest augmenting path over the reduced costs ``a - u - v``; ``u``, ``v``, ``p`` in place."""
    m1 = v.shape[0]
    p[0] = row
    j0 = 0
    for j in range(m1):
        minv[j] = math.inf
        used[j] = False
        way[j] = 0
    while True:
        used[j0] = True
        i0 = p[j0]
        delta = math.inf
        j1 = 0
        for j in range(1, m1):
            if not used[j]:
                cur = a[i0, j] - u[i0] - v[j]
                if cur < minv[j]:
                    minv[j] = cur
                    way[j] = j0
                if minv[j] < delta:
                    delta = minv[j]
                    j1 = j
        for j in range(m1):
            if used[j]:
                u[p[j]] += delta
                v[j] -= delta
            else:
                minv[j] -= delta
        j0 = j1
        if p[j0] == 0:
            break
    while j0 != 0:
        j1 = way[j0]
        p[j0] = p[j1]
        j0 = j1


@numba.njit(cache=True)
def murty(base, c, n, k, bigs, assign, costs):
    """The ``k`` best assignments of the first ``n`` rows of every ``base[r]`` (see the module docstring)."""
    R, m = base.shape[0], base.shape[1]
    m1 = m + 1
    P = 1 + (k - 1) * n
    minv = np.empty(m1)
    way = np.empty(m1, np.int64)
    used = np.empty(m1, np.bool_)
    a = np.zeros((m1, m1))
    pool_cost = np.empty(P)
    pool_u = np.empty((P, m1))
    pool_v = np.empty((P, m1))
    pool_p = np.empty((P, m1), np.int64)
    pool_forbid = np.zeros((P, n, m), np.bool_)
    pool_forced = np.empty((P, n), np.int64)
    blocked = np.zeros((n, m), np.bool_)
    forced_c = np.empty(n, np.int64)
    cols = np.empty(n, np.int64)
    row_of = np.empty(m1, np.int64)
    for r in range(R):
        big = bigs[r]
        for q in range(P):
            pool_cost[q] = math.inf
        # the root: every row of the square matrix
        for i in range(m):
            for j in range(m):
                a[i + 1, j + 1] = base[r, i, j]
        u = pool_u[0]
        v = pool_v[0]
        p = pool_p[0]
        for j in range(m1):
            u[j] = 0.0
            v[j] = 0.0
            p[j] = 0
        for i in range(1, m + 1):
            _augment(a, u, v, p, i, minv, way, used)
        pool_forbid[0, :, :] = False
        pool_forced[0, :] = -1
        pool_cost[0] = _cost(c[r], p, n, pool_forbid[0], pool_forced[0], row_of)
        free_slot = 1
        for rank in range(k):
            best = 0
            for q in range(1, free_slot):
                if pool_cost[q] < pool_cost[best]:
                    best = q
            bc = pool_cost[best]
            if not bc < math.inf:
                break
            costs[r, rank] = bc
            for j in range(1, m1):  # (row_of: each row's column)
                row_of[pool_p[best, j]] = j - 1
            for i in range(n):
                cols[i] = row_of[i + 1]
                assign[r, rank, i] = cols[i]
            pool_cost[best] = math.inf
            if rank == k - 1:
                break
            # the children of `best`: row c forbidden from cols[c], the free rows before it forced
            for i in range(n):
                forced_c[i] = pool_forced[best, i]
            for ch in range(n):
                if pool_forced[best, ch] >= 0:
                    continue
                slot = free_slot
                free_slot += 1
                for i in range(n):
                    for j in range(m):
                        pool_forbid[slot, i, j] = pool_forbid[best, i, j]
                pool_forbid[slot, ch, cols[ch]] = True
                for i in range(n):
                    pool_forced[slot, i] = forced_c[i]
                # the child's matrix: blocked pairs cost big
                for i in range(n):
                    for j in range(m):
                        blocked[i, j] = pool_forbid[slot, i, j]
                for i in range(n):
                    f = forced_c[i]
                    if f >= 0:
                        for j in range(m):
                            if j != f:
                                blocked[i, j] = True
                        for i2 in range(n):
                            if i2 != i:
                                blocked[i2, f] = True
                for i in range(m):
                    for j in range(m):
                        a[i + 1, j + 1] = big if i < n and blocked[i, j] else base[r, i, j]
                uc = pool_u[slot]
                vc = pool_v[slot]
                pc = pool_p[slot]
                for j in range(m1):
                    uc[j] = pool_u[best, j]
                    vc[j] = pool_v[best, j]
                    pc[j] = pool_p[best, j]
                pc[cols[ch] + 1] = 0  # row ch gives up its column
                _augment(a, uc, vc, pc, ch + 1, minv, way, used)
                pool_cost[slot] = _cost(c[r], pc, n, blocked, forced_c, row_of)
                forced_c[ch] = cols[ch]  # the next children keep row ch on its column


@numba.njit(cache=True)
def _cost(c, p, n, blocked, forced, row_of):
    """The true cost of the assignment ``p`` (the row on each column) of the first ``n`` rows of ``c``;
    ``inf`` where it takes a forbidden or blocked pair."""
    m1 = p.shape[0]
    for j in range(1, m1):
        row_of[p[j]] = j - 1
    total = 0.0
    for i in range(n):
        j = row_of[i + 1]
        if blocked[i, j] or (forced[i] >= 0 and forced[i] != j) or not c[i, j] < math.inf:
            return math.inf
        total += c[i, j]
    return total

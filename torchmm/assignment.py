r"""Minimum-cost assignment of batches of small cost matrices (issue 32: the set metrics, later GNN).

:func:`linear_assignment` solves every ``(n, m)`` cost matrix of a batch at once by the Hungarian method
in its shortest-augmenting-path form (Kuhn 1955; Munkres 1957; Jonker & Volgenant, Computing 38, 1987,
whose potentials it keeps): rows are added one at a time, and each addition grows a Dijkstra-like
search over the columns, with dual potentials ``u`` (rows) and ``v`` (columns) keeping the reduced
costs non-negative, until it reaches a free column; the path is then flipped. ``O(n^2 m)`` work per
matrix. The search of one row takes a data-dependent number of scans, at most ``m + 1``; the batch
elements already done are masked, so the Python loop is over the rows and the scans, never over the
batch. On the CPU the scans stop when every element is done (one host read a scan; typically after
two or three of the ``m + 1``); elsewhere all ``m + 1`` run, without a host read, with the same result.

The optimum is exact (up to ties, which change the assignment but not its cost) in the arithmetic of
the costs: tested against ``scipy.optimize.linear_sum_assignment`` and brute-force enumeration
(tests/test_assignment.py).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchmm.contract import Finite, Int, Values, entry_point, unchecked
from torchmm.runtime import host_reads_ok

__all__ = ["assignment_cost", "k_best_assignments", "linear_assignment"]


@entry_point(cost=Finite())
def linear_assignment(cost: Tensor) -> Tensor:
    r"""The minimum-cost assignment of every matrix of a batch.

    Each of the ``min(n, m)`` rows (or columns, if fewer) is assigned one distinct column (row); the sum
    of the chosen entries is the least possible.

    Args:
        cost: ``(*B, n, m)`` finite, floating.

    Returns:
        ``(*B, n)`` long: the column assigned to each row, ``-1`` for a row left unassigned (only when
        ``n > m``).

    Raises:
        ValueError naming ``cost``: not at least two-dimensional, not floating, or not finite.

    Examples:
        >>> cost = torch.tensor([[4.0, 1.0, 3.0], [2.0, 0.0, 5.0], [3.0, 2.0, 2.0]])
        >>> linear_assignment(cost)
        tensor([1, 0, 2])
    """
    if not isinstance(cost, Tensor):
        cost = torch.as_tensor(cost, dtype=torch.get_default_dtype())
    if cost.dim() < 2 or not cost.is_floating_point():
        raise ValueError(f"cost: expected a floating tensor (*B, n, m), got shape {tuple(cost.shape)}, "
                         f"dtype {cost.dtype}")
    n, m = cost.shape[-2:]
    batch = cost.shape[:-2]
    if n == 0 or m == 0:
        return torch.full((*batch, n), -1, dtype=torch.long, device=cost.device)
    if n > m:  # solve the transpose: each column gets a row
        col_to_row = unchecked(linear_assignment)(cost.mT)  # (*B, m): checked once, above
        rows = torch.full((*batch, n), -1, dtype=torch.long, device=cost.device)
        cols = torch.arange(m, device=cost.device).expand(*batch, m)
        return rows.scatter(-1, col_to_row, cols)
    a = cost.reshape(-1, n, m)
    return _hungarian(a).reshape(*batch, n)


@entry_point(cost=Values(), assigned=Values())
def assignment_cost(cost: Tensor, assigned: Tensor) -> Tensor:
    """The sum of the entries of ``cost (*B, n, m)`` that ``assigned (*B, n)`` (as returned by
    :func:`linear_assignment`; ``-1``: none) chooses, ``(*B,)``.

    Raises:
        ValueError naming ``assigned``: not ``(*B, n)`` integer column indices of ``cost``.
    """
    if cost.dim() < 2:
        raise ValueError(f"cost: expected (*B, n, m), got shape {tuple(cost.shape)}")
    if assigned.is_floating_point() or assigned.shape != cost.shape[:-1]:
        raise ValueError(f"assigned: expected integer column indices of shape {tuple(cost.shape[:-1])}, got "
                         f"{tuple(assigned.shape)} {assigned.dtype}")
    taken = cost.gather(-1, assigned.clamp_min(0).unsqueeze(-1)).squeeze(-1)
    return torch.where(assigned >= 0, taken, torch.zeros_like(taken)).sum(-1)


def _hungarian(cost: Tensor) -> Tensor:
    """``(B, n, m)``, ``n <= m`` -> ``(B, n)``: the shortest-augmenting-path Hungarian method, batched
    (1-based rows and columns inside, index 0 the virtual start column)."""
    B, n, m = cost.shape
    a, u, v, p = _padded(cost)
    for i in range(1, n + 1):
        _augment(a, u, v, p, torch.full((B,), i, dtype=torch.long, device=cost.device))
    return _row_columns(p, n)


def _padded(cost: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The Hungarian method's state for ``cost (B, n, m)``: the costs with a zero row and column in front
    (1-based inside), the row and column potentials, and ``p`` (the row on each column, 0: free)."""
    B, n, m = cost.shape
    a = torch.zeros(B, n + 1, m + 1, dtype=cost.dtype, device=cost.device)
    a[:, 1:, 1:] = cost
    u = torch.zeros(B, n + 1, dtype=cost.dtype, device=cost.device)
    v = torch.zeros(B, m + 1, dtype=cost.dtype, device=cost.device)
    p = torch.zeros(B, m + 1, dtype=torch.long, device=cost.device)
    return a, u, v, p


def _row_columns(p: Tensor, n: int) -> Tensor:
    """``(B, n)``: each row's column (0-based) from ``p (B, m + 1)``."""
    B, m = p.shape[0], p.shape[1] - 1
    out = torch.zeros(B, n + 1, dtype=torch.long, device=p.device)
    out = out.scatter(1, p[:, 1:], torch.arange(m, device=p.device).expand(B, m))  # free columns land on row 0
    return out[:, 1:]


def _augment(a: Tensor, u: Tensor, v: Tensor, p: Tensor, row: Tensor) -> None:
    """Assign the unassigned ``row (B,)`` (1-based) of every matrix by one shortest augmenting path
    (Dijkstra over the reduced costs ``a - u - v``), updating the potentials ``u``, ``v`` and the
    assignment ``p`` in place. The other rows' assignment and the potentials must be optimal for them
    (reduced costs non-negative, zero on the assigned pairs): true after the rows before it, and after a
    change that only raises the costs of unassigned pairs (Murty's constraints)."""
    B, m1 = v.shape
    dev = a.device
    inf = torch.full((), torch.inf, dtype=a.dtype, device=dev)
    early = host_reads_ok(a)  # stop the scans when every matrix is done (a host read; CPU only)
    p[:, 0] = row
    j0 = torch.zeros(B, dtype=torch.long, device=dev)
    minv = inf.expand(B, m1).clone()
    way = torch.zeros(B, m1, dtype=torch.long, device=dev)  # the previous column on the search path
    used = torch.zeros(B, m1, dtype=torch.bool, device=dev)
    active = torch.ones(B, dtype=torch.bool, device=dev)
    arange = torch.arange(m1, device=dev)
    for _ in range(m1):  # at most m + 1 scans reach a free column
        used |= active.unsqueeze(-1) & (arange == j0.unsqueeze(-1))
        i0 = p.gather(1, j0.unsqueeze(-1))  # (B, 1)
        reduced = a.gather(1, i0.unsqueeze(-1).expand(B, 1, m1)).squeeze(1) - u.gather(1, i0) - v  # (B, m + 1)
        better = active.unsqueeze(-1) & ~used & (reduced < minv)
        minv = torch.where(better, reduced, minv)
        way = torch.where(better, j0.unsqueeze(-1), way)
        delta, j1 = torch.where(used, inf, minv).min(-1)
        step = active.unsqueeze(-1)
        shift = torch.where(step & used, delta.unsqueeze(-1), torch.zeros_like(v))
        u.scatter_add_(1, p, shift)  # u[p[j]] += delta over the used columns
        v -= shift
        minv = torch.where(step & ~used, minv - delta.unsqueeze(-1), minv)
        j0 = torch.where(active, j1, j0)
        active = active & (p.gather(1, j0.unsqueeze(-1)).squeeze(-1) != 0)
        if early and not bool(active.any()):
            break
    for _ in range(m1):  # flip the path back to the start column
        moving = j0 != 0
        if early and not bool(moving.any()):
            break
        j1 = way.gather(1, j0.unsqueeze(-1))
        p.scatter_(1, j0.unsqueeze(-1), torch.where(moving.unsqueeze(-1), p.gather(1, j1), p.gather(1, j0.unsqueeze(-1))))
        j0 = torch.where(moving, j1.squeeze(-1), j0)


@entry_point(cost=Values(), k=Int(1))
def k_best_assignments(cost: Tensor, k: int) -> tuple[Tensor, Tensor]:
    r"""The ``k`` least-cost assignments of every matrix of a batch, in order (Murty, Oper. Res. 16(3),
    1968), each solved by the batched Hungarian method of :func:`linear_assignment`.

    Murty's partition: the best assignment ``a`` of a subproblem (a cost matrix with some pairs forced
    and some forbidden) splits the rest of its assignments into disjoint subproblems, one per row ``r``
    not forced: rows before ``r`` forced to their columns in ``a``, the pair ``(r, a_r)`` forbidden. The
    next best assignment is the best of the subproblems not yet taken; ``k`` rounds give the ``k`` best,
    each once. Every run keeps its own pool of subproblems (at most ``1 + (k - 1) n``, each with its
    solution and the Hungarian method's optimal potentials); a round solves the ``n`` children of every
    run's chosen subproblem as one batch of ``runs x n`` matrices, each by one augmenting path from its
    parent's optimum (Miller, Stone & Cox, IEEE TAES 33(3), 1997): ``O(n m)`` a child instead of a
    whole solve. The Python loop is over the ``k`` rounds (and the Hungarian method's rows and
    scans), never over runs or subproblems. Forbidden pairs (``+inf`` entries, and Murty's constraints)
    cost more than any whole assignment of allowed ones, so every solve is of a finite matrix; a solution
    that needs one is infeasible and ends the run's list.

    Args:
        cost: ``(*B, n, m)`` floating, ``+inf`` for a forbidden pair (NaN and ``-inf`` are refused).
            Each of the ``min(n, m)`` rows (or columns, if fewer) is assigned one distinct column (row).
        k: how many assignments.

    Returns:
        ``assignments (*B, k, n)`` long (the column of each row, ``-1`` for a row left unassigned when
        ``n > m``; a whole row of ``-1`` past the last feasible assignment) and ``costs (*B, k)``
        ascending (``+inf`` past the last feasible one). Ties are broken arbitrarily; the costs are
        those of an enumeration of every assignment, sorted (tests/test_murty.py).

    Raises:
        ValueError naming ``cost`` (not ``(*B, n, m)`` floating, NaN or ``-inf`` entries) or ``k``.

    Examples:
        >>> cost = torch.tensor([[4.0, 1.0, 3.0], [2.0, 0.0, 5.0], [3.0, 2.0, 2.0]])
        >>> assignments, costs = k_best_assignments(cost, 3)
        >>> costs
        tensor([5., 6., 6.])
        >>> assignments[0]
        tensor([1, 0, 2])
    """
    if not isinstance(cost, Tensor) or cost.dim() < 2 or not cost.is_floating_point():
        raise ValueError(f"cost: expected a floating tensor (*B, n, m), got "
                         f"{tuple(cost.shape) if isinstance(cost, Tensor) else type(cost).__name__}")
    checked = host_reads_ok(cost)  # (value checks read the host; under no_host_sync they are the caller's)
    if checked and bool((torch.isnan(cost) | torch.isneginf(cost)).any()):
        raise ValueError("cost: NaN or -inf entries (+inf forbids a pair; every other entry must be finite)")
    *batch, n, m = cost.shape
    k = int(k)
    if n > m:  # the columns are assigned rows: solve the transpose, then turn column -> row into row -> column
        by_col, costs = unchecked(k_best_assignments)(cost.mT, k)  # (*B, k, m)
        rows = torch.full((*batch, k, n), -1, dtype=torch.long, device=cost.device)
        cols = torch.arange(m, device=cost.device).expand(*batch, k, m)
        return _scatter_rows(rows, by_col, cols, n), costs
    R = math.prod(batch)
    dev, dt = cost.device, cost.dtype
    out_assign = torch.full((R, k, n), -1, dtype=torch.long, device=dev)
    out_cost = torch.full((R, k), math.inf, dtype=dt, device=dev)
    if R == 0:
        return out_assign.reshape(*batch, k, n), out_cost.reshape(*batch, k)
    if n == 0:  # one assignment, the empty one
        out_cost[:, :1].zero_()
        return out_assign.reshape(*batch, k, n), out_cost.reshape(*batch, k)
    c = cost.reshape(R, n, m)
    allowed = torch.isfinite(c)
    finite = torch.where(allowed, c, torch.zeros((), dtype=dt, device=dev))
    big = (finite.abs().amax((-2, -1), keepdim=True) + 1) * (2 * n + 1)  # > any feasible assignment's total
    if checked and not bool(torch.isfinite(big).all()):
        raise ValueError(f"cost: entries up to {float(finite.abs().max()):.3g} in magnitude leave no finite cost "
                         "for a forbidden pair (+inf); rescale the costs")
    base = torch.where(allowed, c, big)
    if _loops_apply(cost):  # the CPU: the compiled loop, one run after another (the same algorithm)
        from torchmm.kernels import assignment_loops

        sq = torch.cat([base, base.new_zeros(R, m - n, m)], -2) if m > n else base
        assign_np = np.full((R, k, n), -1, dtype=np.int64)
        cost_np = np.full((R, k), np.inf)
        assignment_loops.murty(np.ascontiguousarray(sq.detach().double().numpy()),
                               np.ascontiguousarray(c.detach().double().numpy()), n, k,
                               np.ascontiguousarray(big.reshape(R).detach().double().numpy()), assign_np, cost_np)
        out_assign = torch.from_numpy(assign_np)
        out_cost = torch.from_numpy(cost_np).to(dt)
        return out_assign.reshape(*batch, k, n), out_cost.reshape(*batch, k)
    rows_r = torch.arange(R, device=dev)
    cols = torch.arange(m, device=dev)

    def true_cost(sol: Tensor, blocked: Tensor) -> Tensor:
        """``sol (..., n)`` of ``c`` -> its cost, ``inf`` where it takes a forbidden or blocked pair."""
        cc = c.reshape(R, *([1] * (sol.dim() - 2)), n, m).expand(*sol.shape, m)
        taken = cc.gather(-1, sol.unsqueeze(-1)).squeeze(-1)
        bad = blocked.gather(-1, sol.unsqueeze(-1)).squeeze(-1).any(-1) | ~torch.isfinite(taken).all(-1)
        return torch.where(bad, math.inf, taken.sum(-1))

    P = 1 + (k - 1) * n
    pool_cost = torch.full((R, P), math.inf, dtype=dt, device=dev)
    pool_forbid = torch.zeros((R, P, n, m), dtype=torch.bool, device=dev)
    pool_forced = torch.full((R, P, n), -1, dtype=torch.long, device=dev)
    # each subproblem's optimal Hungarian state: potentials and the row on each column (1-based, 0 free)
    pool_u = torch.zeros((R, P, m + 1), dtype=dt, device=dev)
    pool_v = torch.zeros((R, P, m + 1), dtype=dt, device=dev)
    pool_p = torch.zeros((R, P, m + 1), dtype=torch.long, device=dev)
    # square: m - n rows of zeros added (any column left over costs nothing), so that every column is
    # assigned and a child's only free column is the one its row gave up (one augmenting path to it is
    # then optimal; with several free columns of different potentials it need not be)
    def square(t: Tensor, fill) -> Tensor:
        return torch.cat([t, t.new_full((*t.shape[:-2], m - n, m), fill)], -2) if m > n else t

    a0, u0, v0, p0 = _padded(square(base, 0.0))
    for i in range(1, m + 1):
        _augment(a0, u0, v0, p0, torch.full((R,), i, dtype=torch.long, device=dev))
    pool_u[:, 0], pool_v[:, 0], pool_p[:, 0] = u0, v0, p0
    pool_cost[:, 0] = true_cost(_row_columns(p0, m)[:, :n], torch.zeros(R, n, m, dtype=torch.bool, device=dev))
    before = torch.arange(n, device=dev).unsqueeze(-1) > torch.arange(n, device=dev)  # [child, row]: row < child
    child = torch.arange(n, device=dev)
    for r in range(k):
        best = pool_cost.argmin(-1)  # (R,)
        bc = pool_cost[rows_r, best]
        ok = torch.isfinite(bc)
        pp = pool_p[rows_r, best]
        a = _row_columns(pp, m)[:, :n]
        out_cost[:, r] = bc
        out_assign[:, r] = torch.where(ok.unsqueeze(-1), a, -1)
        if r == k - 1:
            break
        pool_cost.scatter_(1, best.unsqueeze(-1), pool_cost.new_full((R, 1), math.inf))  # (taken)
        forbid, forced = pool_forbid[rows_r, best], pool_forced[rows_r, best]  # (R, n, m), (R, n)
        free_row = forced < 0
        # child c: the rows before c that are free forced to a's columns; the pair (c, a_c) forbidden
        forced_c = torch.where(free_row.unsqueeze(-2) & before, a.unsqueeze(-2), forced.unsqueeze(-2))  # (R, n, n)
        forbid_c = forbid.unsqueeze(1).expand(R, n, n, m).clone()
        forbid_c[:, child, child] |= cols == a.unsqueeze(-1)  # (R, n, m) for child c, row c
        exists = free_row & ok.unsqueeze(-1)  # (R, n): child c exists where row c is free
        cell = (cols == forced_c.clamp_min(0).unsqueeze(-1)) & (forced_c >= 0).unsqueeze(-1)  # (R, n, n, m)
        blocked = forbid_c | ((forced_c >= 0).unsqueeze(-1) & ~cell) | (cell.any(-2, keepdim=True) & ~cell)
        # each child from its parent's optimum: the constraints only raise the costs of pairs the parent
        # leaves unassigned once row c is unassigned, so its potentials stay feasible and one augmenting
        # path from row c solves the child (Miller, Stone & Cox, IEEE TAES 33(3), 1997)
        ac, uc, vc, pc = _padded(square(torch.where(blocked, big.unsqueeze(1), base.unsqueeze(1)), 0.0)
                                 .reshape(R * n, m, m))
        uc.copy_(pool_u[rows_r, best].unsqueeze(1).expand(R, n, m + 1).reshape(R * n, m + 1))
        vc.copy_(pool_v[rows_r, best].unsqueeze(1).expand(R, n, m + 1).reshape(R * n, m + 1))
        pc = pp.unsqueeze(1).expand(R, n, m + 1)
        pc = torch.where(pc == (child + 1).reshape(1, n, 1), 0, pc).reshape(R * n, m + 1)  # row c's column freed
        _augment(ac, uc, vc, pc, (child + 1).repeat(R))
        sol = _row_columns(pc, m)[:, :n].reshape(R, n, n)
        slots = 1 + r * n + child
        pool_cost[:, slots] = torch.where(exists, true_cost(sol, blocked), math.inf)
        pool_forbid[:, slots] = forbid_c
        pool_forced[:, slots] = forced_c
        pool_u[:, slots] = uc.reshape(R, n, m + 1)
        pool_v[:, slots] = vc.reshape(R, n, m + 1)
        pool_p[:, slots] = pc.reshape(R, n, m + 1)
    return out_assign.reshape(*batch, k, n), out_cost.reshape(*batch, k)


def _loops_apply(cost: Tensor) -> bool:
    """The compiled CPU loop of :func:`k_best_assignments` runs: a CPU tensor without autograd, Numba
    importable, the stage kernel ``assignment_loops`` switched on (:func:`torchmm.kernels.set_enabled`)."""
    import torchmm.kernels as kernels

    return (cost.device.type == "cpu" and host_reads_ok(cost) and not (cost.requires_grad and torch.is_grad_enabled())
            and kernels.enabled("assignment_loops") and kernels.numba_available())


def _scatter_rows(rows: Tensor, by_col: Tensor, cols: Tensor, n: int) -> Tensor:
    """``rows (..., n)`` filled from the column -> row assignments ``by_col (..., m)`` (``-1``: none)."""
    found = by_col >= 0
    wide = torch.cat([rows, torch.full_like(rows[..., :1], -1)], -1)  # slot n: where the unassigned land
    wide = wide.scatter(-1, torch.where(found, by_col, n), torch.where(found, cols, -1))
    return wide[..., :n]

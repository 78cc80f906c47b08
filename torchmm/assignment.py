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

import torch
from torch import Tensor

from torchmm.contract import Finite, Values, entry_point, unchecked
from torchmm.runtime import host_reads_ok

__all__ = ["assignment_cost", "linear_assignment"]


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
    dev, dt = cost.device, cost.dtype
    inf = torch.full((), torch.inf, dtype=dt, device=dev)
    a = torch.zeros(B, n + 1, m + 1, dtype=dt, device=dev)
    a[:, 1:, 1:] = cost
    u = torch.zeros(B, n + 1, dtype=dt, device=dev)  # row potentials
    v = torch.zeros(B, m + 1, dtype=dt, device=dev)  # column potentials
    p = torch.zeros(B, m + 1, dtype=torch.long, device=dev)  # p[j]: the row on column j (0: free)
    way = torch.zeros(B, m + 1, dtype=torch.long, device=dev)  # the previous column on the search path
    rows = torch.arange(B, device=dev)
    early = host_reads_ok(cost)  # stop the scans when every matrix is done (a host read; CPU only)
    for i in range(1, n + 1):
        p[:, 0].fill_(i)  # (fill_ with a Python number: no host-to-device copy on a GPU)
        j0 = torch.zeros(B, dtype=torch.long, device=dev)
        minv = inf.expand(B, m + 1).clone()
        used = torch.zeros(B, m + 1, dtype=torch.bool, device=dev)
        active = torch.ones(B, dtype=torch.bool, device=dev)
        for _ in range(m + 1):  # at most m + 1 scans reach a free column
            used = used | (active.unsqueeze(-1) & (torch.arange(m + 1, device=dev) == j0.unsqueeze(-1)))
            i0 = p[rows, j0]
            reduced = a[rows, i0] - u[rows, i0].unsqueeze(-1) - v  # (B, m + 1)
            better = active.unsqueeze(-1) & ~used & (reduced < minv)
            minv = torch.where(better, reduced, minv)
            way = torch.where(better, j0.unsqueeze(-1), way)
            delta, j1 = torch.where(used, inf, minv).min(-1)
            step = active.unsqueeze(-1)
            shift = torch.where(step & used, delta.unsqueeze(-1), torch.zeros_like(v))
            u = u.scatter_add(1, p, shift)  # u[p[j]] += delta over the used columns
            v = v - shift
            minv = torch.where(step & ~used, minv - delta.unsqueeze(-1), minv)
            j0 = torch.where(active, j1, j0)
            active = active & (p[rows, j0] != 0)
            if early and not bool(active.any()):
                break
        for _ in range(m + 1):  # flip the path back to the start column
            moving = j0 != 0
            if early and not bool(moving.any()):
                break
            j1 = way[rows, j0]
            p = p.scatter(1, j0.unsqueeze(-1), torch.where(moving, p[rows, j1], p[rows, j0]).unsqueeze(-1))
            j0 = torch.where(moving, j1, j0)
    row_of_col = p[:, 1:]  # (B, m): 1-based rows, 0 free
    out = torch.zeros(B, n + 1, dtype=torch.long, device=dev)
    out = out.scatter(1, row_of_col, torch.arange(m, device=dev).expand(B, m))  # free columns land on row 0
    return out[:, 1:]

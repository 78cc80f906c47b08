"""The Numba loops of :mod:`torchmm.kernels.particle` (imported on first use: importing Numba takes a
moment). Each is compiled once per machine and argument types, and cached on disk by Numba."""

from __future__ import annotations

import math

import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

#: particles a block of the propagation: the block's states, noise and outputs stay in L1
BLOCK = 64


@intrinsic
def fma(typingctx, a, b, c):
    """``a * b + c`` with one rounding (LLVM's intrinsic), as torch's vectorised ``addcmul``."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen


@numba.njit(parallel=True, nogil=True, cache=True)
def two_stage(cdf_models, u0, weights, v0, num):  # pragma: no cover
    R, M, A = cdf_models.shape
    P = weights.shape[2]
    out = np.empty((R, M, num), dtype=np.int64)
    eps = np.finfo(np.float64).eps
    tiny = np.finfo(np.float64).tiny
    for r in numba.prange(R):
        # every ancestor model's systematic resample (systematic_search: counting, cumsum)
        res = np.empty((A, P), dtype=np.int64)
        counts = np.empty(max(P, num) + 1, dtype=np.int64)
        cdf = np.empty(P)
        for a in range(A):
            # the within-model CDF: a cumulative sum (sequential, as torch's), normalised, last 1
            acc = 0.0
            for b in range(P):
                acc += weights[r, a, b]
                cdf[b] = acc
            total = acc if acc >= tiny or acc != acc else tiny  # clamp_min(tiny), NaN kept
            for b in range(P - 1):
                cdf[b] = cdf[b] / total
            cdf[P - 1] = 1.0
            counts[:P + 1] = 0
            va = v0[r, a]
            for b in range(P):
                c = cdf[b]
                pos = P if c >= 1.0 else int(math.ceil(c * P - va))
                counts[pos] += 1
            count = 0
            for q in range(P):
                count += counts[q]
                res[a, q] = count
        for i in range(M):
            counts[:num + 1] = 0
            ui = u0[r, i]
            for a in range(A):
                c = cdf_models[r, i, a]
                pos = num if c >= 1.0 else int(math.ceil(c * num - ui))
                counts[pos] += 1
            a = 0
            for q in range(num):
                a += counts[q]  # the ancestor model of point q
                lo = 0.0 if a == 0 else cdf_models[r, i, a - 1]
                width = cdf_models[r, i, a] - lo
                inv = 1.0 / (width if width >= tiny else tiny)
                inner = ((q + ui) / num - lo) * inv
                inner = min(max(inner, 0.0), 1.0 - eps)
                out[r, i, q] = res[a, int(inner * P)] + a * P
    return out


@numba.njit(inline="always", cache=True)
def _products(out, columns, row, count, nb):  # pragma: no cover
    """``out[t] = (columns[0][t] row[0] + columns[1][t] row[1]) + ...`` for ``t < nb``: the products
    summed in order, as a GEMM's inner loop over a short contraction."""
    value = row[0]
    column = columns[0]
    for t in range(nb):
        out[t] = column[t] * value
    for j in range(1, count):
        value = row[j]
        column = columns[j]
        for t in range(nb):
            out[t] = out[t] + column[t] * value


@numba.njit(parallel=True, cache=True)
def propagate(table, flat, eps, G, offset, F, W, shift, const, x, loglik, nan,  # pragma: no cover
              n_, k_, m_):
    # n, k, m: the lengths of three tuples, so compile-time constants of each specialisation (the
    # short loops unroll; Numba caches one per (n, k, m) on disk)
    n, k, m = len(n_), len(k_), len(m_)
    R, M, Np = flat.shape
    for ri in numba.prange(R * M):
        r = ri // M
        i = ri - r * M
        tab, fl, ep, xo, lo = table[r], flat[r, i], eps[r, i], x[r, i], loglik[r, i]
        bad = False  # a NaN log-likelihood in this set (non-finite particles: a failure, not missing data)
        off, sh = offset[i], shift[r]
        xa = np.empty((n, BLOCK))
        ef = np.empty((k, BLOCK))
        od = np.empty((n, BLOCK))
        wt = np.empty(BLOCK)
        ss = np.empty(BLOCK)
        for q0 in range(0, Np, BLOCK):
            nb = min(BLOCK, Np - q0)
            for t in range(nb):  # the ancestors and their normals, one column a component
                src = fl[q0 + t]
                for j in range(n):
                    xa[j, t] = tab[src, j]
                for j in range(k):
                    ef[j, t] = ep[q0 + t, j]
            for d in range(n):
                # noise: offset + (sum_j eps_j G_dj), as a batched GEMM with beta = 1 sums it
                out = od[d]
                _products(out, ef, G[d], k, nb)
                o = off[d]
                for t in range(nb):
                    out[t] = o + out[t]
                # + F x, from the noise on, as an unbatched addmm_ sums it
                for j in range(n):
                    f = F[d, j]
                    e = xa[j]
                    for t in range(nb):
                        out[t] = out[t] + e[t] * f
            for c in range(m):
                # whitened residual L^-1 z - (L^-1 H) x: shift + (sum_j x_j W_cj)
                _products(wt, od, W[c], n, nb)
                s = sh[c]
                if c == 0:
                    for t in range(nb):
                        v = s + wt[t]
                        ss[t] = v * v
                else:
                    for t in range(nb):
                        v = s + wt[t]
                        ss[t] = fma(v, v, ss[t])
            for t in range(nb):
                value = (ss[t] + const) * -0.5
                if value != value:
                    bad = True
                    value = -np.inf
                lo[q0 + t] = value
                for d in range(n):
                    xo[q0 + t, d] = od[d, t]
        nan[r, i] = bad


@numba.njit(parallel=True, cache=True)
def challenge(scores, a, b, shifts, N):  # pragma: no cover
    R, P = scores.shape
    rounds = shifts.shape[0]
    pool_size = P - N
    out = np.empty((R, N), dtype=np.int64)
    for r in numba.prange(R):
        # the order (a j + b) mod P, by additions (a < P): no division per particle
        order = np.empty(P, dtype=np.int64)
        step = a[r] % P
        value = b[r] % P
        for j in range(P):
            order[j] = value
            value += step
            if value >= P:
                value -= P
        # the pool's scores in pool order (one gather), then round by round: holder p meets slot
        # (p - shift) mod N of window t and keeps the first strict maximum of its challengers (top
        # starts at -inf: a challenger of score -inf is never kept, and could not beat the holder;
        # a NaN challenger makes torch's max NaN, so that holder stays)
        pool = np.empty(pool_size, dtype=scores.dtype)
        for j in range(pool_size):
            pool[j] = scores[r, order[N + j]]
        top = np.full(N, -np.inf, dtype=scores.dtype)
        arg = np.full(N, -1, dtype=np.int64)
        nan = np.zeros(N, dtype=np.bool_)
        for t in range(rounds):
            shift = shifts[t, r]
            base = t * N
            valid = min(N, pool_size - base)  # the last window is short (past it: padding that never wins)
            for lo, hi, offset in ((shift, N, base - shift), (0, shift, base + N - shift)):  # no modulo
                for p in range(lo, hi):
                    if p + offset < base + valid:
                        s = pool[p + offset]
                        if s > top[p]:  # rarely true after the first rounds: a predictable branch
                            top[p] = s
                            arg[p] = p + offset
                        elif s != s:
                            nan[p] = True
        for p in range(N):
            holder = order[p]
            if arg[p] >= 0 and not nan[p] and top[p] > scores[r, holder]:
                holder = order[N + arg[p]]
            out[r, p] = holder
    return out

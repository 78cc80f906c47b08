"""PF-MEVSMM step throughput: torchmm vs a hand-vectorised NumPy reference, same process.

The step of paper 003 (improved version) on scenario ``det_large``: 21 models x ``Np`` particles
per model x ``runs`` Monte Carlo runs at once, float64 state: interaction (systematic points; the
ancestor model by counting, the particle by a search in the within-model CDFs), propagation with
the model's acceleration and noise (normals drawn in float32 by both, ``noise_dtype``), likelihood
(33) (whitened), normalisation (34), challenge match for the N = 420 heaviest particles (one pass,
as one max over the rounds), the Thre = 23 model set and the estimate (31). Both sides get the
same algorithmic choices; each is written in its library's idiom.

1. Agreement: the NumPy step is fed exactly the random numbers torchmm draws (a cloned
   ``torch.Generator`` replays them), and both must give the same particles, weights, model sets
   and estimates (max abs difference printed, must be < 1e-9 relative).
2. Timing: each implementation draws its own random numbers; median time per step. torchmm runs
   twice: as it is (with :mod:`torchmm.kernels.particle`, the fused Numba kernels, on the CPU) and
   with those kernels off (``torchmm_eager``). Both run in this process with
   ``torchmm.runtime.retain_freed_memory`` (``--no-retain`` to compare): freed large arrays stay
   in the heap instead of being unmapped and page-faulted afresh. Each repeat times torchmm, the
   eager path, NumPy and the normals alone back to back; ``fraction_of_rng_cap`` is the median
   over the repeats of (normals alone / torchmm step), each pair from the same repeat.
3. Bandwidth: the bytes a step must move (read and write particles and log-weights once,
   ``2 * runs * M * Np * (n + 1) * 8``) over the machine's measured copy bandwidth; and the same
   bound for the two parts no formulation avoids (the serial normals and one search per particle).

Last line: ``particle_steps_per_s=<x> speedup_vs_numpy=<y> fraction_of_bandwidth=<z> fraction_of_rng_cap=<w>``
(the random-number cap: the throughput of a step that only drew its process-noise normals).
Timings on a shared machine are contended; ratios are what matter.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments.studies.mevsmm import MODELS, paper003_scenario
import torchmm.kernels.particle as cpu_kernels
from torchmm import LinearMotion, kernels
from torchmm.filters.particle import noise_factor
from torchmm.multimodel.mevsmm import ChallengeMatch, MinimumEntropyVSMM, uniform_transition
from torchmm.multimodel.challenge import _units
from torchmm.runtime import retain_freed_memory


# ------------------------------------------------------------------------------------------------
# NumPy reference (hand-vectorised, batch axis first)
# ------------------------------------------------------------------------------------------------
def _logsumexp(x, axis):
    m = np.max(x, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    return np.squeeze(m, axis) + np.log(np.sum(np.exp(x - m), axis=axis))


def _forced_cdf(p):
    c = np.cumsum(p, axis=-1)
    c = c / c[..., -1:]
    c[..., -1] = 1.0
    return c


class NumpyPFMEVSMM:
    """The same step, NumPy float64, batch axis first. ``randoms`` replays torchmm's draws."""

    def __init__(self, F, offsets, factor, H, R, log_transition, num_winners, threshold, mixing="two_stage"):
        self.F, self.offsets, self.factor = F, offsets, factor  # (n,n), (M,n), (n,r)
        self.Rinv_chol = np.linalg.inv(np.linalg.cholesky(R))
        self.white_H = self.Rinv_chol @ H
        self.logdet = 2 * np.log(np.diag(np.linalg.cholesky(R))).sum()
        self.log_transition = log_transition
        self.N, self.thre = num_winners, threshold
        self.mixing = mixing

    def step(self, particles, within, mode_lp, active, z, rng=None, randoms=None):
        B, M, Np, n = particles.shape
        # -- interaction: ancestors of model i from mu_a pi_ai w_{b|a}
        mode_lp = np.where(active, mode_lp, -np.inf)
        mode_lp = mode_lp - _logsumexp(mode_lp, -1)[:, None]
        joint = mode_lp[:, :, None] + self.log_transition[None]  # (B, a, i)
        log_cbar = _logsumexp(joint, 1)  # (B, i)
        mixing = np.exp(np.swapaxes(joint, 1, 2) - log_cbar[:, :, None])  # (B, i, a)
        cdf_m = _forced_cdf(mixing)
        u0 = randoms["u_mix"] if randoms is not None else rng.random((B, M, 1))
        u = (np.arange(Np)[None, None] + u0) / Np  # (B, i, Np)
        # systematic points: the ancestor of point q is the number of CDF entries at grid position
        # ceil(Np * c - u0) <= q -- one bincount and a cumsum (as torchmm), not Np binary searches
        pos = np.clip(np.ceil(cdf_m * Np - u0), 0, Np).astype(np.int64)  # (B, i, a)
        pos += (np.arange(B * M, dtype=np.int64) * (Np + 1)).reshape(B, M, 1)
        counts = np.bincount(pos.ravel(), minlength=B * M * (Np + 1)).reshape(B, M, Np + 1)
        anc = np.minimum(np.cumsum(counts[..., :Np], -1), M - 1)
        low = np.concatenate([np.zeros((B, M, 1)), cdf_m[..., :-1]], -1)
        lo = np.take_along_axis(low, anc, -1)
        hi = np.take_along_axis(cdf_m, anc, -1)
        inner = np.clip((u - lo) / np.maximum(hi - lo, np.finfo(float).tiny), 0, 1 - np.finfo(float).eps)
        w_within = np.exp(within - _logsumexp(within, -1)[..., None])
        if self.mixing == "two_stage":
            # a systematic resample of every model's particles (by counting), then entry
            # floor(Np * inner) of the ancestor's resample
            v0 = randoms["v_mix"] if randoms is not None else rng.random((B, M, 1))
            cw = _forced_cdf(w_within)
            pos = np.clip(np.ceil(cw * Np - v0), 0, Np).astype(np.int64)
            pos += (np.arange(B * M, dtype=np.int64) * (Np + 1)).reshape(B, M, 1)
            counts = np.bincount(pos.ravel(), minlength=B * M * (Np + 1)).reshape(B, M, Np + 1)
            resampled = np.minimum(np.cumsum(counts[..., :Np], -1), Np - 1).reshape(B, M * Np)
            slot = np.minimum((inner * Np).astype(np.int64), Np - 1) + anc * Np
            flat = (np.take_along_axis(resampled, slot.reshape(B, M * Np), 1) + (anc * Np).reshape(B, M * Np))
        else:  # inverse CDF of the product distribution (float run offsets, one flat search)
            cdf_w = (_forced_cdf(w_within) + np.arange(M)[None, :, None]).reshape(B, M * Np)
            values = (anc + inner).reshape(B, M * Np)
            run = (M * np.arange(B, dtype=np.float64))[:, None]
            flat = np.searchsorted((cdf_w + run).ravel(), (values + run).ravel(), side="right").reshape(B, M * Np)
            flat = np.minimum(flat - (np.arange(B)[:, None] * M * Np), M * Np - 1)
        src = particles.reshape(B, M * Np, n)
        x = np.take_along_axis(src, flat[..., None], 1).reshape(B, M, Np, n)
        # -- propagation
        eps = randoms["eps"] if randoms is not None else rng.standard_normal((B, M, Np, self.factor.shape[-1]),
                                                                             dtype=np.float32)
        noise = eps.astype(np.float64) @ self.factor.T
        noise += self.offsets[None, :, None, :]
        x = x @ self.F.T
        x += noise
        # -- weights (33)-(34), whitened: L^-1 (z - H x) = L^-1 z - (L^-1 H) x
        white = x @ self.white_H.T
        white -= (z @ self.Rinv_chol.T)[:, None, None, :]
        sq = white[..., 0] * white[..., 0]
        for j in range(1, white.shape[-1]):
            sq += white[..., j] * white[..., j]
        loglik = -0.5 * (sq + self.logdet + white.shape[-1] * math.log(2 * math.pi))
        jointw = log_cbar[:, :, None] - math.log(Np) + loglik
        per_model = _logsumexp(jointw, -1)
        ev = _logsumexp(per_model, -1)
        mode_post = per_model - ev[:, None]
        within_post = jointw - per_model[..., None]
        # -- challenge match (one pass) on the joint log-weights
        scores = jointw.reshape(B, M * Np)
        P, N = M * Np, self.N
        if randoms is not None:
            a, b0, shifts = randoms["cm_a"], randoms["cm_b"], randoms["cm_shift"]
        else:
            units = _units(P).numpy()
            a = units[rng.integers(0, len(units), (B, 1))]
            b0 = rng.integers(0, P, (B, 1))
            shifts = None
        order = (a * np.arange(P)[None] + b0) % P
        seq1, pool = order[:, :N].copy(), order[:, N:].copy()
        held = np.take_along_axis(scores, seq1, 1)
        pool_size = P - N
        block = min(N, pool_size)
        rounds = math.ceil(pool_size / block)
        ar = np.arange(block)
        rows = np.arange(B)[:, None]
        if shifts is None:
            shifts = rng.integers(0, N, (rounds, B, 1))
        if block == N and pool_size % N == 0:
            # one pass at once, as torchmm: holder p meets challenger (p - shift) mod N of each
            # window, and ends as the first maximum over itself and its challengers
            shift = np.stack(list(shifts), 1)  # (B, rounds, 1)
            ch = np.take_along_axis(pool.reshape(B, rounds, N), (ar[None, None] - shift) % N, 2)
            chs = np.take_along_axis(scores, ch.reshape(B, -1), 1).reshape(B, rounds, N)
            arg = chs.argmax(1)[:, None]
            top = np.take_along_axis(chs, arg, 1)[:, 0]
            win = top > held
            seq1 = np.where(win, np.take_along_axis(ch, arg, 1)[:, 0], seq1)
        else:  # round by round, as the paper describes; the last window is short (no wrap-around)
            for r in range(rounds):
                slots = r * block + ar
                slots = slots[slots < pool_size]
                k = np.arange(len(slots))
                ch = pool[:, slots]
                chs = np.take_along_axis(scores, ch, 1)
                pos = (k[None] + shifts[r]) % N
                hold = seq1[rows, pos]
                holds = held[rows, pos]
                win = chs > holds
                seq1[rows, pos] = np.where(win, ch, hold)
                held[rows, pos] = np.where(win, chs, holds)
                pool[:, slots] = np.where(win, hold, ch)
        model = seq1 // Np
        counts = np.bincount((model + M * rows).ravel(), minlength=B * M).reshape(B, M).astype(np.float64)
        new_active = counts >= self.thre
        empty = ~new_active.any(-1)
        best = np.eye(M, dtype=bool)[counts.argmax(-1)]
        new_active = np.where(empty[:, None], best, new_active)
        carried = np.where(new_active, mode_post, -np.inf)
        carried = carried - _logsumexp(carried, -1)[:, None]
        w = np.exp(carried[..., None] + within_post).reshape(B, M * Np)
        mean = np.einsum("bp,bpn->bn", w, x.reshape(B, M * Np, n))
        return x, within_post, carried, new_active, mean


# ------------------------------------------------------------------------------------------------
def _replay(gen: torch.Generator, B, M, Np, r, P, N, mixing):
    """The random numbers one torchmm PF-MEVSMM step draws, in its order, as NumPy arrays."""
    u_mix = torch.rand((B, M, 1), dtype=torch.float64, generator=gen)
    v_mix = torch.rand((B, M, 1), dtype=torch.float64, generator=gen) if mixing == "two_stage" else None
    eps = torch.randn((B, M, Np, r), dtype=torch.float32, generator=gen)
    units = _units(P)
    pick = torch.randint(0, units.numel(), (B, 1), generator=gen)
    b0 = torch.randint(0, P, (B, 1), generator=gen)
    block = min(N, P - N)
    shifts = [torch.randint(0, N, (B, 1), generator=gen).numpy() for _ in range(math.ceil((P - N) / block))]
    return {"u_mix": u_mix.numpy(), "v_mix": None if v_mix is None else v_mix.numpy(), "eps": eps.numpy(), "cm_a": units[pick].numpy(), "cm_b": b0.numpy(),
            "cm_shift": shifts}


def _best(fn, repeats: int = 3) -> float:
    """Best wall time of ``fn()`` over ``repeats`` calls, seconds."""
    best = math.inf
    for _ in range(repeats):
        tic = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - tic)
    return best


def copy_bandwidth(nbytes: int = 1 << 28, repeats: int = 5) -> float:
    """Measured memory-copy bandwidth (bytes read + written per second), best of ``repeats``."""
    src = torch.empty(nbytes // 8, dtype=torch.float64).fill_(1.0)
    dst = torch.empty_like(src)
    best = math.inf
    for _ in range(repeats):
        tic = time.perf_counter()
        dst.copy_(src)
        best = min(best, time.perf_counter() - tic)
    return 2 * nbytes / best


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--particles", type=int, default=1000, help="per model")
    parser.add_argument("--steps", type=int, default=5, help="timed steps per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--winners", type=int, default=420)
    parser.add_argument("--threshold", type=int, default=23)
    parser.add_argument("--mixing", default="two_stage", choices=["two_stage", "systematic"],
                        help="interaction scheme (the mevsmm study's default: two_stage)")
    parser.add_argument("--bandwidth-mb", type=int, default=256, help="buffer size of the copy-bandwidth probe")
    parser.add_argument("--no-retain", action="store_true",
                        help="leave malloc as it is (default: torchmm.runtime.retain_freed_memory for both)")
    args = parser.parse_args(argv)
    retained = False if args.no_retain else retain_freed_memory()
    torch.set_default_dtype(torch.float64)
    B, Np, M = args.runs, args.particles, len(MODELS)
    N = min(args.winners, M * Np - 1)
    scen = paper003_scenario(name="det_large", R=150.0, maneuvers=[[31, 80, [10.0, -12.0]], [81, 120, [-30.0, 30.0]]])
    truth, _, z = scen.simulate(B, torch.Generator().manual_seed(0))
    acc = torch.tensor(MODELS, dtype=torch.float64)
    qa = 25.0 * torch.eye(2)
    motion = LinearMotion(scen.F, scen.D @ qa @ scen.D.mT, offset=acc @ scen.D.mT)
    transition = uniform_transition(M, 1.0 / M)
    gen = torch.Generator().manual_seed(1)
    filt = MinimumEntropyVSMM(motion, scen.measurement, transition, Np, selection=ChallengeMatch(N, args.threshold),
                              generator=gen, innovation_stats=False, noise_dtype=torch.float32, mixing=args.mixing)
    factor = noise_factor(motion.noise_cov())
    ref = NumpyPFMEVSMM(scen.F.numpy(), motion.offset.numpy(), factor.numpy(), scen.measurement.H.numpy(),
                        scen.measurement.R.numpy(),
                        transition.log().numpy(), N, args.threshold, mixing=args.mixing)
    # a start belief some steps into the scenario
    belief = filt.update(filt.initial_belief(scen.prior(B)), z[0]).belief
    for k in range(1, 4):
        belief = filt.step(belief, z[k]).belief

    # 1. agreement on one step with replayed random numbers
    replay_gen = torch.Generator()
    replay_gen.set_state(gen.get_state())
    randoms = _replay(replay_gen, B, M, Np, factor.shape[-1], M * Np, N, args.mixing)
    out = filt.step(belief, z[4])
    comps = belief.components
    x, within, carried, active, mean = ref.step(comps.particles.numpy(), comps.log_weights.numpy(),
                                                belief.mode_log_probs.numpy(), belief.active.numpy(), z[4].numpy(),
                                                randoms=randoms)
    new = out.belief
    scale = float(np.abs(x).max())
    diffs = {
        "particles": float(np.abs(new.components.particles.numpy() - x).max()) / scale,
        "log_weights": float(np.nanmax(np.abs(np.nan_to_num(new.components.log_weights.numpy() - within)))),
        "model_sets": float((new.active.numpy() != active).sum()),
        "estimate": float(np.abs(new.estimate().mean.numpy() - mean).max()) / scale,
    }
    print("max difference torchmm vs numpy (same random numbers): "
          + " ".join(f"{k}={v:.3e}" for k, v in diffs.items()))

    # 2. timing, each with its own random numbers
    def torch_steps():
        b = belief
        for k in range(args.steps):
            b = filt.step(b, z[5 + k]).belief
        return b

    rng = np.random.default_rng(2)

    def numpy_steps():
        p, w, lp, act = (comps.particles.numpy(), comps.log_weights.numpy(), belief.mode_log_probs.numpy(),
                         belief.active.numpy())
        for k in range(args.steps):
            p, w, lp, act, _ = ref.step(p, w, lp, act, z[5 + k].numpy(), rng=rng)

    r = factor.shape[-1]

    def normals():  # the random-number cap: what the steps draw, and nothing else
        for _ in range(args.steps):
            torch.randn(B, M, Np, r, dtype=torch.float32, generator=gen)

    def eager_steps():  # the same steps without the particle stages (torchmm.kernels.particle)
        with kernels.switched_off(cpu_kernels.NAME):
            torch_steps()

    # each repeat times all four back to back, so that the cap and the step share the machine's state
    times = {"torch": [], "eager": [], "numpy": [], "normals": []}
    fns = {"torch": torch_steps, "eager": eager_steps, "numpy": numpy_steps, "normals": normals}
    for _ in range(args.repeats):
        for name, fn in fns.items():
            tic = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - tic) / args.steps)
    t_torch, t_numpy = statistics.median(times["torch"]), statistics.median(times["numpy"])
    t_eager, t_normals = statistics.median(times["eager"]), statistics.median(times["normals"])
    fractions = sorted(n / t for n, t in zip(times["normals"], times["torch"]))
    n = 4
    moved = 2 * B * M * Np * (n + 1) * 8
    bandwidth = copy_bandwidth(args.bandwidth_mb << 20)
    print(f"runs={B} models={M} particles_per_model={Np} threads={torch.get_num_threads()} "
          f"retain_freed_memory={retained} mixing={args.mixing}")
    print(f"seconds_per_step torchmm={t_torch:.4f} torchmm_eager={t_eager:.4f} numpy={t_numpy:.4f} "
          f"(medians of {args.repeats}; best torchmm={min(times['torch']):.4f}; cpu_kernels={cpu_kernels.enabled()})")
    print(f"bytes_per_step={moved:.3e} achieved={moved / t_torch / 1e9:.3f} GB/s "
          f"copy_bandwidth={bandwidth / 1e9:.2f} GB/s (shared machine: timings are contended)")
    # what no eager formulation of this step avoids: the process-noise normals (torch's CPU
    # generator is serial) and, for the inverse-CDF interaction, one search per particle in the
    # within-model CDFs (two_stage needs none)
    from torchmm.filters.resampling import searchsorted_rows

    floor = {"normals": _best(lambda: torch.randn(B, M, Np, factor.shape[-1], dtype=torch.float32, generator=gen))}
    if args.mixing == "systematic":
        cdf = torch.cumsum(comps.log_weights.exp(), -1)
        cdf = (cdf / cdf[..., -1:] + torch.arange(M, dtype=cdf.dtype).unsqueeze(-1)).flatten(-2).contiguous()
        queries = torch.sort(torch.rand(B, M * Np, dtype=cdf.dtype) * M, -1).values
        floor["search"] = _best(lambda: searchsorted_rows(cdf, queries))
    t_floor = sum(floor.values())
    print("unavoidable parts: " + " ".join(f"{k}={v:.4f}s" for k, v in floor.items())
          + f" -> at most {moved / t_floor / bandwidth:.3f} of the bandwidth bound with these kernels")
    # the random-number cap: the particle-steps/s of a step that did nothing but draw its normals
    cap = B * M * Np / t_normals
    print(f"rng_cap={cap:.4g} particle-steps/s (the process-noise normals alone: {t_normals:.4f} s a step); "
          f"fraction of it per repeat: " + " ".join(f"{f:.3f}" for f in fractions)
          + f" (best {fractions[-1]:.3f}, median {statistics.median(fractions):.3f}; eager "
          f"{t_normals / t_eager:.3f})")
    print(f"particle_steps_per_s={B * M * Np / t_torch:.4g} speedup_vs_numpy={t_numpy / t_torch:.3f} "
          f"fraction_of_bandwidth={moved / t_torch / bandwidth:.4f} "
          f"fraction_of_rng_cap={statistics.median(fractions):.4f}")

if __name__ == "__main__":
    main()

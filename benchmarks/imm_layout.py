"""Which layout pays for the IMM (issue 17): the paper-000 IMM step written in torch with the batch
axis last ("structure of arrays", one ``(M, runs)`` tensor per matrix entry, the 2 x 2 Kalman algebra
in closed form), eager and under ``torch.compile``, against the NumPy SoA reference of
``imm_vs_filterpy.py`` and torchmm's public ``IMM(KalmanFilter(bank))`` (batch first).

The hand-written SoA step here is for n = 2, m = 1: the bound of the route. Beside it, torchmm's
engine: its batch-first steps (``run_filter(..., fast_path=False)``) and its batch-last fast path
(``torchmm/kernels/batch_last/imm.py``, generic in n, m and M, the default of ``run_filter``), eager
and with ``compile=True``; all with ``record="estimate"``. All estimates are checked equal (1e-9
relative). One thread each.

Usage: ``python benchmarks/imm_layout.py [--runs 400 40000] [--steps 100] [--no-compile]``. Last
line: ``soa_eager_vs_numpy_soa=... soa_compiled_vs_numpy_soa=... torchmm_batch_first_vs_numpy_soa=...
torchmm_vs_numpy_soa=... torchmm_compiled_vs_numpy_soa=... torchmm_callable_record_vs_numpy_soa=...`` (at
the largest size; > 1 means faster than the NumPy SoA reference; the last: ``record`` given as a function
returning what ``record="estimate"`` keeps).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one thread each (before numpy)
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from imm_vs_filterpy import best_of, run_numpy_soa, scenario  # noqa: E402

from torchmm import IMM, KalmanFilter, run_filter  # noqa: E402
from torchmm.filters import StepOutput  # noqa: E402


def soa_step(F, b, Q, H, R, Pi):
    """The IMM step on batch-last tensors: ``(x0, x1, p00, p01, p11, mu, z_k) -> (same..., estimate)``,
    each state tensor ``(M, runs)``, ``z_k`` ``(runs,)``."""
    f00, f01, f10, f11 = (F[:, i, j][:, None] for i, j in ((0, 0), (0, 1), (1, 0), (1, 1)))
    b0, b1 = b[:, 0:1], b[:, 1:2]
    q00, q01, q11 = Q[:, 0, 0][:, None], Q[:, 0, 1][:, None], Q[:, 1, 1][:, None]
    h0, h1, r = float(H[0, 0]), float(H[0, 1]), float(R[0, 0])
    PiT, half_log2pi = Pi.T.contiguous(), 0.5 * math.log(2 * math.pi)

    def step(x0, x1, p00, p01, p11, mu, zk):
        cbar = PiT @ mu  # predicted mode probabilities (j, runs)
        w = Pi[:, :, None] * mu[:, None, :] / cbar[None]  # mixing weights (i, j, runs)
        m0, m1 = (w * x0[:, None]).sum(0), (w * x1[:, None]).sum(0)
        d0, d1 = x0[:, None] - m0[None], x1[:, None] - m1[None]
        c00 = (w * (p00[:, None] + d0 * d0)).sum(0)
        c01 = (w * (p01[:, None] + d0 * d1)).sum(0)
        c11 = (w * (p11[:, None] + d1 * d1)).sum(0)
        xp0, xp1 = f00 * m0 + f01 * m1 + b0, f10 * m0 + f11 * m1 + b1  # x- = F m + b
        a00, a01 = f00 * c00 + f01 * c01, f00 * c01 + f01 * c11
        a10, a11 = f10 * c00 + f11 * c01, f10 * c01 + f11 * c11
        pp00, pp01, pp11 = a00 * f00 + a01 * f01 + q00, a00 * f10 + a01 * f11 + q01, a10 * f10 + a11 * f11 + q11
        g0, g1 = pp00 * h0 + pp01 * h1, pp01 * h0 + pp11 * h1  # P- H^T
        s = h0 * g0 + h1 * g1 + r
        nu = zk[None] - (h0 * xp0 + h1 * xp1)
        k0, k1 = g0 / s, g1 / s
        x0, x1 = xp0 + k0 * nu, xp1 + k1 * nu
        p00, p01, p11 = pp00 - k0 * g0, pp01 - k0 * g1, pp11 - k1 * g1
        mu = torch.softmax(-0.5 * nu * nu / s - 0.5 * s.log() - half_log2pi + cbar.log(), 0)
        return x0, x1, p00, p01, p11, mu, torch.stack([(mu * x0).sum(0), (mu * x1).sum(0)], -1)

    return step


def run_soa(step, x0, P0, M: int, z):
    runs = z.shape[1]
    full = lambda v: torch.full((M, runs), float(v), dtype=z.dtype)  # noqa: E731
    state = [full(x0[0]), full(x0[1]), full(P0[0, 0]), full(P0[0, 1]), full(P0[1, 1]), full(1.0 / M)]
    out = []
    for k in range(z.shape[0]):
        *state, estimate = step(*state, z[k, :, 0])
        out.append(estimate)
    return torch.stack(out)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, nargs="+", default=[400, 4000, 40000])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-compile", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print(f"IMM (paper 000, n=2, m=1, M=3), {args.steps} steps, float64, torch {torch.__version__}, one thread")
    ratios = {}
    for runs in args.runs:
        motion, sensor, prior, transition, z = scenario(runs, args.steps, 0)
        M = transition.shape[0]
        F, b, Q = motion.F.expand(M, 2, 2).contiguous(), motion.offset, motion.Q.expand(M, 2, 2).contiguous()
        numpy_args = (F.numpy(), b.numpy(), Q.numpy(), sensor.H.numpy(), sensor.R.numpy(), transition.numpy(),
                      prior.mean.numpy(), prior.cov.numpy(), np.full(M, 1.0 / M), z.numpy())
        step = soa_step(F, b, Q, sensor.H, sensor.R, transition)
        with torch.no_grad():
            t_np, est_np = best_of(lambda: run_numpy_soa(*numpy_args), args.repeats)
            t_eager, est_eager = best_of(lambda: run_soa(step, prior.mean, prior.cov, M, z), args.repeats)
            imm = IMM(KalmanFilter(motion, sensor), transition)
            belief0 = imm.initial_belief(prior.expand(runs))
            engine = lambda **kw: run_filter(imm, belief0, z, record="estimate", **kw).belief.mean  # noqa: E731
            # the same record as a function (issue 47: it used to turn the kernels off)
            as_function = lambda o: StepOutput(o.belief.estimate(), None, o.log_likelihood)  # noqa: E731
            results = {"torch SoA eager": (t_eager, est_eager),
                       "torchmm batch-first": best_of(lambda: engine(fast_path=False), args.repeats),
                       "torchmm": best_of(engine, args.repeats),
                       "torchmm callable record": best_of(
                           lambda: run_filter(imm, belief0, z, record=as_function).belief.mean, args.repeats)}
            line = ""
            if not args.no_compile:
                compiled = torch.compile(step, dynamic=False)
                tic = time.perf_counter()
                run_soa(compiled, prior.mean, prior.cov, M, z[:2])
                line = f" (compile {time.perf_counter() - tic:.1f} s)"
                results["torch SoA compiled"] = best_of(lambda: run_soa(compiled, prior.mean, prior.cov, M, z),
                                                        args.repeats)
                tic = time.perf_counter()
                engine(compile=True)
                line += f" (torchmm compile {time.perf_counter() - tic:.1f} s)"
                results["torchmm compiled"] = best_of(lambda: engine(compile=True), args.repeats)
        scale = 1 + np.abs(est_np).max()
        for name, (t, est) in results.items():
            diff = np.abs(est.numpy() - est_np).max() / scale
            if diff > 1e-9:
                raise SystemExit(f"{name} disagrees with the NumPy SoA reference ({diff:.1e}): the comparison is void")
        cells = [f"{name} {runs * args.steps / t:.3g} run-steps/s ({t_np / t:.2f} x NumPy SoA)"
                 for name, (t, _) in results.items()]
        print(f"runs={runs}: NumPy SoA {runs * args.steps / t_np:.3g} run-steps/s; " + "; ".join(cells) + line)
        ratios = {name: t_np / t for name, (t, _) in results.items()}
    print(f"soa_eager_vs_numpy_soa={ratios['torch SoA eager']:.2f} "
          f"soa_compiled_vs_numpy_soa={ratios.get('torch SoA compiled', float('nan')):.2f} "
          f"torchmm_batch_first_vs_numpy_soa={ratios['torchmm batch-first']:.2f} "
          f"torchmm_vs_numpy_soa={ratios['torchmm']:.2f} "
          f"torchmm_compiled_vs_numpy_soa={ratios.get('torchmm compiled', float('nan')):.2f} "
          f"torchmm_callable_record_vs_numpy_soa={ratios['torchmm callable record']:.2f}")

if __name__ == "__main__":
    main()

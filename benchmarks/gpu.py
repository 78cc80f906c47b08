"""GPU throughput: IMM run-steps/s and particle-filter particle-steps/s from 10^3 to 10^6 runs,
eager against compiled (``torch.compile``; on CUDA ``mode="reduce-overhead"``, i.e. CUDA graphs),
and agreement with the CPU.

Needs only torch and numpy (and this repository on the path)::

    PYTHONPATH=. python3 benchmarks/gpu.py                 # CUDA when present, else CPU
    PYTHONPATH=. python3 benchmarks/gpu.py --device cpu --runs 1000 10000 --steps 20

* IMM: paper 000's IMM (3 acceleration modes, n = 2, m = 1), float64, ``--steps`` steps of
  ``IMM.step`` on all runs at once. Agreement: the estimates of the first ``--check-runs`` runs on
  the device against the same runs filtered on the CPU (float64, relative difference printed, must
  be below 1e-9).
* PF: a bootstrap particle filter (``--particles`` per run, systematic resampling, float32
  process-noise normals) on the constant-velocity model, float32 state. Agreement: the device's
  own random stream differs from the CPU's, so its position RMSE over ``--check-runs`` runs is
  compared with the CPU's (must agree to 10 %).
* Compiled: the compiled step's estimates must equal the eager ones (1e-9, printed).
* IMM through ``run_filter`` (what users get: the engine's batch-last fast path,
  ``record="estimate"``), eager and with ``compile=True``; both checked against ``IMM.step``'s
  estimates (1e-9).
* IMM over extended and unscented banks (issue 31): benchmarks/ct_imm.py's coordinated turn with a
  range-bearing sensor, float64, ``--nonlinear-runs`` runs x 20 steps through ``run_filter``
  (``record="estimate"``): the nonlinear banks' batch-last kernel against the eager steps
  (``fast_path=False``), run-steps/s, and the first ``--check-runs`` runs' estimates against the CPU's
  kernel (1e-9). On the CPU 1,000 runs by default.
* PDA tracking (issue 32): ``--targets`` PDA tracks a run (benchmarks/pda_throughput.py's scenario:
  P_D 0.9, 10 clutter points a scan, Kalman, float64) through ``run_filter`` at ``--tracking-runs``;
  track-scans/s, and the first ``--check-runs`` runs' final means against the CPU's (1e-9). On the
  CPU 100 runs by default.
* Sizes whose particle count exceeds ``--max-particles`` are skipped. A size that takes longer than
  ``--size-seconds`` ends the escalation. The whole script stays under 5 minutes.

Every timing synchronises the device. The last line is
``imm_run_steps_per_s=<run_filter eager, at the largest IMM size> pf_particle_steps_per_s=<at the
largest PF size> agree=<True|False>``.
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from torchmm import (
    IMM,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    ParticleFilter,
    PositionMeasurement,
    run_filter,
)
from torchmm.simulate import simulate_jump_system, simulate_measurements

ACCELERATIONS = [0.25, 0.0, -0.25]
TRANSITION = [[0.50, 0.25, 0.25], [0.25, 0.50, 0.25], [0.25, 0.25, 0.50]]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def imm_setup(runs: int, steps: int, device: torch.device, seed: int = 0):
    """Paper 000's IMM and ``runs`` simulated runs (simulated on the CPU, then moved)."""
    dtype = torch.float64
    motion = ConstantVelocity(1, q=1.0, acceleration=torch.tensor(ACCELERATIONS, dtype=dtype)[:, None], dtype=dtype)
    sensor = PositionMeasurement(2, [0], torch.tensor(100.0, dtype=dtype), dtype=dtype)
    prior = GaussianBelief(torch.tensor([10.0, 10.0], dtype=dtype), torch.tensor([[100.0, 1.0], [1.0, 100.0]], dtype=dtype))
    transition = torch.tensor(TRANSITION, dtype=dtype)
    gen = torch.Generator().manual_seed(seed)
    sim = simulate_jump_system(motion, transition, prior, steps, (runs,), generator=gen)
    z = simulate_measurements(sensor, sim.states, generator=gen)
    imm = IMM(KalmanFilter(motion.to(device), sensor.to(device)), transition.to(device))
    return imm, imm.initial_belief(prior.to(device).expand(runs)), z.to(device)


def imm_estimates(imm, belief, z, step):
    out = []
    for k in range(z.shape[0]):
        belief = step(belief, z[k])
        out.append(belief.estimate().mean)
    return torch.stack(out)


def pf_setup(runs: int, particles: int, steps: int, device: torch.device, seed: int = 0):
    """A constant-velocity target in one axis, positions measured (R = 4); float32 particles."""
    dtype = torch.float32
    motion = ConstantVelocity(1, q=0.5, noise="continuous", dtype=dtype)
    sensor = PositionMeasurement(2, [0], torch.tensor(4.0, dtype=dtype), dtype=dtype)
    prior = GaussianBelief(torch.tensor([0.0, 1.0], dtype=dtype), torch.eye(2, dtype=dtype))
    gen = torch.Generator().manual_seed(seed)
    x = prior.mean + torch.randn(runs, 2, generator=gen, dtype=dtype)
    states, zs = [], []
    noise = torch.linalg.cholesky(motion.noise_cov())
    for _ in range(steps):
        x = motion(x) + torch.randn(runs, 2, generator=gen, dtype=dtype) @ noise.mT
        states.append(x)
        zs.append(x[:, :1] + 2.0 * torch.randn(runs, 1, generator=gen, dtype=dtype))
    device_gen = torch.Generator(device=device).manual_seed(seed + 1)
    pf = ParticleFilter(motion.to(device), sensor.to(device), generator=device_gen, noise_dtype=torch.float32)
    belief = pf.initial_belief(prior.to(device).expand(runs), particles)
    return pf, belief, torch.stack(zs).to(device), torch.stack(states).to(device)


def pf_positions(pf, belief, z, step):
    """The filtered positions ``(T, runs)``; no host read inside the loop."""
    out = []
    for k in range(z.shape[0]):
        belief = step(belief, z[k])
        out.append(belief.estimate().mean[..., 0])
    return torch.stack(out)


def pf_rmse(pf, belief, z, truth, step) -> float:
    return float((pf_positions(pf, belief, z, step) - truth[..., 0]).square().mean().sqrt())


def timed(fn, device: torch.device, repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        _sync(device)
        tic = time.perf_counter()
        fn()
        _sync(device)
        best = min(best, time.perf_counter() - tic)
    return best


def compiled(step, device: torch.device):
    """``step`` compiled; on CUDA captured as CUDA graphs, whose outputs the next replay overwrites:
    each call marks a new step and hands back a copy of the belief (what a loop that feeds a step's
    output to the next needs)."""
    if device.type != "cuda":
        return torch.compile(step, mode="default", dynamic=False)
    graph = torch.compile(step, mode="reduce-overhead", dynamic=False)

    def run(belief, z):
        torch.compiler.cudagraph_mark_step_begin()
        return graph(belief, z).map_tensors(lambda t, _: t.clone())
    return run


def _first_line(error: Exception) -> str:
    return (str(error).splitlines() or [""])[0][:80]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--runs", type=float, nargs="+", default=[1e3, 1e4, 1e5, 1e6])
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--particles", type=int, default=100, help="per run (PF)")
    parser.add_argument("--max-particles", type=float, default=None,
                        help="largest runs x particles for the PF (default 2e8 on CUDA, 4e6 on CPU)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--check-runs", type=int, default=200)
    parser.add_argument("--size-seconds", type=float, default=40.0, help="stop escalating after a size this slow")
    parser.add_argument("--no-compile", action="store_true")
    parser.add_argument("--targets", type=int, default=10, help="PDA tracks a run (tracking)")
    parser.add_argument("--nonlinear-runs", type=float, nargs="*", default=None,
                        help="runs of the IMM over EKF/UKF banks (default 1e4 1e5 on CUDA, 1e3 on the CPU)")
    parser.add_argument("--tracking-runs", type=float, nargs="*", default=None,
                        help="PDA runs (default 1e3 1e4 1e5 on CUDA, 100 on the CPU)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    runs_list = [int(r) for r in args.runs]
    max_particles = args.max_particles or (2e8 if device.type == "cuda" else 4e6)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"device={device} ({name}) torch={torch.__version__} threads={torch.get_num_threads()} steps={args.steps}")
    started = time.perf_counter()
    agree = True

    # -- agreement with the CPU ------------------------------------------------------------------
    n = args.check_runs
    imm_c, b_c, z_c = imm_setup(n, args.steps, torch.device("cpu"))
    imm_d, b_d, z_d = imm_setup(n, args.steps, device)
    with torch.no_grad():
        est_c = imm_estimates(imm_c, b_c, z_c, lambda b, z: imm_c.step(b, z).belief)
        est_d = imm_estimates(imm_d, b_d, z_d, lambda b, z: imm_d.step(b, z).belief)
    diff = float((est_d.cpu() - est_c).abs().max() / (1 + est_c.abs().max()))
    print(f"agreement IMM: max relative difference device vs CPU {diff:.2e} ({n} runs)")
    agree &= diff < 1e-9
    with torch.no_grad():
        rmse = {}
        for dev in (torch.device("cpu"), device):
            pf, b, z, truth = pf_setup(n, args.particles, args.steps, dev)
            rmse[dev.type] = pf_rmse(pf, b, z, truth, lambda b, z, pf=pf: pf.step(b, z).belief)
    rel = abs(rmse[device.type] - rmse["cpu"]) / rmse["cpu"]
    print(f"agreement PF: position RMSE device {rmse[device.type]:.4f} CPU {rmse['cpu']:.4f} (relative {rel:.3f}, "
          f"own random streams)")
    agree &= rel < 0.1

    # -- throughput ------------------------------------------------------------------------------
    imm_rate = pf_rate = float("nan")
    for runs in runs_list:
        tic = time.perf_counter()
        imm, belief, z = imm_setup(runs, args.steps, device)
        eager_step = lambda b, zk: imm.step(b, zk).belief  # noqa: E731
        with torch.no_grad():
            t_eager = timed(lambda: imm_estimates(imm, belief, z, eager_step), device, args.repeats)
            line = f"IMM runs={runs:>8} eager {runs * args.steps / t_eager:10.4g} run-steps/s"
            if not args.no_compile:
                try:
                    step_c = compiled(eager_step, device)
                    tc = time.perf_counter()
                    imm_estimates(imm, belief, z[:2], step_c)  # compile (and capture)
                    t_compile = time.perf_counter() - tc
                    t_comp = timed(lambda: imm_estimates(imm, belief, z, step_c), device, args.repeats)
                    same = imm_estimates(imm, belief, z, step_c) - imm_estimates(imm, belief, z, eager_step)
                    scale = 1 + float(imm_estimates(imm, belief, z[:1], eager_step).abs().max())
                    diff_c = float(same.abs().max()) / scale
                    agree &= diff_c < 1e-9
                    line += (f" | compiled {runs * args.steps / t_comp:10.4g} run-steps/s (compile {t_compile:.1f} s, "
                             f"vs eager {diff_c:.1e})")
                except Exception as error:  # a compiler failure is a measurement, not a crash
                    line += f" | compiled: failed ({type(error).__name__}: {_first_line(error)})"
            # the engine's default route: run_filter's fast path (batch-last kernel), eager and compiled
            reference = imm_estimates(imm, belief, z, eager_step)
            scale = 1 + float(reference.abs().max())
            fast = lambda **kw: run_filter(imm, belief, z, record="estimate", **kw).belief.mean  # noqa: E731
            t_fast = timed(fast, device, args.repeats)
            diff_f = float((fast() - reference).abs().max()) / scale
            agree &= diff_f < 1e-9
            line += f" | run_filter {runs * args.steps / t_fast:10.4g} (vs step {diff_f:.1e})"
            if not args.no_compile:
                try:
                    tc = time.perf_counter()
                    fast(compile=True)
                    t_compile = time.perf_counter() - tc
                    t_fc = timed(lambda: fast(compile=True), device, args.repeats)
                    diff_fc = float((fast(compile=True) - reference).abs().max()) / scale
                    agree &= diff_fc < 1e-9
                    line += f" | run_filter compiled {runs * args.steps / t_fc:10.4g} (compile {t_compile:.1f} s)"
                except Exception as error:  # a compiler failure is a measurement, not a crash
                    line += f" | run_filter compiled: failed ({type(error).__name__})"
        print(line, flush=True)
        imm_rate = runs * args.steps / t_fast
        del imm, belief, z
        if time.perf_counter() - tic > args.size_seconds or time.perf_counter() - started > 200:
            print(f"IMM: stopping after runs={runs} (time budget)")
            break
    for runs in runs_list:
        if runs * args.particles > max_particles:
            print(f"PF runs={runs:>8}: skipped ({runs * args.particles:.2g} particles > --max-particles {max_particles:.2g})")
            continue
        tic = time.perf_counter()
        pf, belief, z, truth = pf_setup(runs, args.particles, args.steps, device)
        with torch.no_grad():
            t_eager = timed(lambda: pf_positions(pf, belief, z, lambda b, zk: pf.step(b, zk).belief),
                            device, max(1, args.repeats - 1))
        pf_rate = runs * args.particles * args.steps / t_eager
        print(f"PF  runs={runs:>8} particles={args.particles} eager {pf_rate:10.4g} particle-steps/s", flush=True)
        del pf, belief, z, truth
        if time.perf_counter() - tic > args.size_seconds or time.perf_counter() - started > 270:
            print(f"PF: stopping after runs={runs} (time budget)")
            break
    nonlinear_runs = args.nonlinear_runs or ([1e4, 1e5] if device.type == "cuda" else [1e3])
    agree &= nonlinear_banks(device, [int(r) for r in nonlinear_runs], args, started)
    tracking_runs = args.tracking_runs or ([1e3, 1e4, 1e5] if device.type == "cuda" else [100])
    track_rate, agree_tracks = pda_tracking(device, [int(r) for r in tracking_runs], args, started)
    agree &= agree_tracks
    print(f"total {time.perf_counter() - started:.1f} s")
    print(f"imm_run_steps_per_s={imm_rate:.4g} pf_particle_steps_per_s={pf_rate:.4g} "
          f"pda_track_scans_per_s={track_rate:.4g} agree={agree}")


def nonlinear_banks(device: torch.device, runs_list: list[int], args, started: float) -> bool:
    """The IMM over EKF and UKF coordinated-turn banks (benchmarks/ct_imm.py's scenario) on the device:
    the kernel's and the eager steps' run-steps/s, and the kernel's estimates against the CPU's."""
    from benchmarks.ct_imm import make_imm, scenario

    agree, steps = True, 20
    for runs in runs_list:
        if time.perf_counter() - started > 250:
            print(f"IMM-EKF/UKF runs={runs:>8}: skipped (time budget)")
            break
        bank, sensor, prior, transition, z = scenario(runs, steps, seed=0)
        n = min(args.check_runs, runs)
        for kind in ("ekf", "ukf"):
            rates, means = {}, {}
            for dev in ((torch.device("cpu"), device) if device.type != "cpu" else (device,)):
                imm = make_imm(kind, bank.to(dev), sensor.to(dev), transition.to(dev))
                data, start = z.to(dev), prior.to(dev).expand(runs)
                if dev.type == "cpu" and dev != device:
                    data, start = data[:, :n], start[:n]
                for label, fast_path in (("kernel", True), ("eager", False)):
                    if dev != device and label == "eager":
                        continue
                    go = lambda imm=imm, data=data, start=start, fast_path=fast_path: run_filter(  # noqa: E731
                        imm, imm.initial_belief(start), data, record="estimate", fast_path=fast_path)
                    with torch.no_grad():
                        go()
                        if dev == device:
                            rates[label] = data.shape[1] * steps / timed(go, device, args.repeats)
                        if label == "kernel":
                            means[dev.type] = go().belief.mean[:, :n].cpu()
            line = (f"IMM-{kind.upper()} runs={runs:>8} kernel {rates['kernel']:10.4g} run-steps/s | eager "
                    f"{rates['eager']:10.4g} ({rates['kernel'] / rates['eager']:.2f}x)")
            if device.type != "cpu":
                ref = means["cpu"]
                diff = float((means[device.type] - ref).abs().max() / (1 + ref.abs().max()))
                agree &= diff < 1e-9
                line += f" | vs CPU {diff:.1e}"
            print(line, flush=True)
    return agree


def pda_tracking(device: torch.device, runs_list: list[int], args, started: float) -> tuple[float, bool]:
    """PDA tracks on the device (benchmarks/pda_throughput.py's scenario); rate and agreement."""
    from benchmarks.pda_throughput import CLUTTER, GATE, P_D, SIDE, scenario
    from torchmm.association import PDA

    rate, agree = float("nan"), True
    for runs in runs_list:
        if time.perf_counter() - started > 285:
            print(f"PDA runs={runs:>8}: skipped (time budget)")
            break
        motion, sensor, z, prior = scenario(runs, args.targets, 30)
        n = min(args.check_runs, runs)
        final = {}
        for dev in ((torch.device("cpu"), device) if device.type != "cpu" else (device,)):
            pda = PDA(KalmanFilter(motion.to(dev), sensor.to(dev)), detection_probability=P_D,
                      clutter_density=CLUTTER / SIDE**2, gate_probability=GATE)
            scans, start = z.to(dev).unsqueeze(2), prior.to(dev)
            if dev.type == "cpu" and dev != device:
                scans, start = scans[:, :n], start[:n]
            go = lambda pda=pda, scans=scans, start=start: run_filter(pda, start, scans, record="estimate")  # noqa: E731
            with torch.no_grad():
                go()
                if dev == device:
                    t = timed(go, device, args.repeats)
                final[dev.type] = go().belief.mean[-1, :n].cpu()
        diff = float((final[device.type] - final["cpu"]).abs().max() / (1 + final["cpu"].abs().max()))
        agree &= diff < 1e-9
        rate = runs * args.targets * 30 / t
        print(f"PDA runs={runs:>8} targets={args.targets} scans=30 (D={z.shape[-2]}) {rate:10.4g} track-scans/s "
              f"(vs CPU {diff:.1e})", flush=True)
    return rate, agree


if __name__ == "__main__":
    main()

"""Scale-out inside one study: wall time of the same study under each executor, side by side.

    python benchmarks/executors.py [--study imm_analysis] [--mc-runs 200] [--workers 1 2] [--unit-runs N]

Runs the study once with ``executor=local`` (the reference: today's single process) and then with
``executor=processes`` for each worker count (and ``submitit_local`` / ``ray`` where installed),
checks that every run's tables equal the local run's bit for bit, and prints the wall times, the
speed-up over local and the fixed cost per unit (start-up of the workers, shipping, rebuild of the
study context). On a machine with C free cores, expect at most min(C, workers) times.
``--unit-runs N`` splits each setting's runs into units of N runs (``unit_runs``) in every run,
and adds a line for the unsplit local study (the cost of splitting).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from hydra import compose, initialize_config_dir  # noqa: E402

from experiments.run import CONFIG_DIR, run_study  # noqa: E402


def _run(study: str, runs: int, out: Path, *overrides: str) -> tuple[float, dict, int]:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("config", overrides=[f"experiment={study}", f"mc_runs={runs}", "logger=none", "progress=false",
                                           *overrides])
    tic = time.perf_counter()
    run_study(cfg, out)
    wall = time.perf_counter() - tic
    units = len(json.loads((out / "checkpoint.json").read_text())["units"])
    return wall, json.loads((out / "results.json").read_text())["tables"], units


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--study", default="imm_analysis")
    parser.add_argument("--mc-runs", type=int, default=200)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--only-processes", action="store_true", help="skip submitit_local and ray")
    parser.add_argument("--unit-runs", type=int, default=None, help="unit_runs (a multiple of block_runs)")
    args = parser.parse_args()
    split = () if args.unit_runs is None else (f"unit_runs={args.unit_runs}",)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        base, tables, units = _run(args.study, args.mc_runs, tmp / "local", "executor=local", *split)
        print(f"{args.study}, {args.mc_runs} runs, {units} units" + (f" of {args.unit_runs} runs" if split else ""))
        print(f"{'executor':<28}{'wall s':>9}{'speed-up':>10}{'overhead s/unit':>17}  identical")
        print(f"{'local (reference)':<28}{base:>9.2f}{1.0:>10.2f}{0.0:>17.3f}  -")
        if split:
            whole, _, _ = _run(args.study, args.mc_runs, tmp / "unsplit", "executor=local")
            print(f"{'local, unsplit':<28}{whole:>9.2f}{base / whole:>10.2f}{'-':>17}  (to rounding)")
        cases = [(f"processes, {w} workers", ("executor=processes", f"executor.workers={w}", *split), w)
                 for w in args.workers]
        if importlib.util.find_spec("submitit") and not args.only_processes:
            cases.append(("submitit_local", ("executor=submitit_local", *split), None))
        if importlib.util.find_spec("ray") and not args.only_processes:
            cases += [(f"ray, {w} workers", ("executor=ray", f"executor.workers={w}", *split), w)
                      for w in args.workers]
        for label, overrides, workers in cases:
            wall, got, _ = _run(args.study, args.mc_runs, tmp / label.replace(" ", "_").replace(",", ""), *overrides)
            # overhead per unit: what the run cost beyond the local work shared over its workers
            share = base / min(workers or 1, units)
            print(f"{label:<28}{wall:>9.2f}{base / wall:>10.2f}{(wall - share) / units:>17.3f}  {got == tables}")


if __name__ == "__main__":
    main()

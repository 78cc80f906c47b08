"""Start-up times of the command line: ``torchmm-run --help``, ``import torch`` and ``import torchmm``.

    python benchmarks/startup.py [--repeats 5]

Each command runs as a fresh subprocess (``--repeats`` times, interpreter start-up included); the
script prints the best and the median wall time of each and, as its last line,
``help_s=<best> import_torchmm_extra_s=<best of import torchmm - best of import torch>``.
``torchmm-run --help`` imports neither torch nor Hydra (experiments/run.py imports them when a run
starts), so it costs about an interpreter plus OmegaConf; ``import torchmm`` costs torch's import
plus torchmm's own modules. On a busy machine the best of several repeats is the figure to quote.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _time(command: list[str], repeats: int) -> tuple[float, float]:
    """Best and median wall seconds of ``command`` (a fresh process each time)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    times = []
    for _ in range(repeats):
        tic = time.perf_counter()
        proc = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300, check=False)
        times.append(time.perf_counter() - tic)
        if proc.returncode != 0:
            raise SystemExit(f"startup: {' '.join(command)} failed (exit {proc.returncode}):\n{proc.stderr[-2000:]}")
    return min(times), statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs of each command (best and median)")
    args = parser.parse_args(argv)
    # the console script beside this interpreter; `python -m experiments.run` where it is not installed
    script = Path(sys.executable).with_name("torchmm-run")
    help_cmd = [str(script), "--help"] if script.exists() else [sys.executable, "-m", "experiments.run", "--help"]
    commands = {
        "torchmm-run --help": help_cmd,
        "python -c 'import torch'": [sys.executable, "-c", "import torch"],
        "python -c 'import torchmm'": [sys.executable, "-c", "import torchmm"],
    }
    best = {}
    for label, command in commands.items():
        best[label], median = _time(command, args.repeats)
        print(f"{label:<28} best {best[label]:.3f} s  median {median:.3f} s  ({args.repeats} runs)", flush=True)
    extra = best["python -c 'import torchmm'"] - best["python -c 'import torch'"]
    print(f"help_s={best['torchmm-run --help']:.3f} import_torchmm_extra_s={extra:.3f}")


if __name__ == "__main__":
    main()

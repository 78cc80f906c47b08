"""``torchmm-plot RUN_DIR``: redraw a run's per-step curves from ``curves.npz`` alone.

One figure per quantity (the part of a curve's tag before ``/``, e.g. ``pos_rmse``), one labelled
line per series (``pos_rmse/IMM``, ``pos_rmse/GPB1``, ...), the legend outside the axes, sized for a
paper's column (3.4 in wide), written as PNG (300 dpi) and PDF into ``RUN_DIR/figures/curves/``.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

__all__ = ["load_curves", "main", "plot_curves"]


def load_curves(run_dir: Path) -> dict[str, tuple]:
    """``{tag: (steps, values)}`` from ``run_dir/curves.npz``."""
    import numpy as np

    path = Path(run_dir) / "curves.npz"
    if not path.exists():
        raise FileNotFoundError(f"RUN_DIR: {path} does not exist (a study run writes it; older runs have none)")
    with np.load(path) as data:
        return {key: (data[f"{key}#step"], data[key]) for key in data.files if not key.endswith("#step")}


def plot_curves(run_dir: Path, formats=("png", "pdf")) -> list[Path]:
    """Draw every quantity's curves; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = load_curves(run_dir)
    groups: dict[str, list[tuple[str, tuple]]] = defaultdict(list)
    for tag, curve in curves.items():
        quantity, _, series = tag.partition("/")
        groups[quantity].append((series or quantity, curve))
    out_dir = Path(run_dir) / "figures" / "curves"
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for quantity, lines in sorted(groups.items()):
        fig, ax = plt.subplots(figsize=(3.4, 2.4), constrained_layout=True)
        for label, (steps, values) in lines:
            ax.plot(steps, values, label=label, linewidth=1.0)
        ax.set_xlabel("time step")
        ax.set_ylabel(quantity.replace("_", " "))
        ax.grid(True, linewidth=0.3, alpha=0.5)
        ax.tick_params(labelsize=7)
        if len(lines) > 1:
            ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=6, frameon=False, borderaxespad=0)
        name = quantity.replace("/", "_") or "curve"
        for fmt in formats:
            path = out_dir / f"{name}.{fmt}"
            fig.savefig(path, dpi=300, bbox_inches="tight")
            written.append(path)
        plt.close(fig)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="torchmm-plot", description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="a study's run folder (with curves.npz)")
    parser.add_argument("--format", default="png,pdf", help="comma-separated: png, pdf, svg (default png,pdf)")
    args = parser.parse_args(argv)
    formats = [f.strip() for f in args.format.split(",") if f.strip()]
    bad = [f for f in formats if f not in ("png", "pdf", "svg")]
    if bad:
        print(f"torchmm-plot: error: --format: unknown {', '.join(bad)} (png, pdf, svg)", file=sys.stderr)
        return 2
    for run_dir in args.run_dirs:
        try:
            written = plot_curves(Path(run_dir), formats)
        except FileNotFoundError as err:
            print(f"torchmm-plot: error: {err}", file=sys.stderr)
            return 2
        print(f"torchmm-plot: {len(written)} files in {Path(run_dir) / 'figures' / 'curves'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``torchmm-plot RUN_DIR``: redraw a run's per-step curves from ``curves.npz`` alone.

One figure per quantity (the part of a curve's tag before ``/``, e.g. ``pos_rmse``), one labelled
line per series (``pos_rmse/IMM``, ``pos_rmse/GPB1``, ...), over time steps or over a swept
parameter (``alpha``), 95 % bands where the run saved standard errors (``pos_rmse_se/IMM``) or
interval bounds (``nees_low/IMM`` and ``nees_high/IMM``: e.g. the chi-square band of a consistent
filter's NEES), the legend outside the axes, sized for a paper's column (3.4 in wide), written as PNG (300 dpi) and
PDF into ``RUN_DIR/figures/curves/``.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

__all__ = ["draw_groups", "load_curves", "main", "plot_curves", "save_tight"]

#: a band of +- Z95 standard errors is drawn around ``<q>/<s>`` where ``<q>_se/<s>`` exists
Z95 = 1.959963984540054


def load_curves(run_dir: Path) -> dict[str, tuple[str, object, object]]:
    """``{tag: (axis, x, values)}`` from ``run_dir/curves.npz``; ``axis`` is ``"step"`` for per-step
    curves, else the swept parameter's name (e.g. ``"alpha"``)."""
    import numpy as np

    path = Path(run_dir) / "curves.npz"
    if not path.exists():
        raise FileNotFoundError(f"RUN_DIR: {path} does not exist (a study run writes it; older runs have none)")
    try:
        with np.load(path) as data:
            axes = {}
            for key in data.files:
                tag, sep, axis = key.rpartition("#")
                if sep:
                    axes[tag] = (axis, data[key])
            return {key: (*axes.get(key, ("step", np.arange(1, len(data[key]) + 1))), data[key])
                    for key in data.files if "#" not in key}
    except Exception as err:  # truncated or not an npz (BadZipFile, EOFError, ValueError, OSError, ...)
        raise ValueError(f"RUN_DIR: {path} is not a readable curves file "
                         f"({type(err).__name__}: {err})") from None


def draw_groups(curves: dict[str, tuple[str, object, object]]) -> list[tuple[str, object]]:
    """One figure per quantity (the tag before its first ``/``), one labelled line per series, the
    legend outside the axes, 3.4 in wide (a paper's column). ``<q>_se/<s>`` curves become shaded
    95 % bands around ``<q>/<s>`` (and get no figure of their own when that curve exists).
    ``<q>_low/<s>`` with ``<q>_high/<s>`` are the bounds of a reference interval of ``<q>/<s>`` (e.g.
    the 95 % chi-square band of the NEES): shaded between them, once in grey with the label "95 %
    band" when every series has the same bounds, else per series in its line's colour, and no figure
    of their own."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    groups: dict[str, list[tuple[str, str, tuple]]] = defaultdict(list)
    for tag, curve in curves.items():
        quantity, _, series = tag.partition("/")
        groups[quantity].append((series or quantity, tag, curve))
    figures = []
    for quantity, lines in sorted(groups.items()):
        if quantity.endswith("_se") and quantity[:-3] in groups:
            continue  # drawn as bands
        if (quantity.endswith("_low") or quantity.endswith("_high")) and quantity.rpartition("_")[0] in groups:
            continue  # drawn as interval bands
        fig, ax = plt.subplots(figsize=(3.4, 2.4), constrained_layout=True)
        axis = lines[0][2][0]
        intervals = {}  # series tag -> (x, low, high): the reference intervals of this quantity
        for _, tag, (_, x, values) in lines:
            series = tag.partition("/")[2]
            low, high = curves.get(f"{quantity}_low/{series}"), curves.get(f"{quantity}_high/{series}")
            if low is not None and high is not None and len(low[2]) == len(high[2]) == len(values):
                intervals[tag] = (x, np.asarray(low[2], dtype=float), np.asarray(high[2], dtype=float))
        shared = len(intervals) == len(lines) and all(
            np.array_equal(b[1], a[1]) and np.array_equal(b[2], a[2])
            for a in intervals.values() for b in intervals.values())
        if shared:
            x, low, high = next(iter(intervals.values()))
            ax.fill_between(x, low, high, color="0.5", alpha=0.2, linewidth=0, label="95 % band")
        # nested series (``<estimator>/<mode>``, e.g. mode probabilities of several estimators): the
        # colour names the inner series, the line style the estimator, and the first estimator is
        # drawn thicker, so that estimators whose lines coincide (GPB2 on IMM) stay visible
        outer = list(dict.fromkeys(label.partition("/")[0] for label, _, _ in lines))
        inner = list(dict.fromkeys(label.partition("/")[2] for label, _, _ in lines))
        nested = len(outer) > 1 and all("/" in label for label, _, _ in lines)
        for i, (label, tag, (_, x, values)) in enumerate(lines):  # past 10 lines: the next line style
            style = {"linewidth": 1.0, "linestyle": ("-", "--", ":", "-.")[(i // 10) % 4]}
            if nested:
                o, _, n = label.partition("/")
                j = outer.index(o)
                style = {"linewidth": 2.2 if j == 0 else 1.0, "linestyle": ("-", "--", ":", "-.")[j % 4],
                         "color": f"C{inner.index(n) % 10}"}
            (line,) = ax.plot(x, values, label=label, marker="o" if axis != "step" else None, ms=2.5, **style)
            band = curves.get(f"{quantity}_se/{tag.partition('/')[2]}")
            if band is not None and len(band[2]) == len(values):
                se = np.asarray(band[2], dtype=float)
                ax.fill_between(x, values - Z95 * se, values + Z95 * se, color=line.get_color(), alpha=0.2,
                                linewidth=0)
            if tag in intervals and not shared:
                _, low, high = intervals[tag]
                ax.fill_between(x, low, high, color=line.get_color(), alpha=0.12, linewidth=0)
        xs = np.concatenate([np.asarray(c[1], dtype=float) for _, _, c in lines])
        if axis != "step" and xs.size and (xs > 0).all() and xs.max() / xs.min() >= 100:
            ax.set_xscale("log")
        ax.set_xlabel("time step" if axis == "step" else axis, fontsize=8)
        ax.set_ylabel(quantity.replace("_", " "), fontsize=8)
        ax.grid(True, linewidth=0.3, alpha=0.5)
        ax.tick_params(labelsize=7)
        if len(lines) > 1 or shared:
            ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=6, frameon=False, borderaxespad=0)
        figures.append((quantity, fig))
    return figures


def save_tight(figure, files) -> bytes | None:
    """Write ``figure`` to every ``(path, dpi)`` of ``files`` (``dpi`` None: the figure's), cropped to
    one tight bounding box; returns the bytes of the first PNG written (None if there is none).

    ``savefig(bbox_inches="tight")`` draws the figure once more per file only to find that box;
    here it is found once, so each file costs one draw. A figure with a layout engine (e.g.
    ``constrained_layout``) is laid out once, by the first draw, and keeps that layout.
    """
    import io

    import matplotlib

    from experiments.files import write_atomic

    figure.draw_without_rendering()  # lays the figure out (its layout engine too, if any)
    if figure.get_layout_engine() is not None:
        figure.set_layout_engine("none")  # keep that layout: the saves below then draw once each
    bbox = figure.get_tightbbox().padded(matplotlib.rcParams["savefig.pad_inches"])
    png = None
    for path, dpi in files:
        path = Path(path)
        kwargs = {} if dpi is None else {"dpi": dpi}
        if path.suffix.lower() == ".png" and png is None:
            buffer = io.BytesIO()
            figure.savefig(buffer, format="png", bbox_inches=bbox, **kwargs)
            png = buffer.getvalue()
            write_atomic(path, png)
        else:  # atomically too: a killed run leaves the old figure or the new one
            fmt = path.suffix[1:].lower() or None
            write_atomic(path, lambda f: figure.savefig(f, format=fmt, bbox_inches=bbox, **kwargs))
    return png


def plot_curves(run_dir: Path, formats=("png", "pdf")) -> list[Path]:
    """Draw every quantity's curves into ``run_dir/figures/curves/``; returns the files written."""
    import matplotlib.pyplot as plt

    out_dir = Path(run_dir) / "figures" / "curves"
    written = []
    for quantity, fig in draw_groups(load_curves(run_dir)):
        name = quantity.replace("/", "_") or "curve"
        paths = [out_dir / f"{name}.{fmt}" for fmt in formats]
        save_tight(fig, [(path, 300) for path in paths])
        written.extend(paths)
        plt.close(fig)
    return written


def main(argv: list[str] | None = None) -> int:
    from experiments.files import RunFolderError

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
        # missing, unreadable, unwritable: one line
        except (FileNotFoundError, ValueError, RunFolderError) as err:
            print(f"torchmm-plot: error: {err}", file=sys.stderr)
            return 2
        print(f"torchmm-plot: {len(written)} files in {Path(run_dir) / 'figures' / 'curves'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

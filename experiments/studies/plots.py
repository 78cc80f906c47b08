"""Figures shared by studies (matplotlib, Agg backend)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from experiments.uncertainty import Z95  # noqa: E402


def rmse_over_time(curves: Mapping[str, Mapping[str, torch.Tensor]], title: str = "",
                   bands: Mapping[str, Mapping[str, torch.Tensor]] | None = None):
    """``curves[panel][estimator] = (T,)`` -> one subplot per panel (e.g. position, velocity).

    ``bands[panel][estimator] = (T,)``, optional: the standard error of each step's value
    (experiments/uncertainty.py :func:`rmse_se_per_step`), drawn as a +- 1.96 se band (95 %) in the
    line's colour.
    """
    bands = bands or {}
    fig, axes = plt.subplots(1, len(curves), figsize=(5.5 * len(curves), 3.8), squeeze=False)
    for ax, (panel, series) in zip(axes[0], curves.items()):
        for name, values in series.items():
            values = torch.as_tensor(values).detach().cpu().double()
            steps = range(1, len(values) + 1)
            (line,) = ax.plot(steps, values, label=name, lw=1.3)
            se = bands.get(panel, {}).get(name)
            if se is not None:
                se = torch.as_tensor(se).detach().cpu().double()
                ax.fill_between(steps, values - Z95 * se, values + Z95 * se, color=line.get_color(), alpha=0.2,
                                lw=0)
        ax.set_xlabel("time step k")
        ax.set_ylabel(panel)
        ax.grid(alpha=0.3)
    # one legend outside the curves (right of the last panel): it never hides a line
    axes[0][-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False, borderaxespad=0)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def mode_probabilities(probs, true_modes: torch.Tensor, labels: Sequence[str], title: str = ""):
    """One run: each filter's mode probabilities ``(T, M)`` over the true mode sequence ``(T,)`` (None:
    unknown, e.g. recorded data).

    ``probs``: one estimator's ``(T, M)`` tensor, or ``{estimator: (T, M)}`` for several. Several
    estimators are drawn as **small multiples** (one stacked-area panel per estimator, shared axes,
    the true modes below), never overlaid: stacked areas cannot be overlaid at all, and overlaid lines
    of filters that agree (GPB2 and IMM often give the same probabilities to three digits) hide one
    another whatever the line style, while one panel each keeps every estimator readable and makes
    the differences a matter of comparing panels on the same scale.
    """
    if not isinstance(probs, Mapping):
        probs = {"": probs}
    probs = {name: torch.as_tensor(p).detach().cpu().double() for name, p in probs.items()}
    known = true_modes is not None  # recorded data: no true mode sequence, no bottom panel
    true_modes = torch.as_tensor(true_modes).detach().cpu() if known else None
    T, M = next(iter(probs.values())).shape
    n = len(probs)
    fig, axes = plt.subplots(n + known, 1, figsize=(8, 2.0 + 2.5 * n), sharex=True,
                             gridspec_kw={"height_ratios": [3] * n + [1] * known}, squeeze=False)
    steps = range(1, T + 1)
    for i, (ax, (name, p)) in enumerate(zip(axes[:n, 0], probs.items())):
        ax.stackplot(steps, p.T.numpy(), labels=labels, alpha=0.85)
        ax.set_ylabel(f"{name}\nmode probability" if name else "mode probability")
        ax.set_ylim(0, 1)
        if i == 0:
            ax.legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("time step k")
    if known:
        ax1 = axes[-1, 0]
        ax1.step(steps, true_modes.numpy(), where="mid", color="k")
        ax1.set_yticks(range(M), labels)
        ax1.set_ylabel("true mode")
    if title:
        axes[0, 0].set_title(title)
    fig.tight_layout()
    return fig


def nees_over_time(nees: Mapping[str, torch.Tensor], bounds: Mapping[str, tuple[float, float]], title: str = ""):
    """The run-averaged NEES of each estimator over time, ``nees[estimator] = (T,)``, with the 95 %
    chi-square band of a consistent filter (``bounds[estimator] = (low, high)``, each a number or a ``(T,)``
    tensor of each step's bound, NaN where no run is scored; experiments/uncertainty.py
    :func:`nees_consistency`) shaded: one grey band when every estimator has the same bounds (the same runs
    and state size), else one band per estimator in its colour."""
    fig, ax = plt.subplots(figsize=(6.5, 3.8))

    def key(b):
        b = torch.as_tensor(b, dtype=torch.float64).detach().cpu()
        return float(b) if b.ndim == 0 else tuple(b.tolist())
    bounds = {name: (key(lo), key(hi)) for name, (lo, hi) in bounds.items()}
    distinct = {(str(lo), str(hi)) for lo, hi in bounds.values()}  # (str: NaN equals NaN)
    steps = None
    for name, values in nees.items():
        values = torch.as_tensor(values).detach().cpu().double()
        steps = range(1, len(values) + 1)
        (line,) = ax.plot(steps, values, label=name, lw=1.2)
        if name in bounds and len(distinct) > 1:
            lo, hi = bounds[name]
            ax.fill_between(steps, lo, hi, color=line.get_color(), alpha=0.12, lw=0)
    if steps is not None and len(distinct) == 1:
        lo, hi = next(iter(bounds.values()))
        ax.fill_between(steps, lo, hi, color="0.5", alpha=0.2, lw=0, label="95 % chi-square band")
    ax.set_yscale("log")
    ax.set_xlabel("time step k")
    ax.set_ylabel("NEES (average over runs)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False, borderaxespad=0)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig


def ellipse_axes(cov: torch.Tensor, sigma: float = 2.0) -> tuple[float, float, float]:
    """``(width, height, angle_deg)`` of the ``sigma``-sigma ellipse of a 2x2 covariance (full axis
    lengths, as :class:`matplotlib.patches.Ellipse` takes them): the semi-axes are ``sigma`` times the
    square roots of the eigenvalues, the angle that of the first eigenvector."""
    cov = torch.as_tensor(cov, dtype=torch.float64)
    cov = (cov + cov.T) / 2
    vals, vecs = torch.linalg.eigh(cov)  # ascending
    vals = vals.clamp_min(0)
    major, minor = vals[1].sqrt().item(), vals[0].sqrt().item()
    angle = math.degrees(math.atan2(vecs[1, 1].item(), vecs[0, 1].item()))
    return 2 * sigma * major, 2 * sigma * minor, angle


def trajectory(truth: torch.Tensor, measurements: torch.Tensor | None,
               estimates: Mapping[str, tuple[torch.Tensor, torch.Tensor]], components: Sequence[int] = (0, 2),
               run: int | None = 0, sigma: float = 2.0, every: int | None = None, title: str = ""):
    """One run's truth, measurements and estimates in position space.

    ``truth``: states ``(T, n)`` or ``(T, runs, n)``; ``measurements``: ``(T, m)`` / ``(T, runs, m)``
    of the position components (column ``i`` measures ``components[i]``; NaN where missing) or None;
    ``estimates[name] = (mean (T[, runs], n), cov (T[, runs], n, n))``; ``run``: the run to draw when
    the arrays have a runs axis. Two ``components`` (x, y): the paths in the plane with each
    estimator's ``sigma``-sigma covariance ellipse every ``every``-th step (about 12 per path by
    default). One component: the component over time with a ``+- sigma`` standard-deviation band.
    """
    from matplotlib.patches import Ellipse

    def pick(t):
        t = torch.as_tensor(t).detach().cpu().double()
        return t[:, run] if run is not None else t

    truth = pick(truth)
    comps = list(components)
    T = truth.shape[0]
    k = every or max(1, T // 12)
    fig, ax = plt.subplots(figsize=(6.5, 5.0) if len(comps) == 2 else (8, 3.8))
    steps = torch.arange(1, T + 1)
    if len(comps) == 2:
        ax.plot(truth[:, comps[0]], truth[:, comps[1]], color="k", lw=1.5, label="truth")
        if measurements is not None:
            z = pick(measurements)
            ax.plot(z[:, 0], z[:, 1], ".", color="0.55", ms=3, label="measurements")
        for name, (mean, cov) in estimates.items():
            mean, cov = pick(mean), pick(cov)
            (line,) = ax.plot(mean[:, comps[0]], mean[:, comps[1]], lw=1.1, label=name)
            for t in range(0, T, k):
                block = cov[t][comps][:, comps]
                width, height, angle = ellipse_axes(block, sigma)
                ax.add_patch(Ellipse((mean[t, comps[0]].item(), mean[t, comps[1]].item()), width, height,
                                     angle=angle, fill=False, edgecolor=line.get_color(), lw=0.8, alpha=0.8))
        ax.set_xlabel(f"x (state component {comps[0]})")
        ax.set_ylabel(f"y (state component {comps[1]})")
        ax.set_aspect("equal", adjustable="datalim")
    elif len(comps) == 1:
        c = comps[0]
        ax.plot(steps, truth[:, c], color="k", lw=1.5, label="truth")
        if measurements is not None:
            z = pick(measurements)
            ax.plot(steps, z[:, 0], ".", color="0.55", ms=3, label="measurements")
        for name, (mean, cov) in estimates.items():
            mean, cov = pick(mean), pick(cov)
            sd = cov[:, c, c].clamp_min(0).sqrt()
            (line,) = ax.plot(steps, mean[:, c], lw=1.1, label=name)
            ax.fill_between(steps, mean[:, c] - sigma * sd, mean[:, c] + sigma * sd, color=line.get_color(),
                            alpha=0.2, lw=0)
        ax.set_xlabel("time step k")
        ax.set_ylabel(f"position (state component {c})")
    else:
        raise ValueError(f"trajectory: components must name 1 or 2 state components, got {comps}")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False, borderaxespad=0)
    band = f"{sigma:g}-sigma ellipses every {k} steps" if len(comps) == 2 else f"+- {sigma:g} sigma bands"
    ax.set_title(f"{title + ': ' if title else ''}{band}", fontsize=9)
    fig.tight_layout()
    return fig


def lines(x: Sequence[float], series: Mapping[str, Sequence[float]], *, xlabel: str, ylabel: str,
          title: str = "", logx: bool = False, ax=None, errors: Mapping[str, Sequence[float]] | None = None):
    """Simple line plot of several series over a common x.

    ``errors[name]``, optional: the standard error of each point of ``series[name]`` (a Monte Carlo
    mean), drawn as +- 1.96 se (95 %) error bars; a series without (or with a missing, None/NaN) se
    is drawn as a plain line.
    """
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(5.5, 3.8))
    errors = errors or {}
    for name, ys in series.items():
        se = errors.get(name)
        if se is not None and all(v is not None and math.isfinite(v) for v in se):
            ax.errorbar(x, ys, yerr=[Z95 * v for v in se], marker="o", ms=3.5, capsize=2.5, elinewidth=0.9,
                        label=name)
        else:
            ax.plot(x, ys, marker="o", ms=3.5, label=name)
    if logx:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    if own:
        fig.tight_layout()
        return fig
    return ax.figure


def tracks_xy(truth: torch.Tensor, present: torch.Tensor, detections: torch.Tensor,
              tracks: Mapping[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]],
              sigma: float = 2.0, every: int | None = None, title: str = ""):
    """One run of a multi-target tracker in the plane, a panel per estimator: the targets' true paths
    (black, where they exist), every scan's detections (grey dots: the targets' and the clutter), and each
    estimator's tracks, one colour per label, with ``sigma``-sigma ellipses every ``every`` scans and the
    label at the track's last shown point.

    ``truth (T, N, 2)``, ``present (T, N)`` bool, ``detections (T, D, 2)`` (NaN rows absent);
    ``tracks[name] = (mean (T, K, 2), cov (T, K, 2, 2), shown (T, K) bool, labels (T, K) long)``.
    """
    from matplotlib.patches import Ellipse

    names = list(tracks)
    T = truth.shape[0]
    k = every or max(1, T // 8)
    cols = min(3, max(1, len(names)))
    rows = math.ceil(max(1, len(names)) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 4.4 * rows), squeeze=False)
    z = detections.reshape(-1, 2)
    z = z[torch.isfinite(z).all(-1)]
    palette = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, name in zip(axes.flat, names):
        ax.plot(z[:, 0], z[:, 1], ".", color="0.7", ms=2, label="detections (targets' and clutter)")
        for i in range(truth.shape[1]):
            path = torch.where(present[:, i, None], truth[:, i], torch.nan)
            ax.plot(path[:, 0], path[:, 1], color="k", lw=1.2, label="truth" if i == 0 else None)
        mean, cov, shown, labels = tracks[name]
        for slot in range(mean.shape[1]):
            visible = shown[:, slot]
            if not bool(visible.any()):
                continue
            label = int(labels[visible, slot][-1])
            color = palette[label % len(palette)]
            path = torch.where(visible[:, None], mean[:, slot], torch.nan)
            ax.plot(path[:, 0], path[:, 1], color=color, lw=1.0)
            for t in range(0, T, k):
                if bool(visible[t]):
                    width, height, angle = ellipse_axes(cov[t, slot], sigma)
                    ax.add_patch(Ellipse((float(mean[t, slot, 0]), float(mean[t, slot, 1])), width, height,
                                         angle=angle, fill=False, edgecolor=color, lw=0.7, alpha=0.8))
            last = int(torch.nonzero(visible)[-1])
            ax.annotate(str(label), (float(mean[last, slot, 0]), float(mean[last, slot, 1])), fontsize=7,
                        color=color, xytext=(3, 3), textcoords="offset points")
        ax.set_title(name, fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    for ax in list(axes.flat)[len(names):]:
        ax.axis("off")
    axes.flat[0].legend(loc="lower left", fontsize=7, frameon=False)
    fig.suptitle(f"{title + ': ' if title else ''}tracks (a colour and number per label), "
                 f"{sigma:g}-sigma ellipses every {k} scans", fontsize=9)
    fig.tight_layout()
    return fig

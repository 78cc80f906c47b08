"""Figures shared by studies (matplotlib, Agg backend)."""

from __future__ import annotations

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


def mode_probabilities(probs: torch.Tensor, true_modes: torch.Tensor, labels: Sequence[str], title: str = ""):
    """One run: the filter's mode probabilities ``(T, M)`` over the true mode sequence ``(T,)``."""
    probs, true_modes = probs.detach().cpu(), true_modes.detach().cpu()
    T, M = probs.shape
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    steps = range(1, T + 1)
    ax0.stackplot(steps, probs.T.numpy(), labels=labels, alpha=0.85)
    ax0.set_ylabel("mode probability")
    ax0.set_ylim(0, 1)
    ax0.legend(loc="upper right", fontsize=8)
    ax1.step(steps, true_modes.numpy(), where="mid", color="k")
    ax1.set_yticks(range(M), labels)
    ax1.set_ylabel("true mode")
    ax1.set_xlabel("time step k")
    if title:
        ax0.set_title(title)
    fig.tight_layout()
    return fig


def lines(x: Sequence[float], series: Mapping[str, Sequence[float]], *, xlabel: str, ylabel: str,
          title: str = "", logx: bool = False, ax=None):
    """Simple line plot of several series over a common x."""
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for name, ys in series.items():
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

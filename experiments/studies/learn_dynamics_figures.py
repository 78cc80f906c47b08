"""The learned-dynamics study's figures (split from :mod:`experiments.studies.learn_dynamics` by concern, issue 47)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from experiments.studies import plots  # noqa: E402

__all__ = ["figures"]


def figures(ctx, histories, scores, curves, true_tpm, q_true, scenario, bands=None) -> None:
    """The study's figures: the training losses, the parameters over the iterations (the transition matrix
    and ``q`` of part A, the MLP mode's implied turn rate of part B, each against the true value), the
    held-out RMSE before and after learning, and the RMSE over time."""
    if histories:
        fig, axes = plt.subplots(1, len(histories), figsize=(5.5 * len(histories), 3.6), squeeze=False)
        for ax, (part, hist) in zip(axes[0], histories.items()):
            ax.plot([h["iteration"] for h in hist], [h["loss"] for h in hist], marker="o", ms=3)
            ax.set_xlabel("iteration")
            ax.set_ylabel("NLL per step and run")
            ax.set_title(f"part {part}")
            ax.grid(alpha=0.3)
        fig.tight_layout()
        ctx.save_figure("loss_curve", fig)

        panels = []
        if "a" in histories:
            panels += ["tpm", "q"]
        if "b" in histories:
            panels.append("mlp")
        fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 3.6), squeeze=False)
        for ax, panel in zip(axes[0], panels):
            if panel == "tpm":
                hist = histories["a"]
                its = [h["iteration"] for h in hist]
                for i in range(3):
                    for j in range(3):
                        line, = ax.plot(its, [h[f"tpm[{i},{j}]"] for h in hist], lw=1.2, label=f"[{i},{j}]")
                        ax.axhline(true_tpm[i, j].item(), color=line.get_color(), ls=":", lw=0.8)
                ax.set_ylabel("transition-matrix entry")
                # every entry labelled, outside the curves
                ax.legend(fontsize=7, title="entry (dotted: true)", title_fontsize=7, loc="upper left",
                          bbox_to_anchor=(1.02, 1.0), frameon=False, borderaxespad=0)
            elif panel == "q":
                hist = histories["a"]
                ax.plot([h["iteration"] for h in hist], [h["q"] for h in hist], marker="o", ms=3)
                ax.axhline(q_true, color="k", ls=":", label="true")
                ax.set_yscale("log")
                ax.set_ylabel("q")
                ax.legend(fontsize=8)
            else:
                hist = histories["b"]
                ax.plot([h["iteration"] for h in hist], [h["mlp_turn_rate"] for h in hist], marker="o", ms=3)
                ax.axhline(scenario.motion.omega[int(ctx.cfg.learn.part_b.replaced_mode)].item(), color="k",
                           ls=":", label="true")
                ax.set_ylabel("turn rate implied by the MLP mode")
                ax.legend(fontsize=8)
            ax.set_xlabel("iteration")
            ax.grid(alpha=0.3)
        fig.tight_layout()
        ctx.save_figure("parameter_trajectories", fig)

    labels = list(scores)
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    for ax, k, name in ((axes[0], 0, "position RMSE"), (axes[1], 1, "velocity RMSE")):
        values = [scores[label][k] for label in labels]
        ax.bar(range(len(labels)), values, color=[f"C{i}" for i in range(len(labels))])
        ax.set_xticks(range(len(labels)), labels, rotation=25, ha="right", fontsize=8)
        ax.set_ylabel(name)
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle("held-out RMSE before / after learning")
    fig.tight_layout()
    ctx.save_figure("rmse_before_after", fig)
    ctx.save_figure("rmse_over_time", plots.rmse_over_time(curves, f"{scenario.name}, held-out runs",
                                                                  bands=bands))

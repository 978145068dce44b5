"""The learning curve of a run: training loss and evaluation scores against steps, from its log records."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def plot_learning_curve(records: list[dict[str, Any]], path: str | Path) -> None:
    """learning_curve.png: training loss and evaluation scores against steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    train = [r for r in records if r["type"] == "train"]
    evals = [r for r in records if r["type"] == "eval"]
    fig, (ax_loss, ax_eval) = plt.subplots(1, 2, figsize=(11, 4))
    ax_loss.plot([r["step"] for r in train], [r["loss"] for r in train], lw=1)
    ax_loss.set(xlabel="step", ylabel="training loss", title="loss", yscale="log")
    ax_loss.grid(alpha=0.3)
    if evals:
        steps = [r["step"] for r in evals]
        ax_eval.plot(steps, [r["mean_max_reward"] for r in evals], "o-", label="mean max reward")
        ax_eval.fill_between(
            steps, [r["mean_max_reward_ci95"][0] for r in evals], [r["mean_max_reward_ci95"][1] for r in evals], alpha=0.2
        )
        ax_eval.plot(steps, [r["success_rate"] for r in evals], "s-", label="success rate")
        ax_eval.legend(loc="upper left")
        first = evals[0]["seeds"]  # [first, last] in newer logs, every seed in older ones
        ax_eval.set_title(f"evaluation ({evals[0].get('episodes', len(first))} episodes, seeds {first[0]}..{first[-1]})")
    else:
        ax_eval.set_title("evaluation (none yet)")
    last_step = max([r["step"] for r in records] + [1])  # a run of 0 steps (a second pass that learns nothing) still has an axis
    ax_eval.set(xlabel="step", ylim=(0, 1), xlim=(0, last_step * 1.02))
    ax_eval.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)

"""Print the markdown table of the shipped policies' held-out scores, from their cards (models/*.json).

    python scripts/results_table.py [--models-dir models] [--env gym-pusht]
    python scripts/results_table.py --stages      # each policy's recipe stages: wall time and score

One row per policy: what it computes, its network evaluations per chunk, success and mean max reward with
their 95 % intervals on the held-out seeds, the mean steps of the successful episodes (n/a on a card
shipped before evaluations reported it), and the recipe that made it with its summed stage wall time.
The README's results table and models/README.md's stage tables are this command's output (tests/test_readme.py
checks them).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository's packages, installed or not

from acting import CardError, read_card  # noqa: E402  (the one card reader)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: the table on stdout; 2 with one line on a missing or bad card."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models-dir", default="models", help="folder of the shipped policies")
    parser.add_argument("--env", default="gym-pusht", choices=("gym-pusht", "pusht"), help="env whose held-out scores to list")
    parser.add_argument("--stages", action="store_true", help="print each policy's recipe stages (wall time, score) instead")
    args = parser.parse_args(argv)
    cards = sorted(Path(args.models_dir).glob("*.json"))
    if not cards:
        print(f"error: no policy cards (*.json) in {args.models_dir}", file=sys.stderr)
        return 2
    try:
        loaded = [read_card(path) for path in cards]
        print(stage_tables(loaded) if args.stages else table(loaded, args.env))
    except (CardError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def table(cards: list, env: str) -> str:
    """The markdown table, the default policy first."""
    lines = [
        "| policy | computes | network evaluations per chunk | success (95 % CI) | mean max reward (95 % CI) "
        "| mean steps to success | held-out episodes | recipe | stage wall time |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for card in sorted(cards, key=lambda c: (not c.default, c.name)):
        score = card.data["heldout_evaluation"][env]
        low, high = score["success_rate_ci95"]
        rlow, rhigh = score["mean_max_reward_ci95"]
        first, last = score["seeds"]
        name = f"**{card.path.stem}** (default)" if card.default else card.path.stem
        recipe = card.data.get("recipe", {}).get("file", "-")
        minutes = card.data.get("stages_wall_time_s", 0) / 60
        steps = score.get("mean_steps_to_success")
        steps = "n/a" if steps is None else f"{steps:.0f}"
        lines.append(
            f"| {name} | {card.computes} | {card.network_evaluations()} | {100 * score['success_rate']:.1f} % "
            f"({100 * low:.1f}..{100 * high:.1f}) | {score['mean_max_reward']:.3f} ({rlow:.3f}..{rhigh:.3f}) | {steps} "
            f"| {score['episodes']} ({first}..{last}, {env}) | `{recipe}` | {minutes:.0f} min |"
        )
    return "\n".join(lines)


def stage_tables(cards: list) -> str:
    """Per policy, its recipe's stages as the recipe runner's summary shows them: wall time and score."""
    from training.recipe import format_score  # torch-free

    blocks = []
    for card in sorted(cards, key=lambda c: (not c.default, c.name)):
        recipe = card.data.get("recipe", {})
        lines = [
            f"`{recipe.get('file', '-')}` ({card.path.stem}, commit {card.data.get('git_commit', '-')[:10]}):",
            "",
            "| stage | run | wall time | score |",
            "| --- | --- | --- | --- |",
        ]
        for stage in card.data.get("stages", []):
            wall = f"{stage['wall_time_s']:.0f} s"
            if "restored_from" in stage:  # not run here: taken from a shipped card (--reuse-shipped)
                origin = stage["restored_from"]
                wall += f" (from {origin['policy']}'s card at commit {origin['git_commit'][:10]})"
            lines.append(f"| {stage['name']} | {stage['run']} | {wall} | {format_score(stage.get('score'))} |")
        lines.append(f"| total | | {card.data.get('stages_wall_time_s', 0):.0f} s | |")
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


if __name__ == "__main__":
    sys.exit(main())

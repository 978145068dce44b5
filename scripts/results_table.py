"""Print the markdown results table of the shipped policies from their cards (models/*.json).

    python scripts/results_table.py [--models-dir models]

One row per shipped policy, checkpoint (final and best) and env, with the held-out scores that
`python -m training.ship` stored in the cards, so the numbers in models/README.md come from a command.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models-dir", default="models", help="folder of the shipped policies")
    args = parser.parse_args(argv)
    models = Path(args.models_dir)
    cards = sorted(models.glob("*.json"))
    if not cards:
        print(f"error: no policy cards (*.json) in {models}", file=sys.stderr)
        return 2
    print("| policy | checkpoint | steps | train wall time | env | mean max reward (95% CI) | success (95% CI) | held-out seeds |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for path in cards:
        final = json.loads(path.read_text())
        best_path = Path(final.get("run", "")) / "best.json"
        rows = [("final", final)]
        if best_path.is_file():
            rows.append(("best", json.loads(best_path.read_text())))
        for label, card in rows:
            for env, score in (card.get("heldout_evaluation") or {}).items():
                print(
                    f"| {final['name']} | {label} | {card['steps']:,} | {card['wall_time_s'] / 60:.0f} min | {env} "
                    f"| {_with_ci(score, 'mean_max_reward')} | {_with_ci(score, 'success_rate', percent=True)} "
                    f"| {score['seeds'][0]}..{score['seeds'][1]} |"
                )
    return 0


def _with_ci(score: dict, key: str, percent: bool = False) -> str:
    low, high = score[f"{key}_ci95"]
    if percent:
        return f"{100 * score[key]:.0f} % ({100 * low:.0f}..{100 * high:.0f})"
    return f"{score[key]:.3f} ({low:.3f}..{high:.3f})"


if __name__ == "__main__":
    sys.exit(main())

"""Re-score shipped policies on their held-out seeds and write the scores into their cards, as `training.ship` does.

    python -m training.rescore --name flow mse

For when the evaluation rule changes but the weights do not: each `models/NAME` is scored through its
ONNX export, and the best checkpoint kept in its record (`records/RUN/best`) through torch, with
`training.ship`'s own scoring; the scores replace `heldout_evaluation` in `models/NAME.json` and in
the record's `last.json` / `best.json`, and the first held-out episode replaces `models/NAME_rollout.gif`.
Nothing is chosen here: the policies stay as shipped. One JSON line is printed per evaluation.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from pusht.spec import HELD_OUT_SEED
from training.checkpoint import load_card, update_card
from training.config import HelpFormatter
from training.evaluate import ENVS, write_gif
from training.ship import score_heldout


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(prog="python -m training.rescore", description=__doc__.splitlines()[0], formatter_class=HelpFormatter)
    parser.add_argument("--name", nargs="+", required=True, help="shipped policies to re-score (models/NAME.json and .onnx)")
    parser.add_argument("--models-dir", default="models", help="where shipped policies live")
    parser.add_argument("--episodes", type=int, default=100, help="held-out episodes")
    parser.add_argument("--seed", type=int, default=HELD_OUT_SEED, help="first held-out episode seed")
    parser.add_argument("--envs", nargs="+", choices=ENVS, default=list(ENVS), help="envs to score in")
    args = parser.parse_args(argv)
    try:
        for name in args.name:
            for line in rescore(Path(args.models_dir), name, args.episodes, args.seed, args.envs):
                print(json.dumps(line), flush=True)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def rescore(models_dir: Path, name: str, episodes: int, seed: int, envs: list[str]) -> list[dict[str, Any]]:
    """Score `models_dir/name` (and its record's best checkpoint, if kept) and write the scores into the cards."""
    stem = models_dir / name
    record = Path(load_card(stem).get("run", ""))
    if not (record / "last.json").is_file():
        raise FileNotFoundError(f"{stem}.json names its record {record}, which has no last.json")
    reports: list[dict[str, Any]] = []
    final, frames = score_heldout(stem.with_suffix(".onnx"), stem.with_suffix(".onnx"), episodes, seed, envs, reports, "final", gif=True)
    best = None
    if (record / "best.safetensors").is_file():
        best = score_heldout(record / "best", record / "best", episodes, seed, envs, reports, "best")[0]
    update_card(stem, heldout_evaluation=final)
    update_card(record / "last", heldout_evaluation=final)
    if best is not None:
        update_card(record / "best", heldout_evaluation=best)
    write_gif(frames, models_dir / f"{name}_rollout.gif")
    return reports


if __name__ == "__main__":
    sys.exit(main())

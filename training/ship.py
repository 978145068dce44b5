"""Ship a training run: its final checkpoint becomes `models/NAME`, exported and scored on held-out seeds.

    python -m training.ship --run runs/flow-sincos-skip-150k --name flow

Writes `models/NAME.{safetensors,json,onnx}` (the run's `last` checkpoint), keeps the run's record in
`models/runs/RUN/` (config, log, learning curve, `best` checkpoint), scores both the final and the best
checkpoint on the held-out episode seeds (never used during training) in every requested env, stores
the scores in the cards (`heldout_evaluation`), writes `models/NAME_rollout.gif`, and prints one JSON
line per evaluation.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import Any

from training.checkpoint import load_card, update_card, write_text_atomic
from training.evaluate import ENVS, evaluate_policy, load_actor, report, write_gif
from training.export import export_onnx

HELDOUT_SEED = 200000
RUN_RECORD_FILES = ("config.json", "log.jsonl", "learning_curve.png", "best.safetensors", "best.json")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(prog="python -m training.ship", description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="the run folder written by training.train (has last.* and best.*)")
    parser.add_argument("--name", required=True, help="the shipped policy's name, e.g. flow or mse")
    parser.add_argument("--models-dir", default="models", help="where shipped policies live")
    parser.add_argument("--episodes", type=int, default=100, help="held-out episodes")
    parser.add_argument("--seed", type=int, default=HELDOUT_SEED, help="first held-out episode seed")
    parser.add_argument("--envs", nargs="+", choices=ENVS, default=list(ENVS), help="envs to score in")
    parser.add_argument("--note", default="", help="what changed from the published recipe and why (stored in the card)")
    args = parser.parse_args(argv)
    try:
        for line in ship(Path(args.run), args.name, Path(args.models_dir), args.episodes, args.seed, args.envs, args.note):
            print(json.dumps(line))
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def ship(run: Path, name: str, models_dir: Path, episodes: int, seed: int, envs: list[str], note: str = "") -> list[dict[str, Any]]:
    """Promote `run`'s final checkpoint to `models_dir/name`, export it, score final and best; returns the reports."""
    for required in ("last.safetensors", "last.json", "best.safetensors", "best.json"):
        if not (run / required).is_file():
            raise FileNotFoundError(f"{run / required} is missing: is {run} a finished training run?")
    record = models_dir / "runs" / run.name
    record.mkdir(parents=True, exist_ok=True)
    for file in RUN_RECORD_FILES:
        if (run / file).is_file():
            shutil.copyfile(run / file, record / file)
    stem = models_dir / name
    shutil.copyfile(run / "last.safetensors", stem.with_suffix(".safetensors"))
    card = load_card(run / "last")
    card.update(name=name, run=str(record), recipe_changes=note or card.get("recipe_changes", ""))
    write_text_atomic(stem.with_suffix(".json"), json.dumps(card, indent=2, allow_nan=False) + "\n")
    export_onnx(stem)

    reports = []
    for label, target, model in (("final", stem, stem.with_suffix(".onnx")), ("best", record / "best", record / "best")):
        scores = {}
        for env in envs:
            actor, kind = load_actor(model)
            summary = evaluate_policy(actor, kind, episodes=episodes, seed=seed, env=env,
                                      record_frames=label == "final" and env == envs[0])
            if summary.frames:
                write_gif(summary.frames, models_dir / f"{name}_rollout.gif")
            line = report(summary, model=str(model), kind=kind, env=env)
            scores[env] = line
            reports.append({"checkpoint": label, **line})
        update_card(target, heldout_evaluation=scores)
    return reports


if __name__ == "__main__":
    sys.exit(main())

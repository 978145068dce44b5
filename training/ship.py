"""Record a training run's held-out scores and, optionally, ship its final checkpoint as `models/NAME`.

    python -m training.ship --run runs/flow-sincos-skip-150k --name flow   # record and ship
    python -m training.ship --run runs/mse-recipe-200k                      # record only

Every run gets a record in `models/runs/RUN/`: its config, log, learning curve, and the cards of its
final (`last.json`) and best (`best.json`) checkpoints, each with `heldout_evaluation`: the scores on
held-out episode seeds (never used during training) in every requested env. With `--name`, the final
checkpoint also becomes `models/NAME.{safetensors,json,onnx}` (scored through its ONNX export, which is
what the service runs), the best checkpoint's weights are kept in the record, and the first held-out
episode is written to `models/NAME_rollout.gif`. One JSON line is printed per evaluation.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import Any

from training.checkpoint import load_card, set_noise_scale, update_card, write_text_atomic
from training.config import command_line
from training.evaluate import ENVS, evaluate_policy, load_actor, report, write_gif
from training.export import export_onnx

HELDOUT_SEED = 200000
RUN_RECORD_FILES = ("config.json", "log.jsonl", "learning_curve.png", "last.json", "best.json")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(prog="python -m training.ship", description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="the run folder written by training.train (has last.* and best.*)")
    parser.add_argument("--name", default=None, help="ship the final checkpoint as models/NAME (e.g. flow, mse); omit to only record the run")
    parser.add_argument("--models-dir", default="models", help="where shipped policies live")
    parser.add_argument("--episodes", type=int, default=100, help="held-out episodes")
    parser.add_argument("--seed", type=int, default=HELDOUT_SEED, help="first held-out episode seed")
    parser.add_argument("--envs", nargs="+", choices=ENVS, default=list(ENVS), help="envs to score in")
    parser.add_argument("--noise-scale", type=float, default=None, help="flow: set the sampling noise_scale of the run's final and best checkpoints first (chosen on non-held-out seeds)")
    parser.add_argument("--note", default="", help="what changed from the published recipe and why (stored in the card)")
    args = parser.parse_args(argv)
    try:
        lines = ship(
            Path(args.run), args.name, Path(args.models_dir), args.episodes, args.seed, args.envs, args.note, args.noise_scale
        )
        for line in lines:
            print(json.dumps(line))
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def ship(
    run: Path,
    name: str | None,
    models_dir: Path,
    episodes: int,
    seed: int,
    envs: list[str],
    note: str = "",
    noise_scale: float | None = None,
) -> list[dict[str, Any]]:
    """Record `run` in `models_dir/runs/`, ship its final checkpoint as `models_dir/name` if named; returns the reports.

    `noise_scale` (flow) is first set on the run's final and best checkpoints, so every score and export uses it.
    """
    for required in ("last.safetensors", "last.json", "best.safetensors", "best.json"):
        if not (run / required).is_file():
            raise FileNotFoundError(f"{run / required} is missing: is {run} a finished training run?")
    if noise_scale is not None:
        for checkpoint in ("last", "best"):
            set_noise_scale(run / checkpoint, noise_scale)
    record = models_dir / "runs" / run.name
    record.mkdir(parents=True, exist_ok=True)
    for file in RUN_RECORD_FILES:
        if (run / file).is_file():
            shutil.copyfile(run / file, record / file)
    if note:
        update_card(record / "last", recipe_changes=note)

    # (label, model to evaluate, cards that receive the scores)
    targets = [("final", run / "last", [record / "last"]), ("best", run / "best", [record / "best"])]
    if name is not None:
        stem = models_dir / name
        shutil.copyfile(run / "last.safetensors", stem.with_suffix(".safetensors"))
        shutil.copyfile(run / "best.safetensors", record / "best.safetensors")
        card = load_card(record / "last")
        card.update(name=name, run=str(record), reproduce=reproduce_commands(card, run, name))
        write_text_atomic(stem.with_suffix(".json"), json.dumps(card, indent=2, allow_nan=False) + "\n")
        export_onnx(stem)
        targets[0] = ("final", stem.with_suffix(".onnx"), [stem, record / "last"])

    reports = []
    for label, model, cards in targets:
        scores = {}
        for env in envs:
            actor, kind = load_actor(model)
            gif = name is not None and label == "final" and env == envs[0]
            summary = evaluate_policy(actor, kind, episodes=episodes, seed=seed, env=env, record_frames=gif)
            if gif:
                write_gif(summary.frames, models_dir / f"{name}_rollout.gif")
            scores[env] = report(summary, model=str(model), kind=kind, env=env)
            reports.append({"checkpoint": label, **scores[env]})
        for card_stem in cards:
            update_card(card_stem, heldout_evaluation=scores)
    return reports


def reproduce_commands(card: dict[str, Any], run: Path, name: str) -> list[str]:
    """The training command (from the run's config) and the ship command that made `models/NAME`."""
    ship_command = f"python -m training.ship --run {run} --name {name}"
    scale = card["architecture"].get("noise_scale")
    if scale is not None:
        ship_command += f" --noise-scale {scale:g}"
    return [command_line(card["config"]), ship_command]


if __name__ == "__main__":
    sys.exit(main())

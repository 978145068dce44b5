"""One human-gated DAgger round: evaluate a policy, train on a human's corrections, evaluate again, report the change.

    python -m training.dagger --model models/flow --corrections runs/viewer --name flow-dagger-1 --steps 2000

The corrections are the zarr stores that `/viewer` saved into PUSHT_VIEWER_DATA_DIR (a person took over
with the mouse where the policy went wrong; data/human marks those steps). The round fine-tunes the
policy from its checkpoint on the demonstrations plus those stores (human-labelled windows weighted
by --human-weight, the policy's own steps by --policy-step-weight, 0 by default as DAgger keeps only
the expert's labels), with the base run's data recipe, then scores base and result on the same seeds
and prints one JSON line: both scores and their difference.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from acting.card import card_stem, read_card
from pusht.spec import TRAIN_EVAL_SEED
from training.config import HelpFormatter, TrainConfig
from training.evaluate import evaluate_policy, load_model

RECIPE_KEYS = ("data", "horizon", "pad_episode_end", "state_noise_start", "state_noise_end", "state_noise_schedule", "action_horizon")
"""What the fine-tuning takes from the base run's config, so the corrections join the data it learned from."""


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: one round, one JSON line; 2 on a bad argument."""
    parser = argparse.ArgumentParser(prog="python -m training.dagger", description=__doc__.splitlines()[0], formatter_class=HelpFormatter)
    parser.add_argument("--model", required=True, help="checkpoint stem of the policy to improve (models/flow; NAME.onnx means its stem)")
    parser.add_argument("--corrections", required=True, help="folder of zarr stores saved by /viewer (PUSHT_VIEWER_DATA_DIR)")
    parser.add_argument("--name", required=True, help="run name of the fine-tuning (OUT_DIR/NAME)")
    parser.add_argument("--out-dir", default="runs", help="parent folder of the run")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing run NAME")
    parser.add_argument("--steps", type=int, default=2000, help="fine-tuning optimizer steps")
    parser.add_argument("--lr", type=float, default=1e-4, help="peak learning rate of the fine-tuning (cosine to 0)")
    parser.add_argument("--batch-size", type=int, default=128, help="batch size of the fine-tuning")
    parser.add_argument("--human-weight", type=float, default=5.0, help="sampling weight of windows whose first action the human gave")
    parser.add_argument("--policy-step-weight", type=float, default=0.0, help="sampling weight of the policy's own steps in the corrections")
    parser.add_argument("--data", default=None, help="the demonstrations (default: the base run's)")
    parser.add_argument("--episodes", type=int, default=100, help="evaluation episodes, before and after")
    parser.add_argument("--seed", type=int, default=TRAIN_EVAL_SEED, help=f"first evaluation episode seed ({TRAIN_EVAL_SEED}: training's evaluation seeds, not the held-out ones)")
    parser.add_argument("--num-envs", type=int, default=100, help="envs in lockstep during evaluation (scores do not depend on it)")
    parser.add_argument("--max-steps", type=int, default=300, help="episode step limit in evaluation")
    parser.add_argument("--train-seed", type=int, default=0, help="seed of the fine-tuning")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars on stderr")
    args = parser.parse_args(argv)
    try:
        line = dagger_round(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(line))
    return 0


def correction_stores(folder: str | Path) -> tuple[list[Path], dict[str, int]]:
    """The zarr stores in `folder` (checked with the dataset's loader) and their episode, frame and human-frame counts."""
    from training.data import human_labels, load_replay

    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder of corrections (the viewer saves into PUSHT_VIEWER_DATA_DIR)")
    stores = sorted(p for p in folder.glob("*.zarr") if p.is_dir())
    counts = {"stores": len(stores), "episodes": 0, "frames": 0, "human_frames": 0}
    for store in stores:
        replay = load_replay(store)
        labels = human_labels(store, len(replay.states))
        counts["episodes"] += replay.num_episodes
        counts["frames"] += len(replay.states)
        counts["human_frames"] += int(labels.sum()) if labels is not None else 0
    if not stores:
        raise ValueError(f"{folder}: no .zarr stores; save corrected episodes with the viewer first")
    if counts["human_frames"] == 0:
        raise ValueError(f"{folder}: no human-labelled steps in {len(stores)} stores; hold the mouse on the board to correct the policy before saving")
    return stores, counts


def dagger_round(args: argparse.Namespace) -> dict[str, Any]:
    """Evaluate, fine-tune on the corrections, evaluate again; the report line."""
    from training.train import train

    stem = card_stem(args.model)
    card = read_card(stem).data
    if (card.get("architecture") or {}).get("onepass_dims"):
        raise ValueError(f"{stem} is a one-pass student (onepass_dims): fine-tuning would train its teacher's flow network, "
                         f"which it does not act with; distil it again from its teacher ({card.get('teacher')}) with more rounds")
    stores, counts = correction_stores(args.corrections)
    base_config = _training_config(card)
    recipe = {k: base_config[k] for k in RECIPE_KEYS if k in base_config}
    if args.data is not None:
        recipe["data"] = args.data
    cfg = TrainConfig(  # validated here, before the first evaluation spends minutes
        policy=card["kind"], name=args.name, out_dir=args.out_dir, overwrite=args.overwrite, init=str(stem),
        extra_data=",".join(str(s) for s in stores), human_weight=args.human_weight, policy_step_weight=args.policy_step_weight,
        steps=args.steps, lr=args.lr, batch_size=args.batch_size, eval_every=-1, seed=args.train_seed,
        progress=not args.no_progress, **recipe,
    )
    if (Path(args.out_dir) / args.name).exists() and not args.overwrite:
        raise ValueError(f"{Path(args.out_dir) / args.name} already exists: choose another --name, or pass --overwrite")
    before = _score(stem, args)
    run = train(cfg)
    if run.exit_code() != 0:
        raise ValueError(f"the fine-tuning stopped before its last step (state in {run.dir}); nothing to compare")
    after = _score(run.dir / "last", args)
    return {
        "base": str(stem), "run": str(run.dir), "checkpoint": str(run.dir / "last"), "corrections": {"folder": str(args.corrections), **counts},
        "human_weight": args.human_weight, "policy_step_weight": args.policy_step_weight, "steps": args.steps,
        "before": before, "after": after,
        "change": {k: round(after[k] - before[k], 6) for k in ("mean_max_reward", "success_rate")},
    }


def _training_config(card: dict[str, Any]) -> dict[str, Any]:
    """The training config behind a card: a fine-tuned flow's (`training.finetune`, frozen weights) is its base's."""
    config = card.get("config") or {}
    for _ in range(4):
        if "algo" not in config or not config.get("init"):
            break
        config = read_card(card_stem(config["init"])).data.get("config") or {}
    return config


def _score(stem: Path, args: argparse.Namespace) -> dict[str, Any]:
    summary = evaluate_policy(load_model(stem), episodes=args.episodes, seed=args.seed, num_envs=args.num_envs,
                              max_steps=args.max_steps, progress=not args.no_progress)
    scores = summary.scores()
    return {k: scores[k] for k in ("episodes", "seeds", "mean_max_reward", "mean_max_reward_ci95", "success_rate", "success_rate_ci95", "mean_length")}


if __name__ == "__main__":
    sys.exit(main())

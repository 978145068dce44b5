"""Collect a policy's successful episodes as demonstrations: what a student learns from its teacher.

    python -m training.collect --model runs/recipes/value-KEY/last --episodes 2048 --seed 10000000 --out chooser.zarr

Plays `--episodes` episodes (seeds seed..seed+episodes-1, clear of the held-out ranges) with the policy,
keeps the successful ones and writes them in the demonstrations' zarr layout, so that `training.train
--extra-data` (or a recipe's `collect` stage and a `train` stage's `extra_from`) learns from them.
Prints one JSON line: counts, seeds and scores of the collection.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pusht.spec import HELD_OUT_RANGES
from training.cli import HelpFormatter
from training.data import Replay, save_replay
from training.evaluate import evaluate_policy, load_model, report

__all__ = ["CollectConfig", "collect"]

EPISODES_STORE = "episodes.zarr"
"""the store a recipe's collect stage writes in its folder"""


@dataclass(frozen=True)
class CollectConfig:
    """What to play and where the successful episodes go."""

    model: str
    out: Path
    episodes: int = 1000
    seed: int = 10_000_000
    num_envs: int = 64
    max_steps: int = 300
    progress: bool = False


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: collect, keep the successes, write, print one JSON line."""
    parser = argparse.ArgumentParser(
        prog="python -m training.collect", description=__doc__.splitlines()[0], formatter_class=HelpFormatter
    )
    parser.add_argument("--model", required=True, help="an ONNX file or a checkpoint stem")
    parser.add_argument("--out", required=True, help="output zarr store (replaced if it exists)")
    parser.add_argument("--episodes", type=int, default=1000, help="episodes to play (seeds seed..seed+episodes-1)")
    parser.add_argument(
        "--seed", type=int, default=10_000_000, help=f"first episode seed, clear of the held-out seeds {_ranges()}"
    )
    parser.add_argument("--num-envs", type=int, default=64, help="environments run in lockstep")
    parser.add_argument("--max-steps", type=int, default=300, help="episode step limit: slower episodes are not kept")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    args = parser.parse_args(argv)
    cfg = CollectConfig(args.model, Path(args.out), args.episodes, args.seed, args.num_envs, args.max_steps, not args.no_progress)
    try:
        line = collect(cfg)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(line))
    return 0


def collect(cfg: CollectConfig) -> dict:
    """Play, keep the successful episodes, write them to `cfg.out`; returns the report line."""
    if cfg.episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {cfg.episodes}")
    last = cfg.seed + cfg.episodes - 1
    if any(cfg.seed < held.stop and last >= held.start for held in HELD_OUT_RANGES):
        raise ValueError(f"seeds {cfg.seed}..{last} overlap the held-out seeds {_ranges()}; choose another seed")
    policy = load_model(cfg.model)
    summary = evaluate_policy(
        policy,
        cfg.episodes,
        cfg.seed,
        num_envs=cfg.num_envs,
        max_steps=cfg.max_steps,
        progress=cfg.progress,
        record_trajectories=True,
    )
    kept = [t for t, episode in zip(summary.trajectories, summary.episodes) if episode.success]
    if not kept:
        raise ValueError(f"none of the {cfg.episodes} episodes succeeded; nothing written to {cfg.out}")
    replay = Replay(
        states=np.concatenate([t.states for t in kept]),
        actions=np.concatenate([t.actions for t in kept]),
        episode_ends=np.cumsum([len(t.states) for t in kept]).astype(np.int64),
    )
    attrs = {"source": f"the successful episodes of {cfg.model} (python -m training.collect)", "seeds": [cfg.seed, last]}
    cfg.out.parent.mkdir(parents=True, exist_ok=True)
    save_replay(cfg.out, replay, {**attrs, "max_steps": cfg.max_steps, "kept_seeds": [t.seed for t in kept]})
    return {
        "out": str(cfg.out),
        "kept_episodes": len(kept),
        "kept_frames": int(replay.episode_ends[-1]),
        **report(summary, model=str(cfg.model), kind=policy.kind, env="pusht"),
    }


def _ranges() -> str:
    return " and ".join(f"{r.start}..{r.stop - 1}" for r in HELD_OUT_RANGES)


if __name__ == "__main__":
    sys.exit(main())

"""Collect a policy's own successful episodes as extra demonstrations (filtered behavioral cloning).

    python -m training.collect --model models/flow --episodes 1000 --seed 300000 --out data/rollouts/flow-r1.zarr

Plays `--episodes` episodes (seeds seed..seed+episodes-1) with the policy, keeps the successful ones
(coverage above 0.95; the env ends an episode there) and writes them in the demonstrations' zarr
layout, so `training.train --extra-data` can learn from them. The recorded demonstrations stop short
of that (their best recorded coverage is 0.88): the kept episodes show the final alignment they lack. Episode seeds may not overlap the held-out seeds, so the held-out scores
stay a measure of unseen episodes. Prints one JSON line: counts, seeds and scores of the collection.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from pusht.rollout import SUCCESS_COVERAGE
from training.data import Replay, save_replay
from training.evaluate import evaluate_policy, load_actor, report

HELDOUT_SEEDS = range(200000, 200100)
"""Seeds of the shipped models' held-out evaluation (training.ship): never collected from."""


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: collect, filter, write, print one JSON line."""
    parser = argparse.ArgumentParser(prog="python -m training.collect", description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="an ONNX file or a checkpoint stem (models/flow)")
    parser.add_argument("--episodes", type=int, default=1000, help="episodes to play (seeds seed..seed+episodes-1)")
    parser.add_argument("--seed", type=int, default=300000, help="first episode seed; must keep the range clear of the held-out seeds 200000..200099")
    parser.add_argument("--num-envs", type=int, default=250, help="environments run in lockstep")
    parser.add_argument("--out", required=True, help="output zarr store (replaced if it exists)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    args = parser.parse_args(argv)
    try:
        line = collect(args.model, args.episodes, args.seed, args.num_envs, Path(args.out), not args.no_progress)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(line))
    return 0


def collect(model: str, episodes: int, seed: int, num_envs: int, out: Path, progress: bool = False) -> dict:
    """Play, keep the successful episodes and write them to `out`; returns the report line."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if seed < HELDOUT_SEEDS.stop and seed + episodes > HELDOUT_SEEDS.start:
        raise ValueError(
            f"seeds {seed}..{seed + episodes - 1} overlap the held-out seeds "
            f"{HELDOUT_SEEDS.start}..{HELDOUT_SEEDS.stop - 1}; choose another --seed"
        )
    actor, kind = load_actor(model)
    summary = evaluate_policy(
        actor, kind, episodes=episodes, seed=seed, num_envs=num_envs, progress=progress, record_trajectories=True
    )
    kept = [t for t, episode in zip(summary.trajectories, summary.episodes) if episode.success]
    if not kept:
        raise ValueError(f"none of the {episodes} episodes succeeded; nothing written to {out}")
    replay = Replay(
        states=np.concatenate([t.states for t in kept]),
        actions=np.concatenate([t.actions for t in kept]),
        episode_ends=np.cumsum([len(t.states) for t in kept]).astype(np.int64),
    )
    attrs = {
        "source": f"successful episodes (coverage > {SUCCESS_COVERAGE}) of {model} (python -m training.collect)",
        "model": str(model),
        "seeds": [seed, seed + episodes - 1],
        "kept_seeds": [t.seed for t in kept],
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    save_replay(out, replay, attrs)
    return {
        "out": str(out),
        "kept_episodes": len(kept),
        "kept_frames": int(replay.episode_ends[-1]),
        **report(summary, model=str(model), kind=kind, env="pusht"),
    }


if __name__ == "__main__":
    sys.exit(main())

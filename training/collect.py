"""Collect a policy's own successful episodes as extra demonstrations (filtered behavioral cloning).

    python -m training.collect --model models/flow --episodes 1000 --seed 300000 --out data/rollouts/flow-r1.zarr

Plays `--episodes` episodes (seeds seed..seed+episodes-1) with the policy, keeps the successful ones
(coverage above 0.95; the env ends an episode there) and writes them in the demonstrations' zarr
layout, so `training.train --extra-data` can learn from them: the recorded demonstrations stop short
of success (their best recorded coverage is 0.88). Measured in models/README.md: training on these
episodes did not raise success (end-padded windows did). Episode seeds may not overlap the held-out
seeds, so the held-out scores stay a measure of unseen episodes. Prints one JSON line: counts, seeds
and scores of the collection.

With `--retries K`, every failed episode that came within `--retry-coverage` of the goal is played
again K times from its first state there (the env restored to it, each retry with other noise), and
the first retry that succeeds is kept, behind the failed episode's steps up to that state: these
are the corrections near the goal that the policy usually misses.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from acting import Policy, rollout_act
from pusht.geometry import coverage
from pusht.rollout import Trajectory, default_env_factory, run_episodes
from pusht.spec import HELD_OUT_RANGES, SUCCESS_COVERAGE
from training.cli import HelpFormatter
from training.data import Replay, save_replay
from training.evaluate import evaluate_policy, load_model, report

RETRY_SEED_STRIDE = 10**9
"""Retries of a collection from --seed S play episode seeds from (S + 1) * 10**9 on (their noise only)."""


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: collect, filter, write, print one JSON line."""
    parser = argparse.ArgumentParser(prog="python -m training.collect", description=__doc__.splitlines()[0], formatter_class=HelpFormatter)
    parser.add_argument("--model", required=True, help="an ONNX file or a checkpoint stem (models/flow)")
    parser.add_argument("--episodes", type=int, default=1000, help="episodes to play (seeds seed..seed+episodes-1)")
    parser.add_argument("--seed", type=int, default=300000, help="first episode seed; the range must keep clear of the held-out seeds " + _ranges())
    parser.add_argument("--num-envs", type=int, default=250, help="environments run in lockstep")
    parser.add_argument("--noise-scale", type=float, default=1.0, help="flow: multiply the start noise by this (on top of the model's own noise_scale)")
    parser.add_argument("--retries", type=int, default=0, help="replay each near-miss this many times from its first state within --retry-coverage")
    parser.add_argument("--retry-coverage", type=float, default=0.85, help="coverage at which a failed episode's retries start")
    parser.add_argument("--max-steps", type=int, default=300, help="episode step limit (retries get what their episode had left)")
    parser.add_argument("--out", required=True, help="output zarr store (replaced if it exists)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    args = parser.parse_args(argv)
    try:
        line = collect(
            args.model, args.episodes, args.seed, args.num_envs, Path(args.out), not args.no_progress, args.noise_scale,
            args.retries, args.retry_coverage, args.max_steps,
        )
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(line))
    return 0


def collect(
    model: str,
    episodes: int,
    seed: int,
    num_envs: int,
    out: Path,
    progress: bool = False,
    noise_scale: float = 1.0,
    retries: int = 0,
    retry_coverage: float = 0.85,
    max_steps: int = 300,
) -> dict:
    """Play, keep the successful episodes (and successful retries of near misses) and write them to `out`; returns the report line."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if retries < 0:
        raise ValueError(f"retries must be >= 0, got {retries}")
    if not 0 < retry_coverage < SUCCESS_COVERAGE:
        raise ValueError(f"retry_coverage must be in (0, {SUCCESS_COVERAGE}), got {retry_coverage}")
    if any(seed < held.stop and seed + episodes > held.start for held in HELD_OUT_RANGES):
        raise ValueError(f"seeds {seed}..{seed + episodes - 1} overlap the held-out seeds {_ranges()}; choose another --seed")
    policy = load_model(model)
    summary = evaluate_policy(
        policy, episodes=episodes, seed=seed, num_envs=num_envs, progress=progress, record_trajectories=True,
        noise_scale=noise_scale, max_steps=max_steps,
    )
    kept = [t for t, episode in zip(summary.trajectories, summary.episodes) if episode.success]
    failed = [t for t, episode in zip(summary.trajectories, summary.episodes) if not episode.success]
    retried = _retry_near_misses(policy, failed, retries, retry_coverage, max_steps, seed, noise_scale) if retries else []
    kept += [trajectory for trajectory, _ in retried]
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
        "noise_scale": noise_scale,
        "kept_seeds": [t.seed for t in kept],
        "retries": retries,
        "retry_coverage": retry_coverage,
        "retried_episodes": len(retried),
        # the last `retried_episodes` episodes switch to their retry at these frames (the env restored there)
        "retry_start_frames": [t for _, t in retried],
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    save_replay(out, replay, attrs)
    return {
        "out": str(out),
        "kept_episodes": len(kept),
        "kept_from_retries": len(retried),
        "kept_frames": int(replay.episode_ends[-1]),
        **report(summary, model=str(model), kind=policy.kind, env="pusht"),
    }


def _retry_near_misses(
    policy: Policy, failed: list[Trajectory], retries: int, retry_coverage: float, max_steps: int, seed: int, noise_scale: float
) -> list[tuple[Trajectory, int]]:
    """For each failed episode that reached `retry_coverage`: its steps up to there plus the first of `retries` successful retries.

    Returns (trajectory, frame where the retry starts) pairs.
    """
    starts = []
    for trajectory in failed:
        covered = [coverage(*map(float, state[2:5])) >= retry_coverage for state in trajectory.states]
        if any(covered):
            starts.append((trajectory, covered.index(True)))
    if not starts:
        return []
    restore = [trajectory.states[t] for trajectory, t in starts]
    budgets = [max_steps - t for _, t in starts]
    # Retry r of start i plays episode seed base + i * retries + r: the env restores start i, and the
    # seed, far above any evaluation's, gives each retry of each collection its own noise.
    base = (seed + 1) * RETRY_SEED_STRIDE
    summary = run_episodes(
        rollout_act(policy, noise_scale),
        [base + k for k in range(len(starts) * retries)],
        num_envs=min(1000, len(starts) * retries),
        max_steps=max_steps,
        env_factory=lambda: _RestoringEnv(restore, budgets, retries, base),
        record_trajectories=True,
    )
    chosen: dict[int, Trajectory] = {}
    for trajectory, episode in zip(summary.trajectories, summary.episodes):
        start = (episode.seed - base) // retries
        if episode.success and start not in chosen:
            chosen[start] = trajectory
    out = []
    for start, retry in sorted(chosen.items()):
        original, t = starts[start]
        joined = Trajectory(
            seed=original.seed,
            states=np.concatenate([original.states[:t], retry.states]),
            actions=np.concatenate([original.actions[:t], retry.actions]),
        )
        out.append((joined, t))
    return out


class _RestoringEnv:
    """The Push-T env whose reset(seed=base + i * retries + r) restores start i, truncating after that start's step budget."""

    def __init__(self, starts: list[np.ndarray], budgets: list[int], retries: int, base: int) -> None:
        self.env = default_env_factory()
        self.starts, self.budgets, self.retries, self.base = starts, budgets, retries, base
        self._budget = 0
        self._steps = 0

    def reset(self, seed: int):
        start = (seed - self.base) // self.retries
        self._budget, self._steps = self.budgets[start], 0
        return self.env.reset(options={"restore_state": self.starts[start]})

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._steps += 1
        return obs, reward, terminated, truncated or self._steps >= self._budget, info

    def close(self) -> None:
        self.env.close()


def _ranges() -> str:
    """The held-out seed ranges, for messages."""
    return " and ".join(f"{r.start}..{r.stop - 1}" for r in HELD_OUT_RANGES)


if __name__ == "__main__":
    sys.exit(main())

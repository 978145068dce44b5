"""Evaluate a policy (ONNX file or checkpoint stem) with the shared batched rollout runner.

    python -m training.evaluate --model models/flow.onnx --episodes 100 --seed 200000

prints ONE JSON line with the scores, their 95% bootstrap intervals and the seeds; `--out FILE` adds
one JSON line per episode, `--gif FILE` the first episode. The policy is loaded and run by `acting`
(`acting.load_policy`, `acting.rollout_act`), as collection, shipping and the service do; training's
periodic evaluation calls `evaluate_policy` with its in-memory module. An ONNX file needs no torch
(the serve extra suffices); a checkpoint needs the train extra.

Randomness (`pusht/seeding.py`): episode i is reset with seed `seed + i`; its decision d asks with
request seed `decision_seed(seed + i, d)`, from which a flow policy's start noise is that row's
`row_noise`, the rule the service applies to a request's `seeds`. `Policy.act` pads batches to a
multiple of four rows, so an episode's result does not depend on `--num-envs`.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from acting import Policy, load_policy, read_card, rollout_act
from pusht.gif import FPS, annotated_frame
from pusht.gif import write_gif as _write_gif
from pusht.results import add_output_arguments
from pusht.rollout import RolloutSummary, card_id, check_output_path, episode_seeds, run_episodes, write_episode_records
from pusht.spec import HELD_OUT_SEED, TRAIN_EVAL_SEED
from training.cli import HelpFormatter

ENVS = ("pusht", "gym-pusht")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: evaluate a model and print one JSON line."""
    parser = _parser()
    args = parser.parse_args(argv)

    try:
        out = check_output_path("--out", args.out) if args.out is not None else None
        gif = check_output_path("--gif", args.gif) if args.gif is not None else None
        policy = load_model(args.model, num_steps=args.num_steps)
        summary = evaluate_policy(
            policy,
            episodes=args.episodes,
            seed=args.seed,
            num_envs=args.num_envs,
            env=args.env,
            action_horizon=args.action_horizon,
            max_steps=args.max_steps,
            noise_scale=args.noise_scale,
            fixed_noise=args.fixed_noise,
            progress=not args.no_progress,
            record_frames=gif is not None,
        )
        if out is not None:
            write_episode_records(out, summary, *model_identity(args.model))
            print(f"episodes: wrote {len(summary.episodes)} lines to {out}", file=sys.stderr)
        if gif is not None:
            write_gif(summary.frames, gif)
            print(f"gif: wrote {gif} ({len(summary.frames)} frames at {FPS} fps, real speed)", file=sys.stderr)
    except (ValueError, FileNotFoundError) as exc:  # acting's CardError is a ValueError
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(report(summary, model=args.model, kind=policy.kind, env=args.env)))
    return 0


def _parser() -> argparse.ArgumentParser:
    """The command line."""
    parser = argparse.ArgumentParser(
        prog="python -m training.evaluate",
        description="Roll out a policy in Push-T (batched, lockstep) and print one JSON line with its scores.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument(
        "--model",
        required=True,
        help="an ONNX file (models/flow.onnx, card NAME.json beside it) or a checkpoint stem (models/flow)",
    )
    parser.add_argument("--episodes", type=int, default=100, help="number of episodes (seeds seed..seed+episodes-1)")
    parser.add_argument(
        "--seed", type=int, default=HELD_OUT_SEED, help="first episode seed; each episode's noise comes from its own seed"
    )
    parser.add_argument(
        "--num-envs",
        type=int,
        default=100,
        help="environments run in lockstep (one policy call per decision for all); scores do not depend on it",
    )
    parser.add_argument("--env", choices=ENVS, default="pusht", help="our env (pusht) or the reference gym-pusht 0.1.8")
    parser.add_argument(
        "--action-horizon",
        type=int,
        default=None,
        help="actions of each chunk executed open loop (default: the card's horizon, the whole chunk)",
    )
    parser.add_argument(
        "--num-steps",
        type=int,
        default=None,
        help="flow: Euler steps of sampling (default: the card's count: 10, or a distilled flow's own; an ONNX file has its count fixed)",
    )
    parser.add_argument(
        "--noise-scale",
        type=float,
        default=1.0,
        help="flow: multiply the start noise by this (on top of the model's own noise_scale)",
    )
    parser.add_argument(
        "--fixed-noise",
        type=int,
        default=None,
        metavar="SEED",
        help="flow: every decision starts from the noise of this one seed (the policy as a deterministic map)",
    )
    _output_arguments(parser)
    return parser


def _output_arguments(parser: argparse.ArgumentParser) -> None:
    """The episode limit and what the run writes besides its JSON line."""
    parser.add_argument("--max-steps", type=int, default=300, help="episode step limit")
    add_output_arguments(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def load_model(model: str | Path, num_steps: int | None = None) -> Policy:
    """`acting.load_policy(model, num_steps=...)`, naming a missing ONNX file itself rather than its card."""
    path = Path(model)
    if path.suffix == ".onnx" and not path.exists() and not path.is_symlink():
        raise FileNotFoundError(f"no ONNX file {path}")
    return load_policy(path, num_steps=num_steps)


@dataclass(frozen=True)
class EvalSettings:
    """How `evaluate_policy` plays: `num_envs=None`: all episodes at once; `action_horizon=None`: the policy's whole chunk;
    flow noise times `noise_scale`, each row's from its own seed or every row's from `fixed_noise`; frames captioned."""

    num_envs: int | None = None
    env: str = "pusht"
    action_horizon: int | None = None
    max_steps: int = 300
    noise_scale: float = 1.0
    progress: bool | Callable[[int, int], None] = False
    record_frames: bool = False
    record_trajectories: bool = False
    fixed_noise: int | None = None


def evaluate_policy(
    policy: Policy | Any, episodes: int = 100, seed: int = TRAIN_EVAL_SEED, settings: EvalSettings | None = None, **changes: Any
) -> RolloutSummary:
    """Roll out `policy` (an `acting.Policy`, or a torch ActingPolicy module) on seeds seed..seed+episodes-1.

    `settings` (default `EvalSettings()`) with `changes`, its fields by name, applied. A flow samples in the policy's own
    step count (`load_policy(..., num_steps=)`; a module's `num_steps`); row noise from `row_noise`.
    """
    s = replace(settings or EvalSettings(), **changes)
    action_horizon, progress = s.action_horizon, s.progress
    policy = as_policy(policy)
    if action_horizon is None:
        action_horizon = policy.horizon
    elif isinstance(action_horizon, int) and action_horizon > policy.horizon:
        raise ValueError(f"action_horizon {action_horizon} exceeds the policy's chunk of {policy.horizon} actions")
    act = rollout_act(policy, s.noise_scale, s.fixed_noise)
    seeds = episode_seeds(seed, episodes)
    if progress is True:
        progress = _tqdm_progress(len(seeds))
    return run_episodes(
        act,
        seeds,
        num_envs=s.num_envs or len(seeds),
        max_steps=s.max_steps,
        action_horizon=action_horizon,
        env_factory=env_factory(s.env, s.max_steps),
        progress=progress,
        record_frames=annotated_frame if s.record_frames else False,
        record_trajectories=s.record_trajectories,
        prev_states=policy.takes_prev_state,
    )


def as_policy(policy: Policy | Any) -> Policy:
    """`policy` itself if an `acting.Policy`, a torch ActingPolicy module wrapped (`TorchPolicy.from_module`), else ValueError."""
    if isinstance(policy, Policy):
        return policy
    if callable(policy) and hasattr(policy, "policy") and hasattr(policy, "num_steps"):
        from acting.torch_backend import TorchPolicy

        return TorchPolicy.from_module(policy)
    raise ValueError(f"policy must be an acting.Policy or a torch ActingPolicy, got {type(policy).__name__}")


def model_identity(model: str | Path) -> tuple[str, str]:
    """(policy name, card id) of an ONNX file or checkpoint stem, for per-episode records."""
    card = read_card(model).data
    return card["name"], card_id(card["name"], card.get("git_commit"), card.get("steps"))


def report(summary: RolloutSummary, model: str, kind: str, env: str) -> dict[str, Any]:
    """The one-line JSON report of an evaluation."""
    return {"model": str(model), "kind": kind, "env": env, **summary.scores()}


def env_factory(env: str, max_steps: int = 300) -> Callable[[], Any]:
    """A factory of state-observation Push-T envs: ours (`pusht`, truncating after `max_steps`) or the reference `gym-pusht`."""
    if env == "pusht":
        from functools import partial

        from pusht.rollout import default_env_factory

        return partial(default_env_factory, max_steps)
    if env == "gym-pusht":
        import importlib

        import gymnasium

        importlib.import_module("gym_pusht")  # registers gym_pusht/PushT-v0

        # unwrapped: the runner enforces max_steps itself
        return lambda: gymnasium.make("gym_pusht/PushT-v0", obs_type="state", render_mode="rgb_array").unwrapped
    raise ValueError(f"unknown env {env!r}; expected one of {ENVS}")


def write_gif(frames: list[np.ndarray], path: str | Path) -> None:
    """Write frames as an animated GIF at the control rate (real speed)."""
    _write_gif(frames, path)


def _tqdm_progress(total: int) -> Callable[[int, int], None]:
    from tqdm import tqdm

    bar = tqdm(total=total, desc="episodes", unit="ep", file=sys.stderr, leave=False)

    def update(done: int, total: int) -> None:
        bar.n = done
        bar.refresh()
        if done == total:
            bar.close()

    return update


if __name__ == "__main__":
    sys.exit(main())

"""Evaluate a policy (ONNX file or checkpoint stem) with the shared batched rollout runner.

    python -m training.evaluate --model models/flow.onnx --episodes 100 --seed 200000

prints ONE JSON line with the scores, their 95% bootstrap intervals and the seeds; `--out FILE` adds
one JSON line per episode, `--gif FILE` the first episode. Training's periodic evaluation calls
`evaluate_policy` too, so the act-function logic lives only here. An ONNX file needs no torch (the
serve extra suffices); a checkpoint needs the train extra.

Randomness (`pusht/seeding.py`): episode i is reset with seed `seed + i`; its decision d asks with
request seed `decision_seed(seed + i, d)`, from which a flow policy's start noise is that row's
`row_noise`, the rule the service applies to a request's `seeds`. Batches are padded to a multiple
of four rows, so an episode's result does not depend on `--num-envs`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pusht.gif import FPS, annotated_frame, write_gif as _write_gif
from pusht.rollout import (
    ActFn,
    RolloutSummary,
    card_id,
    check_output_path,
    episode_seeds,
    pad_rows,
    row_noise,
    run_episodes,
    write_episode_records,
)
from training.config import HelpFormatter

ENVS = ("pusht", "gym-pusht")
KINDS = ("mse", "flow")
CHUNK_HORIZON = 12
ACTION_DIM = 2


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: evaluate a model and print one JSON line."""
    parser = argparse.ArgumentParser(
        prog="python -m training.evaluate",
        description="Roll out a policy in Push-T (batched, lockstep) and print one JSON line with its scores.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--model", required=True, help="an ONNX file (models/flow.onnx, card NAME.json beside it) or a checkpoint stem (models/flow)")
    parser.add_argument("--episodes", type=int, default=100, help="number of episodes (seeds seed..seed+episodes-1)")
    parser.add_argument("--seed", type=int, default=200000, help="first episode seed; each episode's noise comes from its own seed")
    parser.add_argument("--num-envs", type=int, default=100, help="environments run in lockstep (one policy call per decision for all); scores do not depend on it")
    parser.add_argument("--env", choices=ENVS, default="pusht", help="our env (pusht) or the reference gym-pusht 0.1.8")
    parser.add_argument("--action-horizon", type=int, default=12, help="actions of each 12-action chunk executed open loop")
    parser.add_argument("--num-steps", type=int, default=10, help="flow: Euler steps of sampling (ONNX files have theirs fixed)")
    parser.add_argument("--noise-scale", type=float, default=1.0, help="flow: multiply the start noise by this (on top of the model's own noise_scale)")
    parser.add_argument("--max-steps", type=int, default=300, help="episode step limit")
    parser.add_argument("--out", default=None, metavar="FILE", help="write one JSON line per episode (seed, max_reward, success, length, policy, card) to FILE")
    parser.add_argument("--gif", default=None, metavar="FILE", help="write the first episode as an animated GIF (real speed, step/coverage/success caption) to FILE")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    args = parser.parse_args(argv)

    try:
        out = check_output_path("--out", args.out) if args.out is not None else None
        gif = check_output_path("--gif", args.gif) if args.gif is not None else None
        actor, kind = load_actor(args.model, num_steps=args.num_steps)
        summary = evaluate_policy(
            actor,
            kind,
            episodes=args.episodes,
            seed=args.seed,
            num_envs=args.num_envs,
            env=args.env,
            action_horizon=args.action_horizon,
            max_steps=args.max_steps,
            noise_scale=args.noise_scale,
            progress=not args.no_progress,
            record_frames=gif is not None,
        )
        if out is not None:
            write_episode_records(out, summary, *model_identity(args.model))
            print(f"episodes: wrote {len(summary.episodes)} lines to {out}", file=sys.stderr)
        if gif is not None:
            write_gif(summary.frames, gif)
            print(f"gif: wrote {gif} ({len(summary.frames)} frames at {FPS} fps, real speed)", file=sys.stderr)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(report(summary, model=args.model, kind=kind, env=args.env)))
    return 0


Actor = Callable[[np.ndarray, "np.ndarray | None"], np.ndarray]
"""(states float32 [B, 5] env units, noise float32 [B, 12, 2] or None) -> actions float32 [B, 12, 2] env units."""


def evaluate_policy(
    actor: Actor | Any,
    kind: str,
    episodes: int = 100,
    seed: int = 100000,
    num_envs: int | None = None,
    env: str = "pusht",
    action_horizon: int = 12,
    max_steps: int = 300,
    num_steps: int = 10,
    noise_scale: float = 1.0,
    progress: bool | Callable[[int, int], None] = False,
    record_frames: bool = False,
    record_trajectories: bool = False,
) -> RolloutSummary:
    """Roll out `actor` (an Actor or a torch ActingPolicy) on seeds seed..seed+episodes-1; `num_envs=None`: all at once.

    Each row's flow noise comes from its own seed (`row_noise`) times `noise_scale`; recorded frames are captioned.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown policy kind {kind!r}; expected one of {KINDS}")
    if not callable(actor):
        raise ValueError(f"actor must be callable, got {type(actor).__name__}")
    if not _is_numpy_actor(actor):
        actor = torch_actor(actor, num_steps=num_steps)
    act = make_act_fn(actor, kind, noise_scale)
    seeds = episode_seeds(seed, episodes)
    if progress is True:
        progress = _tqdm_progress(len(seeds))
    return run_episodes(
        act,
        seeds,
        num_envs=num_envs or len(seeds),
        max_steps=max_steps,
        action_horizon=action_horizon,
        env_factory=env_factory(env),
        progress=progress,
        record_frames=annotated_frame if record_frames else False,
        record_trajectories=record_trajectories,
    )


def make_act_fn(actor: Actor, kind: str, noise_scale: float = 1.0) -> ActFn:
    """The runner's act function: row i's flow noise comes from seeds[i], as the service does; batches padded to 4 rows."""
    if not 0 <= noise_scale <= 10:
        raise ValueError(f"noise_scale must be in [0, 10], got {noise_scale}")
    if kind not in KINDS:
        raise ValueError(f"unknown policy kind {kind!r}; expected one of {KINDS}")

    def act(states: np.ndarray, seeds: list[int]) -> np.ndarray:
        noise = None
        if kind == "flow":
            noise = row_noise(seeds, CHUNK_HORIZON, ACTION_DIM)
            noise = pad_rows(noise if noise_scale == 1.0 else noise * np.float32(noise_scale))
        # padding: a row's rounding then does not depend on its batch (pusht/seeding.py)
        return actor(pad_rows(states), noise)[: len(states)]

    return act


def load_actor(model: str | Path, num_steps: int = 10) -> tuple[Actor, str]:
    """An Actor and its kind from an ONNX file (`.onnx`, card beside it) or a checkpoint stem (needs torch)."""
    path = Path(model)
    if path.suffix == ".onnx":
        return onnx_actor(path, num_steps=num_steps)
    read_card(path)  # a missing or broken card is named before torch is needed
    try:
        from training.checkpoint import load_acting_policy
    except ModuleNotFoundError as exc:
        if exc.name not in ("torch", "safetensors"):
            raise
        raise ValueError(
            f"{path} is a torch checkpoint and {exc.name} is not installed: install the train extra "
            f"(pip install -e '.[train]'), or evaluate its ONNX export (--model {path}.onnx), which needs only the serve extra"
        ) from None
    acting = load_acting_policy(path, num_steps=num_steps)  # validates the card and the weights
    return torch_actor(acting, num_steps=num_steps), acting.kind


def read_card(stem: str | Path) -> dict[str, Any]:
    """The card STEM.json as a dict with a known `kind`, read without torch."""
    path = Path(stem).with_suffix(".json")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint card not found")
    try:
        card = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: card is not valid JSON: {exc}") from None
    if not isinstance(card, dict):
        raise ValueError(f"{path}: card must be a JSON object, got {type(card).__name__}")
    if card.get("kind") not in KINDS:
        raise ValueError(f"{path}: card kind must be one of {KINDS}, got {card.get('kind')!r}")
    return card


def model_identity(model: str | Path) -> tuple[str, str]:
    """(policy name, card id) of an ONNX file or checkpoint stem, for per-episode records."""
    stem = Path(model).with_suffix("") if Path(model).suffix == ".onnx" else Path(model)
    card = read_card(stem)
    name = card.get("name", stem.name)
    return name, card_id(name, card.get("git_commit"), card.get("steps"))


def onnx_actor(path: Path, num_steps: int = 10) -> tuple[Actor, str]:
    """An Actor running an exported policy with ONNX Runtime; the kind comes from the card NAME.json."""
    if not path.exists():
        raise FileNotFoundError(f"no ONNX file {path}")
    card = read_card(path.with_suffix(""))  # the card NAME.json beside NAME.onnx says the kind
    kind = card["kind"]
    exported_steps = (card.get("onnx") or {}).get("num_steps")
    if kind == "flow" and exported_steps is not None and exported_steps != num_steps:
        raise ValueError(f"{path} unrolls {exported_steps} flow steps; --num-steps {num_steps} needs a torch checkpoint")
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    try:
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own unrelated types for a bad file
        raise ValueError(f"{path}: not a loadable ONNX model: {exc}") from None
    input_names = {i.name for i in session.get_inputs()}

    def actor(states: np.ndarray, noise: np.ndarray | None) -> np.ndarray:
        feeds = {"state": np.ascontiguousarray(states, dtype=np.float32)}
        if "noise" in input_names:
            if noise is None:
                raise ValueError(f"{path} expects a noise input but none was given")
            feeds["noise"] = np.ascontiguousarray(noise, dtype=np.float32)
        return session.run(["actions"], feeds)[0]

    actor._numpy_actor = True  # type: ignore[attr-defined]
    return actor, kind


def torch_actor(acting: Any, num_steps: int = 10) -> Actor:
    """An Actor around a torch ActingPolicy (env units in, clipped env-unit actions out), run without grad."""
    import inspect

    import torch

    takes_num_steps = "num_steps" in inspect.signature(acting.forward).parameters

    def actor(states: np.ndarray, noise: np.ndarray | None) -> np.ndarray:
        was_training = acting.training
        acting.eval()
        try:
            with torch.inference_mode():
                args = [torch.from_numpy(np.ascontiguousarray(states, dtype=np.float32))]
                kwargs = {}
                if noise is not None:
                    args.append(torch.from_numpy(np.ascontiguousarray(noise, dtype=np.float32)))
                    if takes_num_steps:
                        kwargs["num_steps"] = num_steps
                out = acting(*args, **kwargs)
        finally:
            acting.train(was_training)
        return out.numpy()

    actor._numpy_actor = True  # type: ignore[attr-defined]
    return actor


def report(summary: RolloutSummary, model: str, kind: str, env: str) -> dict[str, Any]:
    """The one-line JSON report of an evaluation."""
    return {"model": str(model), "kind": kind, "env": env, **summary.scores()}


def env_factory(env: str) -> Callable[[], Any]:
    """A factory of state-observation Push-T envs: ours (`pusht`) or the reference `gym-pusht`."""
    if env == "pusht":
        from pusht.rollout import default_env_factory

        return default_env_factory
    if env == "gym-pusht":
        import gymnasium
        import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)

        # unwrapped: the runner enforces the 300-step limit itself
        return lambda: gymnasium.make("gym_pusht/PushT-v0", obs_type="state", render_mode="rgb_array").unwrapped
    raise ValueError(f"unknown env {env!r}; expected one of {ENVS}")


def write_gif(frames: list[np.ndarray], path: str | Path) -> None:
    """Write frames as an animated GIF at the control rate (real speed)."""
    _write_gif(frames, path)


def _is_numpy_actor(actor: Any) -> bool:
    return getattr(actor, "_numpy_actor", False)


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

"""Evaluate a policy (ONNX file or checkpoint stem) with the shared batched rollout runner.

    python -m training.evaluate --model models/flow.onnx --episodes 100 --seed 200000

prints ONE JSON line with the scores, their 95% bootstrap intervals and the seeds. Training's
periodic evaluation calls `evaluate_policy` too, so the act-function logic lives only here.

Randomness: episode i is reset with seed `seed + i`; decision step d of the run asks for a chunk
with request seed `pusht.rollout.decision_seed(seed, d)`, from which a flow policy's initial noise is
`pusht.rollout.chunk_noise(request_seed, B)`, the same rule the service applies to a request's seed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pusht.rollout import ActFn, RolloutSummary, chunk_noise, episode_seeds, run_episodes

ENVS = ("pusht", "gym-pusht")
KINDS = ("mse", "flow")
CHUNK_HORIZON = 12
ACTION_DIM = 2
GIF_SIZE = 256
GIF_FPS = 10


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: evaluate a model and print one JSON line."""
    parser = argparse.ArgumentParser(
        prog="python -m training.evaluate",
        description="Roll out a policy in Push-T (batched, lockstep) and print one JSON line with its scores.",
    )
    parser.add_argument("--model", required=True, help="an ONNX file (models/flow.onnx, card NAME.json beside it) or a checkpoint stem (models/flow)")
    parser.add_argument("--episodes", type=int, default=100, help="number of episodes (seeds seed..seed+episodes-1)")
    parser.add_argument("--seed", type=int, default=200000, help="first episode seed; also seeds the per-decision request seeds")
    parser.add_argument("--num-envs", type=int, default=100, help="environments run in lockstep (one policy call per decision for all)")
    parser.add_argument("--env", choices=ENVS, default="pusht", help="our env (pusht) or the reference gym-pusht 0.1.8")
    parser.add_argument("--action-horizon", type=int, default=12, help="actions of each 12-action chunk executed open loop")
    parser.add_argument("--num-steps", type=int, default=10, help="flow: Euler steps of sampling (ONNX files have theirs fixed)")
    parser.add_argument("--noise-scale", type=float, default=1.0, help="flow: multiply the start noise by this (on top of the model's own noise_scale)")
    parser.add_argument("--max-steps", type=int, default=300, help="episode step limit")
    parser.add_argument("--gif", default=None, help="write the first episode as an animated GIF to this path")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    args = parser.parse_args(argv)

    try:
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
            record_frames=args.gif is not None,
        )
        if args.gif is not None:
            write_gif(summary.frames, args.gif)
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
    """Roll out `actor` on episode seeds seed..seed+episodes-1; `actor` is an Actor or a torch ActingPolicy.

    `num_envs=None` runs all episodes at once. Flow noise comes from `chunk_noise(request_seed, B)`,
    times `noise_scale`.
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
        seed=seed,
        env_factory=env_factory(env),
        progress=progress,
        record_frames=_shrink_frame if record_frames else False,
        record_trajectories=record_trajectories,
    )


def make_act_fn(actor: Actor, kind: str, noise_scale: float = 1.0) -> ActFn:
    """The runner's act function: flow draws its initial noise from the request seed, as the service does."""
    if not 0 <= noise_scale <= 10:
        raise ValueError(f"noise_scale must be in [0, 10], got {noise_scale}")
    if kind == "flow":
        def act(states: np.ndarray, request_seed: int) -> np.ndarray:
            noise = chunk_noise(request_seed, len(states), CHUNK_HORIZON, ACTION_DIM)
            return actor(states, noise if noise_scale == 1.0 else noise * np.float32(noise_scale))
    elif kind == "mse":
        def act(states: np.ndarray, request_seed: int) -> np.ndarray:
            return actor(states, None)
    else:
        raise ValueError(f"unknown policy kind {kind!r}; expected one of {KINDS}")
    return act


def load_actor(model: str | Path, num_steps: int = 10) -> tuple[Actor, str]:
    """An Actor and its kind from an ONNX file (`.onnx`, card beside it) or a checkpoint stem."""
    path = Path(model)
    if path.suffix == ".onnx":
        return onnx_actor(path, num_steps=num_steps)
    from training.checkpoint import load_acting_policy

    acting = load_acting_policy(path, num_steps=num_steps)  # validates the card and the weights
    return torch_actor(acting, num_steps=num_steps), acting.kind


def onnx_actor(path: Path, num_steps: int = 10) -> tuple[Actor, str]:
    """An Actor running an exported policy with ONNX Runtime; the kind comes from the card NAME.json."""
    if not path.exists():
        raise FileNotFoundError(f"no ONNX file {path}")
    from training.checkpoint import load_card

    card = load_card(path.with_suffix(""))  # the card NAME.json beside NAME.onnx says the kind
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
    """Write frames as an animated GIF at the control rate."""
    if not frames:
        raise ValueError("no frames recorded to write a GIF")
    import imageio.v2 as imageio

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(str(path), frames, duration=1000 / GIF_FPS, loop=0)


def _shrink_frame(frame: np.ndarray) -> np.ndarray:
    # 300 full-size frames would take ~400 MB; a GIF needs far less.
    from PIL import Image

    return np.asarray(Image.fromarray(np.asarray(frame, dtype=np.uint8)).resize((GIF_SIZE, GIF_SIZE), Image.BILINEAR))


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

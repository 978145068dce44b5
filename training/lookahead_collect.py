"""Collect episodes from a lookahead teacher: at each decision the flow's best of K chunks, each simulated one chunk ahead.

    python -m training.lookahead_collect --model records/flow-outcome16-stretch/last --episodes 500 --seed 3000000 --out data/rollouts/lookahead-16.zarr

The teacher is the oracle of ../shared/notes/policy-quality.md (16 candidates lift success from 60 % to
82 %): it simulates, so it exists at training time only. Its episodes (all of them, or only the
successful ones with --successful-only) are written in the demonstrations' zarr layout, for
`training.train --extra-data` to distil the teacher's finishes into a policy that acts from its
inputs alone. Seeds must avoid every evaluation and held-out range.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from acting import load_policy
from pusht.env import MAX_EPISODE_STEPS, PushTEnv
from pusht.spec import RESERVED_SEEDS, SUCCESS_COVERAGE
from training.config import HelpFormatter
from training.data import Replay, save_replay
from training.finetune_config import CHOOSER


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: collect, write the zarr, print one JSON line."""
    parser = argparse.ArgumentParser(prog="python -m training.lookahead_collect", description=__doc__.splitlines()[0], formatter_class=HelpFormatter)
    parser.add_argument("--model", default=CHOOSER, help="flow checkpoint stem (or its ONNX file; default: the outcome chooser)")
    parser.add_argument("--episodes", type=int, default=500, help="episodes to play")
    parser.add_argument("--seed", type=int, default=3_000_000, help=f"first episode seed (outside the evaluation ranges {RESERVED_SEEDS.start}..{RESERVED_SEEDS.stop - 1})")
    parser.add_argument("--candidates", type=int, default=16, help="chunks simulated per decision")
    parser.add_argument("--num-envs", type=int, default=32, help="episodes played side by side")
    parser.add_argument("--successful-only", action="store_true", help="write only the episodes that succeeded")
    parser.add_argument("--out", required=True, help="output zarr store (replaced if it exists)")
    args = parser.parse_args(argv)
    if args.seed < RESERVED_SEEDS.stop and args.seed + args.episodes > RESERVED_SEEDS.start:
        parser.error(f"seeds {args.seed}..{args.seed + args.episodes - 1} overlap the evaluation ranges "
                     f"{RESERVED_SEEDS.start}..{RESERVED_SEEDS.stop - 1}")
    torch.set_num_threads(1)
    try:
        report = collect(args.model, args.episodes, args.seed, args.candidates, args.num_envs, Path(args.out), args.successful_only)
    except (ValueError, FileNotFoundError) as exc:  # acting's CardError is a ValueError
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(report))
    return 0


def collect(model: str, episodes: int, seed: int, candidates: int, num_envs: int, out: Path, successful_only: bool) -> dict:
    """Play the lookahead teacher on seeds seed..seed+episodes-1 and write its episodes to `out`; returns the report."""
    from tqdm import tqdm

    policy = load_policy(model, threads=1)
    if policy.kind != "flow":
        raise ValueError(f"{model}: the lookahead teacher samples candidate chunks from a flow, not a {policy.kind} policy")
    if policy.takes_prev_state:
        raise ValueError(f"{model}: the policy takes prev_state, which the lookahead teacher does not carry")
    generator = torch.Generator().manual_seed(seed)
    scratch = PushTEnv(render_mode=None)
    scratch.reset(seed=0)
    kept, results, next_seed = [], [], seed
    envs: list[dict] = []
    bar = tqdm(total=episodes, desc="episodes", file=sys.stderr)
    while len(results) < episodes:
        while len(envs) < num_envs and next_seed < seed + episodes:
            env = PushTEnv(render_mode=None)
            obs, _ = env.reset(seed=next_seed)
            envs.append({"env": env, "seed": next_seed, "obs": obs, "states": [], "actions": [], "max": 0.0, "steps": 0})
            next_seed += 1
        states = np.stack([e["obs"] for e in envs]).astype(np.float32)
        # the candidates' noise from one torch stream, as before acting existed: the same seed gives the same teacher
        noise = torch.randn((len(envs) * candidates, policy.horizon, policy.action_dim), generator=generator).numpy()
        chunks = policy.act(np.repeat(states, candidates, axis=0), noise=noise)
        chunks = chunks.reshape(len(envs), candidates, policy.horizon, policy.action_dim)
        for e, options in zip(envs, chunks):
            chunk = options[_best(scratch, e, options)]
            for action in chunk:
                e["states"].append(e["obs"].astype(np.float32))
                e["actions"].append(action)
                e["obs"], reward, terminated, _, info = e["env"].step(action)
                e["steps"] += 1
                e["max"] = max(e["max"], reward)
                if terminated or e["steps"] >= MAX_EPISODE_STEPS:
                    e["done"], e["success"] = True, info["coverage"] > SUCCESS_COVERAGE
                    break
        for e in [e for e in envs if e.get("done")]:
            results.append((e["max"], e["success"]))
            if e["success"] or not successful_only:
                kept.append(e)
            envs.remove(e)
            bar.update(1)
    bar.close()
    replay = Replay(states=np.concatenate([np.stack(e["states"]) for e in kept]), actions=np.concatenate([np.stack(e["actions"]) for e in kept]),
                    episode_ends=np.cumsum([len(e["states"]) for e in kept]).astype(np.int64))
    attrs = {"source": f"lookahead teacher: best of {candidates} chunks of {model}, each simulated one chunk ahead (python -m training.lookahead_collect)",
             "seeds": [seed, seed + episodes - 1], "kept_seeds": [e["seed"] for e in kept]}
    out.parent.mkdir(parents=True, exist_ok=True)
    save_replay(out, replay, attrs)
    rewards = np.array([r for r, _ in results])
    return {"out": str(out), "episodes": len(results), "kept_episodes": len(kept), "kept_frames": int(replay.episode_ends[-1]),
            "teacher_mean_max_reward": round(float(rewards.mean()), 4), "teacher_success_rate": round(float(np.mean([s for _, s in results])), 4)}


def _best(scratch: PushTEnv, episode: dict, options: np.ndarray) -> int:
    """The option whose chunk, simulated from the episode's present state, ends with the highest reward (success first)."""
    snapshot = episode["env"].physics_snapshot()
    scores = []
    for chunk in options:
        scratch.restore_physics(snapshot)
        best, steps = 0.0, episode["steps"]
        for action in chunk:
            _, reward, terminated, _, _ = scratch.step(action)
            steps += 1
            best = reward
            if terminated:
                best = 2.0  # success ends the episode: nothing beats it
                break
            if steps >= MAX_EPISODE_STEPS:
                break
        scores.append(best)
    return int(np.argmax(scores))


if __name__ == "__main__":
    sys.exit(main())

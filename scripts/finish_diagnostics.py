"""Diagnostics of where a flow's headroom lies, with simulating oracles that exist at training time only.

    python scripts/finish_diagnostics.py smoothness --states 300
    python scripts/finish_diagnostics.py local --episodes 200 --where gate
    python scripts/finish_diagnostics.py best-of --episodes 200 --candidates 16 --codebook

`smoothness` asks whether a chunk's outcome is a smooth function of the chunk: from states near the goal
(coverage >= 0.85) it runs one flow chunk, then the same chunk shifted by 0.1, 0.5 and 2 px, and
reports how the coverage changes agree. `local` plays the flow and, at each decision (`--where all`) or
only inside the goal gate (`--where gate`: the block within about coverage 0.7 of the goal), improves
its chunk by a cross-entropy search over a smooth correction (4 knots, linear between them), each
candidate simulated one chunk ahead: the best any local residual on the chunk could do with a one-chunk
criterion. `best-of` plays the flow taking the best of K start noises by the same criterion, either
fresh noises at each decision or one fixed codebook of K noises (what a learned selector over K
discrete starts could at best reach). Criterion everywhere: the reward after the chunk, success first.
Tuning seeds only (default 300000); each prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import torch

from pusht.env import MAX_EPISODE_STEPS, PushTEnv
from pusht.geometry import GOAL_POSE, coverage
from pusht.seeding import decision_seed, row_noise
from pusht.spec import SUCCESS_COVERAGE
from training.checkpoint import load_checkpoint
from training.cli import HelpFormatter
from training.features import tee_keypoints
from training.finetune_config import CHOOSER

KEYPOINT_SCALE = 128.0  # training.features scales arena pixels by 1/128

HORIZON = 12
KNOTS = 4
CRITERIA = ("reward", "keypoints")
# The goal gate of `local`: (position error / 12 px)^2 + 2 (1 - cos angle error) / 0.15^2 < 1, about coverage >= 0.7.
GATE_PX, GATE_RAD = 12.0, 0.15


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: run one diagnostic, print one JSON line."""
    parser = argparse.ArgumentParser(prog="python scripts/finish_diagnostics.py", description=__doc__.splitlines()[0], formatter_class=HelpFormatter)
    parser.add_argument("--model", default=CHOOSER, help="flow checkpoint stem (default: the outcome chooser)")
    sub = parser.add_subparsers(dest="mode", required=True)
    smooth = sub.add_parser("smoothness", help="agreement of one chunk's outcome with the same chunk shifted by a few px", formatter_class=HelpFormatter)
    smooth.add_argument("--states", type=int, default=300, help="near-goal states to test")
    smooth.add_argument("--seed", type=int, default=12_000_000, help="first seed of the episodes the states come from (training range)")
    local = sub.add_parser("local", help="the flow with each chunk improved by a simulated local search", formatter_class=HelpFormatter)
    local.add_argument("--where", choices=("gate", "all"), default="gate", help="search inside the goal gate only, or at every decision")
    local.add_argument("--population", type=int, default=16, help="candidates per search iteration")
    local.add_argument("--iterations", type=int, default=3, help="search iterations")
    local.add_argument("--sigma", type=float, default=3.0, help="initial std (px) of the knots' correction")
    best = sub.add_parser("best-of", help="the flow choosing the best of K start noises, each simulated one chunk ahead", formatter_class=HelpFormatter)
    best.add_argument("--candidates", type=int, default=16, help="start noises per decision")
    best.add_argument("--codebook", action="store_true", help="one fixed set of K noises for every decision (default: fresh noises each time)")
    best.add_argument("--criterion", choices=CRITERIA, default="reward",
                      help="reward: the env's reward after the chunk; keypoints: minus the mean squared distance of the tee's corners to the goal's")
    for p in (local, best):
        p.add_argument("--episodes", type=int, default=200, help="episodes (seeds seed..seed+episodes-1)")
        p.add_argument("--seed", type=int, default=300000, help="first episode seed (tuning seeds, never held-out ones)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    flow, _ = load_checkpoint(args.model)
    rng = np.random.default_rng(0)
    started = time.time()
    if args.mode == "smoothness":
        result = smoothness(flow, args.states, args.seed, rng)
    elif args.mode == "local":
        result = play(flow, args.episodes, args.seed, LocalSearch(args.where, args.population, args.iterations, args.sigma, rng))
    else:
        result = play(flow, args.episodes, args.seed, BestOf(flow, args.candidates, args.codebook, rng, args.criterion))
    print(json.dumps({"mode": args.mode, **{k: v for k, v in vars(args).items() if k != "mode"}, **result,
                      "wall_time_s": round(time.time() - started, 1)}))
    return 0


def flow_chunks(flow, states: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Env-unit chunks [B, H, 2] of the flow from states [B, 5] and standard-normal noise [B, H, 2], as served (10 steps)."""
    with torch.no_grad():
        x0 = flow.noise_scale * torch.as_tensor(noise, dtype=torch.float32)
        return flow.act_from_start(torch.as_tensor(states, dtype=torch.float32), x0, 10).numpy()


def in_gate(state: np.ndarray) -> bool:
    """Whether the block is within the goal gate (about coverage >= 0.7)."""
    gx, gy, ga = GOAL_POSE
    return ((state[2] - gx) ** 2 + (state[3] - gy) ** 2) / GATE_PX**2 + 2 * (1 - np.cos(state[4] - ga)) / GATE_RAD**2 < 1


def goal_keypoint_distance(state: np.ndarray) -> float:
    """Mean squared distance (px^2) of the tee's corners at the state's block pose to the goal's corners."""
    poses = torch.tensor([list(state[2:5]), list(GOAL_POSE)], dtype=torch.float64)
    corners = tee_keypoints(poses).reshape(2, -1, 2)
    return float(((corners[0] - corners[1]) ** 2).sum(-1).mean()) * KEYPOINT_SCALE**2


class Lookahead:
    """Scores chunks by simulating them from a physics snapshot in a scratch env: the criterion after the chunk, 2 on success."""

    def __init__(self, criterion: str = "reward") -> None:
        self.scratch = PushTEnv(obs_type="state", render_mode=None)
        self.scratch.reset(seed=0)
        self.criterion = criterion

    def score(self, snapshot: tuple, chunk: np.ndarray, elapsed: int) -> float:
        """The criterion of `chunk` played from `snapshot` at step `elapsed`."""
        self.scratch.restore_physics(snapshot)
        reward, state = 0.0, None
        for action in chunk:
            state, reward, terminated, _, _ = self.scratch.step(action)
            elapsed += 1
            if terminated:
                return 2.0
            if elapsed >= MAX_EPISODE_STEPS:
                break
        return reward if self.criterion == "reward" else -goal_keypoint_distance(state)


class LocalSearch(Lookahead):
    """Cross-entropy search over a smooth correction of the flow's own chunk (its decision-seed noise)."""

    def __init__(self, where: str, population: int, iterations: int, sigma: float, rng: np.random.Generator) -> None:
        super().__init__()
        self.where, self.population, self.iterations, self.sigma, self.rng = where, population, iterations, sigma, rng
        positions = np.arange(HORIZON) * (KNOTS - 1) / (HORIZON - 1)
        left = np.minimum(positions.astype(int), KNOTS - 2)
        self.knots_to_chunk = np.zeros((HORIZON, KNOTS))
        self.knots_to_chunk[np.arange(HORIZON), left] = 1 - (positions - left)
        self.knots_to_chunk[np.arange(HORIZON), left + 1] = positions - left

    def choose(self, flow, env: PushTEnv, state: np.ndarray, elapsed: int, seed: int) -> np.ndarray:
        """The chunk to play."""
        chunk = flow_chunks(flow, state[None], row_noise([seed]))[0]
        if self.where == "gate" and not in_gate(state):
            return chunk
        snapshot = env.physics_snapshot()
        mean, sigma = np.zeros((KNOTS, 2)), self.sigma
        best, best_score = chunk, self.score(snapshot, chunk, elapsed)
        for _ in range(self.iterations):
            corrections = mean + sigma * self.rng.standard_normal((self.population, KNOTS, 2))
            candidates = np.clip(chunk + self.knots_to_chunk @ corrections, 0, 512)
            scores = np.array([self.score(snapshot, c, elapsed) for c in candidates])
            order = np.argsort(-scores)
            if scores[order[0]] > best_score:
                best, best_score = candidates[order[0]], scores[order[0]]
            mean, sigma = corrections[order[:4]].mean(axis=0), max(0.6 * sigma, 0.5)
        return best


class BestOf(Lookahead):
    """The best of K start noises (fresh at each decision, or one fixed codebook)."""

    def __init__(self, flow, candidates: int, codebook: bool, rng: np.random.Generator, criterion: str = "reward") -> None:
        super().__init__(criterion)
        self.candidates, self.rng = candidates, rng
        self.codebook = rng.standard_normal((candidates, HORIZON, 2)) if codebook else None

    def choose(self, flow, env: PushTEnv, state: np.ndarray, elapsed: int, seed: int) -> np.ndarray:
        """The chunk to play."""
        noise = self.codebook if self.codebook is not None else self.rng.standard_normal((self.candidates, HORIZON, 2))
        chunks = flow_chunks(flow, np.repeat(state[None], self.candidates, axis=0), noise)
        snapshot = env.physics_snapshot()
        return chunks[int(np.argmax([self.score(snapshot, c, elapsed) for c in chunks]))]


def play(flow, episodes: int, seed: int, chooser) -> dict:
    """Play `episodes` episodes (seeds seed..) choosing each chunk with `chooser`; success rate with its 95 % interval."""
    from pusht.results import bootstrap_ci95

    success, max_reward = np.zeros(episodes, dtype=bool), np.zeros(episodes)
    for i in range(episodes):
        env = PushTEnv(obs_type="state", render_mode=None)
        state, _ = env.reset(seed=seed + i)
        for decision in range(MAX_EPISODE_STEPS // HORIZON):
            chunk = chooser.choose(flow, env, state, env.elapsed_steps, decision_seed(seed + i, decision))
            for action in chunk:
                state, reward, terminated, truncated, info = env.step(action)
                max_reward[i] = max(max_reward[i], reward)
                success[i] |= info["coverage"] > SUCCESS_COVERAGE
                if terminated or env.elapsed_steps >= MAX_EPISODE_STEPS:
                    break
            if terminated or env.elapsed_steps >= MAX_EPISODE_STEPS:
                break
        print(f"\r{i + 1}/{episodes} episodes, success {success[: i + 1].mean():.3f}", end="", file=sys.stderr)
    print(file=sys.stderr)
    return {"success_rate": float(success.mean()), "success_rate_ci95": list(bootstrap_ci95(success.astype(float))),
            "mean_max_reward": float(max_reward.mean()), "seeds": [seed, seed + episodes - 1]}


def smoothness(flow, count: int, seed: int, rng: np.random.Generator) -> dict:
    """Correlation of one chunk's coverage change with that of the same chunk shifted by 0.1, 0.5 and 2 px."""
    lookahead, shifts = Lookahead(), (0.1, 0.5, 2.0)
    changes: list[list[float]] = []
    episode = 0
    while len(changes) < count:
        env = PushTEnv(obs_type="state", render_mode=None)
        state, _ = env.reset(seed=seed + episode)
        episode += 1
        for decision in range(MAX_EPISODE_STEPS // HORIZON):
            chunk = flow_chunks(flow, state[None], rng.standard_normal((1, HORIZON, 2)))[0]
            start = coverage(*state[2:5])
            if start >= 0.85 and len(changes) < count:
                snapshot, row = env.physics_snapshot(), []
                for shift in (0.0, *shifts):
                    direction = rng.standard_normal(2)
                    moved = chunk + shift * direction / np.linalg.norm(direction)
                    lookahead.scratch.restore_physics(snapshot)
                    for action in moved:
                        lookahead.scratch.step(action)
                    row.append(coverage(*lookahead.scratch.get_state()[2:5]) - start)
                changes.append(row)
            terminated = False
            for action in chunk:
                state, _, terminated, _, _ = env.step(action)
                if terminated or env.elapsed_steps >= MAX_EPISODE_STEPS:
                    break
            if terminated or env.elapsed_steps >= MAX_EPISODE_STEPS:
                break
    table = np.array(changes)
    return {"states": len(table), "coverage_change_std": float(table[:, 0].std()),
            **{f"shift_{s}px": {"correlation": round(float(np.corrcoef(table[:, 0], table[:, j + 1])[0, 1]), 3),
                                "mean_abs_difference": round(float(np.abs(table[:, 0] - table[:, j + 1]).mean()), 4)}
               for j, s in enumerate(shifts)}}


if __name__ == "__main__":
    sys.exit(main())

"""Probe the next lead for the outcome chooser: score each candidate by a learned value of its predicted next state.

    python scripts/value_probe.py --collect 6000 --episodes 500 --seed 300000

The outcome chooser (`records/flow-outcome16-stretch`, shipped before its one-pass student) scores a
candidate chunk by how close its predicted end pose of the block lies to the goal: one chunk deep, blind
to where the agent ends. This probe plays the chooser on training seeds (from 21,000,000), fits
V(state) = E[gamma^(chunks until success)] (0 if the episode fails) on the states it visits, then plays
episodes choosing by V of each candidate's predicted next state (the model's block pose, the agent at the
chunk's last target) and, on the same seeds, by the corner distance, in one torch loop (no ONNX tie
margin in either). Tuning seeds only (default 300000); prints one JSON line. A probe: it measures a criterion, it ships nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository's packages, installed or not

from pusht.env import MAX_EPISODE_STEPS, PushTEnv  # noqa: E402
from pusht.geometry import GOAL_POSE  # noqa: E402
from pusht.results import bootstrap_ci95  # noqa: E402
from pusht.seeding import decision_seed, row_noise  # noqa: E402
from training.checkpoint import load_checkpoint  # noqa: E402
from training.cli import HelpFormatter  # noqa: E402
from training.finetune_config import CHOOSER  # noqa: E402
from training.outcome import goal_corner_distance  # noqa: E402

HORIZON = 12


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: collect, fit, compare; one JSON line."""
    parser = argparse.ArgumentParser(prog="python scripts/value_probe.py", description=__doc__.splitlines()[0], formatter_class=HelpFormatter)
    parser.add_argument("--model", default=CHOOSER, help="checkpoint stem of a flow with an outcome chooser")
    parser.add_argument("--collect", type=int, default=6000, help="episodes of the chooser whose states fit the value")
    parser.add_argument("--collect-seed", type=int, default=21_000_000, help="first seed of those episodes (training range)")
    parser.add_argument("--gamma", type=float, default=0.97, help="discount per chunk of the value's target")
    parser.add_argument("--fit-steps", type=int, default=6000, help="optimizer steps of the value fit")
    parser.add_argument("--episodes", type=int, default=500, help="comparison episodes (seeds seed..seed+episodes-1)")
    parser.add_argument("--seed", type=int, default=300000, help="first comparison seed (tuning seeds, never held-out ones)")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    torch.manual_seed(0)
    flow, card = load_checkpoint(args.model)
    if flow.outcome is None:
        print(f"error: {args.model} has no outcome chooser (outcome_dims in its architecture)", file=sys.stderr)
        return 2
    started = time.time()
    states, targets = collect(flow, args.collect, args.collect_seed, args.gamma)
    value, fit = fit_value(states, targets, args.fit_steps)
    results = {name: play(flow, args.episodes, args.seed, criterion) for name, criterion in
               (("corner_distance", None), ("value_of_next_state", value))}
    print(json.dumps({"model": args.model, "collect": args.collect, "gamma": args.gamma, "value_fit": fit, **results,
                      "wall_time_s": round(time.time() - started, 1)}))
    return 0


def features(state: torch.Tensor) -> torch.Tensor:
    """The value's view of env-unit states [B, 5]: the block's error to the goal, the agent in the block's frame, the agent's place."""
    gx, gy, ga = GOAL_POSE
    cos, sin = torch.cos(state[:, 4]), torch.sin(state[:, 4])
    rx, ry = state[:, 0] - state[:, 2], state[:, 1] - state[:, 3]
    turn = state[:, 4] - ga
    return torch.stack([(state[:, 2] - gx) / 100, (state[:, 3] - gy) / 100, torch.sin(turn), torch.cos(turn),
                        (cos * rx + sin * ry) / 100, (-sin * rx + cos * ry) / 100, state[:, 0] / 256 - 1, state[:, 1] / 256 - 1], dim=1)


def choose(flow, states: np.ndarray, seeds: list[int], value: nn.Module | None) -> np.ndarray:
    """The chunk [B, H, 2] each criterion picks among the chooser's candidates (None: the corner distance)."""
    sel, k = flow.outcome, flow.outcome.choices
    state = torch.as_tensor(states, dtype=torch.float32)
    with torch.no_grad():
        _, actions = sel.candidate_chunks(flow, flow.policy_state(state), torch.as_tensor(row_noise(seeds)), 10)
        chunks = actions.reshape(-1, HORIZON, 2)
        poses = sel.model(state.unsqueeze(1).expand(-1, k, -1).reshape(-1, 5), chunks)
        if value is None:
            score = -goal_corner_distance(poses)
        else:
            score = value(features(torch.cat([chunks[:, -1], poses], dim=1))).squeeze(1)
        best = score.reshape(-1, k).argmax(dim=1)
    return actions[torch.arange(len(states)), best].numpy()


def play(flow, episodes: int, seed: int, value: nn.Module | None) -> dict:
    """Lockstep episodes (seeds seed..) with one criterion; success and mean max reward with 95 % intervals."""
    envs = [PushTEnv(obs_type="state", render_mode=None) for _ in range(episodes)]
    obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(envs)])
    alive, success, best = np.ones(episodes, dtype=bool), np.zeros(episodes), np.zeros(episodes)
    for decision in range(MAX_EPISODE_STEPS // HORIZON):
        rows = np.flatnonzero(alive)
        if not len(rows):
            break
        chunks = choose(flow, obs[rows], [decision_seed(seed + i, decision) for i in rows], value)
        for chunk, i in zip(chunks, rows):
            for action in chunk:
                obs[i], reward, terminated, _, _ = envs[i].step(action)
                best[i] = max(best[i], reward)
                success[i] = success[i] or terminated
                if terminated or envs[i].elapsed_steps >= MAX_EPISODE_STEPS:
                    alive[i] = False
                    break
    return {"success_rate": float(success.mean()), "success_rate_ci95": list(bootstrap_ci95(success)),
            "mean_max_reward": float(best.mean()), "seeds": [seed, seed + episodes - 1]}


def collect(flow, episodes: int, seed: int, gamma: float) -> tuple[np.ndarray, np.ndarray]:
    """States at the chooser's decisions and their targets gamma^(chunks until success), 0 where the episode fails."""
    envs = [PushTEnv(obs_type="state", render_mode=None) for _ in range(episodes)]
    obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(envs)])
    alive, success_at = np.ones(episodes, dtype=bool), np.full(episodes, -1)
    states, steps, owners = [], [], []
    for decision in range(MAX_EPISODE_STEPS // HORIZON):
        rows = np.flatnonzero(alive)
        if not len(rows):
            break
        states.append(obs[rows].copy())
        steps.append(np.array([envs[i].elapsed_steps for i in rows]))
        owners.append(rows)
        for chunk, i in zip(choose(flow, obs[rows], [decision_seed(seed + i, decision) for i in rows], None), rows):
            for action in chunk:
                obs[i], _, terminated, _, _ = envs[i].step(action)
                if terminated:
                    success_at[i] = envs[i].elapsed_steps
                if terminated or envs[i].elapsed_steps >= MAX_EPISODE_STEPS:
                    alive[i] = False
                    break
    owner, step = np.concatenate(owners), np.concatenate(steps)
    done = success_at[owner]
    return np.concatenate(states), np.where(done >= 0, gamma ** ((done - step) / HORIZON), 0.0)


def fit_value(states: np.ndarray, targets: np.ndarray, steps: int) -> tuple[nn.Module, dict]:
    """An MLP fitted by binary cross-entropy on 90 % of the states; its held-back loss beside a constant's."""
    x, y = features(torch.as_tensor(states, dtype=torch.float32)), torch.as_tensor(targets, dtype=torch.float32)
    order = torch.randperm(len(x))
    train, held = order[: int(0.9 * len(x))], order[int(0.9 * len(x)) :]
    net = nn.Sequential(nn.Linear(x.shape[1], 256), nn.SiLU(), nn.Linear(256, 256), nn.SiLU(), nn.Linear(256, 256), nn.SiLU(), nn.Linear(256, 1))
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=1e-4)
    loss_fn = nn.functional.binary_cross_entropy_with_logits
    for _ in range(steps):
        batch = train[torch.randint(0, len(train), (512,))]
        loss = loss_fn(net(x[batch]).squeeze(1), y[batch])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        held_loss = float(loss_fn(net(x[held]).squeeze(1), y[held]))
        constant = float(nn.functional.binary_cross_entropy(torch.full_like(y[held], float(y[train].mean())), y[held]))
    return net.eval(), {"states": len(x), "held_back_bce": round(held_loss, 4), "constant_bce": round(constant, 4)}


if __name__ == "__main__":
    sys.exit(main())

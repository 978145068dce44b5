"""The one batched lockstep rollout loop, shared by training's evaluation and the HTTP client.

K environments advance in lockstep. At each decision step the policy is asked ONCE for an action
chunk for every running environment, and each chunk is executed open loop for `action_horizon`
steps (default: the whole chunk, as long as the first answer's chunks; the runner assumes no chunk
length of its own). Episode seeds are spread over the K environments: an environment that finishes its episode
takes the next unplayed seed at the following decision step. Each row of a call carries its own
request seed, `decision_seed(episode_seed, d)` for the episode's decision d (`pusht/seeding.py`), so
an episode's result depends on its own seed only, whatever `num_envs`.

Imports only numpy, the standard library and (lazily) `pusht` itself, so that the torch-free HTTP
client can use it.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Callable, Sequence

import numpy as np

from pusht.spec import ACTION_DIM, SUCCESS_COVERAGE
from pusht.results import EpisodeResult, RolloutSummary, Trajectory, card_id, check_output_path, write_episode_records
from pusht.seeding import (
    BATCH_MULTIPLE,
    chunk_noise,
    check_seed_value,
    decision_seed,
    episode_seeds,
    pad_rows,
    row_noise,
)

__all__ = [
    "ActFn",
    "BATCH_MULTIPLE",
    "EpisodeResult",
    "FrameFn",
    "RolloutSummary",
    "SUCCESS_COVERAGE",
    "Trajectory",
    "card_id",
    "check_output_path",
    "chunk_noise",
    "decision_seed",
    "default_env_factory",
    "episode_seeds",
    "pad_rows",
    "row_noise",
    "run_episodes",
    "write_episode_records",
]

ActFn = Callable[..., np.ndarray]
"""(states [B, 5] float32 in env units, one request seed per row) -> actions [B, H, 2], H >= action_horizon; with
`run_episodes(..., prev_states=True)` a third argument, the states one env step before (`states` at an episode's start)."""

ProgressFn = Callable[[int, int], None]
"""(episodes_done, episodes_total) -> None, called after every finished episode."""

FrameFn = Callable[[np.ndarray, int, float, bool], np.ndarray]
"""(rendered frame, step, coverage, success so far) -> the frame to keep (e.g. shrunk and captioned)."""



def run_episodes(
    act: ActFn,
    seeds: Sequence[int],
    num_envs: int,
    max_steps: int = 300,
    action_horizon: int | None = None,
    env_factory: Callable[[], Any] | None = None,
    progress: bool | ProgressFn = False,
    record_frames: bool | FrameFn = False,
    record_trajectories: bool = False,
    prev_states: bool = False,
) -> RolloutSummary:
    """Play one episode per seed with `num_envs` envs in lockstep, one `act` call per decision, row seeds `decision_seed(e, d)`.

    `action_horizon`: actions of each chunk run open loop (None: the whole chunk, as long as the first call's).
    `prev_states`: also give `act` each env's observation one step before its current one (a policy with history).
    `progress`: bool or `(done, total)`; `record_frames`: keep the first episode's frames (through a FrameFn if callable).
    """
    seeds = _check_seeds(seeds)
    for name, value in (("num_envs", num_envs), ("max_steps", max_steps), ("action_horizon", action_horizon)):
        if name == "action_horizon" and value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if env_factory is None:
        env_factory = partial(default_env_factory, int(max_steps))  # the env's own time limit must not cut max_steps short
    report = _progress_callback(progress)

    start = time.perf_counter()
    num_envs = min(int(num_envs), len(seeds))
    envs = [env_factory() for _ in range(num_envs)]
    try:
        results, frames, trajectories, decisions, action_horizon = _lockstep(
            envs, act, seeds, max_steps, action_horizon, report, record_frames, record_trajectories, prev_states
        )
    finally:
        for env in envs:
            close = getattr(env, "close", None)
            if close is not None:
                close()
    wall_time_s = time.perf_counter() - start
    return RolloutSummary.from_episodes(
        results,
        decisions=decisions,
        wall_time_s=wall_time_s,
        num_envs=num_envs,
        action_horizon=int(action_horizon),
        max_steps=int(max_steps),
        frames=frames,
        trajectories=trajectories,
    )


def default_env_factory(max_episode_steps: int = 300):
    """A fresh `pusht.PushTEnv` with state observations and rgb_array rendering, truncating after `max_episode_steps`."""
    return _push_t_env_class()(obs_type="state", render_mode="rgb_array", max_episode_steps=max_episode_steps)


def _push_t_env_class():
    # lazy, so this module imports (and the client works) without the env's dependencies loaded
    try:
        from pusht import PushTEnv
    except ImportError:
        from pusht.env import PushTEnv
    return PushTEnv


@dataclass
class _Slot:
    """One environment and the episode it is playing."""

    env: Any
    index: int = -1  # position of the episode's seed in `seeds`; -1 when idle
    obs: np.ndarray | None = None
    prev_obs: np.ndarray | None = None  # the observation one step before obs (obs itself at the episode's start)
    length: int = 0
    decisions: int = 0  # the episode's own decision counter: its request seeds depend on nothing else
    max_reward: float = 0.0
    success: bool = False
    coverage: float = 0.0
    states: list[np.ndarray] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)


def _lockstep(envs, act, seeds, max_steps, action_horizon, report, record_frames, record_trajectories, with_prev=False):
    results: list[EpisodeResult | None] = [None] * len(seeds)
    trajectories: list[Trajectory | None] = [None] * len(seeds)
    frames: list[np.ndarray] = []
    keep = record_frames if callable(record_frames) else (lambda frame, step, coverage, success: frame)
    next_index = 0
    done_count = 0
    slots = [_Slot(env) for env in envs]

    def start(slot: _Slot) -> None:
        nonlocal next_index
        if next_index >= len(seeds):
            slot.index = -1
            return
        slot.index = next_index
        next_index += 1
        obs, info = slot.env.reset(seed=seeds[slot.index])
        slot.obs = slot.prev_obs = np.asarray(obs, dtype=np.float64)
        slot.length = slot.decisions = 0
        slot.max_reward = 0.0
        slot.success = False
        slot.coverage = float(info.get("coverage", 0.0)) if isinstance(info, dict) else 0.0
        slot.states, slot.actions = [], []
        if record_frames and slot.index == 0:
            frames.append(keep(slot.env.render(), 0, slot.coverage, False))

    for slot in slots:
        start(slot)

    decisions = 0
    while True:
        running = [s for s in slots if s.index >= 0]
        if not running:
            break
        states = np.stack([s.obs for s in running]).astype(np.float32)
        row_seeds = [decision_seed(seeds[s.index], s.decisions) for s in running]
        if with_prev:
            prev = np.stack([s.prev_obs for s in running]).astype(np.float32)
            chunk = _check_actions(act(states, row_seeds, prev), len(running), action_horizon)
        else:
            chunk = _check_actions(act(states, row_seeds), len(running), action_horizon)
        if action_horizon is None:
            action_horizon = chunk.shape[1]  # the policy's chunk length: every later chunk runs as many actions
        decisions += 1

        finished: list[_Slot] = []
        for row, slot in enumerate(running):
            slot.decisions += 1
            for t in range(action_horizon):
                if record_trajectories:
                    slot.states.append(slot.obs.astype(np.float32))
                    slot.actions.append(chunk[row, t])
                obs, reward, terminated, truncated, info = slot.env.step(chunk[row, t])
                slot.prev_obs, slot.obs = slot.obs, np.asarray(obs, dtype=np.float64)
                slot.length += 1
                slot.max_reward = max(slot.max_reward, float(reward))
                slot.coverage = float(info["coverage"])
                slot.success = slot.success or bool(info.get("is_success", False)) or slot.coverage > SUCCESS_COVERAGE
                if record_frames and slot.index == 0:
                    frames.append(keep(slot.env.render(), slot.length, slot.coverage, slot.success))
                if terminated or truncated or slot.length >= max_steps:
                    finished.append(slot)
                    break
        # New episodes start only after the whole chunk ran, so every env stays on the same decision clock.
        for slot in finished:
            results[slot.index] = EpisodeResult(
                seed=int(seeds[slot.index]),
                max_reward=slot.max_reward,
                success=slot.success,
                length=slot.length,
                final_coverage=slot.coverage,
            )
            if record_trajectories:
                trajectories[slot.index] = Trajectory(
                    seed=int(seeds[slot.index]), states=np.stack(slot.states), actions=np.stack(slot.actions)
                )
            done_count += 1
            report(done_count, len(seeds))
            start(slot)
    kept = [t for t in trajectories if t is not None]
    return [r for r in results if r is not None], frames, kept, decisions, action_horizon


def _check_actions(actions: Any, batch: int, action_horizon: int | None) -> np.ndarray:
    try:
        actions = np.asarray(actions, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"act returned something that is not a numeric array: {exc}") from None
    if actions.ndim != 3 or actions.shape[0] != batch or actions.shape[1] < 1 or actions.shape[2] != ACTION_DIM:
        raise ValueError(
            f"act returned actions of shape {actions.shape}; expected [{batch}, >= {action_horizon or 1}, {ACTION_DIM}]"
        )
    if action_horizon is not None and actions.shape[1] < action_horizon:
        raise ValueError(
            f"act returned chunks of {actions.shape[1]} actions; action_horizon needs at least {action_horizon}"
        )
    if not np.all(np.isfinite(actions)):
        raise ValueError("act returned non-finite actions (NaN or inf)")
    return actions


def _check_seeds(seeds: Sequence[int]) -> list[int]:
    if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__len__"):
        raise ValueError(f"seeds must be a sequence of integers, got {type(seeds).__name__}")
    if len(seeds) == 0:
        raise ValueError("seeds is empty: nothing to play")
    out = []
    for s in seeds:
        check_seed_value("episode seed", s)
        out.append(int(s))
    return out


def _progress_callback(progress: bool | ProgressFn) -> ProgressFn:
    if callable(progress):
        return progress
    if progress is True:
        def to_stderr(done: int, total: int) -> None:
            end = "\n" if done == total else ""
            print(f"\rrollout: {done}/{total} episodes", end=end, file=sys.stderr, flush=True)

        return to_stderr
    if progress is False or progress is None:
        return lambda done, total: None
    raise ValueError(f"progress must be a bool or a callable (done, total), got {progress!r}")

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
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any, Callable, Sequence

import numpy as np

from pusht.results import EpisodeResult, RolloutSummary, Trajectory, card_id, check_output_path, write_episode_records
from pusht.seeding import (
    BATCH_MULTIPLE,
    check_seed_value,
    chunk_noise,
    decision_seed,
    episode_seeds,
    pad_rows,
    row_noise,
)
from pusht.spec import ACTION_DIM, SUCCESS_COVERAGE

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


@dataclass(frozen=True)
class RolloutSettings:
    """How `run_episodes` plays: `action_horizon` actions of each chunk open loop (None: the whole chunk, as long as the
    first call's); `prev_states`: also give `act` each env's observation one step before its current one; `progress`:
    bool or `(done, total)`; `record_frames`: keep the first episode's frames (through a FrameFn if callable)."""

    max_steps: int = 300
    action_horizon: int | None = None
    env_factory: Callable[[], Any] | None = None
    progress: bool | ProgressFn = False
    record_frames: bool | FrameFn = False
    record_trajectories: bool = False
    prev_states: bool = False


def run_episodes(
    act: ActFn, seeds: Sequence[int], num_envs: int, settings: RolloutSettings | None = None, **changes: Any
) -> RolloutSummary:
    """Play one episode per seed with `num_envs` envs in lockstep, one `act` call per decision, row seeds `decision_seed(e, d)`.

    `settings` (default `RolloutSettings()`) with `changes`, its fields by name, applied."""
    settings = replace(settings or RolloutSettings(), **changes)
    seeds = _check_seeds(seeds)
    max_steps, action_horizon = settings.max_steps, settings.action_horizon
    for name, value in (("num_envs", num_envs), ("max_steps", max_steps), ("action_horizon", action_horizon)):
        if name == "action_horizon" and value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    # the env's own time limit must not cut max_steps short
    env_factory = settings.env_factory or partial(default_env_factory, int(max_steps))
    start = time.perf_counter()
    num_envs = min(int(num_envs), len(seeds))
    envs = [env_factory() for _ in range(num_envs)]
    try:
        play = _Lockstep(envs, act, seeds, settings)
        play.run()
    finally:
        for env in envs:
            close = getattr(env, "close", None)
            if close is not None:
                close()
    return RolloutSummary.from_episodes(
        [r for r in play.results if r is not None],
        decisions=play.decisions,
        wall_time_s=time.perf_counter() - start,
        num_envs=num_envs,
        action_horizon=int(play.action_horizon),
        max_steps=int(max_steps),
        frames=play.frames,
        trajectories=[t for t in play.trajectories if t is not None],
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


class _Lockstep:
    """The envs on one decision clock: each asks `act` once per decision for all its running episodes."""

    def __init__(self, envs: list[Any], act: ActFn, seeds: list[int], settings: RolloutSettings) -> None:
        self.act, self.seeds, self.settings = act, seeds, settings
        self.action_horizon = settings.action_horizon
        self.report = _progress_callback(settings.progress)
        record = settings.record_frames
        self.keep = record if callable(record) else (lambda frame, step, coverage, success: frame)
        self.results: list[EpisodeResult | None] = [None] * len(seeds)
        self.trajectories: list[Trajectory | None] = [None] * len(seeds)
        self.frames: list[np.ndarray] = []
        self.next_index = self.done_count = self.decisions = 0
        self.slots = [_Slot(env) for env in envs]

    def run(self) -> None:
        for slot in self.slots:
            self._start(slot)
        while running := [s for s in self.slots if s.index >= 0]:
            chunk = self._ask(running)
            finished = [slot for row, slot in enumerate(running) if self._play(slot, chunk[row])]
            # New episodes start only after the whole chunk ran, so every env stays on the same decision clock.
            for slot in finished:
                self._finish(slot)
                self._start(slot)

    def _start(self, slot: _Slot) -> None:
        """The next seed's episode in `slot`, or the slot idle when every seed has started."""
        if self.next_index >= len(self.seeds):
            slot.index = -1
            return
        slot.index = self.next_index
        self.next_index += 1
        obs, info = slot.env.reset(seed=self.seeds[slot.index])
        slot.obs = slot.prev_obs = np.asarray(obs, dtype=np.float64)
        slot.length = slot.decisions = 0
        slot.max_reward = 0.0
        slot.success = False
        slot.coverage = float(info.get("coverage", 0.0)) if isinstance(info, dict) else 0.0
        slot.states, slot.actions = [], []
        self._record_frame(slot)

    def _ask(self, running: list[_Slot]) -> np.ndarray:
        """One `act` call for every running episode: their chunks, checked."""
        states = np.stack([s.obs for s in running]).astype(np.float32)
        row_seeds = [decision_seed(self.seeds[s.index], s.decisions) for s in running]
        if self.settings.prev_states:
            prev = np.stack([s.prev_obs for s in running]).astype(np.float32)
            chunk = _check_actions(self.act(states, row_seeds, prev), len(running), self.action_horizon)
        else:
            chunk = _check_actions(self.act(states, row_seeds), len(running), self.action_horizon)
        if self.action_horizon is None:
            self.action_horizon = chunk.shape[1]  # the policy's chunk length: every later chunk runs as many actions
        self.decisions += 1
        return chunk

    def _play(self, slot: _Slot, chunk: np.ndarray) -> bool:
        """Run the chunk's first `action_horizon` actions in the slot's env; True when its episode ended."""
        slot.decisions += 1
        for t in range(self.action_horizon):
            if self.settings.record_trajectories:
                slot.states.append(slot.obs.astype(np.float32))
                slot.actions.append(chunk[t])
            obs, reward, terminated, truncated, info = slot.env.step(chunk[t])
            slot.prev_obs, slot.obs = slot.obs, np.asarray(obs, dtype=np.float64)
            slot.length += 1
            slot.max_reward = max(slot.max_reward, float(reward))
            slot.coverage = float(info["coverage"])
            slot.success = slot.success or bool(info.get("is_success", False)) or slot.coverage > SUCCESS_COVERAGE
            self._record_frame(slot)
            if terminated or truncated or slot.length >= self.settings.max_steps:
                return True
        return False

    def _record_frame(self, slot: _Slot) -> None:
        if self.settings.record_frames and slot.index == 0:
            self.frames.append(self.keep(slot.env.render(), slot.length, slot.coverage, slot.success))

    def _finish(self, slot: _Slot) -> None:
        seed = int(self.seeds[slot.index])
        self.results[slot.index] = EpisodeResult(
            seed=seed, max_reward=slot.max_reward, success=slot.success, length=slot.length, final_coverage=slot.coverage
        )
        if self.settings.record_trajectories:
            self.trajectories[slot.index] = Trajectory(seed=seed, states=np.stack(slot.states), actions=np.stack(slot.actions))
        self.done_count += 1
        self.report(self.done_count, len(self.seeds))


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
        raise ValueError(f"act returned chunks of {actions.shape[1]} actions; action_horizon needs at least {action_horizon}")
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

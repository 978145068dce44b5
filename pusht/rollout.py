"""The one batched lockstep rollout loop, shared by training's evaluation and the HTTP client.

K environments advance in lockstep. At each decision step the policy is asked ONCE for an action
chunk for every running environment, and each chunk is executed open loop for `action_horizon`
steps. Episode seeds are spread over the K environments: an environment that finishes its episode
takes the next unplayed seed at the following decision step.

Imports only numpy, the standard library and (lazily) `pusht` itself, so that the torch-free HTTP
client can use it.
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

__all__ = [
    "ActFn",
    "EpisodeResult",
    "RolloutSummary",
    "SUCCESS_COVERAGE",
    "Trajectory",
    "chunk_noise",
    "row_noise",
    "decision_seed",
    "default_env_factory",
    "episode_seeds",
    "run_episodes",
]

ActFn = Callable[[np.ndarray, int], np.ndarray]
"""(states [B, 5] float32 in env units, request_seed) -> actions [B, H >= action_horizon, 2]."""

ProgressFn = Callable[[int, int], None]
"""(episodes_done, episodes_total) -> None, called after every finished episode."""

SUCCESS_COVERAGE = 0.95
"""An episode succeeds once the block covers more than this fraction of the goal (as gym-pusht)."""

STATE_DIM = 5
ACTION_DIM = 2
_MAX_SEED = 2**63
_BOOTSTRAP_RESAMPLES = 10_000
_BOOTSTRAP_SEED = 0


def run_episodes(
    act: ActFn,
    seeds: Sequence[int],
    num_envs: int,
    max_steps: int = 300,
    action_horizon: int = 12,
    seed: int = 0,
    env_factory: Callable[[], Any] | None = None,
    progress: bool | ProgressFn = False,
    record_frames: bool | Callable[[np.ndarray], np.ndarray] = False,
    record_trajectories: bool = False,
) -> RolloutSummary:
    """Play one episode per seed with `num_envs` envs in lockstep, one `act` call per decision step.

    `seed` fixes the request seeds: decision step d asks `act` with `decision_seed(seed, d)`.
    `progress` is False, True (a line on stderr) or a callback `(done, total)`. With
    `record_frames`, the summary holds the rendered frames (`env.render()`) of the first seed's
    episode; a callable `record_frames` is applied to each frame before it is kept (e.g. to shrink it).
    With `record_trajectories`, the summary holds every episode's states and executed actions.
    """
    seeds = _check_seeds(seeds)
    for name, value in (("num_envs", num_envs), ("max_steps", max_steps), ("action_horizon", action_horizon)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    _check_seed_value("seed", seed)
    if env_factory is None:
        env_factory = default_env_factory
    report = _progress_callback(progress)

    start = time.perf_counter()
    num_envs = min(int(num_envs), len(seeds))
    envs = [env_factory() for _ in range(num_envs)]
    try:
        results, frames, trajectories, decisions = _lockstep(
            envs, act, seeds, max_steps, action_horizon, seed, report, record_frames, record_trajectories
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
        seed=int(seed),
        num_envs=num_envs,
        action_horizon=int(action_horizon),
        max_steps=int(max_steps),
        frames=frames,
        trajectories=trajectories,
    )


def episode_seeds(seed: int, n: int) -> list[int]:
    """The `n` consecutive episode seeds `[seed, seed + 1, ..., seed + n - 1]`."""
    _check_seed_value("seed", seed)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    return list(range(int(seed), int(seed) + int(n)))


def decision_seed(seed: int, decision_index: int) -> int:
    """The request seed of decision step `decision_index` of a rollout run with `seed`, in [0, 2**63).

    Rule: words = np.random.SeedSequence([seed, decision_index]).generate_state(2, np.uint64);
    result = (words[0] XOR words[1]) with the top bit cleared. Both inputs must be non-negative.
    """
    _check_seed_value("seed", seed)
    _check_seed_value("decision_index", decision_index)
    words = np.random.SeedSequence([int(seed), int(decision_index)]).generate_state(2, np.uint64)
    return int(words[0] ^ words[1]) & (_MAX_SEED - 1)


def chunk_noise(seed: int, batch: int, horizon: int = 12, action_dim: int = 2) -> np.ndarray:
    """The standard-normal start of flow sampling for a request seed: float32 [batch, horizon, action_dim].

    Drawn as `np.random.default_rng(seed).standard_normal(shape, dtype=np.float32)`; the service
    uses this same function, so HTTP and in-process evaluation see the same noise.
    """
    _check_seed_value("seed", seed)
    for name, value in (("batch", batch), ("horizon", horizon), ("action_dim", action_dim)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    rng = np.random.default_rng(int(seed))
    return rng.standard_normal((int(batch), int(horizon), int(action_dim)), dtype=np.float32)


def row_noise(seeds: Sequence[int], horizon: int = 12, action_dim: int = 2) -> np.ndarray:
    """Per-row noise: row i is `chunk_noise(seeds[i], 1, horizon, action_dim)[0]`, so it depends on its own seed only.

    float32 [len(seeds), horizon, action_dim]; the service applies this to a request's `seeds`.
    """
    if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__len__") or len(seeds) == 0:
        raise ValueError("seeds must be a non-empty sequence of integers")
    return np.concatenate([chunk_noise(int(s) if isinstance(s, np.integer) else s, 1, horizon, action_dim) for s in seeds])


def default_env_factory():
    """A fresh `pusht.PushTEnv` with state observations and rgb_array rendering."""
    return _push_t_env_class()(obs_type="state", render_mode="rgb_array")


def _push_t_env_class():
    # lazy, so this module imports (and the client works) without the env's dependencies loaded
    try:
        from pusht import PushTEnv
    except ImportError:
        from pusht.env import PushTEnv
    return PushTEnv


@dataclass(frozen=True)
class EpisodeResult:
    """The outcome of one episode."""

    seed: int
    max_reward: float
    success: bool
    length: int
    final_coverage: float


@dataclass(frozen=True)
class Trajectory:
    """One episode as a demonstration: the state before each step and the action executed from it."""

    seed: int
    states: np.ndarray  # [T, 5] float32, env units
    actions: np.ndarray  # [T, 2] float32, env units


@dataclass
class RolloutSummary:
    """Per-episode results and their means with 95% bootstrap intervals."""

    episodes: list[EpisodeResult]
    mean_max_reward: float
    mean_max_reward_ci95: tuple[float, float]
    success_rate: float
    success_rate_ci95: tuple[float, float]
    mean_length: float
    decisions: int
    wall_time_s: float
    seed: int
    num_envs: int
    action_horizon: int
    max_steps: int
    frames: list[np.ndarray] = field(default_factory=list, repr=False)
    trajectories: list[Trajectory] = field(default_factory=list, repr=False)

    @classmethod
    def from_episodes(cls, episodes: list[EpisodeResult], **kwargs: Any) -> RolloutSummary:
        """Aggregate episode results; the bootstrap uses a fixed RNG, so the same episodes give the same intervals."""
        if not episodes:
            raise ValueError("cannot summarize zero episodes")
        max_rewards = np.array([e.max_reward for e in episodes], dtype=np.float64)
        successes = np.array([e.success for e in episodes], dtype=np.float64)
        return cls(
            episodes=list(episodes),
            mean_max_reward=float(max_rewards.mean()),
            mean_max_reward_ci95=_bootstrap_ci95(max_rewards),
            success_rate=float(successes.mean()),
            success_rate_ci95=_bootstrap_ci95(successes),
            mean_length=float(np.mean([e.length for e in episodes])),
            **kwargs,
        )

    @property
    def seeds(self) -> list[int]:
        """The episode seeds, in the order they were given."""
        return [e.seed for e in self.episodes]

    def scores(self) -> dict[str, Any]:
        """The headline figures of a one-line report: rounded scores with their intervals, seed range, counts, time."""
        return {
            "episodes": len(self.episodes),
            "seeds": [self.seeds[0], self.seeds[-1]],
            "mean_max_reward": round(self.mean_max_reward, 4),
            "mean_max_reward_ci95": [round(x, 4) for x in self.mean_max_reward_ci95],
            "success_rate": round(self.success_rate, 4),
            "success_rate_ci95": [round(x, 4) for x in self.success_rate_ci95],
            "mean_length": round(self.mean_length, 2),
            "num_envs": self.num_envs,
            "action_horizon": self.action_horizon,
            "max_steps": self.max_steps,
            "decisions": self.decisions,
            "wall_time_s": round(self.wall_time_s, 2),
        }

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (without frames)."""
        return {
            "episodes": [asdict(e) for e in self.episodes],
            "seeds": self.seeds,
            "mean_max_reward": self.mean_max_reward,
            "mean_max_reward_ci95": list(self.mean_max_reward_ci95),
            "success_rate": self.success_rate,
            "success_rate_ci95": list(self.success_rate_ci95),
            "mean_length": self.mean_length,
            "decisions": self.decisions,
            "wall_time_s": self.wall_time_s,
            "seed": self.seed,
            "num_envs": self.num_envs,
            "action_horizon": self.action_horizon,
            "max_steps": self.max_steps,
        }


@dataclass
class _Slot:
    """One environment and the episode it is playing."""

    env: Any
    index: int = -1  # position of the episode's seed in `seeds`; -1 when idle
    obs: np.ndarray | None = None
    length: int = 0
    max_reward: float = 0.0
    success: bool = False
    coverage: float = 0.0
    states: list[np.ndarray] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)


def _lockstep(envs, act, seeds, max_steps, action_horizon, seed, report, record_frames, record_trajectories):
    results: list[EpisodeResult | None] = [None] * len(seeds)
    trajectories: list[Trajectory | None] = [None] * len(seeds)
    frames: list[np.ndarray] = []
    keep = record_frames if callable(record_frames) else (lambda frame: frame)
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
        slot.obs = np.asarray(obs, dtype=np.float64)
        slot.length = 0
        slot.max_reward = 0.0
        slot.success = False
        slot.coverage = float(info.get("coverage", 0.0)) if isinstance(info, dict) else 0.0
        slot.states, slot.actions = [], []
        if record_frames and slot.index == 0:
            frames.append(keep(slot.env.render()))

    for slot in slots:
        start(slot)

    decisions = 0
    while True:
        running = [s for s in slots if s.index >= 0]
        if not running:
            break
        states = np.stack([s.obs for s in running]).astype(np.float32)
        request_seed = decision_seed(seed, decisions)
        chunk = _check_actions(act(states, request_seed), len(running), action_horizon)
        decisions += 1

        finished: list[_Slot] = []
        for row, slot in enumerate(running):
            for t in range(action_horizon):
                if record_trajectories:
                    slot.states.append(slot.obs.astype(np.float32))
                    slot.actions.append(chunk[row, t])
                obs, reward, terminated, truncated, info = slot.env.step(chunk[row, t])
                slot.obs = np.asarray(obs, dtype=np.float64)
                slot.length += 1
                slot.max_reward = max(slot.max_reward, float(reward))
                slot.coverage = float(info["coverage"])
                slot.success = slot.success or bool(info.get("is_success", False)) or slot.coverage > SUCCESS_COVERAGE
                if record_frames and slot.index == 0:
                    frames.append(keep(slot.env.render()))
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
    return [r for r in results if r is not None], frames, kept, decisions


def _check_actions(actions: Any, batch: int, action_horizon: int) -> np.ndarray:
    try:
        actions = np.asarray(actions, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"act returned something that is not a numeric array: {exc}") from None
    if actions.ndim != 3 or actions.shape[0] != batch or actions.shape[2] != ACTION_DIM:
        raise ValueError(
            f"act returned actions of shape {actions.shape}; expected [{batch}, >= {action_horizon}, {ACTION_DIM}]"
        )
    if actions.shape[1] < action_horizon:
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
        _check_seed_value("episode seed", s)
        out.append(int(s))
    return out


def _check_seed_value(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if not 0 <= int(value) < _MAX_SEED:
        raise ValueError(f"{name} must be in [0, 2**63), got {value}")


def _bootstrap_ci95(values: np.ndarray) -> tuple[float, float]:
    rng = np.random.default_rng(_BOOTSTRAP_SEED)
    idx = rng.integers(0, len(values), size=(_BOOTSTRAP_RESAMPLES, len(values)))
    means = values[idx].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


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

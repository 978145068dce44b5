"""What a rollout returns: per-episode results, their summary with bootstrap intervals, per-episode records.

`write_episode_records` writes the `--out FILE` of `training.evaluate` and of the HTTP client: one
JSON line per episode, `{"policy", "card", "seed", "max_reward", "success", "length", "final_coverage"}`,
where `card` is `card_id(name, git_commit, steps)`: the card's name, git commit and training steps,
which both the card file and `GET /policies` give, so the two files of one model compare line by line.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "EpisodeResult",
    "RolloutSummary",
    "Trajectory",
    "bootstrap_ci95",
    "card_id",
    "check_output_path",
    "episode_records",
    "write_episode_records",
]

_BOOTSTRAP_RESAMPLES = 10_000
_BOOTSTRAP_SEED = 0


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
    states: np.ndarray  # [T, state_dim] float32, env units
    actions: np.ndarray  # [T, action_dim] float32, env units


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
    num_envs: int
    action_horizon: int
    max_steps: int
    mean_steps_to_success: float | None = None  # over the successful episodes; None without one
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
            mean_max_reward_ci95=bootstrap_ci95(max_rewards),
            success_rate=float(successes.mean()),
            success_rate_ci95=bootstrap_ci95(successes),
            mean_length=float(np.mean([e.length for e in episodes])),
            mean_steps_to_success=float(np.mean(lengths)) if (lengths := [e.length for e in episodes if e.success]) else None,
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
            "mean_steps_to_success": None if self.mean_steps_to_success is None else round(self.mean_steps_to_success, 2),
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
            "mean_steps_to_success": self.mean_steps_to_success,
            "decisions": self.decisions,
            "wall_time_s": self.wall_time_s,
            "num_envs": self.num_envs,
            "action_horizon": self.action_horizon,
            "max_steps": self.max_steps,
        }


def card_id(name: Any, git_commit: Any, steps: Any) -> str:
    """`NAME@GIT_COMMIT:STEPS`, the model identity written into per-episode records."""
    return f"{name}@{git_commit}:{steps}"


def episode_records(summary: RolloutSummary, policy: str, card: str) -> list[dict[str, Any]]:
    """One JSON-ready dict per episode, in seed order."""
    return [{"policy": policy, "card": card, **asdict(e)} for e in summary.episodes]


def write_episode_records(path: str | Path, summary: RolloutSummary, policy: str, card: str) -> None:
    """Write one JSON line per episode to `path` (replaced if it exists)."""
    lines = [json.dumps(record) for record in episode_records(summary, policy, card)]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def add_output_arguments(parser: Any) -> None:
    """`--out FILE` and `--gif FILE` on an argparse parser: what a rollout writes besides its summary."""
    parser.add_argument(
        "--out",
        default=None,
        metavar="FILE",
        help="write one JSON line per episode (seed, max_reward, success, length, policy, card) to FILE",
    )
    parser.add_argument(
        "--gif",
        default=None,
        metavar="FILE",
        help="write the first episode as an animated GIF (real speed, step/coverage/success caption) to FILE",
    )


def check_output_path(flag: str, path: str | Path) -> Path:
    """`path` as a Path once its folder exists and is writable; ValueError naming `flag` otherwise (checked before a rollout)."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{flag} {path} is a directory; give a file path inside it")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"{flag} {path}: cannot create its folder: {' '.join(str(exc).split())}") from None
    if not os.access(path.parent, os.W_OK):
        raise ValueError(f"{flag} {path}: its folder {path.parent} is not writable")
    return path


def bootstrap_ci95(values: np.ndarray) -> tuple[float, float]:
    """The 95 % bootstrap interval of the mean of `values` (fixed RNG: the same values give the same interval)."""
    rng = np.random.default_rng(_BOOTSTRAP_SEED)
    idx = rng.integers(0, len(values), size=(_BOOTSTRAP_RESAMPLES, len(values)))
    means = values[idx].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)

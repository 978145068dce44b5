"""One viewer episode: the project's env, stepped by a policy's chunks or a human's pointer, and recorded.

The policy side follows `pusht.rollout.run_episodes` exactly (reset with the episode seed, decision d
asks with request seed `decision_seed(seed, d)`, each chunk run open loop to its end, as long as the
policy's card makes it, the episode ends on success, truncation or 300 steps), so a pure policy episode
scores what `training.evaluate` scores on that seed at its default action horizon (the whole chunk). A human's step drops the rest of the current chunk; the policy's next step then
asks afresh. `save_episode` writes the recording in the dataset's zarr layout, with numpy only (the
service does not depend on zarr or on training.data).
"""

from __future__ import annotations

import json
import os
import re
import uuid
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from pusht.env import MAX_EPISODE_STEPS, PushTEnv
from pusht.geometry import GOAL_POSE, tee_polygons
from pusht.seeding import decision_seed
from pusht.spec import ACTION_HIGH, ACTION_LOW, SUCCESS_COVERAGE

__all__ = ["Episode", "goal_polygons", "save_episode"]


def goal_polygons() -> list[list[list[float]]]:
    """The goal tee as two rectangles of [x, y] pixel corners, for the page to draw."""
    return _polygons(GOAL_POSE)


def _polygons(pose: tuple[float, float, float]) -> list[list[list[float]]]:
    return [[[float(x), float(y)] for x, y in rect] for rect in tee_polygons(*pose)]


class Episode:
    """An episode of `seed` under `policy` (None: teleop only); `step` is synchronous and runs off the event loop."""

    def __init__(self, seed: int, policy: str | None, max_steps: int = MAX_EPISODE_STEPS) -> None:
        self.seed, self.policy, self.max_steps = seed, policy, max_steps
        self.env = PushTEnv(obs_type="state", render_mode=None)
        obs, info = self.env.reset(seed=seed)
        self.obs = np.asarray(obs, dtype=np.float64)
        self.coverage = float(info["coverage"])
        self.decisions = 0  # policy calls so far: the next one asks with decision_seed(seed, decisions)
        self.chunk: np.ndarray | None = None
        self.chunk_index = 0
        self.length = 0
        self.max_reward = 0.0
        self.success = False
        self.done = False
        self.states: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []
        self.human: list[bool] = []
        self.last_action: list[float] | None = None

    def needs_chunk(self) -> bool:
        """Whether the policy's next step needs a new chunk (none left of the current one: every chunk runs to its end)."""
        return self.chunk is None or self.chunk_index >= len(self.chunk)

    def next_request(self) -> tuple[np.ndarray, int]:
        """The state [1, 5] float32 and request seed of the next policy decision (counts the decision)."""
        seed = decision_seed(self.seed, self.decisions)
        self.decisions += 1
        return self.obs[None].astype(np.float32), seed

    def set_chunk(self, chunk: np.ndarray) -> None:
        """The policy's answer [horizon, 2] for the decision just requested."""
        self.chunk, self.chunk_index = np.asarray(chunk, dtype=np.float32), 0

    def step(self, human_action: tuple[float, float] | None = None) -> dict[str, Any]:
        """One env step with the human's action, or else the chunk's next action; returns the state message."""
        if self.done:
            raise ValueError("the episode is over: start a new one")
        if human_action is not None:
            action = np.clip(np.asarray(human_action, dtype=np.float32), ACTION_LOW, ACTION_HIGH)
            self.chunk = None  # the human took over: the policy asks afresh when it gets control back
        else:
            if self.needs_chunk():
                raise ValueError("no policy chunk to step with")
            action = self.chunk[self.chunk_index]
            self.chunk_index += 1
        self.states.append(self.obs.astype(np.float32))
        self.actions.append(action.copy())
        self.human.append(human_action is not None)
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.obs = np.asarray(obs, dtype=np.float64)
        self.length += 1
        self.max_reward = max(self.max_reward, float(reward))
        self.coverage = float(info["coverage"])
        self.success = self.success or bool(info["is_success"]) or self.coverage > SUCCESS_COVERAGE
        self.done = bool(terminated or truncated or self.length >= self.max_steps)
        self.last_action = [float(action[0]), float(action[1])]
        return self.message(actor="human" if human_action is not None else "policy")

    def message(self, actor: str | None = None) -> dict[str, Any]:
        """What the page draws and reports: the state, the block's corners and the scores so far."""
        agent_x, agent_y, block_x, block_y, angle = (float(v) for v in self.obs)
        return {
            "type": "state",
            "step": self.length,
            "state": [agent_x, agent_y, block_x, block_y, angle],
            "block": _polygons((block_x, block_y, angle)),
            "action": self.last_action,
            "actor": actor,
            "coverage": self.coverage,
            "maxReward": self.max_reward,
            "done": self.done,
            "success": self.success,
            "humanSteps": int(sum(self.human)),
            "seed": self.seed,
            "policy": self.policy,
        }


def save_episode(folder: Path, episode: Episode, extra: dict[str, Any] | None = None) -> Path:
    """Write the episode as FOLDER/<time>-<policy|teleop>-seed<N>-<id>.zarr (data/state, data/action, data/human, meta/episode_ends)."""
    if not episode.states:
        raise ValueError("the episode has no steps yet: nothing to save")
    label = re.sub(r"[^A-Za-z0-9_-]", "_", episode.policy or "teleop")[:40]
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    path = folder / f"{stamp}-{label}-seed{episode.seed}-{uuid.uuid4().hex[:6]}.zarr"
    attrs = {
        "source": "python -m service /viewer: states, actions and who acted (data/human: 1 where a human's pointer gave the action)",
        "policy": episode.policy,
        "seed": episode.seed,
        "steps": episode.length,
        "human_steps": int(sum(episode.human)),
        "max_reward": episode.max_reward,
        "success": episode.success,
        "created": stamp,
        **(extra or {}),
    }
    arrays = {
        "data/state": np.stack(episode.states).astype(np.float32),
        "data/action": np.stack(episode.actions).astype(np.float32),
        "data/human": np.asarray(episode.human, dtype=np.uint8),
        "meta/episode_ends": np.asarray([episode.length], dtype=np.int64),
    }
    folder.mkdir(parents=True, exist_ok=True)
    partial = folder / f".{path.name}.partial"
    write_zarr_v2(partial, arrays, attrs)
    os.replace(partial, path)  # a reader never sees a half-written store
    return path


def write_zarr_v2(path: Path, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> None:
    """A zarr v2 directory store of uncompressed single-chunk arrays (what `zarr.open_group` reads back)."""
    path.mkdir(parents=True)
    _write_json(path / ".zgroup", {"zarr_format": 2})
    _write_json(path / ".zattrs", attrs)
    for name, array in arrays.items():
        folder = path / name
        for parent in reversed(folder.relative_to(path).parents[:-1]):
            (path / parent).mkdir(exist_ok=True)
            _write_json(path / parent / ".zgroup", {"zarr_format": 2})
        folder.mkdir()
        array = np.ascontiguousarray(array)
        _write_json(
            folder / ".zarray",
            {
                "zarr_format": 2,
                "shape": list(array.shape),
                "chunks": list(array.shape),
                "dtype": array.dtype.str,
                "compressor": None,
                "fill_value": 0,
                "filters": None,
                "order": "C",
                "dimension_separator": ".",
            },
        )
        (folder / ".".join(["0"] * array.ndim)).write_bytes(array.tobytes())


def _write_json(path: Path, value: Any) -> None:
    path.write_text(json.dumps(value, indent=1) + "\n", encoding="utf-8")

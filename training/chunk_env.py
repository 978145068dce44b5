"""Push-T as a decision process over action chunks: N envs, one 12-action chunk per env per step.

Reinforcement learning in the flow's noise space decides once per chunk, so one transition here is a
whole chunk executed open loop, exactly as evaluation and the service execute it. Envs that end
(success or the 300-step limit) restart at once on the next training seed, so every step returns a
full batch. Training seeds come from a range disjoint from every evaluation and held-out range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pusht.env import MAX_EPISODE_STEPS, PushTEnv
from pusht.spec import SUCCESS_COVERAGE

__all__ = ["ChunkStep", "ChunkVectorEnv"]


@dataclass
class ChunkStep:
    """What one chunk did in each env (arrays of length N)."""

    reward_start: np.ndarray  # env reward (coverage / 0.95, clipped) before the chunk
    reward_end: np.ndarray  # env reward after the chunk's last executed step
    success: np.ndarray  # bool: coverage exceeded 0.95 during the chunk (the episode then ended)
    done: np.ndarray  # bool: the episode ended (success or step limit); the env restarted
    finished_max_reward: list[float]  # max reward of each episode that ended during this step
    finished_success: list[bool]
    next_obs: np.ndarray | None = None  # lookahead only: the state after each candidate [K, 5]
    next_time_fraction: np.ndarray | None = None  # lookahead only: its clock [K]


class ChunkVectorEnv:
    """`num_envs` Push-T envs stepped in lockstep by chunks, restarting on seeds `seed_start, seed_start + 1, ...`."""

    def __init__(self, num_envs: int, seed_start: int, max_steps: int = MAX_EPISODE_STEPS) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.envs = [PushTEnv(obs_type="state", render_mode=None) for _ in range(num_envs)]
        self.max_steps = max_steps
        self.seed_start = int(seed_start)
        self._next_seed = self.seed_start
        self.obs = np.zeros((num_envs, 5), dtype=np.float64)
        self.elapsed = np.zeros(num_envs, dtype=np.int64)
        self._reward = np.zeros(num_envs, dtype=np.float64)
        self._max_reward = np.zeros(num_envs, dtype=np.float64)
        self._scratch: PushTEnv | None = None
        for i in range(num_envs):
            self._restart(i)

    @property
    def num_envs(self) -> int:
        """Number of envs."""
        return len(self.envs)

    @property
    def episodes_started(self) -> int:
        """Episodes started so far (the next one takes seed `seed_start + episodes_started`)."""
        return self._next_seed - self.seed_start

    def time_fraction(self) -> np.ndarray:
        """Elapsed steps of each env's episode over the step limit, in [0, 1): the critic's clock."""
        return self.elapsed / self.max_steps

    def step(self, chunks: np.ndarray) -> ChunkStep:
        """Execute chunks [N, H, 2] (env units) open loop; envs whose episode ends restart."""
        n = self.num_envs
        start = self._reward.copy()
        end = np.zeros(n)
        success = np.zeros(n, dtype=bool)
        done = np.zeros(n, dtype=bool)
        finished_max, finished_success = [], []
        for i, env in enumerate(self.envs):
            reward = self._reward[i]
            for action in chunks[i]:
                obs, reward, terminated, truncated, info = env.step(action)
                self.elapsed[i] += 1
                self._max_reward[i] = max(self._max_reward[i], reward)
                if info["coverage"] > SUCCESS_COVERAGE:
                    success[i] = True
                if terminated or truncated or self.elapsed[i] >= self.max_steps:
                    done[i] = True
                    break
            end[i] = reward
            self._reward[i] = reward
            self.obs[i] = obs
            if done[i]:
                finished_max.append(float(self._max_reward[i]))
                finished_success.append(bool(success[i]))
                self._restart(i)
        return ChunkStep(start, end, success, done, finished_max, finished_success)

    def lookahead(self, i: int, chunks: np.ndarray) -> ChunkStep:
        """What each of the chunks [K, H, 2] would do from env i's present state; env i itself does not move.

        Each candidate runs in a scratch env restored from env i's `physics_snapshot` (no contact cache),
        so it matches a real step closely, not bit for bit.
        """
        snapshot = self.envs[i].physics_snapshot()
        if self._scratch is None:
            self._scratch = PushTEnv(obs_type="state", render_mode=None)
            self._scratch.reset(seed=0)
        scratch = self._scratch
        k = len(chunks)
        start = np.full(k, self._reward[i])
        end, success, done = np.zeros(k), np.zeros(k, dtype=bool), np.zeros(k, dtype=bool)
        next_obs, next_elapsed = np.zeros((k, 5)), np.zeros(k, dtype=np.int64)
        for c, chunk in enumerate(chunks):
            scratch.restore_physics(snapshot)
            elapsed, reward = int(self.elapsed[i]), self._reward[i]
            for action in chunk:
                obs, reward, terminated, _, info = scratch.step(action)
                elapsed += 1
                if info["coverage"] > SUCCESS_COVERAGE:
                    success[c] = True
                if terminated or elapsed >= self.max_steps:
                    done[c] = True
                    break
            end[c], next_obs[c], next_elapsed[c] = reward, obs, elapsed
        return ChunkStep(start, end, success, done, [], [], next_obs, next_elapsed / self.max_steps)

    def _restart(self, i: int) -> None:
        obs, info = self.envs[i].reset(seed=self._next_seed)
        self._next_seed += 1
        self.obs[i] = obs
        self.elapsed[i] = 0
        self._reward[i] = min(info["coverage"] / SUCCESS_COVERAGE, 1.0)
        self._max_reward[i] = self._reward[i]

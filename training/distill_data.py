"""What a student distils: states with start noises, and the teacher's chunks there.

States come from the demonstrations (each with a fresh noise) and from episodes a policy plays (each
decision's state with the very noise it was played with, `pusht.seeding`): the teacher's own episodes
show where it goes, the student's show where the student goes wrong (DAgger, Ross et al. 2011, with the
teacher as the expert that labels every state the student visits).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from pusht.seeding import chunk_noise, decision_seed, row_noise

__all__ = ["PAIRS_FILE", "Pairs", "decision_pairs", "teacher_chunks"]

LABEL_BATCH = 512
PAIRS_FILE = "pairs.safetensors"
"""where a distillation run keeps its labelled pairs (after every round), for `--pairs-from`"""


class Pairs:
    """The growing set of (normalized state, standard-normal start noise, teacher's normalized chunk) triples."""

    def __init__(self, teacher: torch.nn.Module, teacher_name: str, teacher_steps: int, progress: bool = False,
                 fixed_noise: int = -1) -> None:
        self.teacher, self.teacher_name, self.teacher_steps, self.progress = teacher, str(teacher_name), teacher_steps, progress
        # With a fixed noise every state is labelled from that one start: the teacher as a deterministic policy.
        self.fixed_noise = fixed_noise
        self.labels = {"teacher": self.teacher_name, "teacher_steps": str(teacher_steps), "fixed_noise": str(fixed_noise)}
        self.parts: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []

    def __len__(self) -> int:
        return sum(len(part[0]) for part in self.parts)

    def add(self, states: np.ndarray, noise: np.ndarray, source: str) -> None:
        """Label env-unit `states` [N, S] at standard-normal `noise` [N, H, A] with the teacher's chunks and keep them."""
        print(f"labelling {len(states)} states of the {source} with {self.teacher_name}", file=sys.stderr)
        if self.fixed_noise >= 0:
            noise = np.broadcast_to(chunk_noise(self.fixed_noise, 1, *noise.shape[1:]), noise.shape).copy()
        state_n = self.teacher.policy_state(torch.as_tensor(states))
        noise = torch.as_tensor(noise)
        self.parts.append((state_n, noise, teacher_chunks(self.teacher, state_n, noise, self.teacher_steps, self.progress)))

    def batch(self, size: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A uniform random batch of the triples."""
        if len(self.parts) > 1:
            self.parts = [tuple(torch.cat(column) for column in zip(*self.parts))]
        idx = torch.randint(0, len(self), (size,), generator=generator)
        return tuple(column[idx] for column in self.parts[0])

    def save(self, path: Path) -> None:
        """Write every triple to `path` (safetensors), naming the teacher that labelled them."""
        from safetensors.torch import save_file

        columns = [torch.cat(column).contiguous() for column in zip(*self.parts)]
        save_file(dict(zip(("state_n", "noise", "target"), columns)), str(path), metadata=self.labels)

    def load(self, path: Path) -> None:
        """Add the triples saved at `path`; ValueError unless they were labelled the same way (teacher, steps, noise)."""
        from safetensors import safe_open

        if not path.is_file():
            raise FileNotFoundError(f"{path}: no saved pairs (a distillation run writes them after its first round)")
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            if {k: meta.get(k) for k in self.labels} != self.labels:
                raise ValueError(f"{path}: labelled by {meta.get('teacher')} in {meta.get('teacher_steps')} steps with fixed noise "
                                 f"{meta.get('fixed_noise')}, not by {self.teacher_name} in {self.teacher_steps} with {self.fixed_noise}")
            self.parts.append(tuple(f.get_tensor(k) for k in ("state_n", "noise", "target")))
        print(f"loaded {len(self)} pairs from {path}", file=sys.stderr)


def decision_pairs(module: torch.nn.Module, episodes: int, seed: int, num_envs: int = 500) -> tuple[np.ndarray, np.ndarray, dict]:
    """The decision states [N, S] and standard-normal start noises [N, H, A] of the episodes `module` (an ActingPolicy)
    plays on seeds seed..seed+episodes-1, and the scores of those episodes."""
    from training.evaluate import evaluate_policy

    policy = module.policy
    summary = evaluate_policy(module, episodes=episodes, seed=seed, num_envs=num_envs, record_trajectories=True)
    states, noise = [], []
    for trajectory in summary.trajectories:
        decisions = trajectory.states[:: policy.horizon]
        states.append(decisions)
        noise.append(row_noise([decision_seed(trajectory.seed, d) for d in range(len(decisions))], policy.horizon, policy.action_dim))
    scores = {k: v for k, v in summary.scores().items() if k != "wall_time_s"}
    return np.concatenate(states).astype(np.float32), np.concatenate(noise), scores


@torch.no_grad()
def teacher_chunks(teacher: torch.nn.Module, state_n: torch.Tensor, noise: torch.Tensor, num_steps: int, progress: bool = False) -> torch.Tensor:
    """The teacher's normalized chunks [N, H, A] for its network's inputs `state_n` [N, S'] and standard-normal noises [N, H, A]."""
    from tqdm import tqdm

    out = []
    for i in tqdm(range(0, len(state_n), LABEL_BATCH), desc="label", disable=not progress, file=sys.stderr):
        out.append(teacher.sample_actions(state_n[i : i + LABEL_BATCH], noise[i : i + LABEL_BATCH], num_steps))
    return torch.cat(out)

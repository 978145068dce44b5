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

__all__ = ["PAIRS_FILE", "Pairs", "decision_pairs", "teacher_choices", "teacher_chunks", "teacher_top"]

LABEL_BATCH = 512
PAIRS_FILE = "pairs.safetensors"
"""where a distillation run keeps its labelled pairs (after every round), for `--pairs-from`"""


class Pairs:
    """The growing set of labelled states: (normalized state, standard-normal start noise, teacher's normalized chunk)
    triples, or with `choices` (a one-pass student) (normalized state, the chooser's K candidates, their K x S predicted
    goal distances)."""

    def __init__(self, teacher: torch.nn.Module, teacher_name: str, teacher_steps: int, progress: bool = False,
                 fixed_noise: int = -1, choices: bool = False, top: int = 1) -> None:
        self.teacher, self.teacher_name, self.teacher_steps, self.progress = teacher, str(teacher_name), teacher_steps, progress
        # With a fixed noise every state is labelled from that one start: the teacher as a deterministic policy.
        self.fixed_noise = fixed_noise
        self.choices = choices
        self.top = top  # > 1: each state's label is the chooser's `top` best chunks [top, H, A], best first
        self.columns = ("state_n", "candidates", "distances") if choices else ("state_n", "noise", "target")
        self.labels = {"teacher": self.teacher_name, "teacher_steps": str(teacher_steps), "fixed_noise": str(fixed_noise)}
        if choices:  # files of chunk labels carry no such key
            self.labels["labels"] = "choices"
        if top > 1:
            self.labels["labels"] = f"top {top}"
        self.parts: list[tuple[torch.Tensor, ...]] = []

    def __len__(self) -> int:
        return sum(len(part[0]) for part in self.parts)

    def add(self, states: np.ndarray, noise: np.ndarray, source: str) -> None:
        """Label env-unit `states` [N, S] at standard-normal `noise` [N, H, A] with the teacher's chunks (or choices) and keep them."""
        self.add_inputs(self.teacher.policy_state(torch.as_tensor(states)), torch.as_tensor(noise), source)

    def add_inputs(self, state_n: torch.Tensor, noise: torch.Tensor, source: str) -> None:
        """`add` for states already as the teacher's network inputs [N, S']."""
        print(f"labelling {len(state_n)} states of the {source} with {self.teacher_name}", file=sys.stderr)
        if self.fixed_noise >= 0:
            noise = torch.as_tensor(chunk_noise(self.fixed_noise, 1, *noise.shape[1:])).expand(len(noise), -1, -1)
        if self.choices:
            self.parts.append((state_n, *teacher_choices(self.teacher, state_n, noise, self.teacher_steps, self.progress)))
        elif self.top > 1:
            self.parts.append((state_n, noise, teacher_top(self.teacher, state_n, noise, self.teacher_steps, self.top, self.progress)))
        else:
            self.parts.append((state_n, noise, teacher_chunks(self.teacher, state_n, noise, self.teacher_steps, self.progress)))

    def batch(self, size: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A uniform random batch of the labelled states (a tuple of `columns`)."""
        if len(self.parts) > 1:
            self.parts = [tuple(torch.cat(column) for column in zip(*self.parts))]
        idx = torch.randint(0, len(self), (size,), generator=generator)
        return tuple(column[idx] for column in self.parts[0])

    def save(self, path: Path) -> None:
        """Write every labelled state to `path` (safetensors), naming the teacher that labelled them."""
        from safetensors.torch import save_file

        columns = [torch.cat(column).contiguous() for column in zip(*self.parts)]
        save_file(dict(zip(self.columns, columns)), str(path), metadata=self.labels)

    def relabel(self, path: Path, limit: int | None = None, generator: torch.Generator | None = None) -> None:
        """Label anew the states saved at `path` by any distillation run (with their noises, unless this labelling fixes one);
        of more than `limit`, that many drawn at random."""
        from safetensors import safe_open

        with safe_open(str(_saved_pairs(path)), framework="pt") as f:
            state_n = f.get_tensor("state_n")
            if "noise" in f.keys():
                noise = f.get_tensor("noise")
            elif self.fixed_noise >= 0:
                noise = torch.zeros(len(state_n), self.teacher.horizon, self.teacher.action_dim)  # replaced by the fixed one
            else:
                raise ValueError(f"{path}: its states carry no start noises to label them with; give a fixed noise")
        if limit is not None and len(state_n) > limit:
            rows = torch.randperm(len(state_n), generator=generator)[:limit]
            state_n, noise = state_n[rows], noise[rows]
        self.add_inputs(state_n, noise, f"states of {path}")

    def saved_states(self, path: Path) -> torch.Tensor:
        """The network inputs [N, S'] of the states saved at `path` by any distillation run (their labels unread)."""
        from safetensors import safe_open

        with safe_open(str(_saved_pairs(path)), framework="pt") as f:
            return f.get_tensor("state_n")

    def load(self, path: Path) -> None:
        """Add the labels saved at `path`; ValueError unless they were labelled the same way (teacher, steps, noise, kind)."""
        from safetensors import safe_open

        with safe_open(str(_saved_pairs(path)), framework="pt") as f:
            meta = f.metadata() or {}
            if ({k: meta.get(k) for k in self.labels} != self.labels or meta.get("labels") != self.labels.get("labels")
                    or set(f.keys()) != set(self.columns)):
                raise ValueError(f"{path}: {meta.get('labels', 'chunks')} labelled by {meta.get('teacher')} in {meta.get('teacher_steps')} "
                                 f"steps with fixed noise {meta.get('fixed_noise')}, not {self.labels.get('labels', 'chunks')} by "
                                 f"{self.teacher_name} in {self.teacher_steps} with {self.fixed_noise}")
            self.parts.append(tuple(f.get_tensor(k) for k in self.columns))
        print(f"loaded {len(self)} pairs from {path}", file=sys.stderr)


def _saved_pairs(path: Path) -> Path:
    """`path`, or FileNotFoundError naming it unless a distillation run saved pairs there."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no saved pairs (a distillation run writes them after its first round)")
    return path


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


@torch.no_grad()
def teacher_choices(teacher: torch.nn.Module, state_n: torch.Tensor, noise: torch.Tensor, num_steps: int,
                    progress: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """An outcome chooser's K unstretched normalized candidates [N, K, H, A] and the predicted goal distances of all K x S
    choices [N, K * S] (`OutcomeSelector.scored_candidates`) at its network's inputs `state_n` [N, S'] and noises [N, H, A]."""
    from tqdm import tqdm

    k = teacher.outcome.candidates
    candidates, distances = [], []
    for i in tqdm(range(0, len(state_n), LABEL_BATCH), desc="label", disable=not progress, file=sys.stderr):
        chunks_n, distance = teacher.outcome.scored_candidates(teacher, state_n[i : i + LABEL_BATCH], noise[i : i + LABEL_BATCH], num_steps)
        candidates.append(chunks_n[:, :k].clone())  # the stretched ones follow from these
        distances.append(distance)
    return torch.cat(candidates), torch.cat(distances)


@torch.no_grad()
def teacher_top(teacher: torch.nn.Module, state_n: torch.Tensor, noise: torch.Tensor, num_steps: int, top: int,
                progress: bool = False) -> torch.Tensor:
    """An outcome chooser's `top` best (candidate, stretch) chunks [N, top, H, A] (normalized, best first) at its network's
    inputs `state_n` [N, S'] and noises [N, H, A]: as good as its pick by its own model, and spread over its modes."""
    from tqdm import tqdm

    out = []
    for i in tqdm(range(0, len(state_n), LABEL_BATCH), desc="label", disable=not progress, file=sys.stderr):
        chunks_n, distance = teacher.outcome.scored_candidates(teacher, state_n[i : i + LABEL_BATCH], noise[i : i + LABEL_BATCH], num_steps)
        best = distance.argsort(dim=1)[:, :top]
        out.append(torch.gather(chunks_n, 1, best[:, :, None, None].expand(-1, -1, *chunks_n.shape[2:])))
    return torch.cat(out)

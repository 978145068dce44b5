"""`training.finetune --algo dagger`: distil an outcome chooser into a plain flow, labelled by the chooser at the flow's own states.

The chooser plays the best of its flow's candidate chunks; its flow alone samples any of them. Here a student
flow, starting from the chooser's own flow weights (or from `--init` when `--dagger-teacher` names the chooser),
learns the chooser's picks by DAgger: each iteration plays `dagger_episodes` episodes (training seeds) in which each
chunk comes from the chooser with probability `dagger_teacher_share` (always in the first iteration of a student that
starts from the chooser's flow) and otherwise from the student, and every decision's state is labelled with the chunk
the chooser picks there. The student is then fitted by flow matching on all labels so far (`dagger_updates`
minibatches, the rate constant or annealed to 0 in each fit). The chooser never changes; the checkpoint is the
student, a plain flow-matching sampler whose noise changes its actions.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from policies.base import ActingPolicy
from policies.checkpoint import load_checkpoint, read_tensors, write_tensors
from policies.factory import build_policy
from pusht.rollout import row_noise, run_episodes
from training.finetune_config import FinetuneConfig
from training.outcome_fit import FlowChooser, Resumable
from training.replay import ReplayBuffer

__all__ = ["DaggerFit", "Student", "read_labels"]

CHOOSER_KEYS = ("outcome_dims", "outcome_candidates", "outcome_stretches", "value_dims")
"""the architecture keys of a flow's chooser: the student's architecture is the chooser's without them"""


@dataclass
class Student:
    """What a fit trains, saves and evaluates (for the outcome and value fits, the chooser itself: `FlowChooser`)."""

    policy: torch.nn.Module
    normalization: dict
    acting: ActingPolicy


class DaggerFit(Resumable):
    """DAgger of a plain flow toward the frozen chooser `agent`: label the chooser's picks at the visited states, fit."""

    def __init__(self, agent: FlowChooser, cfg: FinetuneConfig, generator: torch.Generator) -> None:
        self.agent, self.cfg, self.generator = agent, cfg, generator
        chooser = agent.policy
        plain = {k: v for k, v in chooser.architecture.items() if k not in CHOOSER_KEYS}
        policy = build_policy("flow", **plain)
        policy.load_state_dict(_student_weights(chooser, cfg))
        policy.normalizer.set(chooser.normalizer)
        self.trained = Student(policy, policy.normalizer.to_dict(), ActingPolicy(policy, num_steps=cfg.flow_num_steps))
        self.opt = torch.optim.AdamW(policy.parameters(), lr=cfg.dagger_lr, weight_decay=1e-4)
        self.replay = ReplayBuffer(
            cfg.buffer_size, chooser.state_dim, chooser.horizon * chooser.action_dim, {"state": 0, "x0": 0}
        )
        self.rng = np.random.default_rng(cfg.seed)
        self.episodes = 0  # played so far: the next iteration starts at train_seed_start + episodes
        if cfg.dagger_labels:
            widths = {k: v.shape[1] for k, v in self.replay.data.items()}
            self.replay.add(**read_labels(cfg.dagger_labels, policy.normalizer.to_dict(), widths))

    def parts(self) -> tuple[dict, dict, dict]:
        """(modules, optimizers, replays) by name: the student, its optimizer, the labels (chunks as `x0`)."""
        return {"student": self.trained.policy}, {"student": self.opt}, {"labels": self.replay}

    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """As `Resumable.state`, plus the episodes played and the stream that picks who plays each chunk."""
        tensors, extra = super().state()
        return tensors, {**extra, "dagger_episodes_played": self.episodes, "numpy_rng": self.rng.bit_generator.state}

    def load_state(self, tensors: dict[str, torch.Tensor], extra: dict) -> None:
        """Restore what `state` saved."""
        super().load_state(tensors, extra)
        self.episodes = int(extra["dagger_episodes_played"])
        self.rng.bit_generator.state = extra["numpy_rng"]

    def iterate(self, finished_max: list, finished_success: list) -> dict:
        """One round: episodes played by the student and the chooser, every decision labelled; the student refitted."""
        cfg = self.cfg
        share = 1.0 if self.episodes == 0 and not cfg.dagger_teacher else cfg.dagger_teacher_share
        first = cfg.train_seed_start + self.episodes
        summary = run_episodes(self._labelling_act(share), range(first, first + cfg.dagger_episodes), cfg.num_envs)
        self.episodes += cfg.dagger_episodes
        finished_max.extend(e.max_reward for e in summary.episodes)
        finished_success.extend(e.success for e in summary.episodes)
        return {"episodes": self.episodes, "flow_loss": self._fit(), "labels": self.replay.size, "teacher_share": share}

    def save_outputs(self, run_dir: Path) -> None:
        """The pool as labels.safetensors, for `dagger_labels` of a later run."""
        self.save_labels(run_dir / "labels.safetensors")

    def save_labels(self, path: str | Path) -> None:
        """Write the pool (states and the chooser's normalized picks) for `dagger_labels` of a later run."""
        write_tensors(Path(path), self.replay.filled(), {"normalization": _stamp(self.trained.normalization)})

    def _labelling_act(self, share: float):
        """The rollout's act: every row labelled with the chooser's pick, played by the chooser in a `share` of rows."""
        chooser, student, steps = self.agent.policy, self.trained.policy, self.agent.num_steps
        student.eval()

        def act(states: np.ndarray, seeds: list[int]) -> np.ndarray:
            state = torch.as_tensor(states, dtype=torch.float32)
            noise = torch.as_tensor(row_noise(seeds))
            with torch.no_grad():
                # the student's normalizer is the chooser's, so the chooser's normalized pick is the student's label
                label = chooser.sample_actions(chooser.policy_state(state), noise=noise, num_steps=steps)
                taught = chooser.arena_actions(state, label)
                own = student.act(state, noise, self.cfg.flow_num_steps)
            self.replay.add(state=state, x0=label.flatten(1))
            by_chooser = torch.as_tensor(self.rng.random(len(state)) < share)[:, None, None]
            return torch.where(by_chooser, taught, own).numpy()

        return act

    def _fit(self) -> float:
        """`dagger_updates` minibatches of flow matching on the labels; the mean loss of the last 100."""
        cfg, student = self.cfg, self.trained.policy
        student.train()
        losses = []
        for update in range(cfg.dagger_updates):
            if cfg.dagger_lr_schedule == "cosine":
                for group in self.opt.param_groups:
                    group["lr"] = cfg.dagger_lr * 0.5 * (1 + math.cos(math.pi * update / cfg.dagger_updates))
            batch = self.replay.sample(cfg.batch_size, self.generator)
            chunk_n = batch["x0"].reshape(-1, student.horizon, student.action_dim)
            loss = student.normalized_loss(student.policy_state(batch["state"]), chunk_n, generator=self.generator)
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            self.opt.step()
            losses.append(float(loss.detach()))
        student.eval()
        return float(np.mean(losses[-100:]))


def _student_weights(chooser: torch.nn.Module, cfg: FinetuneConfig) -> dict[str, torch.Tensor]:
    """The student's first weights: the chooser's flow, or the plain flow `--init` when `--dagger-teacher` is the chooser."""
    flow = {k: v for k, v in chooser.state_dict().items() if not k.startswith("outcome.")}
    if not cfg.dagger_teacher:
        return flow
    student, card = load_checkpoint(cfg.init)
    weights = student.state_dict()
    if (
        card["kind"] != "flow"
        or "outcome_dims" in card["architecture"]
        or {k: v.shape for k, v in weights.items()} != {k: v.shape for k, v in flow.items()}
    ):
        raise ValueError(f"{cfg.init}: a dagger student must be a plain flow of the architecture of the chooser's flow")
    return weights


def read_labels(path: str, normalization: dict, widths: dict[str, int]) -> dict[str, torch.Tensor]:
    """The labels `DaggerFit.save_labels` wrote, checked against the chooser's normalization (its picks are normalized)."""
    labels, metadata = read_tensors(Path(path), "labels file of a dagger run")
    shapes = {k: list(v.shape) for k, v in labels.items()}
    if set(labels) != set(widths) or any(
        v.ndim != 2 or v.shape[1] != widths[k] or len(v) != len(labels["state"]) for k, v in labels.items()
    ):
        raise ValueError(f"{path}: a labels file holds state and x0 rows of widths {widths}, as many of each, got {shapes}")
    if metadata.get("normalization") != _stamp(normalization):
        raise ValueError(f"{path}: labelled under another normalization than this chooser's")
    return labels


def _stamp(normalization: dict) -> str:
    """The normalization as a labels file records it (its picks are in those units)."""
    return json.dumps(normalization, sort_keys=True)

"""`training.finetune --algo value`: fit the outcome chooser's value of time, by policy iteration on its own episodes.

The outcome chooser (training.outcome_fit) plays the chunk it predicts leaves the tee closest to the goal:
greedy over one chunk, so it dithers where a better approach takes a detour, and it is slower than the
demonstrators it copies. Each iteration here plays `value_episodes` episodes of up to `value_max_steps`
steps with the current chooser, labels every state exp(-steps to success / tau) (0 where the episode
failed), and fits `policies.chooser.ValueModel` on the latest labels (a ring of `buffer_size` states);
the chooser then plays the candidate whose predicted end state the value ranks best. Each iteration is a
step of policy iteration: the value of the chooser of the iteration before. Episodes use training seeds
(`train_seed_start` on, consecutive), never an evaluation or held-out one.
"""

from __future__ import annotations

import numpy as np
import torch

from pusht.rollout import RolloutSummary
from training.evaluate import evaluate_policy
from training.finetune_config import FinetuneConfig
from training.outcome_fit import FlowChooser, Resumable
from training.replay import ReplayBuffer

__all__ = ["ValueFit", "value_labels"]


class ValueFit(Resumable):
    """Policy iteration of `policy.outcome.value`: collect episodes with the current chooser, refit the value on them."""

    FIELDS = {"state": 0, "value": 1}

    def __init__(self, agent: FlowChooser, cfg: FinetuneConfig, generator: torch.Generator) -> None:
        self.agent, self.cfg, self.generator = agent, cfg, generator
        self.trained = agent
        self.value = agent.policy.outcome.value
        self.replay = ReplayBuffer(cfg.buffer_size, agent.policy.state_dim, 0, self.FIELDS)
        self.episodes = 0  # played so far: the next iteration starts at train_seed_start + episodes
        # until the first fit the chooser ranks by distance, as it did before this stage (a random value ranks at random)
        agent.policy.outcome.rank_by_value = False

    def parts(self) -> tuple[dict, dict, dict]:
        """(modules, optimizers, replays) by name (each iteration's fit starts a fresh optimizer)."""
        return {"value": self.value}, {}, {"labels": self.replay}

    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """As `Resumable.state`, plus how many episodes were played."""
        tensors, extra = super().state()
        return tensors, {**extra, "value_episodes_played": self.episodes}

    def load_state(self, tensors: dict[str, torch.Tensor], extra: dict) -> None:
        """Restore what `state` saved."""
        super().load_state(tensors, extra)
        self.episodes = int(extra["value_episodes_played"])
        self.agent.policy.outcome.rank_by_value = self.episodes > 0

    def iterate(self, finished_max: list, finished_success: list) -> dict:
        """One round: the chooser's episodes (their results join `finished_*`), their labels, the value refitted."""
        cfg = self.cfg
        summary = evaluate_policy(
            self.agent.acting,
            cfg.value_episodes,
            cfg.train_seed_start + self.episodes,
            num_envs=cfg.num_envs,
            max_steps=cfg.value_max_steps,
            record_trajectories=True,
        )
        self.episodes += cfg.value_episodes
        finished_max.extend(e.max_reward for e in summary.episodes)
        finished_success.extend(e.success for e in summary.episodes)
        states, values = value_labels(summary, cfg.value_tau)
        self.replay.add(state=torch.as_tensor(states), value=torch.as_tensor(values))
        loss = self._fit()
        self.agent.policy.outcome.rank_by_value = True
        lengths = [e.length for e in summary.episodes if e.success]
        return {
            "episodes": self.episodes,
            "value_loss": loss,
            "labels": self.replay.size,
            "collect_mean_steps_to_success": float(np.mean(lengths)) if lengths else None,
        }

    def _fit(self) -> float:
        """`value_updates` minibatches of regression, the learning rate annealed to 0; the mean loss of the last 100."""
        cfg = self.cfg
        self.value.train()
        opt = torch.optim.AdamW(self.value.parameters(), lr=cfg.critic_lr, weight_decay=1e-4)
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.value_updates)
        losses = []
        for _ in range(cfg.value_updates):
            batch = self.replay.sample(cfg.batch_size, self.generator)
            loss = torch.nn.functional.mse_loss(self.value(batch["state"]), batch["value"][:, 0])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            schedule.step()
            losses.append(float(loss.detach()))
        self.value.eval()
        return float(np.mean(losses[-100:]))


def value_labels(summary: RolloutSummary, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Every recorded state [N, 5] (float32) and its label [N]: exp(-steps to success / tau), 0 in a failed episode."""
    success = {e.seed: e.success for e in summary.episodes}
    states, values = [], []
    for trajectory in summary.trajectories:
        steps = len(trajectory.states)
        to_go = steps - np.arange(steps)
        values.append(np.exp(-to_go / tau) if success[trajectory.seed] else np.zeros(steps))
        states.append(trajectory.states)
    return np.concatenate(states).astype(np.float32), np.concatenate(values).astype(np.float32)

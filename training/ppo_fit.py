"""`training.finetune --algo ppo`: fine-tune a plain flow's weights in the env by PPO on a discounted return.

The flow samples a chunk by integrating its velocity from start noise; here that chunk is the mean of a Gaussian of
fixed std `ppo_sigma` (normalized chunk units) over the chunk the env executes, so the sampler has a likelihood given
its start noise, and the policy gradient reaches the flow's weights through its Euler steps (ReinFlow injects such noise
at every step; one draw at the end is enough here). One decision is one 12-action chunk, executed open loop in
`num_envs` envs (`training.chunk_env`) on training seeds. The return rewards finishing early: 1 at success, discounted
by `ppo_gamma` per env step, shaped by the env's reward as a potential (gamma^12 phi(s') - phi(s), phi 0 past the end:
each chunk is credited with its progress, and a finished episode's shaping sums to -phi(start)). A critic of the state
and the episode's clock gives the advantages (GAE; an episode cut at the step limit ends there as a failure, which the
clock lets the critic foresee); the first `ppo_warmup` iterations fit only the critic. The checkpoint is the flow
itself, acting without the Gaussian: still a sampler whose start noise changes its actions, with `flow_num_steps`
Euler steps.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from policies.base import ActingPolicy
from policies.networks import mlp
from training.chunk_env import ChunkVectorEnv
from training.dagger_fit import Student
from training.finetune_config import FinetuneConfig
from training.outcome_fit import FlowChooser, Resumable

__all__ = ["PPOFit"]


class PPOFit(Resumable):
    """PPO of the plain flow `agent.policy` (its chunk the mean of a fixed Gaussian) with a state-and-clock critic."""

    def __init__(self, agent: FlowChooser, cfg: FinetuneConfig, generator: torch.Generator) -> None:
        self.cfg, self.generator = cfg, generator
        policy = agent.policy
        self.trained = Student(policy, agent.normalization, ActingPolicy(policy, num_steps=cfg.flow_num_steps))
        self.critic = Critic(policy, cfg.value_dims_list())
        self.opt = torch.optim.Adam(policy.parameters(), lr=cfg.ppo_lr)
        self.critic_opt = torch.optim.Adam(self.critic.net.parameters(), lr=cfg.critic_lr)
        self.discount = cfg.ppo_gamma**policy.horizon  # per chunk
        self.iterations = 0
        self.episodes_before = 0  # started before a resume: the envs go on at the next training seed
        self.envs: ChunkVectorEnv | None = None  # built at the first iteration, after any resume

    def parts(self) -> tuple[dict, dict, dict]:
        """(modules, optimizers, replays) by name: the flow, its critic, their optimizers."""
        modules = {"flow": self.trained.policy, "critic": self.critic.net}
        return modules, {"flow": self.opt, "critic": self.critic_opt}, {}

    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """As `Resumable.state`, plus the iterations done and the episodes started (a resumed run starts fresh episodes)."""
        tensors, extra = super().state()
        return tensors, {**extra, "ppo_iterations": self.iterations, "episodes_started": self.episodes}

    def load_state(self, tensors: dict[str, torch.Tensor], extra: dict) -> None:
        """Restore what `state` saved."""
        super().load_state(tensors, extra)
        self.iterations = int(extra["ppo_iterations"])
        self.episodes_before = int(extra["episodes_started"])

    @property
    def episodes(self) -> int:
        """Episodes started so far: a resumed run never replays an episode seed."""
        return self.episodes_before + (self.envs.episodes_started if self.envs is not None else 0)

    def iterate(self, finished_max: list, finished_success: list) -> dict:
        """`rollout_decisions` chunks in every env, then `ppo_epochs` passes over them (the critic's only while warming up)."""
        cfg = self.cfg
        if self.envs is None:
            self.envs = ChunkVectorEnv(cfg.num_envs, cfg.train_seed_start + self.episodes_before)
        batch = self._collect(finished_max, finished_success)
        self.iterations += 1
        stats = {"episodes": self.episodes, "critic_loss": self._fit_critic(batch)}
        if self.iterations > cfg.ppo_warmup:
            stats.update(self._fit_flow(batch))
        return stats

    def _mean(self, state: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
        """The flow's normalized chunks, flat [B, H * A], integrated from standard-normal starts [B, H, A]."""
        policy = self.trained.policy
        x0 = policy.start_noise(state, start)
        return policy.integrate(policy.policy_state(state), x0, self.cfg.flow_num_steps).flatten(1)

    def _log_prob(self, mean: torch.Tensor, chunk: torch.Tensor) -> torch.Tensor:
        # the constant terms cancel in every ratio
        return -0.5 * (((chunk - mean) / self.cfg.ppo_sigma) ** 2).sum(1)

    def _collect(self, finished_max: list, finished_success: list) -> dict[str, torch.Tensor]:
        """Play `rollout_decisions` chunks in every env; the batch with its advantages and returns."""
        cfg, envs, policy = self.cfg, self.envs, self.trained.policy
        policy.eval()
        steps = []
        for _ in range(cfg.rollout_decisions):
            state = torch.as_tensor(envs.obs, dtype=torch.float32)
            clock = torch.as_tensor(envs.time_fraction(), dtype=torch.float32)
            start = torch.randn((envs.num_envs, policy.horizon, policy.action_dim), generator=self.generator)
            with torch.no_grad():
                mean = self._mean(state, start)
                chunk = mean + cfg.ppo_sigma * torch.randn(mean.shape, generator=self.generator)
                actions = policy.arena_actions(state, chunk.reshape(start.shape)).numpy()
            result = envs.step(actions)
            finished_max.extend(result.finished_max_reward)
            finished_success.extend(result.finished_success)
            reward = result.success + cfg.ppo_shaping * (
                self.discount * np.where(result.done, 0.0, result.reward_end) - result.reward_start
            )
            steps.append((state, clock, start, chunk, self._log_prob(mean, chunk), reward, result.done))
        return self._advantages(steps)

    def _advantages(self, steps: list) -> dict[str, torch.Tensor]:
        """Generalized advantage estimates (lambda `ppo_lambda`) over the decisions, the batch flattened."""
        cfg, envs = self.cfg, self.envs
        state, clock, start, chunk, log_prob = (torch.stack([s[i] for s in steps]) for i in range(5))
        reward = torch.as_tensor(np.stack([s[5] for s in steps]), dtype=torch.float32)
        going = 1.0 - torch.as_tensor(np.stack([s[6] for s in steps]), dtype=torch.float32)
        with torch.no_grad():
            value = self.critic(state.flatten(0, 1), clock.flatten()).reshape(reward.shape)
            last = self.critic(
                torch.as_tensor(envs.obs, dtype=torch.float32), torch.as_tensor(envs.time_fraction(), dtype=torch.float32)
            )
        advantage = torch.zeros_like(reward)
        running = torch.zeros_like(last)
        for t in reversed(range(len(steps))):
            following = last if t == len(steps) - 1 else value[t + 1]
            delta = reward[t] + self.discount * following * going[t] - value[t]
            running = delta + self.discount * cfg.ppo_lambda * going[t] * running
            advantage[t] = running
        flat = {"state": state, "clock": clock, "start": start, "chunk": chunk, "log_prob": log_prob, "advantage": advantage}
        batch = {k: v.flatten(0, 1) for k, v in flat.items()}
        batch["return"] = (advantage + value).flatten()
        return batch

    def _minibatches(self, size: int):
        for _ in range(self.cfg.ppo_epochs):
            order = torch.randperm(size, generator=self.generator)
            yield from order.split(self.cfg.batch_size)

    def _fit_critic(self, batch: dict[str, torch.Tensor]) -> float:
        losses = []
        for rows in self._minibatches(len(batch["return"])):
            loss = nn.functional.mse_loss(self.critic(batch["state"][rows], batch["clock"][rows]), batch["return"][rows])
            self.critic_opt.zero_grad(set_to_none=True)
            loss.backward()
            self.critic_opt.step()
            losses.append(float(loss.detach()))
        return float(np.mean(losses))

    def _fit_flow(self, batch: dict[str, torch.Tensor]) -> dict:
        """Clipped-ratio updates of the flow; an epoch past a mean KL of `ppo_target_kl` ends them."""
        cfg, policy = self.cfg, self.trained.policy
        advantage = (batch["advantage"] - batch["advantage"].mean()) / (batch["advantage"].std() + 1e-8)
        per_epoch = -(-len(advantage) // cfg.batch_size)
        policy.train()
        kls, clipped = [], []
        for n, rows in enumerate(self._minibatches(len(advantage)), 1):
            log_ratio = (
                self._log_prob(self._mean(batch["state"][rows], batch["start"][rows]), batch["chunk"][rows])
                - batch["log_prob"][rows]
            )
            ratio = log_ratio.exp()
            gain = torch.min(ratio * advantage[rows], ratio.clamp(1 - cfg.ppo_clip, 1 + cfg.ppo_clip) * advantage[rows])
            self.opt.zero_grad(set_to_none=True)
            (-gain.mean()).backward()
            nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
            self.opt.step()
            with torch.no_grad():
                kls.append(float((ratio - 1 - log_ratio).mean()))
                clipped.append(float(((ratio - 1).abs() > cfg.ppo_clip).float().mean()))
            if n % per_epoch == 0 and np.mean(kls[-per_epoch:]) > cfg.ppo_target_kl:
                break
        policy.eval()
        return {"kl": float(np.mean(kls)), "clip_fraction": float(np.mean(clipped)), "updates": len(kls)}


class Critic(nn.Module):
    """The value of a state and the episode's clock (elapsed steps over the limit): an MLP on the flow's own encoding of
    the state, which it does not train."""

    def __init__(self, policy: nn.Module, widths: list[int]) -> None:
        super().__init__()
        self.features = lambda state: policy.encode_state(policy.policy_state(state))
        self.net = mlp(self.features(torch.zeros(1, policy.state_dim)).shape[1] + 1, widths, 1, 0.0)

    def forward(self, state: torch.Tensor, clock: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            features = self.features(state)
        return self.net(torch.cat([features, clock[:, None]], dim=1)).squeeze(1)

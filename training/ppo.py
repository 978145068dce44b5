"""PPO (clipped surrogate, GAE) for a steering actor over a frozen flow; the algorithm only, no env or I/O.

The actor's action is the flow's start noise x0 [H, A]; its log density comes from
`NoiseSteering.log_prob`. The critic sees the encoded state and the episode's clock (the step
limit makes the value depend on time; the actor acts from the state alone, as the service does).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import nn

__all__ = ["Critic", "PPOSettings", "Rollout", "gae", "ppo_update"]


class Critic(nn.Module):
    """V(encoded state, time fraction): an MLP with SiLU activations."""

    def __init__(self, state_dim: int, hidden_dims: Sequence[int] = (256, 256)) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        prev = state_dim + 1
        for width in hidden_dims:
            layers += [nn.Linear(prev, width), nn.SiLU()]
            prev = width
        layers.append(nn.Linear(prev, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, encoded_state: torch.Tensor, time_fraction: torch.Tensor) -> torch.Tensor:
        """Values [B] of states [B, S'] at clock [B]."""
        return self.net(torch.cat([encoded_state, time_fraction[:, None]], dim=1)).squeeze(1)


@dataclass
class PPOSettings:
    """The update's hyperparameters."""

    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip: float = 0.2
    epochs: int = 4
    minibatch: int = 256
    entropy_coef: float = 0.0
    max_grad_norm: float = 0.5


@dataclass
class Rollout:
    """T decisions of N envs, time-major ([T, N, ...]); `last_value` [N] bootstraps the final step."""

    encoded: torch.Tensor  # [T, N, S']
    time_fraction: torch.Tensor  # [T, N]
    x0: torch.Tensor  # [T, N, H, A]
    log_prob: torch.Tensor  # [T, N]
    value: torch.Tensor  # [T, N]
    reward: torch.Tensor  # [T, N]
    done: torch.Tensor  # [T, N] float: the episode ended with this decision
    last_value: torch.Tensor  # [N]


def gae(rollout: Rollout, gamma: float, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Advantages and returns [T, N] by generalized advantage estimation; an ended episode bootstraps nothing."""
    steps = rollout.reward.shape[0]
    advantages = torch.zeros_like(rollout.reward)
    running = torch.zeros_like(rollout.last_value)
    for t in reversed(range(steps)):
        next_value = rollout.last_value if t == steps - 1 else rollout.value[t + 1]
        keep = 1.0 - rollout.done[t]
        delta = rollout.reward[t] + gamma * next_value * keep - rollout.value[t]
        running = delta + gamma * lam * keep * running
        advantages[t] = running
    return advantages, advantages + rollout.value


def ppo_update(
    steering: nn.Module,
    critic: Critic,
    actor_opt: torch.optim.Optimizer,
    critic_opt: torch.optim.Optimizer,
    rollout: Rollout,
    noise_scale: float,
    settings: PPOSettings,
    generator: torch.Generator | None = None,
) -> dict[str, float]:
    """Some epochs of clipped-surrogate updates of the steering and regression of the critic; returns means for the log."""
    advantages, returns = gae(rollout, settings.gamma, settings.gae_lambda)
    flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731
    enc, clock, x0, old_logp = flat(rollout.encoded), flat(rollout.time_fraction), flat(rollout.x0), flat(rollout.log_prob)
    adv, ret = flat(advantages), flat(returns)
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    total = enc.shape[0]
    sums = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "approx_kl": 0.0, "clip_fraction": 0.0}
    count = 0
    for _ in range(settings.epochs):
        order = torch.randperm(total, generator=generator)
        for start in range(0, total, settings.minibatch):
            idx = order[start : start + settings.minibatch]
            logp, entropy = steering.log_prob(enc[idx], x0[idx], noise_scale)
            log_ratio = logp - old_logp[idx]
            ratio = torch.exp(log_ratio)
            surrogate = torch.min(ratio * adv[idx], torch.clamp(ratio, 1 - settings.clip, 1 + settings.clip) * adv[idx])
            policy_loss = -surrogate.mean() - settings.entropy_coef * entropy.mean()
            actor_opt.zero_grad(set_to_none=True)
            policy_loss.backward()
            nn.utils.clip_grad_norm_(steering.parameters(), settings.max_grad_norm)
            actor_opt.step()

            value_loss = 0.5 * (critic(enc[idx], clock[idx]) - ret[idx]).pow(2).mean()
            critic_opt.zero_grad(set_to_none=True)
            value_loss.backward()
            nn.utils.clip_grad_norm_(critic.parameters(), settings.max_grad_norm)
            critic_opt.step()

            with torch.no_grad():
                sums["policy_loss"] += float(policy_loss)
                sums["value_loss"] += float(value_loss)
                sums["entropy"] += float(entropy.mean())
                sums["approx_kl"] += float(((ratio - 1) - log_ratio).mean())
                sums["clip_fraction"] += float(((ratio - 1).abs() > settings.clip).float().mean())
            count += 1
    return {k: v / count for k, v in sums.items()}

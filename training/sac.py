"""Soft actor-critic in a frozen flow's noise space (DSRL-SAC); the algorithm only, no env or I/O.

The actor is the flow's `NoiseSteering` (a Gaussian over the start noise x0 with a bounded mean);
twin critics Q(encoded state, clock, x0) learn from a replay of chunk-level transitions, so every
simulated chunk is reused many times instead of once as in PPO.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import nn

__all__ = ["ReplayBuffer", "SACLearner", "SACSettings"]


@dataclass
class SACSettings:
    """The update's hyperparameters."""

    gamma: float = 0.99
    tau: float = 0.005
    batch_size: int = 256
    lr: float = 3e-4
    critic_lr: float = 3e-4
    target_entropy: float = 0.0


class ReplayBuffer:
    """A ring buffer of transitions: one [capacity, width] tensor per field (by default SAC's fields)."""

    SAC_FIELDS = {"enc": 0, "clock": 1, "x0": 0, "reward": 1, "done": 1, "next_enc": 0, "next_clock": 1}

    def __init__(self, capacity: int, state_dim: int, noise_dim: int, fields: dict[str, int] | None = None) -> None:
        self.capacity = capacity
        self.size = 0
        self._at = 0
        # width 0 stands for the state's (enc, next_enc) or the noise's (x0) width
        widths = {k: w or (noise_dim if k == "x0" else state_dim) for k, w in (fields or self.SAC_FIELDS).items()}
        self.data = {k: torch.zeros(capacity, w) for k, w in widths.items()}

    def add(self, **batch: torch.Tensor) -> None:
        """Append a batch of transitions (each tensor [N, ...])."""
        n = next(iter(batch.values())).shape[0]
        idx = (torch.arange(n) + self._at) % self.capacity
        for key, value in batch.items():
            self.data[key][idx] = value.reshape(n, -1).float()
        self._at = int((self._at + n) % self.capacity)
        self.size = min(self.capacity, self.size + n)

    def sample(self, batch_size: int, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """A uniform minibatch."""
        idx = torch.randint(0, self.size, (batch_size,), generator=generator)
        return {k: v[idx] for k, v in self.data.items()}


class TwinQ(nn.Module):
    """Two Q(encoded state, clock, x0) MLPs with SiLU activations."""

    def __init__(self, state_dim: int, noise_dim: int, hidden_dims: Sequence[int] = (256, 256)) -> None:
        super().__init__()

        def net() -> nn.Sequential:
            layers: list[nn.Module] = []
            prev = state_dim + 1 + noise_dim
            for width in hidden_dims:
                layers += [nn.Linear(prev, width), nn.SiLU()]
                prev = width
            return nn.Sequential(*layers, nn.Linear(prev, 1))

        self.q1, self.q2 = net(), net()

    def forward(self, enc: torch.Tensor, clock: torch.Tensor, x0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Both values [B] of starts x0 [B, ...] in states enc [B, S'] at clock [B, 1]."""
        inputs = torch.cat([enc, clock.reshape(-1, 1), x0.reshape(len(enc), -1)], dim=1)
        return self.q1(inputs).squeeze(1), self.q2(inputs).squeeze(1)


class SACLearner:
    """Twin critics with a Polyak target, an entropy temperature tuned to a target, and the steering as actor."""

    def __init__(self, steering: nn.Module, state_dim: int, noise_scale: float, settings: SACSettings, hidden_dims: Sequence[int]) -> None:
        self.steering = steering
        self.noise_scale = noise_scale
        self.settings = settings
        self.chunk_shape = steering.chunk_shape
        noise_dim = self.chunk_shape[0] * self.chunk_shape[1]
        self.critic = TwinQ(state_dim, noise_dim, hidden_dims)
        self.target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = torch.zeros(1, requires_grad=True)
        self.actor_opt = torch.optim.Adam(steering.parameters(), lr=settings.lr)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=settings.critic_lr)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=settings.lr)

    def update(self, batch: dict[str, torch.Tensor], update_actor: bool, generator: torch.Generator | None = None) -> dict[str, float]:
        """One critic step (and, with `update_actor`, one actor and temperature step); returns figures for the log."""
        s, ns = self.settings, self.noise_scale
        enc, clock, x0 = batch["enc"], batch["clock"], batch["x0"].reshape(-1, *self.chunk_shape)
        alpha = self.log_alpha.exp().detach()
        with torch.no_grad():
            noise = torch.randn(x0.shape, generator=generator)
            next_x0 = self.steering(batch["next_enc"], noise, ns)
            next_logp, _ = self.steering.log_prob(batch["next_enc"], next_x0, ns)
            t1, t2 = self.target(batch["next_enc"], batch["next_clock"], next_x0)
            target = batch["reward"][:, 0] + s.gamma * (1 - batch["done"][:, 0]) * (torch.min(t1, t2) - alpha * next_logp)
        q1, q2 = self.critic(enc, clock, x0)
        critic_loss = 0.5 * ((q1 - target).pow(2).mean() + (q2 - target).pow(2).mean())
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()
        out = {"critic_loss": float(critic_loss.detach()), "q": float(q1.mean().detach())}

        if update_actor:
            noise = torch.randn(x0.shape, generator=generator)
            new_x0 = self.steering(enc, noise, ns)
            logp, _ = self.steering.log_prob(enc, new_x0, ns)
            a1, a2 = self.critic(enc, clock, new_x0)
            actor_loss = (alpha * logp - torch.min(a1, a2)).mean()
            self.actor_opt.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.actor_opt.step()
            alpha_loss = -(self.log_alpha * (logp.detach() + s.target_entropy)).mean()
            self.alpha_opt.zero_grad(set_to_none=True)
            alpha_loss.backward()
            self.alpha_opt.step()
            out.update(actor_loss=float(actor_loss.detach()), alpha=float(alpha), entropy=float(-logp.mean().detach()))

        with torch.no_grad():
            for p, tp in zip(self.critic.parameters(), self.target.parameters()):
                tp.mul_(1 - s.tau).add_(p, alpha=s.tau)
        return out

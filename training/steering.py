"""Noise-space steering of a frozen flow (DSRL, Wagenmaker et al. 2025): a small network picks the start noise.

The flow maps a start noise x0 to an action chunk. Imitation alone samples x0 ~ N(0, s^2 I) and so
copies demonstrators who rarely finish; the flow's samples already contain successful chunks (the
oracle in ../shared/notes/policy-quality.md). `NoiseSteering` learns, from the env's reward with the
flow's weights untouched, where to start instead:

    x0 = mean(state) + noise_scale * exp(log_std) * noise,   noise ~ N(0, I)

It is part of the flow policy (an architecture key, weights in the same checkpoint), so the exported
graph keeps its `state` and `noise` inputs and the service, the client and evaluation need nothing
new. Initialized with a zero mean and unit std, a steered flow acts exactly as the flow it starts from.
Imports only torch.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

DEFAULT_STEERING_DIMS = (256, 256)
# The mean stays within +-MEAN_BOUND (in units of the flow's start noise): far outside the training
# distribution of x0 the flow's output is arbitrary, and nothing there was asked for by the reward.
MEAN_BOUND = 2.0
LOG_STD_MIN, LOG_STD_MAX = -5.0, 1.0


class NoiseSteering(nn.Module):
    """State -> start-noise mean [B, H, A] (bounded), plus a learned per-dimension log std."""

    def __init__(self, state_dim: int, chunk_shape: tuple[int, int], hidden_dims: Sequence[int] = DEFAULT_STEERING_DIMS) -> None:
        super().__init__()
        self.chunk_shape = tuple(chunk_shape)
        out_dim = self.chunk_shape[0] * self.chunk_shape[1]
        layers: list[nn.Module] = []
        prev = state_dim
        for width in hidden_dims:
            layers += [nn.Linear(prev, width), nn.SiLU()]
            prev = width
        self.hidden = nn.Sequential(*layers)
        self.mean_head = nn.Linear(prev, out_dim)
        # Zero head: the untrained steering is the identity on the flow's sampling.
        nn.init.zeros_(self.mean_head.weight)
        nn.init.zeros_(self.mean_head.bias)
        self.log_std = nn.Parameter(torch.zeros(out_dim))

    def mean(self, encoded_state: torch.Tensor) -> torch.Tensor:
        """The start-noise mean [B, H, A] for encoded (normalized) states [B, S']."""
        raw = self.mean_head(self.hidden(encoded_state))
        return (MEAN_BOUND * torch.tanh(raw / MEAN_BOUND)).reshape(-1, *self.chunk_shape)

    def std(self) -> torch.Tensor:
        """The per-dimension std multiplier [H, A] (before the flow's noise_scale)."""
        return torch.exp(self.log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)).reshape(self.chunk_shape)

    def forward(self, encoded_state: torch.Tensor, noise: torch.Tensor, noise_scale: float) -> torch.Tensor:
        """The flow's start x0 [B, H, A] from standard-normal `noise` [B, H, A]."""
        return self.mean(encoded_state) + (noise_scale * self.std()) * noise

    def log_prob(self, encoded_state: torch.Tensor, x0: torch.Tensor, noise_scale: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Log density [B] of starts x0 [B, H, A] under this steering, and the entropy [B] of its Gaussian."""
        mean = self.mean(encoded_state)
        std = noise_scale * self.std()
        dist = torch.distributions.Normal(mean, std.expand_as(mean))
        return dist.log_prob(x0).sum(dim=(1, 2)), dist.entropy().sum(dim=(1, 2))

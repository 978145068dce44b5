"""An exponential moving average of a policy's weights, as Diffusion Policy evaluates and ships.

The average lives in a copy of the policy (normalizer included), so evaluating or saving it is
evaluating or saving a policy; the decay warms up as Diffusion Policy's EMAModel does
(1 - (1 + step)^-0.75, capped at `max_decay`), so early weights are soon forgotten.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

__all__ = ["WeightAverage"]


class WeightAverage:
    """`module`: the averaged copy of `policy`; `update(step)` after every optimizer step."""

    def __init__(self, policy: nn.Module, max_decay: float) -> None:
        if not 0 < max_decay < 1:
            raise ValueError(f"ema decay must be in (0, 1), got {max_decay}")
        self.policy, self.max_decay = policy, max_decay
        self.module = copy.deepcopy(policy).eval()

    def decay(self, step: int) -> float:
        """The weight of the old average at optimizer step `step` (1-based)."""
        return min(self.max_decay, 1.0 - (1.0 + step) ** -0.75)

    @torch.no_grad()
    def update(self, step: int) -> None:
        """Move the average towards the policy's current weights."""
        weight = 1.0 - self.decay(step)
        for averaged, current in zip(self.module.parameters(), self.policy.parameters()):
            averaged.lerp_(current.detach(), weight)

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The averaged weights (for resumable state)."""
        return self.module.state_dict()

    def load_state_dict(self, tensors: dict[str, torch.Tensor]) -> None:
        """Restore the averaged weights (the normalizer follows the policy's)."""
        self.module.load_state_dict(tensors)
        self.module.normalizer.set(self.policy.normalizer)

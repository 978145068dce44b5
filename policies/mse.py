"""The MSE policy: an MLP from state to a whole action chunk, trained by mean squared error on normalized actions."""

from __future__ import annotations

from typing import Any

import torch
from torch.nn import functional as F

from policies.base import ChunkPolicy
from policies.configuration import architecture_with_defaults, check_architecture
from pusht.spec import DEFAULT_NUM_STEPS


class MSEPolicy(ChunkPolicy):
    """An MLP from state to a whole action chunk, trained by mean squared error on normalized actions."""

    kind = "mse"

    def __init__(self, **architecture: Any) -> None:
        """`architecture`: keys of `MSE_DEFAULTS` (policies.configuration), the others at their defaults."""
        super().__init__()
        encoded_dim = self._init_common(check_architecture(**architecture_with_defaults("mse", architecture)))
        self._init_net(encoded_dim, encoded_dim, self.horizon * self.action_dim)

    def forward(self, state_n: torch.Tensor) -> torch.Tensor:
        """The predicted normalized chunk [B, H, A] of normalized states [B, S]."""
        encoded = self.encode_state(state_n)
        return self._run_net(encoded, encoded).reshape(-1, self.horizon, self.action_dim)

    def normalized_loss(
        self, state_n: torch.Tensor, chunk_n: torch.Tensor, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Mean squared error between the predicted and the demonstrated normalized chunk."""
        return F.mse_loss(self(state_n), chunk_n)

    def sample_actions(
        self, state_n: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int = DEFAULT_NUM_STEPS
    ) -> torch.Tensor:
        """The deterministic normalized chunk [B, H, A]; `noise` and `num_steps` are accepted for the common interface and ignored."""
        return self(state_n)

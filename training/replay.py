"""A replay of chunk-level transitions for the noise-space learners, resident as tensors."""

from __future__ import annotations

import torch

__all__ = ["ReplayBuffer"]


class ReplayBuffer:
    """A ring buffer of transitions: one [capacity, width] tensor per field."""

    def __init__(self, capacity: int, state_dim: int, noise_dim: int, fields: dict[str, int]) -> None:
        self.capacity = capacity
        self.size = 0
        self._at = 0
        # width 0 stands for the state's (enc, next_enc) or the noise's (x0) width
        widths = {k: w or (noise_dim if k == "x0" else state_dim) for k, w in fields.items()}
        self.data = {k: torch.zeros(capacity, w) for k, w in widths.items()}

    def add(self, **batch: torch.Tensor) -> None:
        """Append a batch of transitions (each tensor [N, ...])."""
        n = next(iter(batch.values())).shape[0]
        idx = (torch.arange(n) + self._at) % self.capacity
        for key, value in batch.items():
            self.data[key][idx] = value.reshape(n, -1).float()
        self._at = int((self._at + n) % self.capacity)
        self.size = min(self.capacity, self.size + n)

    def filled(self) -> dict[str, torch.Tensor]:
        """The filled rows of each field (views)."""
        return {k: v[: self.size] for k, v in self.data.items()}

    def state(self, prefix: str) -> tuple[dict[str, torch.Tensor], dict[str, int]]:
        """The filled part as tensors, and the ring's position, for a resumable checkpoint."""
        return {f"{prefix}.{k}": v for k, v in self.filled().items()}, {"size": self.size, "at": self._at}

    def load_state(self, prefix: str, tensors: dict[str, torch.Tensor], extra: dict[str, int]) -> None:
        """Refill from what `state` returned."""
        self.size, self._at = int(extra["size"]), int(extra["at"])
        for k, v in self.data.items():
            v[: self.size] = tensors[f"{prefix}.{k}"]

    def sample(self, batch_size: int, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """A uniform minibatch."""
        idx = torch.randint(0, self.size, (batch_size,), generator=generator)
        return {k: v[idx] for k, v in self.data.items()}

"""The process group under torchrun (gloo) or a single process, and the rank-0 progress bar."""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

import torch
import torch.distributed as dist


@dataclass
class Distributed:
    """This process's rank and the world size; collective helpers that are no-ops in a single process."""

    rank: int = 0
    world_size: int = 1

    @property
    def is_main(self) -> bool:
        """Rank 0: the one that logs, evaluates and saves."""
        return self.rank == 0

    @classmethod
    def start(cls) -> Distributed:
        """Join the torchrun process group when WORLD_SIZE > 1."""
        world_size = int(os.environ.get("WORLD_SIZE", "1"))
        if world_size <= 1:
            return cls()
        # evaluation on rank 0 can take minutes while the others wait at a barrier
        dist.init_process_group("gloo", timeout=timedelta(hours=2))
        return cls(rank=dist.get_rank(), world_size=dist.get_world_size())

    def barrier(self) -> None:
        """Wait for every rank."""
        if self.world_size > 1:
            dist.barrier()

    def mean(self, value: float) -> float:
        """The mean of `value` over ranks."""
        if self.world_size == 1:
            return value
        box = torch.tensor([value], dtype=torch.float64)
        dist.all_reduce(box)
        return box.item() / self.world_size

    def any(self, flag: bool) -> bool:
        """True on every rank when `flag` is true on one (so all stop at the same step)."""
        if self.world_size == 1:
            return flag
        box = torch.tensor([int(flag)])
        dist.all_reduce(box, op=dist.ReduceOp.MAX)
        return bool(box.item())

    def gather(self, tensor: torch.Tensor) -> list[torch.Tensor]:
        """Every rank's `tensor` (same shape and dtype on all), in rank order."""
        if self.world_size == 1:
            return [tensor]
        out = [torch.empty_like(tensor) for _ in range(self.world_size)]
        dist.all_gather(out, tensor)
        return out

    def broadcast_str(self, value: str) -> str:
        """Rank 0's `value` on every rank."""
        if self.world_size == 1:
            return value
        box = [value]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    def stop(self) -> None:
        """Leave the process group."""
        if self.world_size > 1 and dist.is_initialized():
            dist.destroy_process_group()


def progress_bar(total: int, done: int, enabled: bool) -> Any:
    """A tqdm bar on stderr starting at `done` of `total`, or None when disabled."""
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=done, desc="train", unit="step", file=sys.stderr, mininterval=0.5)

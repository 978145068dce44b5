"""The torch backend: a checkpoint NAME.safetensors rebuilt by `policies.checkpoint`, any flow step count.

Imported only when asked for, so that serving ONNX needs no torch.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from acting.policy import Policy
from policies.card import Card, CardError, require_regular_file
from pusht.seeding import BATCH_MULTIPLE

__all__ = ["TorchPolicy"]


class TorchPolicy(Policy):
    """A policy run by torch from its checkpoint (or from an in-memory `ActingPolicy`, as training evaluates)."""

    backend = "torch"

    def __init__(self, card: Card, threads: int = 0, module: Any = None) -> None:
        super().__init__(card)
        try:
            import torch
        except ModuleNotFoundError as exc:
            raise CardError(
                f"{card.stem}: the torch backend needs torch ({exc.name} is not installed): install the train extra "
                f"(pip install -e '.[train]'), or use the ONNX export ({card.stem}.onnx), which needs only the serve extra"
            ) from None
        self._torch = torch
        if threads:
            torch.set_num_threads(threads)
        if module is None:
            from policies.checkpoint import load_acting_policy

            require_regular_file(card.stem.with_suffix(".safetensors"), "weights file")
            module = load_acting_policy(card.stem)
        self.module = module
        self.takes_prev_state = bool(module.policy.architecture.get("prev_state", False))

    @classmethod
    def from_module(cls, module: Any, name: str = "in-memory") -> "TorchPolicy":
        """A policy around a torch `ActingPolicy` that has no files (training's periodic evaluation)."""
        policy = module.policy
        data = {
            "name": name,
            "kind": policy.kind,
            "architecture": policy.architecture,
            "onnx": None,
            "sampler_steps": getattr(module, "sampler_steps", None),
        }
        acting = cls(Card(Path(f"{name}.json"), data), module=module)
        acting.default_num_steps = module.num_steps if policy.kind == "flow" else None
        return acting

    def _run(
        self, states: np.ndarray, prev_states: np.ndarray | None, noise: np.ndarray | None, num_steps: int | None
    ) -> np.ndarray:
        torch = self._torch
        was_training = self.module.training
        self.module.eval()
        steps = self.default_num_steps if num_steps is None else num_steps
        outs = []
        try:
            with torch.inference_mode():
                # One padded group of rows per call: on some CPUs torch's matrix products round a group of four
                # differently when more rows share the call, and a row's actions must not depend on its batch.
                for lo in range(0, len(states), BATCH_MULTIPLE):
                    rows = slice(lo, lo + BATCH_MULTIPLE)
                    state_t = torch.from_numpy(states[rows])
                    prev_t = None if prev_states is None else torch.from_numpy(prev_states[rows])
                    if noise is None:
                        outs.append(self.module(state_t, prev_state=prev_t))
                    else:
                        outs.append(self.module(state_t, torch.from_numpy(noise[rows]), steps, prev_t))
        finally:
            self.module.train(was_training)
        return torch.cat(outs).numpy()

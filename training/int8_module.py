"""A card's fixed-int8 graph played in torch: what the torch backend runs for a checkpoint exported with `--int8`.

The int8 graph plays other actions than the float32 module (a few pixels at the median, more where the quantized
scores reorder the hypotheses), and a policy must act alike on every backend. So the torch backend plays the
same function: the lean graph (`training.onepass_graph`) with each quantized layer computed as ONNX Runtime does:
its input rounded to uint8 at the card's recorded scale and zero point, int8 weights per output unit
(`training.quantize.quantize_weights`), the integer product exact (float64 holds it), then both scales and the bias
in float32.
"""

from __future__ import annotations

import torch
from torch import nn

from training.onepass_graph import LeanScoredChoice
from training.quantize import quantize_weights

__all__ = ["Int8Acting", "Int8Linear"]


class Int8Acting(nn.Module):
    """An `ActingPolicy` of a scoring student as its card's int8 graph: `inputs` maps each quantized layer's ONNX weight name
    (lean.gen.1.weight, ...) to its input's [scale, zero point] (the card's `onnx.int8.inputs`)."""

    def __init__(self, acting: nn.Module, inputs: dict[str, list[float]]) -> None:
        super().__init__()
        self.policy, self.kind, self.num_steps = acting.policy, acting.kind, acting.num_steps
        self.lean = LeanScoredChoice(acting.policy).eval()
        for name, (scale, zero) in inputs.items():
            path = name.removeprefix("lean.").removesuffix(".weight")
            parent, _, child = path.rpartition(".")
            holder = self.lean.get_submodule(parent) if parent else self.lean
            setattr(holder, child, Int8Linear(holder.get_submodule(child), float(scale), int(zero)))

    def forward(self, state: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int | None = None,
                prev_state: torch.Tensor | None = None) -> torch.Tensor:
        """Clipped actions [B, H, A] for env-unit states [B, 5]; a scoring student reads no noise and has no steps."""
        if noise is None:
            noise = state.new_zeros(len(state), *self.lean.chunk_shape)
        return self.lean(state, noise)


class Int8Linear(nn.Module):
    """x @ W.T + b as the int8 graph computes it: x in uint8 at `scale` around `zero`, W in int8 per output unit."""

    def __init__(self, layer: nn.Linear, scale: float, zero: int) -> None:
        super().__init__()
        w_q, w_scale = quantize_weights(layer.weight.detach().numpy())
        self.register_buffer("w_q", torch.from_numpy(w_q).double())
        self.register_buffer("multiplier", torch.tensor(scale, dtype=torch.float32) * torch.from_numpy(w_scale))
        self.register_buffer("bias", layer.bias.detach().clone())
        self.scale, self.zero = scale, zero

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        steps = torch.clamp(torch.round(x / torch.tensor(self.scale, dtype=x.dtype)) + self.zero, 0, 255) - self.zero
        return (steps.double() @ self.w_q.T).float() * self.multiplier + self.bias

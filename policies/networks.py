"""The MLPs inside the policies: plain, or with a conditioning fed again into every layer."""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn
from torch.nn import functional as F


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters (buffers excluded)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def mlp(in_dim: int, hidden_dims: Sequence[int], out_dim: int, dropout: float) -> nn.Sequential:
    """Linear -> ReLU -> Dropout per hidden layer, then a linear output layer."""
    layers: list[nn.Module] = []
    prev = in_dim
    for width in hidden_dims:
        layers += [nn.Linear(prev, width), nn.ReLU(), nn.Dropout(dropout)]
        prev = width
    layers.append(nn.Linear(prev, out_dim))
    return nn.Sequential(*layers)


def silu_mlp(in_dim: int, hidden_dims: Sequence[int], out_dim: int) -> nn.Sequential:
    """Linear -> SiLU per hidden layer, then a linear output layer (the outcome model's and the one-pass heads' trunk)."""
    layers: list[nn.Module] = []
    prev = in_dim
    for width in hidden_dims:
        layers += [nn.Linear(prev, width), nn.SiLU()]
        prev = width
    return nn.Sequential(*layers, nn.Linear(prev, out_dim))


class StateSkipMLP(nn.Module):
    """Like `mlp`, but the conditioning `cond` [B, C] is concatenated again to the input of every hidden layer after the first and of the output layer."""

    def __init__(self, in_dim: int, cond_dim: int, hidden_dims: Sequence[int], out_dim: int, dropout: float) -> None:
        super().__init__()
        self.hidden = nn.ModuleList()
        prev = in_dim
        for i, width in enumerate(hidden_dims):
            self.hidden.append(nn.Linear(prev + (cond_dim if i else 0), width))
            prev = width
        self.out = nn.Linear(prev + cond_dim, out_dim)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """Outputs [B, out_dim] of inputs [B, in_dim] and conditioning [B, cond_dim]."""
        h = x
        for i, layer in enumerate(self.hidden):
            if i:
                h = torch.cat([h, cond], dim=1)
            h = self.dropout(F.relu(layer(h)))
        return self.out(torch.cat([h, cond], dim=1))

    @torch.no_grad()
    def grow_from(self, narrow: StateSkipMLP) -> None:
        """Compute `narrow`'s function with this net's wider layers: its units copied in, the extra units' outputs read
        with zero weights (their inputs stay random), so training grows into them."""
        pairs = [*zip(self.hidden, narrow.hidden), (self.out, narrow.out)]
        if (
            len(self.hidden) != len(narrow.hidden)
            or self.hidden[0].in_features != narrow.hidden[0].in_features
            or self.out.out_features != narrow.out.out_features
            or self.out.in_features - self.hidden[-1].out_features != narrow.out.in_features - narrow.hidden[-1].out_features
            or any(wide.out_features < small.out_features for wide, small in pairs)
        ):
            raise ValueError("a net grows only from one as deep, no wider in any layer, with the same inputs and outputs")
        prev_small = prev_wide = 0
        for i, (wide, small) in enumerate(pairs):
            rows = slice(0, small.out_features)
            if i == 0:
                wide.weight[rows] = small.weight
            else:  # inputs: the previous layer's units, then the conditioning
                wide.weight[rows, :prev_small] = small.weight[:, :prev_small]
                wide.weight[rows, prev_small:prev_wide] = 0.0
                wide.weight[rows, prev_wide:] = small.weight[:, prev_small:]
            wide.bias[rows] = small.bias
            prev_small, prev_wide = small.out_features, wide.out_features

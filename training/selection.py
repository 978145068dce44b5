"""Value-guided choice of a frozen flow's start noise: a learned Q(state, x0) picks the best of K candidates.

The flow's samples already contain successful chunks: keeping, at each decision, the best of 16 start
noises by simulating each lifts success from 60 % to 82 % (the oracle in
../shared/notes/policy-quality.md). `NoiseSelector` replaces the simulator by a learned critic, as
IDQL (Hansen-Estruch et al. 2023) selects among a diffusion policy's samples by Q, and moves DSRL's
critic (Wagenmaker et al. 2025) into the noise space: candidates come from the one standard-normal
`noise` input through K fixed orthogonal maps (each R_k n is again standard normal), the critic
scores each, and the flow integrates only the winner. Nothing simulates the env at acting time, and
the exported graph keeps its `state` and `noise` inputs. Imports only torch.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

DEFAULT_SELECTOR_DIMS = (256, 256)
DEFAULT_CANDIDATES = 16
# The candidate maps are drawn once from this seed; they are buffers in every checkpoint as well.
_ROTATION_SEED = 20251201


class NoiseSelector(nn.Module):
    """Q(encoded state, x0) and K orthogonal candidate maps; `forward` returns the best-scored start."""

    def __init__(self, state_dim: int, chunk_shape: tuple[int, int], hidden_dims: Sequence[int] = DEFAULT_SELECTOR_DIMS,
                 candidates: int = DEFAULT_CANDIDATES) -> None:
        super().__init__()
        self.chunk_shape = tuple(chunk_shape)
        self.candidates = int(candidates)
        dim = self.chunk_shape[0] * self.chunk_shape[1]
        layers: list[nn.Module] = []
        prev = state_dim + dim
        for width in hidden_dims:
            layers += [nn.Linear(prev, width), nn.SiLU()]
            prev = width
        self.q = nn.Sequential(*layers, nn.Linear(prev, 1))
        self.register_buffer("rotations", orthogonal_maps(self.candidates, dim))

    # Shapes below use -1 and flatten, never a traced batch size, so the exported graph keeps a dynamic batch.
    def value(self, encoded_state: torch.Tensor, x0: torch.Tensor) -> torch.Tensor:
        """Q [B] of starts x0 [B, H, A] in encoded states [B, S']."""
        return self.q(torch.cat([encoded_state, x0.flatten(1)], dim=1)).squeeze(1)

    def candidates_of(self, noise: torch.Tensor, noise_scale: float) -> torch.Tensor:
        """The K candidate starts [B, K, H, A] of standard-normal `noise` [B, H, A] (candidate 0 is noise_scale * noise)."""
        return candidate_starts(noise, self.rotations, noise_scale)

    def forward(self, encoded_state: torch.Tensor, noise: torch.Tensor, noise_scale: float) -> torch.Tensor:
        """The flow's start x0 [B, H, A]: the candidate of `noise` with the highest Q."""
        k = self.candidates
        cands = self.candidates_of(noise, noise_scale)
        states = encoded_state.unsqueeze(1).expand(-1, k, -1).reshape(-1, encoded_state.shape[1])
        scores = self.value(states, cands.reshape(-1, *self.chunk_shape)).reshape(-1, k)
        index = scores.argmax(dim=1).reshape(-1, 1, 1, 1).expand(-1, 1, *self.chunk_shape)
        return torch.gather(cands, 1, index).squeeze(1)


def candidate_starts(noise: torch.Tensor, rotations: torch.Tensor, noise_scale: float) -> torch.Tensor:
    """The K starts [B, K, H, A] that K orthogonal maps [K, D, D] make of standard-normal `noise` [B, H, A], times noise_scale.

    Each map keeps the noise standard normal; shapes use -1, never a traced batch size (a dynamic-batch ONNX graph)."""
    cands = torch.einsum("bd,ked->bke", noise.flatten(1), rotations)
    return (noise_scale * cands).reshape(-1, rotations.shape[0], *noise.shape[1:])


def orthogonal_maps(k: int, dim: int) -> torch.Tensor:
    """K orthogonal [dim, dim] matrices, the first the identity, the rest Haar-random from a fixed seed."""
    generator = torch.Generator().manual_seed(_ROTATION_SEED)
    maps = [torch.eye(dim)]
    for _ in range(k - 1):
        q, r = torch.linalg.qr(torch.randn(dim, dim, generator=generator))
        maps.append(q * torch.sign(torch.diagonal(r)))  # sign fix: Haar-distributed
    return torch.stack(maps)

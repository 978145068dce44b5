"""Candidate start noises of a frozen flow: K fixed orthogonal maps of the one standard-normal `noise` input.

Each map R_k keeps the noise standard normal, so the K candidates are K honest samples of the flow, and
the exported graph keeps its `state` and `noise` inputs (the outcome chooser, policies.chooser, picks
among them). Imports only torch.
"""

from __future__ import annotations

import torch

# The candidate maps are drawn once from this seed; they are buffers in every checkpoint as well.
_ROTATION_SEED = 20251201


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

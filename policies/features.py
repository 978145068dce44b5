"""State features computed inside the policy (and so inside its ONNX graph): the tee's corners in the arena, and the motion since the previous step."""

from __future__ import annotations

import math

import torch

from pusht.geometry import TEE_RECTS

# The tee's outline corners in its body frame: the bar's four and the stem's two far ones (the stem's
# near corners lie on the bar's edge).
_CORNERS = (*TEE_RECTS[0], TEE_RECTS[1][1], TEE_RECTS[1][2])
KEYPOINT_FEATURES = 2 * len(_CORNERS)
_CENTER, _SCALE = 256.0, 128.0  # arena pixels to about [-2, 2]


def tee_keypoints(pose: torch.Tensor) -> torch.Tensor:
    """The corners [B, 12] (x, y per corner, scaled) of tees at env-unit poses [B, 3] (x, y, angle), as the env places them."""
    corners = torch.tensor(_CORNERS, dtype=pose.dtype, device=pose.device)  # [K, 2]
    cos, sin = torch.cos(pose[:, 2:3]), torch.sin(pose[:, 2:3])  # [B, 1]
    x = pose[:, 0:1] + cos * corners[:, 0] - sin * corners[:, 1]
    y = pose[:, 1:2] + sin * corners[:, 0] + cos * corners[:, 1]
    return (torch.stack([x, y], dim=2).flatten(1) - _CENTER) / _SCALE


MOTION_FEATURES = 5
# About the demonstrations' per-step std of each channel (agent x, y; block x, y in px; angle in rad), so the
# features are of order 1 without statistics to carry in the card.
_MOTION_SCALE = (8.0, 8.0, 2.0, 2.0, 0.03)


def motion_features(state: torch.Tensor, prev_state: torch.Tensor) -> torch.Tensor:
    """The change [B, 5] from env-unit `prev_state` to `state` (the angle's wrapped to [-pi, pi)), scaled to about unit std.

    The five numbers show no velocity, and the agent is a PD-controlled body: where it is going depends on how it moves."""
    delta = state - prev_state
    angle = torch.remainder(delta[:, 4:5] + math.pi, 2 * math.pi) - math.pi
    delta = torch.cat([delta[:, :4], angle], dim=1)
    return delta / torch.tensor(_MOTION_SCALE, dtype=state.dtype, device=state.device)

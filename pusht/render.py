"""Headless Push-T frames drawn with Pillow: the goal tee, the block, the agent and the last action."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from pusht.geometry import GOAL_POSE, tee_polygons

__all__ = ["render_frame"]

_WORLD = 512.0  # the arena is 512 x 512 px in env units
_AGENT_RADIUS = 15.0
_BACKGROUND = (255, 255, 255)
_WALL = (211, 211, 211)  # LightGray, as gym-pusht
_GOAL = (144, 238, 144)  # LightGreen
_BLOCK = (119, 136, 153)  # LightSlateGray
_AGENT = (65, 105, 225)  # RoyalBlue
_AGENT_FILL = (78, 126, 255)  # gym-pusht fills shapes 1.2x lighter than their outline
_ACTION = (255, 0, 0)


def render_frame(
    agent_xy: tuple[float, float],
    block_pose: tuple[float, float, float],
    size: int = 512,
    action: tuple[float, float] | None = None,
) -> np.ndarray:
    """An RGB uint8 image [size, size, 3] of the scene; `block_pose` is the block body's x, y, angle."""
    scale = size / _WORLD
    image = Image.new("RGB", (size, size), _BACKGROUND)
    draw = ImageDraw.Draw(image)

    def px(points):
        return [(x * scale, y * scale) for x, y in points]

    wall = max(1, round(4 * scale))
    draw.rectangle([5 * scale, 5 * scale, 506 * scale, 506 * scale], outline=_WALL, width=wall)
    for rect in tee_polygons(*GOAL_POSE):
        draw.polygon(px(rect), fill=_GOAL)
    for rect in tee_polygons(*block_pose):
        draw.polygon(px(rect), fill=_BLOCK)
    ax, ay = agent_xy
    r = _AGENT_RADIUS * scale
    box = [(ax * scale - r, ay * scale - r), (ax * scale + r, ay * scale + r)]
    draw.ellipse(box, fill=_AGENT_FILL, outline=_AGENT)
    if action is not None:
        cx, cy = action[0] * scale, action[1] * scale
        arm = max(2.0, 6 * scale)
        width = max(1, round(2 * scale))
        draw.line([(cx - arm, cy), (cx + arm, cy)], fill=_ACTION, width=width)
        draw.line([(cx, cy - arm), (cx, cy + arm)], fill=_ACTION, width=width)
    return np.asarray(image, dtype=np.uint8)

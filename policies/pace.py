"""The pace of training chunks: how many demonstration frames one action of a chunk advances.

The demonstrators are slow: the shipped flow, which copies their pace, succeeds in 66 % of 300-step
episodes and in 96 % when given 900 steps (models/README.md). A chunk at pace s plays the demonstrated
path s times as fast (`training.data.make_windows`). Far from the goal the policy can hurry; the last
alignment needs the demonstrators' own pace, so the pace may depend on how far the window's block is
from the goal:

    distance = |block xy - goal xy| / 40 px + |block angle - goal angle| / 0.6 rad
    pace     = far if distance >= radius else near                       (ramp 0)
    pace     = near + (far - near) * clip((distance - radius) / ramp, 0, 1)   (ramp > 0)

Used on the training data alone, the policy learns a pace per state, and its graph, inputs and outputs
stay those of any flow. A policy with a pace input (`pace_input`) is trained at random paces instead and
acts at the rule in its card (`acting_pace`, computed inside its graph by `Pace.speeds_t`). Measured so
far (models/README.md, "Time, not skill"): with all 12 actions of a chunk executed, neither is better
than the shipped flow.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from pusht.geometry import GOAL_POSE

POSITION_UNIT, ANGLE_UNIT = 40.0, 0.6  # px and rad that count as one unit of goal distance


def goal_distance(states: np.ndarray) -> np.ndarray:
    """Distance [N] of env-unit states' [N, 5] blocks from the goal pose, in goal units (40 px or 0.6 rad each)."""
    return goal_distance_t(torch.as_tensor(np.asarray(states, dtype=np.float64))).numpy()


def goal_distance_t(states: torch.Tensor) -> torch.Tensor:
    """`goal_distance` in torch (inside a policy's graph)."""
    # not torch.hypot: the ONNX exporter has no conversion for it
    offset = torch.sqrt((states[:, 2] - GOAL_POSE[0]) ** 2 + (states[:, 3] - GOAL_POSE[1]) ** 2)
    turn = torch.abs(torch.remainder(states[:, 4] - GOAL_POSE[2] + math.pi, 2 * math.pi) - math.pi)
    return offset / POSITION_UNIT + turn / ANGLE_UNIT


@dataclass(frozen=True)
class Pace:
    """Chunk pace `far` for windows whose block is at least `radius` (+ `ramp`) goal units from the goal, `near` (default: far) closer,
    linear in between."""

    far: float = 1.0
    near: float | None = None
    radius: float = 0.0
    ramp: float = 0.0

    def __post_init__(self) -> None:
        for name, value in (("far", self.far), ("near", self.near_pace)):
            if not 0.25 <= value <= 4:
                raise ValueError(f"pace {name} must be in [0.25, 4], got {value}")
        if not (self.radius >= 0 and self.ramp >= 0):
            raise ValueError(f"pace radius and ramp must be >= 0, got {self.radius} and {self.ramp}")

    @classmethod
    def of(cls, pace: "Pace | float") -> "Pace":
        """`pace` itself, or a uniform pace of that number."""
        return pace if isinstance(pace, Pace) else cls(float(pace))

    @property
    def near_pace(self) -> float:
        """The pace near the goal."""
        return self.far if self.near is None else self.near

    @property
    def fastest(self) -> float:
        """The largest pace any window gets."""
        return max(self.far, self.near_pace)

    def speeds(self, states: np.ndarray) -> np.ndarray:
        """The pace [N] of windows starting in env-unit states [N, 5]."""
        return self.speeds_t(torch.as_tensor(np.asarray(states, dtype=np.float64))).numpy()

    def speeds_t(self, states: torch.Tensor) -> torch.Tensor:
        """`speeds` in torch: what a policy with a pace input acts at (`acting_pace`, inside its graph)."""
        if (self.radius == 0 and self.ramp == 0) or self.far == self.near_pace:
            return torch.full_like(states[:, 0], self.far)
        distance = goal_distance_t(states)
        if self.ramp == 0:
            return torch.where(distance >= self.radius, self.far, self.near_pace).to(states.dtype)
        return self.near_pace + (self.far - self.near_pace) * torch.clamp((distance - self.radius) / self.ramp, 0.0, 1.0)

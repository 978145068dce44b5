"""Push-T as a gymnasium env: gym-pusht 0.1.8 (obs_type="state") step for step, several times faster.

The physics is pymunk 6 built exactly as gym-pusht builds it (same shapes, same insertion order, same
PD control loop with the same floating-point operations), so for any seed and actions the states match
the reference's. The speed comes from what is done around the physics:
- coverage is computed by clipping rectangles (`pusht.geometry.coverage`) instead of by shapely;
- the PD loop runs on Python floats instead of numpy arrays and Vec2d, in the reference's exact
  operation order, reading the agent's position once per substep;
- no collision callback: gym-pusht's only counts contact points for `info["n_contacts"]`, which this
  env leaves out (it is the one info key it does not reproduce); the contact physics is unchanged.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import pymunk
from gymnasium import spaces

from pusht.geometry import GOAL_POSE, TEE_RECTS, coverage
from pusht.render import render_frame
from pusht.spec import STATE_DIM, SUCCESS_COVERAGE

__all__ = ["PushTEnv", "MAX_EPISODE_STEPS"]

"""An episode succeeds (and terminates) once coverage exceeds this fraction of the goal."""

MAX_EPISODE_STEPS = 300
"""Steps after which an episode is truncated."""

_DT = 0.01  # physics substep (s)
_CONTROL_HZ = 10
_N_SUBSTEPS = int(1 / (_DT * _CONTROL_HZ))  # 10, computed as gym-pusht computes it
_K_P, _K_V = 100, 20  # PD gains of the agent
_TWO_PI = 2 * np.pi


class PushTEnv(gym.Env):
    """Push a tee-shaped block onto a fixed goal pose with a circular agent driven by a PD target.

    Observation: float64 `[agent_x, agent_y, block_x, block_y, block_angle mod 2pi]`; the block position
    is its pymunk body origin. Action: the agent's PD target `[x, y]` in pixels (Box(0, 512)); like
    gym-pusht, actions outside the box are used as given, not clipped. Reward: clip(coverage / 0.95, 0,
    1); terminated once coverage > 0.95; truncated after `max_episode_steps` steps.

    `reset(options={"reset_to_state": s})` sets the state as gym-pusht 0.1.8 does (block position, then
    angle: the block ends up rotated about its centre of gravity, not at s); `reset(options=
    {"restore_state": s})` restores a recorded dataset state exactly (angle first, then position).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": _CONTROL_HZ}

    def __init__(
        self,
        obs_type: str = "state",
        render_mode: str | None = "rgb_array",
        render_size: int = 512,
        max_episode_steps: int = MAX_EPISODE_STEPS,
    ):
        super().__init__()
        if obs_type != "state":
            raise ValueError(f"obs_type must be 'state' (the only observation this env provides), got {obs_type!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}")
        if not isinstance(render_size, (int, np.integer)) or not 16 <= render_size <= 4096:
            raise ValueError(f"render_size must be an int in [16, 4096], got {render_size!r}")
        if not isinstance(max_episode_steps, (int, np.integer)) or max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be a positive int, got {max_episode_steps!r}")
        self.obs_type = obs_type
        self.render_mode = render_mode
        self.render_size = int(render_size)
        self.max_episode_steps = int(max_episode_steps)
        self.observation_space = spaces.Box(
            low=np.array([0, 0, 0, 0, 0]),
            high=np.array([512, 512, 512, 512, _TWO_PI]),
            dtype=np.float64,
        )
        self.action_space = spaces.Box(low=0, high=512, shape=(2,), dtype=np.float32)
        self.goal_pose = np.array(GOAL_POSE)
        self.success_threshold = SUCCESS_COVERAGE

        self._space: pymunk.Space | None = None
        self._agent: pymunk.Body | None = None
        self._block: pymunk.Body | None = None
        # The agent is kinematic: contacts never change its velocity, so the velocity last set is
        # its velocity, and its position only changes inside space.step.
        self._agent_pos = (0.0, 0.0)
        self._agent_vel = (0.0, 0.0)
        self._last_action: tuple[float, float] | None = None
        self._elapsed_steps = 0

    # ------------------------------------------------------------------ gymnasium API

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode: a random start drawn from `seed` as gym-pusht draws it, or a given state."""
        reset_to, restore = _state_options(options)  # validate before anything changes
        super().reset(seed=seed)
        self._build_space()
        if restore is not None:
            self._place(restore, angle_first=True)
        else:
            if reset_to is None:
                # Same draws, in the same order, from the same generator as gym-pusht 0.1.8.
                reset_to = np.array(
                    [
                        self.np_random.integers(50, 450),
                        self.np_random.integers(50, 450),
                        self.np_random.integers(100, 400),
                        self.np_random.integers(100, 400),
                        self.np_random.uniform(-np.pi, np.pi),
                    ]
                )
            self._place(reset_to, angle_first=False)
        self._elapsed_steps = 0
        self._last_action = None
        bx, by = self._block.position
        angle = self._block.angle
        cov = coverage(bx, by, angle)
        info = self._info(bx, by, angle, cov)
        info["is_success"] = False
        return self._obs(bx, by, angle), info

    def step(self, action):
        """Run one control step (10 physics substeps of PD control towards `action`)."""
        if self._space is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        ax, ay = _check_action(action)
        agent = self._agent
        space = self._space
        px, py = self._agent_pos
        vx, vy = self._agent_vel
        for _ in range(_N_SUBSTEPS):
            # gym-pusht: acc = k_p * (action - pos) + k_v * (Vec2d(0, 0) - vel); vel += acc * dt.
            # Same operations in the same order, hence the same doubles.
            acc_x = _K_P * (ax - px) + _K_V * (0 - vx)
            acc_y = _K_P * (ay - py) + _K_V * (0 - vy)
            vx = vx + acc_x * _DT
            vy = vy + acc_y * _DT
            agent.velocity = (vx, vy)
            space.step(_DT)
            px, py = agent.position
        self._agent_pos = (px, py)
        self._agent_vel = (vx, vy)
        self._last_action = (ax, ay)
        self._elapsed_steps += 1

        bx, by = self._block.position
        angle = self._block.angle
        cov = coverage(bx, by, angle)
        reward = min(max(cov / SUCCESS_COVERAGE, 0.0), 1.0)
        terminated = cov > SUCCESS_COVERAGE
        truncated = self._elapsed_steps >= self.max_episode_steps
        info = self._info(bx, by, angle, cov)
        info["is_success"] = terminated
        return self._obs(bx, by, angle), reward, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """An RGB uint8 frame [render_size, render_size, 3] of goal, block and agent (headless)."""
        if self.render_mode is None:
            return None
        if self._space is None:
            raise gym.error.ResetNeeded("call reset() before render()")
        bx, by = self._block.position
        return render_frame(
            agent_xy=self._agent_pos,
            block_pose=(bx, by, self._block.angle),
            size=self.render_size,
            action=self._last_action,
        )

    def close(self) -> None:
        """Release the physics space."""
        self._space = self._agent = self._block = None

    # ------------------------------------------------------------------ extras

    def get_state(self) -> np.ndarray:
        """The current state `[agent_x, agent_y, block_x, block_y, block_angle mod 2pi]` (the observation)."""
        if self._space is None:
            raise gym.error.ResetNeeded("call reset() before get_state()")
        bx, by = self._block.position
        return self._obs(bx, by, self._block.angle)

    def physics_snapshot(self) -> tuple:
        """The bodies' positions and velocities and the PD loop's memory: enough for `restore_physics` to go on from here.

        The solver's contact cache is not included, so a restored env matches the original closely
        (a median 0.01 px after a 12-step push), not bit for bit. For lookahead at training time.
        """
        if self._space is None:
            raise gym.error.ResetNeeded("call reset() before physics_snapshot()")
        agent, block = self._agent, self._block
        return (
            tuple(agent.position),
            tuple(agent.velocity),
            tuple(block.position),
            block.angle,
            tuple(block.velocity),
            block.angular_velocity,
            self._agent_pos,
            self._agent_vel,
            self._elapsed_steps,
        )

    def restore_physics(self, snapshot: tuple) -> None:
        """Rebuild the space at a `physics_snapshot` (also of another env instance)."""
        agent_position, agent_velocity, block_position, angle, block_velocity, angular_velocity, pos, vel, elapsed = snapshot
        self._build_space()
        self._agent.position, self._agent.velocity = agent_position, agent_velocity
        self._block.angle, self._block.position = angle, block_position
        self._block.velocity, self._block.angular_velocity = block_velocity, angular_velocity
        self._agent_pos, self._agent_vel, self._elapsed_steps = pos, vel, elapsed
        self._last_action = None

    @property
    def elapsed_steps(self) -> int:
        """Steps taken since the last reset."""
        return self._elapsed_steps

    # ------------------------------------------------------------------ internals

    def _obs(self, bx: float, by: float, angle: float) -> np.ndarray:
        px, py = self._agent_pos
        return np.array([px, py, bx, by, angle % _TWO_PI], dtype=np.float64)

    def _info(self, bx: float, by: float, angle: float, cov: float) -> dict[str, Any]:
        return {
            "pos_agent": np.array(self._agent_pos),
            "vel_agent": np.array(self._agent_vel),
            "block_pose": np.array([bx, by, angle]),
            "goal_pose": self.goal_pose.copy(),
            "coverage": cov,
        }

    def _build_space(self) -> None:
        """A fresh space with walls, agent and tee, built in gym-pusht's order (the order fixes the solver's)."""
        space = pymunk.Space()
        space.gravity = 0, 0
        space.damping = 0.0
        walls = [
            pymunk.Segment(space.static_body, a, b, 2)
            for a, b in (((5, 506), (5, 5)), ((5, 5), (506, 5)), ((506, 5), (506, 506)), ((5, 506), (506, 506)))
        ]
        space.add(*walls)

        agent = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        agent.position = (256, 400)
        space.add(agent, pymunk.Circle(agent, 15))

        mass = 1
        bar, stem = TEE_RECTS
        # gym-pusht sums the bar's moment twice (it passes the bar's vertices for the stem too).
        inertia = pymunk.moment_for_poly(mass, vertices=bar) + pymunk.moment_for_poly(mass, vertices=bar)
        block = pymunk.Body(mass, inertia)
        bar_shape = pymunk.Poly(block, bar)
        stem_shape = pymunk.Poly(block, stem)
        bar_shape.filter = pymunk.ShapeFilter(mask=pymunk.ShapeFilter.ALL_MASKS())
        stem_shape.filter = pymunk.ShapeFilter(mask=pymunk.ShapeFilter.ALL_MASKS())
        block.center_of_gravity = (bar_shape.center_of_gravity + stem_shape.center_of_gravity) / 2
        block.angle = 0
        block.position = (256, 300)
        space.add(block, bar_shape, stem_shape)

        self._space, self._agent, self._block = space, agent, block

    def _place(self, state: np.ndarray, angle_first: bool) -> None:
        """Put agent and block at `state`, then run one physics substep as gym-pusht does."""
        self._agent.position = (state[0], state[1])
        if angle_first:
            self._block.angle = state[4]
            self._block.position = (state[2], state[3])
        else:
            self._block.position = (state[2], state[3])
            self._block.angle = state[4]
        self._space.step(_DT)
        self._agent_pos = tuple(self._agent.position)
        self._agent_vel = (0.0, 0.0)


def _check_action(action) -> tuple[float, float]:
    """The action as two finite floats, or a ValueError that says what is wrong with it."""
    try:
        arr = np.asarray(action, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"action must be 2 numbers [x, y], got {action!r} ({exc})") from None
    if arr.shape != (2,):
        raise ValueError(f"action must have shape (2,) ([x, y] in pixels), got shape {arr.shape}")
    ax = float(arr[0])
    ay = float(arr[1])
    if not (math.isfinite(ax) and math.isfinite(ay)):
        raise ValueError(f"action must be finite, got [{ax}, {ay}]")
    return ax, ay


def _state_options(options: dict[str, Any] | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The validated `reset_to_state` and `restore_state` options (either may be None)."""
    if options is None:
        return None, None
    if not isinstance(options, dict):
        raise ValueError(f"options must be a dict, got {type(options).__name__}")
    found = {}
    for key in ("reset_to_state", "restore_state"):
        value = options.get(key)
        if value is None:
            continue
        try:
            state = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"options[{key!r}] must be {STATE_DIM} numbers, got {value!r} ({exc})") from None
        if state.shape != (STATE_DIM,):
            raise ValueError(
                f"options[{key!r}] must have shape ({STATE_DIM},) "
                f"[agent_x, agent_y, block_x, block_y, block_angle], got shape {state.shape}"
            )
        if not np.all(np.isfinite(state)):
            raise ValueError(f"options[{key!r}] must be finite, got {state.tolist()}")
        found[key] = state
    if len(found) == 2:
        raise ValueError("options may hold 'reset_to_state' or 'restore_state', not both")
    return found.get("reset_to_state"), found.get("restore_state")

"""Unit tests of the Push-T env: spaces, registration, seeding, episode ends, rendering, bad input, coverage."""

from __future__ import annotations

import math

import gymnasium
import numpy as np
import pymunk
import pytest
import shapely.geometry as sg

import pusht
from pusht import PushTEnv
from pusht.geometry import GOAL_POSE, TEE_AREA, TEE_RECTS, coverage

AWAY = [60.0, 60.0]  # an agent position far from a block on the goal


def _on_goal(dx: float = 0.0, dy: float = 0.0, dangle: float = 0.0) -> list[float]:
    """A restore_state with the agent far away and the block at the goal pose, shifted by (dx, dy, dangle)."""
    return [*AWAY, GOAL_POSE[0] + dx, GOAL_POSE[1] + dy, GOAL_POSE[2] + dangle]


@pytest.fixture
def env():
    return PushTEnv()


def test_spaces_and_dtypes(env):
    assert env.action_space == gymnasium.spaces.Box(0, 512, (2,), np.float32)
    assert env.observation_space.shape == (5,) and env.observation_space.dtype == np.float64
    obs, info = env.reset(seed=0)
    assert obs.dtype == np.float64 and obs.shape == (5,)
    assert env.observation_space.contains(obs)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert obs.dtype == np.float64 and obs.shape == (5,)
    assert isinstance(reward, float) and isinstance(terminated, bool) and isinstance(truncated, bool)
    assert 0.0 <= obs[4] < 2 * math.pi
    for key in ("pos_agent", "vel_agent", "block_pose", "goal_pose", "coverage", "is_success"):
        assert key in info
    np.testing.assert_array_equal(info["pos_agent"], obs[:2])


def test_gymnasium_make_registers_and_truncates_at_300():
    env = gymnasium.make(pusht.ENV_ID)
    assert env.spec.max_episode_steps == 300
    obs, _ = env.reset(seed=1)
    for t in range(300):
        obs, _, terminated, truncated, _ = env.step(obs[:2].astype(np.float32))  # hold still
        assert not terminated
        assert truncated == (t == 299)


def test_truncation_at_300_without_wrappers(env):
    obs, _ = env.reset(seed=2)
    for t in range(300):
        obs, _, terminated, truncated, _ = env.step(obs[:2])
        assert not terminated and truncated == (t == 299)
    assert env.elapsed_steps == 300


def test_seeding_is_deterministic_and_draws_like_gym_pusht(env):
    first, _ = env.reset(seed=42)
    again, _ = env.reset(seed=42)
    other, _ = env.reset(seed=43)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    # gym-pusht draws the agent's start as integers in [50, 450) and the settling substep leaves it there.
    rng = np.random.default_rng(42)
    assert first[0] == rng.integers(50, 450) and first[1] == rng.integers(50, 450)

    def trajectory(seed):
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        out = [obs]
        for _ in range(30):
            obs, *_ = env.step(rng.uniform(0, 512, 2))
            out.append(obs)
        return np.array(out)

    np.testing.assert_array_equal(trajectory(5), trajectory(5))


def test_block_on_goal_succeeds_and_terminates(env):
    obs, info = env.reset(options={"restore_state": _on_goal()})
    assert info["coverage"] == pytest.approx(1.0, abs=1e-9)
    assert info["is_success"] is False  # as gym-pusht: no success is reported at reset
    obs, reward, terminated, truncated, info = env.step(obs[:2])
    assert info["coverage"] == pytest.approx(1.0, abs=1e-9)
    assert reward == 1.0 and terminated and info["is_success"] and not truncated


def test_partial_coverage_gives_proportional_reward(env):
    obs, _ = env.reset(options={"restore_state": _on_goal(dx=8.0, dangle=0.1)})
    obs, reward, terminated, _, info = env.step(obs[:2])
    assert 0.3 < info["coverage"] < 0.95
    assert reward == pytest.approx(info["coverage"] / 0.95, abs=1e-12)
    assert not terminated and not info["is_success"]


def test_restore_state_is_exact_and_reset_to_state_rotates_about_the_centre(env):
    state = [100.0, 400.0, 300.0, 200.0, 1.0]
    restored, _ = env.reset(options={"restore_state": state})
    np.testing.assert_allclose(restored, state, rtol=0, atol=1e-9)
    legacy, _ = env.reset(options={"reset_to_state": state})
    # Position first, then angle about the centre of gravity (0, 45): the origin moves by (0,45) - R(1)(0,45).
    expected = np.array(state[2:4]) + 45 * np.array([math.sin(1.0), 1 - math.cos(1.0)])
    np.testing.assert_allclose(legacy[2:4], expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(legacy[[0, 1, 4]], [100.0, 400.0, 1.0], rtol=0, atol=1e-12)


def test_render_is_headless_rgb_with_goal_block_and_agent():
    env = PushTEnv(render_size=256)
    env.reset(options={"restore_state": [400.0, 100.0, 150.0, 350.0, 0.0]})
    frame = env.render()
    assert frame.shape == (256, 256, 3) and frame.dtype == np.uint8

    def pixel(x, y):
        return tuple(int(c) for c in frame[int(y * 256 / 512), int(x * 256 / 512)])

    assert pixel(256, 280) == (144, 238, 144)  # inside the goal's stem
    assert pixel(150, 365) == (119, 136, 153)  # inside the block's bar
    assert pixel(400, 100)[2] > 200 and pixel(400, 100)[0] < 100  # the agent is blue
    assert pixel(30, 480) == (255, 255, 255)
    assert PushTEnv(render_mode=None).render() is None


BAD_ACTIONS = [
    pytest.param([1.0, 2.0, 3.0], "shape", id="three-values"),
    pytest.param([[1.0, 2.0]], "shape", id="batched"),
    pytest.param(5.0, "shape", id="scalar"),
    pytest.param([float("nan"), 2.0], "finite", id="nan"),
    pytest.param(np.array([1.0, np.inf], dtype=np.float32), "finite", id="inf"),
    pytest.param(["a", "b"], "2 numbers", id="strings"),
    pytest.param(None, "shape", id="none"),
]


@pytest.mark.parametrize("action, message", BAD_ACTIONS)
def test_bad_action_raises_and_leaves_env_usable(env, action, message):
    obs, _ = env.reset(seed=3)
    with pytest.raises(ValueError, match=message):
        env.step(action)
    np.testing.assert_array_equal(env.get_state(), obs)  # nothing moved
    assert env.elapsed_steps == 0
    after, *_ = env.step(obs[:2])
    reference = PushTEnv()
    ref_obs, _ = reference.reset(seed=3)
    np.testing.assert_array_equal(after, reference.step(ref_obs[:2])[0])


BAD_STATES = [
    pytest.param([1.0, 2.0, 3.0, 4.0], "shape", id="four-values"),
    pytest.param([1.0, 2.0, 3.0, 4.0, 5.0, 6.0], "shape", id="six-values"),
    pytest.param([1.0, 2.0, float("nan"), 4.0, 0.0], "finite", id="nan"),
    pytest.param([1.0, 2.0, 3.0, float("-inf"), 0.0], "finite", id="inf"),
    pytest.param("abcde", "5 numbers", id="string"),
]


@pytest.mark.parametrize("key", ["reset_to_state", "restore_state"])
@pytest.mark.parametrize("state, message", BAD_STATES)
def test_bad_reset_state_raises_and_leaves_env_usable(env, key, state, message):
    obs, _ = env.reset(seed=4)
    env.step(obs[:2])
    before = env.get_state()
    with pytest.raises(ValueError, match=f"{key}.*{message}|{message}.*{key}"):
        env.reset(options={key: state})
    np.testing.assert_array_equal(env.get_state(), before)
    assert env.elapsed_steps == 1
    env.step(before[:2])
    obs, _ = env.reset(options={key: [100.0, 100.0, 300.0, 300.0, 0.5]})
    assert np.all(np.isfinite(obs))


def test_both_state_options_at_once_is_an_error(env):
    with pytest.raises(ValueError, match="not both"):
        env.reset(options={"reset_to_state": _on_goal(), "restore_state": _on_goal()})


def test_misuse_is_reported():
    with pytest.raises(ValueError, match="obs_type"):
        PushTEnv(obs_type="pixels")
    with pytest.raises(ValueError, match="render_mode"):
        PushTEnv(render_mode="human")
    with pytest.raises(gymnasium.error.ResetNeeded):
        PushTEnv().step([1.0, 2.0])


def _shapely_tee(body: pymunk.Body) -> sg.MultiPolygon:
    """The tee as gym-pusht 0.1.8 builds it for shapely: pymunk's world vertices of each rectangle."""
    polygons = []
    for rect in TEE_RECTS:
        vertices = [body.local_to_world(v) for v in rect]
        polygons.append(sg.Polygon(vertices + [vertices[0]]))
    return sg.MultiPolygon(polygons)


def test_coverage_matches_shapely_on_random_poses():
    goal = pymunk.Body(1, pymunk.moment_for_box(1, (50, 100)))
    goal.position = GOAL_POSE[:2]
    goal.angle = GOAL_POSE[2]
    goal_geom = _shapely_tee(goal)
    assert goal_geom.area == pytest.approx(TEE_AREA, abs=1e-9)
    block = pymunk.Body(1, 1)
    block.center_of_gravity = (0, 45)
    rng = np.random.default_rng(0)
    overlapping = 0
    for i in range(3000):
        spread = (i % 4) * 25.0  # a quarter anywhere, the rest ever closer to the goal
        if spread == 0.0:
            pose = (rng.uniform(30, 480), rng.uniform(30, 480), rng.uniform(-7, 7))
        else:
            pose = (256 + rng.normal(0, spread), 256 + rng.normal(0, spread), math.pi / 4 + rng.normal(0, spread / 80))
        block.angle = pose[2]
        block.position = pose[:2]
        expected = goal_geom.intersection(_shapely_tee(block)).area / goal_geom.area
        got = coverage(*block.position, block.angle)
        assert abs(got - expected) <= 1e-9, f"pose {pose}: {got} vs shapely {expected}"
        overlapping += expected > 0
    assert overlapping > 1500
    for exact in (math.pi / 4, math.pi / 4 + 2 * math.pi, -7 * math.pi / 4):
        assert coverage(256.0, 256.0, exact) == pytest.approx(1.0, abs=1e-12)


def test_physics_snapshot_restores_into_another_env_and_goes_on_alike() -> None:
    env, other = PushTEnv(render_mode=None), PushTEnv(render_mode=None)
    env.reset(seed=11)
    other.reset(seed=12)
    rng = np.random.default_rng(0)
    for _ in range(20):  # walk the agent into the block, so the restored state carries contact and velocity
        env.step(env.get_state()[2:4] + rng.normal(0, 10, 2))
    snapshot = env.physics_snapshot()
    other.restore_physics(snapshot)
    np.testing.assert_array_equal(other.get_state(), env.get_state())
    assert other.elapsed_steps == env.elapsed_steps == 20
    actions = env.get_state()[2:4] + rng.normal(0, 10, (12, 2))
    for action in actions:
        a, ra, *_ = env.step(action)
        b, rb, *_ = other.step(action)
    # no contact cache in the snapshot: close, not bit for bit (chaotic pushes, e.g. into a wall, can drift more)
    assert np.abs(a - b).max() < 1.0 and abs(ra - rb) < 1e-2
    assert np.abs(a[2:4] - snapshot[2]).max() > 1.0  # the block was pushed: the comparison covers contact

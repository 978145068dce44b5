"""Our env against gym-pusht 0.1.8 (obs_type="state"): same observations, rewards and flags at every step."""

from __future__ import annotations

import math

import numpy as np
import pytest

gym_pusht = pytest.importorskip("gym_pusht")

import gymnasium  # noqa: E402

from pusht import PushTEnv  # noqa: E402

ATOL = 1e-6
COG_OFFSET = 45.0  # the tee's centre of gravity lies 45 px along its stem from the body origin


def _reference():
    return gymnasium.make("gym_pusht/PushT-v0", obs_type="state", render_mode="rgb_array").unwrapped


def _cog(obs: np.ndarray) -> np.ndarray:
    """World position of the block's centre of gravity, from a state observation."""
    angle = obs[4]
    return obs[2:4] + COG_OFFSET * np.array([-math.sin(angle), math.cos(angle)])


def _pusher(rng: np.random.Generator, obs: np.ndarray, reach: float = 0.15, noise: float = 20.0) -> np.ndarray:
    """A target beyond the block's centre as seen from the agent, plus noise: the agent keeps hitting the block."""
    cog = _cog(obs)
    target = cog + reach * (cog - obs[0:2]) + rng.normal(0.0, noise, 2)
    return np.clip(target, 0.0, 512.0).astype(np.float32)


def _compare(ref, ours, ref_out, our_out, where: str) -> None:
    o1, r1, te1, tr1, i1 = ref_out
    o2, r2, te2, tr2, i2 = our_out
    assert o2.dtype == np.float64 and o2.shape == (5,)
    np.testing.assert_allclose(o2, o1, rtol=0, atol=ATOL, err_msg=f"observation differs {where}")
    assert abs(float(r2) - float(r1)) <= ATOL, f"reward differs {where}: {r2} vs {r1}"
    assert bool(te2) == bool(te1), f"terminated differs {where}"
    assert bool(i2["is_success"]) == bool(i1["is_success"]), f"is_success differs {where}"
    assert abs(i2["coverage"] - i1["coverage"]) <= ATOL, f"coverage differs {where}"
    for key in ("pos_agent", "vel_agent", "block_pose", "goal_pose"):
        np.testing.assert_allclose(i2[key], i1[key], rtol=0, atol=ATOL, err_msg=f"info[{key!r}] differs {where}")


def _rollout_both(ref, ours, actions_from, steps: int, label: str, reset_kwargs: dict):
    """Reset both envs alike, then step both with the same actions; returns stats of the run."""
    o1, i1 = ref.reset(**reset_kwargs)
    o2, i2 = ours.reset(**reset_kwargs)
    np.testing.assert_allclose(o2, o1, rtol=0, atol=ATOL, err_msg=f"reset observation differs ({label})")
    contact_steps = terminated_steps = 0
    max_coverage = 0.0
    obs = o1
    for t in range(steps):
        action = actions_from(obs)
        ref_out = ref.step(action)
        our_out = ours.step(action)
        _compare(ref, ours, ref_out, our_out, f"({label}, step {t})")
        obs = ref_out[0]
        contact_steps += ref_out[4]["n_contacts"] > 0
        terminated_steps += bool(ref_out[2])
        max_coverage = max(max_coverage, ref_out[4]["coverage"])
    return contact_steps, terminated_steps, max_coverage


@pytest.mark.parametrize("seed", range(12))
def test_seeded_pushing_rollouts_match(seed):
    """12 seeds x 150 steps of actions aimed through the block: the same trajectory, with many contacts."""
    ref, ours = _reference(), PushTEnv()
    rng = np.random.default_rng(1000 + seed)
    contacts, _, _ = _rollout_both(ref, ours, lambda obs: _pusher(rng, obs), 150, f"seed {seed}", {"seed": seed})
    # The comparison only means something if the agent really pushes the block.
    assert contacts >= 40, f"only {contacts} of 150 steps had contacts; the test policy no longer pushes"


def _reset_to_state_landing_at(block_xy, angle, agent_xy) -> list[float]:
    """A reset_to_state input that puts the block origin at block_xy under gym-pusht's position-then-angle rule."""
    # Setting the angle after the position rotates the body about its centre of gravity (0, 45) in body
    # coordinates, so the origin lands at p + (0, 45) - R(angle) (0, 45).
    rotated = COG_OFFSET * np.array([-math.sin(angle), math.cos(angle)])
    p = np.asarray(block_xy) - np.array([0.0, COG_OFFSET]) + rotated
    return [agent_xy[0], agent_xy[1], p[0], p[1], angle]


RESET_STATES = [
    pytest.param([100.0, 100.0, 300.0, 300.0, 0.5], id="apart"),
    pytest.param([256.0, 330.0, 256.0, 300.0, 0.0], id="agent-overlapping-block"),
    pytest.param([20.0, 20.0, 480.0, 200.0, 2.0], id="block-near-wall"),
    pytest.param(_reset_to_state_landing_at((256.0, 256.0), math.pi / 4, (420.0, 420.0)), id="block-on-goal"),
    pytest.param(_reset_to_state_landing_at((262.0, 251.0), math.pi / 4 + 0.08, (256.0, 180.0)), id="block-near-goal"),
    pytest.param(_reset_to_state_landing_at((240.0, 270.0), math.pi / 4 - 0.2, (330.0, 200.0)), id="block-off-goal"),
]


@pytest.mark.parametrize("state", RESET_STATES)
def test_reset_to_state_rollouts_match(state):
    """reset_to_state (position then angle, as 0.1.8) and 100 pushing steps from it: the same trajectory."""
    ref, ours = _reference(), PushTEnv()
    rng = np.random.default_rng(7)
    policy = lambda obs: _pusher(rng, obs, reach=0.2, noise=10.0)  # noqa: E731
    _rollout_both(ref, ours, policy, 100, f"state {state}", {"options": {"reset_to_state": state}})


def test_rollouts_near_the_goal_cross_the_success_threshold_alike():
    """Pushes around the goal pose: coverage crosses 0.95 both ways and termination agrees at every step."""
    ref, ours = _reference(), PushTEnv()
    total_terminated = 0
    seen_coverage = []
    for k in range(6):
        rng = np.random.default_rng(50 + k)
        angle = math.pi / 4 + rng.normal(0.0, 0.05)
        state = _reset_to_state_landing_at(256.0 + rng.normal(0.0, 3.0, 2), angle, (256.0 + 60 * (k - 3), 150.0))
        policy = lambda obs, rng=rng: _pusher(rng, obs, reach=0.05, noise=6.0)  # noqa: E731
        _, terminated, max_cov = _rollout_both(ref, ours, policy, 60, f"near goal {k}", {"options": {"reset_to_state": state}})
        total_terminated += terminated
        seen_coverage.append(max_cov)
    assert total_terminated > 0, f"no step terminated; max coverages {seen_coverage}"


def test_reused_env_and_float64_list_actions_match():
    """One env object across episodes (a fresh space per reset), with actions as lists of float64 (not float32)."""
    ref, ours = _reference(), PushTEnv()
    rng = np.random.default_rng(3)

    def float64_list_action(obs):
        return [float(v) + rng.uniform(-0.5, 0.5) for v in _pusher(rng, obs)]

    for seed in (11, 12, 13):
        _rollout_both(ref, ours, float64_list_action, 40, f"episode seed {seed}", {"seed": seed})

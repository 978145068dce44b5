"""Replaying all 206 demonstrations: restored angle first, the recorded actions reproduce the recorded states.

Each episode starts from `reset(options={"restore_state": state[start]})` and steps the recorded actions;
after action t the env must be at state t+1 (within 1e-3 px and rad) for the whole episode, except for
the episodes listed in DIVERGENT.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pusht import PushTEnv

zarr = pytest.importorskip("zarr")

REPO = Path(__file__).resolve().parents[1]
DATASETS = [
    REPO / "data" / "pusht_lowdim.zarr",  # the project's low-dimensional copy, when it has been made
    REPO.parent / "shared" / "data" / "pusht" / "pusht_cchi_v7_replay.zarr",
]
TOLERANCE = 1e-3

# Measured (x86-64, pymunk 6.11): the other 204 episodes stay within 9e-4 of their recordings (median
# 2.4e-5, the float32 rounding of the records). These two are chaotic: contact sequences that amplify the
# float32 rounding of the recorded start state. Replayed from that start moved by less than its rounding
# (3e-5 px, 2e-7 rad), the simulation itself ends up to 3e-3 px (episode 78) and 0.1-0.75 px (episode 107)
# away from the unperturbed replay, so no simulator can reproduce them from the stored float32 state.
DIVERGENT = {
    78: "chaotic contacts amplify the float32 rounding of the start: 1e-4 px at step 45, 1.25e-3 px max at step 65",
    107: "chaotic contacts amplify the float32 rounding of the start: error doubles per step from step 46, 0.17 px",
}
DIVERGENT_BOUND = 1.0  # even these stay within a pixel: a gross mismatch is a bug, not chaos


def _dataset_path() -> Path:
    for path in DATASETS:
        if path.exists():
            return path
    pytest.skip(f"no Push-T dataset at any of {[str(p) for p in DATASETS]}")


@pytest.fixture(scope="module")
def demonstrations():
    root = zarr.open(str(_dataset_path()), "r")
    states = np.asarray(root["data/state"][:], dtype=np.float64)
    actions = np.asarray(root["data/action"][:], dtype=np.float64)
    ends = np.asarray(root["meta/episode_ends"][:], dtype=np.int64)
    return states, actions, ends


def _state_error(obs: np.ndarray, recorded: np.ndarray) -> float:
    """Largest coordinate error, with the angle compared on the circle."""
    angle_error = abs((obs[4] - recorded[4] + np.pi) % (2 * np.pi) - np.pi)
    return max(float(np.max(np.abs(obs[:4] - recorded[:4]))), angle_error)


def _replay_errors(env: PushTEnv, states: np.ndarray, actions: np.ndarray, start: int, end: int) -> np.ndarray:
    """Per-step state error of one episode replayed from its restored first state."""
    obs, _ = env.reset(options={"restore_state": states[start]})
    errors = [_state_error(obs, states[start])]
    for t in range(start, end - 1):
        obs, *_ = env.step(actions[t])
        errors.append(_state_error(obs, states[t + 1]))
    return np.asarray(errors)


@pytest.mark.slow
def test_every_demonstration_replays_exactly(demonstrations):
    """All 206 episodes (~25k steps): recorded states reproduced within 1e-3, except the named chaotic ones."""
    states, actions, ends = demonstrations
    assert len(ends) == 206 and ends[-1] == len(states) == len(actions)
    starts = np.concatenate([[0], ends[:-1]])
    env = PushTEnv()
    failures = []
    for episode, (start, end) in enumerate(zip(starts, ends)):
        errors = _replay_errors(env, states, actions, int(start), int(end))
        worst, first = float(errors.max()), int(np.argmax(errors > TOLERANCE))
        if episode in DIVERGENT:
            assert worst < DIVERGENT_BOUND, f"episode {episode} is off by {worst:.3g} px, more than chaos explains"
        elif worst > TOLERANCE:
            failures.append(f"episode {episode}: error {worst:.3g} from step {first}")
    assert not failures, f"{len(failures)} episodes do not reproduce: {failures}"


def test_restore_state_puts_the_block_at_the_recorded_pose(demonstrations):
    """restore_state sets angle then position, so the block lands on the recorded pose; reset_to_state does not."""
    states, _, ends = demonstrations
    env = PushTEnv()
    for start in np.concatenate([[0], ends[:-1]])[::20]:
        recorded = states[start]
        restored, _ = env.reset(options={"restore_state": recorded})
        assert _state_error(restored, recorded) < 1e-9
        legacy, _ = env.reset(options={"reset_to_state": recorded})
        assert np.abs(legacy[2:4] - recorded[2:4]).max() > 1.0  # rotated about the centre of gravity

"""Policy inputs beyond the state: the previous observation (`prev_state`) and the chunk's pace (`pace_input`)."""

from __future__ import annotations

import math

import numpy as np
import onnxruntime as ort
import pytest
import torch

from acting import load_policy
from policies.checkpoint import load_acting_policy, save_checkpoint
from policies.factory import build_policy
from policies.features import motion_features
from policies.normalization import Normalizer
from policies.pace import Pace, goal_distance
from pusht.geometry import GOAL_POSE
from pusht.rollout import run_episodes
from training.config import TrainConfig
from training.data import chunks_at, load_replay, previous_states, training_set
from training.export import export_onnx
from training.train import train

ARCH = {"angle_encoding": "sincos", "state_skip": True, "action_frame": "agent", "prev_state": True}


@pytest.fixture(scope="module")
def replay():
    return load_replay()


def test_motion_features_wrap_the_angle_and_vanish_without_motion() -> None:
    state = torch.tensor([[100.0, 200.0, 300.0, 300.0, 0.01]])
    prev = torch.tensor([[92.0, 200.0, 298.0, 300.0, 2 * math.pi - 0.02]])
    got = motion_features(state, prev)[0]
    assert torch.allclose(got, torch.tensor([1.0, 0.0, 1.0, 0.0, 1.0]), atol=1e-4)  # 0.03 rad across 2 pi, not -6.25
    assert torch.count_nonzero(motion_features(state, state)) == 0


def test_previous_states_are_one_frame_back_within_an_episode(replay) -> None:
    first = int(replay.episode_ends[0])  # the second episode's first frame
    frames = np.array([0, 5, first, first + 1])
    prev = previous_states(replay, frames)
    np.testing.assert_array_equal(prev, replay.states[[0, 4, first, first]])
    data = training_set("data/pusht_lowdim.zarr", pad_end=True)
    np.testing.assert_array_equal(data.prev_states[5].numpy(), replay.states[4])


@pytest.mark.parametrize("kind", ["mse", "flow"])
def test_the_previous_state_changes_the_actions_and_defaults_to_no_motion(kind, replay) -> None:
    torch.manual_seed(0)
    policy = build_policy(kind, **ARCH, dropout=0.0)
    policy.normalizer.set(Normalizer.fit(replay.states, replay.actions, action_frame="agent").to_dict())
    assert policy.architecture["prev_state"] is True
    state = torch.as_tensor(replay.states[10:14])
    prev = torch.as_tensor(replay.states[9:13])
    noise = torch.zeros(4, 12, 2)
    with torch.no_grad():
        moving = policy.act(state, noise, prev_state=prev)
        still = policy.act(state, noise, prev_state=state)
        default = policy.act(state, noise)
    assert not torch.allclose(moving, still)
    assert torch.equal(still, default)
    loss = policy.compute_loss(
        state, torch.as_tensor(np.stack([replay.actions[i : i + 12] for i in range(10, 14)])), prev_state=prev
    )
    assert torch.isfinite(loss)


def test_plain_policies_keep_their_architecture_and_ignore_prev_state(replay) -> None:
    policy = build_policy("flow", angle_encoding="sincos")
    assert "prev_state" not in policy.architecture
    with pytest.raises(ValueError, match="prev_state must be true or false"):
        build_policy("flow", prev_state="yes")


@pytest.fixture(scope="module")
def exported(tmp_path_factory, replay):
    torch.manual_seed(1)
    policy = build_policy("flow", **ARCH)
    stem = tmp_path_factory.mktemp("prev") / "flow-prev"
    save_checkpoint(stem, policy, Normalizer.fit(replay.states, replay.actions, action_frame="agent").to_dict())
    export_onnx(stem)
    return stem


def test_onnx_takes_prev_state_and_matches_torch(exported, replay) -> None:
    session = ort.InferenceSession(str(exported.with_suffix(".onnx")), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["state", "noise", "prev_state"]
    rng = np.random.default_rng(0)
    feeds = {
        "state": replay.states[20:25].astype(np.float32),
        "noise": rng.standard_normal((5, 12, 2)).astype(np.float32),
        "prev_state": replay.states[19:24].astype(np.float32),
    }
    got = session.run(["actions"], feeds)[0]
    with torch.inference_mode():
        want = load_acting_policy(exported)(
            torch.from_numpy(feeds["state"]), torch.from_numpy(feeds["noise"]), prev_state=torch.from_numpy(feeds["prev_state"])
        ).numpy()
    assert np.abs(got - want).max() < 1e-3


def test_rollouts_give_the_step_before_and_both_backends_agree(exported) -> None:
    seen: list[tuple[np.ndarray, np.ndarray]] = []

    def act(states, seeds, prev_states):
        seen.append((states.copy(), prev_states.copy()))
        return np.repeat(states[:, None, :2], 12, axis=1)  # stay put: the agent barely moves

    run_episodes(act, [5, 6], num_envs=2, max_steps=24, prev_states=True)
    assert np.array_equal(seen[0][0], seen[0][1])  # an episode's first decision: no step before
    assert not np.array_equal(seen[1][0], seen[1][1])

    summaries = [
        run_episodes(_rollout(load_policy(path)), [7, 8, 9], num_envs=3, max_steps=48, prev_states=True)
        for path in (exported.with_suffix(".onnx"), exported)
    ]
    assert [e.max_reward for e in summaries[0].episodes] == pytest.approx([e.max_reward for e in summaries[1].episodes], abs=1e-4)


def _rollout(policy):
    assert policy.takes_prev_state

    def act(states, seeds, prev_states):
        return policy.act(states, prev_states, seeds=seeds)

    return act


PACE_ARCH = {
    "angle_encoding": "sincos",
    "state_skip": True,
    "action_frame": "agent",
    "pace_input": True,
    "acting_pace": [2.0, 1.0, 2.0, 0.0],
}


def test_pace_copies_repeat_each_window_at_paces_from_one_to_the_fastest(replay) -> None:
    plain = training_set("data/pusht_lowdim.zarr", pad_end=True)
    paced = training_set("data/pusht_lowdim.zarr", pad_end=True, pace=2.5, pace_copies=3, seed=4)
    assert len(paced) == 3 * len(plain) and plain.paces is None
    paces = paced.paces.numpy()
    assert 1.0 <= paces.min() and paces.max() <= 2.5 and paces.std() > 0.3
    frames = np.repeat(np.arange(len(replay.states)), 3)
    np.testing.assert_array_equal(paced.states.numpy(), replay.states[frames])
    np.testing.assert_allclose(paced.chunks[:9].numpy(), chunks_at(replay, frames[:9], paces[:9], pad_end=True), atol=1e-5)
    np.testing.assert_array_equal(paced.prev_states[3:6].numpy(), replay.states[[0, 0, 0]])  # frame 1's step before
    again = training_set("data/pusht_lowdim.zarr", pad_end=True, pace=2.5, pace_copies=3, seed=4)
    assert torch.equal(again.paces, paced.paces)


def test_a_pace_input_acts_at_the_card_s_rule_of_the_state(replay) -> None:
    policy = build_policy("flow", **PACE_ARCH, dropout=0.0)
    policy.normalizer.set(Normalizer.fit(replay.states, replay.actions, action_frame="agent").to_dict())
    near = [100.0, 100.0, GOAL_POSE[0] + 20, GOAL_POSE[1], GOAL_POSE[2]]  # 0.5 goal units away
    far = [100.0, 100.0, GOAL_POSE[0] + 200, GOAL_POSE[1], GOAL_POSE[2]]  # 5 units
    states = torch.tensor([near, far])
    np.testing.assert_allclose(goal_distance(states.numpy()), [0.5, 5.0], atol=1e-5)
    assert policy.policy_state(states)[:, -1].tolist() == [0.0, 1.0]  # pace 1 near, 2 far, fed as pace - 1
    chosen = policy.policy_state(states, pace=torch.tensor([1.5, 1.5]))
    assert chosen[:, -1].tolist() == [0.5, 0.5]
    assert Pace(2.0, 1.0, 2.0).speeds(states.numpy()).tolist() == [1.0, 2.0]
    with pytest.raises(ValueError, match="acting_pace must be"):
        build_policy("flow", pace_input=True, acting_pace=[2.0, 1.0])


def test_a_pace_input_trains_only_with_pace_copies(tmp_path) -> None:
    arch = '{"pace_input": true}'
    with pytest.raises(ValueError, match="pace input trains with --pace-copies"):
        train(TrainConfig(policy="flow", steps=1, arch=arch, out_dir=str(tmp_path), eval_every=-1, progress=False))
    with pytest.raises(ValueError, match="pace input trains with --pace-copies"):
        train(
            TrainConfig(
                policy="flow", steps=1, pace_copies=2, action_speed=2.0, out_dir=str(tmp_path), eval_every=-1, progress=False
            )
        )
    assert not (tmp_path / "flow").exists()


def test_onnx_of_a_pace_input_matches_torch_near_and_far(tmp_path, replay) -> None:
    torch.manual_seed(2)
    policy = build_policy("flow", **PACE_ARCH)
    stem = tmp_path / "flow-pace"
    save_checkpoint(stem, policy, Normalizer.fit(replay.states, replay.actions, action_frame="agent").to_dict())
    export_onnx(stem)
    session = ort.InferenceSession(str(stem.with_suffix(".onnx")), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["state", "noise"]
    states = np.array(
        [
            [100.0, 100.0, GOAL_POSE[0] + 20, GOAL_POSE[1], GOAL_POSE[2]],
            [100.0, 100.0, GOAL_POSE[0] + 200, GOAL_POSE[1], GOAL_POSE[2]],
        ],
        dtype=np.float32,
    )
    noise = np.random.default_rng(0).standard_normal((2, 12, 2)).astype(np.float32)
    got = session.run(["actions"], {"state": states, "noise": noise})[0]
    with torch.inference_mode():
        want = load_acting_policy(stem)(torch.from_numpy(states), torch.from_numpy(noise)).numpy()
    assert np.abs(got - want).max() < 1e-3

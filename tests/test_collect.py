"""Collecting a shipped policy's successful episodes, and fine-tuning on them (training.collect, --init, --extra-data)."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest
import zarr

from pusht.rollout import default_env_factory
from training.checkpoint import load_checkpoint
from training.collect import main as collect_main
from training.data import load_replay, make_windows
from training.normalization import Normalizer
from training.train import main as train_main

REPO = Path(__file__).resolve().parent.parent
SHIPPED_FLOW = REPO / "models" / "flow"
DATA = REPO / "data" / "pusht_lowdim.zarr"


@pytest.fixture(scope="module")
def collected(tmp_path_factory) -> tuple[Path, dict]:
    """12 episodes of the shipped flow on seeds 300000..300011, successes kept."""
    out = tmp_path_factory.mktemp("collect") / "flow.zarr"
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        assert collect_main(["--model", str(SHIPPED_FLOW.with_suffix(".onnx")), "--episodes", "12", "--seed", "300000",
                             "--num-envs", "12", "--out", str(out), "--no-progress"]) == 0
    return out, json.loads(buffer.getvalue())


def test_collect_keeps_exactly_the_successful_episodes(collected):
    out, line = collected
    replay = load_replay(out)
    assert line["episodes"] == 12 and line["seeds"] == [300000, 300011]
    assert line["kept_episodes"] == round(line["success_rate"] * 12) == replay.num_episodes >= 1
    assert line["kept_frames"] == len(replay.states)
    kept_seeds = zarr.open_group(str(out), mode="r").attrs["kept_seeds"]
    assert len(kept_seeds) == replay.num_episodes and all(300000 <= s <= 300011 for s in kept_seeds)


def test_collected_episodes_replay_to_success(collected):
    """Replaying the stored actions from each kept seed reproduces the stored states and ends in success."""
    out, _ = collected
    replay = load_replay(out)
    kept_seeds = zarr.open_group(str(out), mode="r").attrs["kept_seeds"]
    for seed, start, end in zip(kept_seeds, replay.episode_starts(), replay.episode_ends, strict=True):
        env = default_env_factory()
        obs, _ = env.reset(seed=seed)
        for t in range(start, end):
            np.testing.assert_array_equal(replay.states[t], np.asarray(obs, dtype=np.float32))
            obs, _, terminated, _, info = env.step(replay.actions[t])
        assert terminated and info["is_success"]


@pytest.mark.slow
def test_retries_of_near_misses_replay_to_success(tmp_path):
    """A retried episode is the failed episode's steps up to a near-goal state, then a retry from that state that succeeds."""
    out = tmp_path / "retries.zarr"
    # the imitation flow alone, which misses often enough (the shipped chooser succeeds in about 9 of 10 episodes)
    imitation = REPO / "records" / "flow-agentframe-padend-150k-noise0.3" / "last"
    assert collect_main(["--model", str(imitation), "--episodes", "12", "--seed", "300000",
                         "--num-envs", "12", "--retries", "4", "--out", str(out), "--no-progress"]) == 0
    replay = load_replay(out)
    attrs = zarr.open_group(str(out), mode="r").attrs
    retried = attrs["retried_episodes"]
    assert retried >= 1 and len(attrs["retry_start_frames"]) == retried
    first = replay.num_episodes - retried
    for e, t in zip(range(first, replay.num_episodes), attrs["retry_start_frames"], strict=True):
        start, end = int(replay.episode_starts()[e]), int(replay.episode_ends[e])
        env = default_env_factory()
        obs, _ = env.reset(seed=attrs["kept_seeds"][e])
        for i in range(start, start + t):  # the failed episode's own steps, from its seed
            np.testing.assert_array_equal(replay.states[i], np.asarray(obs, dtype=np.float32))
            obs, *_ = env.step(replay.actions[i])
        obs, _ = env.reset(options={"restore_state": replay.states[start + t]})
        for i in range(start + t, end):  # the retry, from the restored near-goal state
            np.testing.assert_array_equal(replay.states[i], np.asarray(obs, dtype=np.float32))
            obs, _, terminated, _, info = env.step(replay.actions[i])
        assert terminated and info["is_success"]


def test_collect_refuses_the_heldout_seeds(tmp_path, capsys):
    code = collect_main(["--model", str(SHIPPED_FLOW.with_suffix(".onnx")), "--episodes", "10", "--seed", "199995",
                         "--out", str(tmp_path / "x.zarr"), "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err
    assert "held-out" in err and "Traceback" not in err
    assert not (tmp_path / "x.zarr").exists()


def test_agent_frame_windows_are_relative_to_the_agent():
    replay = load_replay(DATA)
    states, absolute = make_windows(replay, 12)
    relative = Normalizer(action_frame="agent").in_frame(states, absolute)
    np.testing.assert_allclose(relative + states[:, None, :2], absolute, atol=1e-4)


@pytest.mark.slow
def test_fine_tuning_on_collected_episodes_keeps_the_base_normalization(collected, tmp_path, capsys):
    out, line = collected
    args = ["--policy", "flow", "--name", "ft", "--out-dir", str(tmp_path), "--data", str(DATA), "--init", str(SHIPPED_FLOW),
            "--extra-data", str(out), "--steps", "20", "--batch-size", "32", "--eval-every", "-1", "--no-progress"]
    assert train_main(args) == 0
    err = capsys.readouterr().err
    base_windows = len(make_windows(load_replay(DATA), 12)[0])
    extra_windows = len(make_windows(load_replay(out), 12)[0])
    assert f"windows: {base_windows + extra_windows} ({base_windows} demonstration, {extra_windows} extra)" in err
    tuned, card = load_checkpoint(tmp_path / "ft" / "last")
    base, base_card = load_checkpoint(SHIPPED_FLOW)
    assert card["normalization"] == base_card["normalization"] and card["architecture"] == base_card["architecture"]
    changed = [k for k, v in tuned.state_dict().items() if not np.array_equal(v.numpy(), base.state_dict()[k].numpy())]
    assert changed, "fine-tuning left every weight as it was"

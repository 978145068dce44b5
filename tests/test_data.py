"""The committed low-dimensional dataset, windows inside episodes, the demonstrations' statistics, and clear dataset errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import zarr

from policies.factory import build_policy
from policies.normalization import Normalizer
from policies.pace import Pace, goal_distance
from pusht.geometry import GOAL_POSE
from training.config import TrainConfig
from training.data import DEFAULT_DATASET, DatasetError, ExtraData, Replay, load_replay, make_windows, training_set, window_starts

REPO = Path(__file__).resolve().parent.parent
FULL_DATASET = REPO.parent / "shared" / "data" / "pusht" / "pusht_cchi_v7_replay.zarr"
LOWDIM_ARRAYS = ("data/state", "data/action", "data/keypoint", "data/n_contacts", "meta/episode_ends")


@pytest.fixture(scope="module")
def replay() -> Replay:
    return load_replay()


def test_default_dataset_shapes(replay: Replay) -> None:
    assert DEFAULT_DATASET == REPO / "data" / "pusht_lowdim.zarr"
    assert replay.states.shape == (25650, 5) and replay.states.dtype == np.float32
    assert replay.actions.shape == (25650, 2) and replay.actions.dtype == np.float32
    assert replay.episode_ends.shape == (206,) and replay.episode_ends.dtype == np.int64
    assert replay.episode_ends[-1] == 25650


def test_windows_on_the_real_data(replay: Replay) -> None:
    states, chunks = make_windows(replay)
    assert states.shape == (23384, 5) and chunks.shape == (23384, 12, 2)
    assert states.dtype == np.float32 and chunks.dtype == np.float32
    starts = window_starts(replay.episode_ends)
    np.testing.assert_array_equal(states, replay.states[starts])
    for w in (0, 1, 5000, 23383):
        np.testing.assert_array_equal(chunks[w], replay.actions[starts[w] : starts[w] + 12])


def test_windows_never_cross_episode_ends(replay: Replay) -> None:
    starts = window_starts(replay.episode_ends)
    episode_of_first = np.searchsorted(replay.episode_ends, starts, side="right")
    episode_of_last = np.searchsorted(replay.episode_ends, starts + 11, side="right")
    np.testing.assert_array_equal(episode_of_first, episode_of_last)
    # and every frame that can start a window does: per episode, length - 11 windows
    lengths = np.diff(np.concatenate([[0], replay.episode_ends]))
    np.testing.assert_array_equal(np.bincount(episode_of_first, minlength=206), lengths - 11)


def test_padded_windows_start_at_every_frame_and_repeat_the_last_action() -> None:
    actions = np.arange(20, dtype=np.float32).reshape(10, 2)
    replay = Replay(np.arange(50, dtype=np.float32).reshape(10, 5), actions, np.array([3, 10]))
    states, chunks = make_windows(replay, horizon=4, pad_end=True)
    np.testing.assert_array_equal(states, replay.states)  # every frame starts a window
    np.testing.assert_array_equal(chunks[1], actions[[1, 2, 2, 2]])  # episode 1 ends at frame 2
    np.testing.assert_array_equal(chunks[3], actions[3:7])
    np.testing.assert_array_equal(chunks[8], actions[[8, 9, 9, 9]])
    unpadded = make_windows(replay, horizon=4)[1]
    np.testing.assert_array_equal(chunks[3:7], unpadded)  # the windows inside episodes are unchanged


RECORDED_RUNS = sorted((REPO / "records").glob("*/last.json"))


def test_faster_windows_interpolate_the_demonstrated_path_and_stay_in_their_episode() -> None:
    actions = np.arange(40, dtype=np.float32).reshape(20, 2)  # action at frame f: (2f, 2f + 1)
    replay = Replay(np.arange(100, dtype=np.float32).reshape(20, 5), actions, np.array([6, 20]))
    states, chunks = make_windows(replay, horizon=4, pad_end=True, pace=1.5)
    np.testing.assert_array_equal(states, replay.states)
    frames = lambda w: (chunks[w][:, 0] / 2).tolist()  # noqa: E731  (the frame each action was read at)
    assert frames(6) == [6.0, 7.5, 9.0, 10.5]
    assert frames(2) == [2.0, 3.5, 5.0, 5.0]  # padded with episode 0's last action (frame 5), never episode 1's
    assert frames(17) == [17.0, 18.5, 19.0, 19.0]
    # without padding a window starts only where its whole span (1 + ceil(1.5 * 3) = 6 frames) fits in its episode
    states, chunks = make_windows(replay, horizon=4, pace=1.5)
    np.testing.assert_array_equal(states[:, 0] / 5, [0, 6, 7, 8, 9, 10, 11, 12, 13, 14])
    assert (chunks[-1][:, 0] / 2).tolist() == [14.0, 15.5, 17.0, 18.5]
    np.testing.assert_array_equal(make_windows(replay, 4, True, pace=1.0)[1], make_windows(replay, 4, True)[1])
    with pytest.raises(ValueError, match="pace far must be in"):
        make_windows(replay, 4, True, pace=0.0)


def test_a_pace_per_window_hurries_only_far_from_the_goal(replay: Replay) -> None:
    pace = Pace(far=2.0, near=1.0, radius=2.0)
    states, chunks = make_windows(replay, 12, True, pace)
    far = goal_distance(states) >= 2.0
    assert 0.3 < far.mean() < 0.7  # both kinds of window are common in the demonstrations
    np.testing.assert_array_equal(chunks[far], make_windows(replay, 12, True, 2.0)[1][far])
    np.testing.assert_array_equal(chunks[~far], make_windows(replay, 12, True)[1][~far])
    assert goal_distance(np.array([[0, 0, *GOAL_POSE]]))[0] == 0
    assert goal_distance(np.array([[0, 0, GOAL_POSE[0] + 40, GOAL_POSE[1], GOAL_POSE[2] + 2 * np.pi - 0.3]]))[0] == pytest.approx(
        1.5
    )
    ramped = Pace(far=2.0, near=1.0, radius=1.0, ramp=2.0).speeds(
        np.array([[0, 0, *GOAL_POSE], [0, 0, GOAL_POSE[0] + 80, *GOAL_POSE[1:]], [0, 0, GOAL_POSE[0] + 200, *GOAL_POSE[1:]]])
    )
    np.testing.assert_allclose(ramped, [1.0, 1.5, 2.0])
    with pytest.raises(ValueError, match="pace near must be in"):
        Pace(far=2.0, near=5.0, radius=1.0)


@pytest.mark.parametrize("card_path", RECORDED_RUNS, ids=[p.parent.name for p in RECORDED_RUNS])
def test_training_set_reproduces_every_recorded_run_s_statistics(card_path: Path) -> None:
    """A policy fitted on the one-call dataset must normalize exactly as the runs behind the recorded scores did."""
    card = json.loads(card_path.read_text())
    config = card["config"]
    if config.get("init"):
        pytest.skip("fine-tuned runs keep their base's normalization")
    copies = config.get("pace_copies", 0)
    data = training_set(
        REPO / config["data"],
        config["horizon"],
        bool(config.get("pad_episode_end")),
        pace=TrainConfig(**config).pace(),
        pace_copies=copies,
        seed=config["seed"],
    )
    policy = build_policy(card["kind"], **card["architecture"])
    policy.normalizer.set(data.statistics(policy.action_frame))
    assert policy.normalizer.to_dict() == card["normalization"]
    assert len(data) == data.demo_windows == max(1, copies) * (25650 if config.get("pad_episode_end") else 23384)


@pytest.mark.parametrize("pad_end", [False, True])
def test_training_set_is_the_env_unit_windows(replay: Replay, pad_end: bool) -> None:
    data = training_set(DEFAULT_DATASET, 12, pad_end, extra=ExtraData((DEFAULT_DATASET,)))
    states, chunks = make_windows(replay, 12, pad_end)
    assert data.demo_windows == len(states) and len(data) == 2 * len(states)  # the extra store's windows follow
    assert torch.equal(data.states, torch.cat([torch.from_numpy(states)] * 2))
    assert torch.equal(data.chunks, torch.cat([torch.from_numpy(chunks)] * 2))


def test_extra_stride_keeps_the_decision_points_of_each_extra_episode(replay: Replay) -> None:
    """--extra-stride 12: extra windows start only at frames 0, 12, 24, ... of their episode (where a collector chose a chunk)."""
    data = training_set(DEFAULT_DATASET, 12, True, extra=ExtraData((DEFAULT_DATASET,), stride=12))
    starts = np.concatenate([[0], replay.episode_ends[:-1]])
    decisions = np.concatenate([np.arange(s, e, 12) for s, e in zip(starts, replay.episode_ends)])
    states, chunks = make_windows(replay, 12, True)
    assert len(data) - data.demo_windows == len(decisions)
    assert torch.equal(data.states[data.demo_windows :], torch.from_numpy(states[decisions]))
    assert torch.equal(data.chunks[data.demo_windows :], torch.from_numpy(chunks[decisions]))
    assert torch.equal(data.states[: data.demo_windows], torch.from_numpy(states))  # the demonstrations keep every window
    with pytest.raises(ValueError, match="extra_stride"):
        training_set(DEFAULT_DATASET, 12, True, extra=ExtraData((DEFAULT_DATASET,), stride=0))


@pytest.mark.parametrize("frame", ["absolute", "agent"])
def test_statistics_are_the_demonstrations_alone_in_the_frame(replay: Replay, frame: str) -> None:
    data = training_set(DEFAULT_DATASET, 12, extra=ExtraData((DEFAULT_DATASET,)))
    stats = data.statistics(frame)
    assert stats.action_frame == frame
    np.testing.assert_allclose(stats.state_mean, replay.states.astype(np.float64).mean(0), rtol=1e-6)
    states, chunks = make_windows(replay, 12)
    actions = replay.actions if frame == "absolute" else chunks - states[:, None, :2]
    np.testing.assert_allclose(stats.action_std, actions.astype(np.float64).reshape(-1, 2).std(0), rtol=1e-6)


def test_short_episodes_give_no_windows() -> None:
    replay = Replay(np.zeros((10, 5), np.float32), np.arange(20, dtype=np.float32).reshape(10, 2), np.array([3, 10]))
    states, chunks = make_windows(replay, horizon=4)
    assert len(states) == 4  # episode 1 (3 frames) none; episode 2 (7 frames) four
    np.testing.assert_array_equal(chunks[0], replay.actions[3:7])


def test_normalizer_statistics(replay: Replay) -> None:
    norm = Normalizer.fit(replay.states, replay.actions)
    np.testing.assert_allclose(norm.state_mean, replay.states.astype(np.float64).mean(0), rtol=1e-6)
    np.testing.assert_allclose(norm.action_std, replay.actions.astype(np.float64).std(0), rtol=1e-6)
    states = torch.from_numpy(replay.states)
    states_n = norm.state(states)
    torch.testing.assert_close(states_n.mean(0), torch.zeros(5), atol=1e-4, rtol=0)
    torch.testing.assert_close(states_n.std(0), torch.ones(5), atol=1e-4, rtol=0)
    chunk = torch.from_numpy(replay.actions[:24]).reshape(2, 12, 2)
    torch.testing.assert_close(norm.actions(states[:2], norm.chunk(states[:2], chunk)), chunk, atol=1e-4, rtol=0)


def test_normalizer_guards_constant_dimensions() -> None:
    states = np.ones((4, 5), np.float32)
    norm = Normalizer.fit(states, np.zeros((4, 2)))
    assert torch.all(norm.state_std == 1.0) and torch.all(norm.action_std == 1.0)
    assert torch.isfinite(norm.state(torch.from_numpy(states))).all()


def test_normalizer_dict_round_trip_and_errors(replay: Replay) -> None:
    norm = Normalizer.fit(replay.states, replay.actions)
    assert Normalizer().set(norm.to_dict()).to_dict() == norm.to_dict() == Normalizer().set(norm).to_dict()
    with pytest.raises(ValueError, match="action_std must be a list of 2"):
        Normalizer().set({**norm.to_dict(), "action_std": [1.0]})
    with pytest.raises(ValueError, match="no normalization yet"):
        Normalizer().to_dict()


# --- the committed copy and its provenance ---


@pytest.mark.skipif(not FULL_DATASET.is_dir(), reason=f"full dataset not present at {FULL_DATASET}")
def test_lowdim_copy_equals_the_full_dataset() -> None:
    full = zarr.open_group(str(FULL_DATASET), mode="r")
    copy = zarr.open_group(str(DEFAULT_DATASET), mode="r")
    for name in LOWDIM_ARRAYS:
        a, b = np.asarray(full[name][...]), np.asarray(copy[name][...])
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert a.tobytes() == b.tobytes(), name
    assert "img" not in copy["data"]


def test_lowdim_copy_is_small() -> None:
    files = [f for f in DEFAULT_DATASET.rglob("*") if f.is_file()]
    assert sum(f.stat().st_size for f in files) < 2_000_000 and len(files) <= 20


def test_make_lowdim_dataset_help() -> None:
    result = subprocess.run(
        [sys.executable, "scripts/make_lowdim_dataset.py", "--help"], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0 and "--src" in result.stdout and "--out" in result.stdout


# --- malformed stores: each error names the path and the problem ---


def _store(path: Path, states=None, actions=None, ends=None, skip: tuple[str, ...] = ()) -> Path:
    """A small zarr replay (2 episodes, 30 frames), with parts replaced or left out."""
    root = zarr.open_group(str(path), mode="w")
    arrays = {
        "data/state": np.zeros((30, 5), np.float32) if states is None else states,
        "data/action": np.zeros((30, 2), np.float32) if actions is None else actions,
        "meta/episode_ends": np.array([14, 30], np.int64) if ends is None else ends,
    }
    for name, values in arrays.items():
        if name not in skip:
            root.create_dataset(name, data=values)
    return path


def test_valid_small_store(tmp_path: Path) -> None:
    replay = load_replay(_store(tmp_path / "ok.zarr"))
    assert replay.num_episodes == 2 and len(make_windows(replay)[0]) == 30 - 2 * 11


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"nowhere\.zarr: dataset not found"):
        load_replay(tmp_path / "nowhere.zarr")


def test_path_is_a_file(tmp_path: Path) -> None:
    path = tmp_path / "file.zarr"
    path.write_text("hello")
    with pytest.raises(DatasetError, match=r"file\.zarr: not a zarr directory store"):
        load_replay(path)


def test_empty_directory(tmp_path: Path) -> None:
    path = tmp_path / "empty.zarr"
    path.mkdir()
    with pytest.raises(DatasetError, match=r"empty\.zarr: not a readable zarr group"):
        load_replay(path)


@pytest.mark.parametrize("name", ["data/state", "data/action", "meta/episode_ends"])
def test_missing_array(tmp_path: Path, name: str) -> None:
    path = _store(tmp_path / "m.zarr", skip=(name,))
    with pytest.raises(DatasetError, match=rf"m\.zarr: missing array {name}"):
        load_replay(path)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"states": np.zeros((30, 4), np.float32)}, r"data/state must have shape \[N, 5\], got \[30, 4\]"),
        ({"actions": np.zeros((30, 2, 1), np.float32)}, r"data/action must have shape \[N, 2\]"),
        ({"actions": np.zeros((29, 2), np.float32)}, "data/state has 30 frames but data/action has 29"),
        ({"ends": np.array([20, 14, 30])}, "meta/episode_ends must be positive and strictly increasing"),
        ({"ends": np.array([14, 14, 30])}, "meta/episode_ends must be positive and strictly increasing"),
        ({"ends": np.array([14, 28])}, "meta/episode_ends ends at 28 but there are 30 frames"),
        ({"ends": np.array([14.0, 30.0])}, "meta/episode_ends must be integers"),
        ({"ends": np.zeros((0,), np.int64)}, "meta/episode_ends must be a non-empty 1-D array"),
        ({"states": np.full((30, 5), np.nan, np.float32)}, "data/state contains NaN or inf"),
    ],
)
def test_malformed_store(tmp_path: Path, kwargs: dict, message: str) -> None:
    path = _store(tmp_path / "bad.zarr", **kwargs)
    with pytest.raises(DatasetError, match=rf"bad\.zarr: {message}"):
        load_replay(path)


def test_corrupt_chunk(tmp_path: Path) -> None:
    path = _store(tmp_path / "c.zarr")
    for chunk in (path / "data" / "state").glob("[0-9]*"):
        chunk.write_bytes(b"not blosc at all")
    with pytest.raises(DatasetError, match=r"c\.zarr: cannot read data/state"):
        load_replay(path)

"""The Push-T demonstrations: a validated replay buffer and 12-action windows inside episodes, in env units.

    replay = load_replay()                      # data/pusht_lowdim.zarr
    states, chunks = make_windows(replay)       # [23384, 5], [23384, 12, 2] on the real data
    data = training_set("data/pusht_lowdim.zarr")  # what a training loop needs, in one call

Window t pairs the state at frame t with the actions of frames t..t+11 of the same episode. Nothing
here normalizes or changes frames: the policy does both (`policy.normalizer`, policies.normalization).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import zarr

from policies.normalization import Normalizer
from policies.pace import Pace
from pusht.spec import ACTION_DIM, DEFAULT_HORIZON, STATE_DIM

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATASET = REPO_ROOT / "data" / "pusht_lowdim.zarr"


class DatasetError(ValueError):
    """The replay store is missing or malformed."""


@dataclass(frozen=True)
class Replay:
    """Frames of all episodes back to back; episode e covers [episode_ends[e-1], episode_ends[e])."""

    states: np.ndarray  # [N, 5] float32, env units
    actions: np.ndarray  # [N, 2] float32, env units
    episode_ends: np.ndarray  # [E] int64, exclusive ends, strictly increasing, last == N

    @property
    def num_episodes(self) -> int:
        """Number of episodes."""
        return int(len(self.episode_ends))

    def episode_starts(self) -> np.ndarray:
        """Start frame of each episode."""
        return np.concatenate([[0], self.episode_ends[:-1]]).astype(np.int64)


def load_replay(path: str | Path | None = None) -> Replay:
    """Read and validate data/state, data/action and meta/episode_ends from a zarr store (default DEFAULT_DATASET)."""
    path = Path(path) if path is not None else DEFAULT_DATASET
    if not path.exists():
        raise DatasetError(f"{path}: dataset not found (expected a zarr store with data/state, data/action, meta/episode_ends)")
    if not path.is_dir():
        raise DatasetError(f"{path}: not a zarr directory store")
    try:
        root = zarr.open_group(str(path), mode="r")
    except Exception as exc:  # zarr raises several unrelated types for a bad store
        raise DatasetError(f"{path}: not a readable zarr group: {exc}") from None
    arrays = {name: _read_array(root, path, name) for name in ("data/state", "data/action", "meta/episode_ends")}
    states, actions, ends = arrays["data/state"], arrays["data/action"], arrays["meta/episode_ends"]

    if states.ndim != 2 or states.shape[1] != STATE_DIM:
        raise DatasetError(f"{path}: data/state must have shape [N, {STATE_DIM}], got {list(states.shape)}")
    if actions.ndim != 2 or actions.shape[1] != ACTION_DIM:
        raise DatasetError(f"{path}: data/action must have shape [N, {ACTION_DIM}], got {list(actions.shape)}")
    if len(states) != len(actions):
        raise DatasetError(f"{path}: data/state has {len(states)} frames but data/action has {len(actions)}")
    if len(states) == 0:
        raise DatasetError(f"{path}: the dataset has no frames")
    for name, values in (("data/state", states), ("data/action", actions)):
        if not np.issubdtype(values.dtype, np.floating) and not np.issubdtype(values.dtype, np.integer):
            raise DatasetError(f"{path}: {name} must be numeric, got dtype {values.dtype}")
        if not np.isfinite(values.astype(np.float64)).all():
            raise DatasetError(f"{path}: {name} contains NaN or inf")
    if ends.ndim != 1 or len(ends) == 0:
        raise DatasetError(f"{path}: meta/episode_ends must be a non-empty 1-D array, got shape {list(ends.shape)}")
    if not np.issubdtype(ends.dtype, np.integer):
        raise DatasetError(f"{path}: meta/episode_ends must be integers, got dtype {ends.dtype}")
    ends = ends.astype(np.int64)
    if ends[0] <= 0 or np.any(np.diff(ends) <= 0):
        raise DatasetError(f"{path}: meta/episode_ends must be positive and strictly increasing")
    if ends[-1] != len(states):
        raise DatasetError(f"{path}: meta/episode_ends ends at {int(ends[-1])} but there are {len(states)} frames")
    return Replay(states=states.astype(np.float32), actions=actions.astype(np.float32), episode_ends=ends)


def save_replay(path: str | Path, replay: Replay, attrs: dict[str, Any] | None = None) -> None:
    """Write `replay` as a zarr v2 store with the dataset's layout (data/state, data/action, meta/episode_ends), replacing `path`."""
    path = Path(path)
    root = zarr.open_group(str(path), mode="w", zarr_version=2)
    root.create_dataset("data/state", data=np.asarray(replay.states, dtype=np.float32))
    root.create_dataset("data/action", data=np.asarray(replay.actions, dtype=np.float32))
    root.create_dataset("meta/episode_ends", data=np.asarray(replay.episode_ends, dtype=np.int64))
    root.attrs.update(attrs or {})


def make_windows(
    replay: Replay, horizon: int = DEFAULT_HORIZON, pad_end: bool = False, pace: Pace | float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """States [W, 5] and action chunks [W, horizon, 2]: the state at t and actions t..t+horizon-1 of one episode.

    With `pad_end`, every frame starts a window, and chunks that would run past their episode's end
    repeat its last action (as Diffusion Policy's sampler pads), so the final frames are learned too.
    At pace s (a number, or a `Pace` that sets it per window from its state), action k of a chunk is
    the demonstration's at frame t + s k, linearly interpolated: the demonstrated path s times as fast.
    """
    pace = Pace.of(pace)
    starts = window_frames(replay, horizon, pad_end, pace.fastest)
    states = replay.states[starts].copy()
    return states, chunks_at(replay, starts, pace.speeds(states), horizon, pad_end)


def chunks_at(
    replay: Replay, starts: np.ndarray, speeds: np.ndarray, horizon: int = DEFAULT_HORIZON, pad_end: bool = False
) -> np.ndarray:
    """Action chunks [W, horizon, 2] starting at frames `starts`, action k the demonstration's at frame t + speeds[w] k
    (interpolated; with `pad_end`, the episode's last action past its end)."""
    positions = starts[:, None] + np.asarray(speeds, dtype=np.float64)[:, None] * np.arange(horizon)[None, :]
    if pad_end:
        last = np.repeat(replay.episode_ends - 1, np.diff(np.concatenate([[0], replay.episode_ends])))[starts]
        positions = np.minimum(positions, last[:, None])
    if np.all(speeds == 1.0):  # integer frames: the demonstration's actions exactly
        return replay.actions[positions.astype(np.int64)]
    below = np.floor(positions).astype(np.int64)
    above = np.minimum(below + 1, np.ceil(positions).astype(np.int64))  # never past the clamp (an episode's last frame)
    weight = (positions - below)[..., None]
    chunks = (1 - weight) * replay.actions[below] + weight * replay.actions[above]
    return chunks.astype(np.float32)


def window_frames(replay: Replay, horizon: int = DEFAULT_HORIZON, pad_end: bool = False, speed: float = 1.0) -> np.ndarray:
    """The frame each of `make_windows`' windows starts at (every frame with `pad_end`; else where a chunk at pace `speed` fits)."""
    if pad_end:
        return np.arange(len(replay.states), dtype=np.int64)
    return window_starts(replay.episode_ends, window_span(horizon, speed))


def window_span(horizon: int, speed: float = 1.0) -> int:
    """Demonstration frames a chunk of `horizon` actions at pace `speed` covers."""
    if not speed > 0:
        raise ValueError(f"speed must be > 0, got {speed}")
    return int(np.ceil(speed * (horizon - 1) - 1e-9)) + 1


def human_labels(path: str | Path, frames: int) -> np.ndarray | None:
    """A store's data/human as bools (True: a human gave that frame's action, as /viewer records), or None without it."""
    root = zarr.open_group(str(path), mode="r")
    if "data/human" not in root:
        return None
    labels = _read_array(root, Path(path), "data/human").reshape(-1)
    if len(labels) != frames:
        raise DatasetError(f"{path}: data/human has {len(labels)} frames but data/state has {frames}")
    return labels.astype(bool)


@dataclass(frozen=True)
class TrainingSet:
    """Training windows in env units, resident as float32 tensors (a few MB, so no DataLoader), and the demonstrations they start with."""

    states: torch.Tensor  # [W, 5]
    chunks: torch.Tensor  # [W, H, 2]
    prev_states: torch.Tensor  # [W, 5]: the state a step before (the state itself at an episode's first frame)
    demonstrations: Replay  # the first demo_windows rows are its windows, the rest come from extra data
    demo_windows: int
    paces: torch.Tensor | None = None  # [W]: each chunk's pace, for a policy that takes it as an input; None: no pace input
    weights: torch.Tensor | None = None  # sampling weight per window; None: all equal (plain permutations)

    def __len__(self) -> int:
        return len(self.states)

    def statistics(self, action_frame: str = "absolute") -> Normalizer:
        """A normalizer fitted on the demonstrations alone, for a policy whose chunks are in `action_frame`."""
        d, demos = self.demo_windows, self.demonstrations
        normalizer = Normalizer(demos.states.shape[1], demos.actions.shape[1], action_frame)
        return normalizer.fit_demonstrations(demos.states, demos.actions, self.states[:d], self.chunks[:d])

    def epoch_order(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """`count` window indices for an epoch: a permutation, or with weights a draw with replacement in proportion to them."""
        if self.weights is None:
            return torch.randperm(len(self.states), generator=generator)[:count]
        return torch.multinomial(self.weights, count, replacement=True, generator=generator)


@dataclass(frozen=True)
class ExtraData:
    """Stores trained on beside the demonstrations (e.g. the viewer's saved corrections). Windows whose first action a human
    gave (data/human) weigh `human_weight`, the others of such stores `policy_step_weight`. With `stride` k, windows start
    only every k-th frame of an episode (a policy's decision points when k is its chunk length)."""

    paths: tuple[str | Path, ...] = ()
    human_weight: float = 1.0
    policy_step_weight: float = 1.0
    stride: int = 1


def training_set(
    data: str | Path,
    horizon: int = DEFAULT_HORIZON,
    pad_end: bool = False,
    extra: ExtraData = ExtraData(),
    pace: Pace | float = 1.0,
    pace_copies: int = 0,
    seed: int = 0,
) -> TrainingSet:
    """The demonstrations' windows plus those of the `extra` stores, in env units.

    `pace`: how fast the chunks play the demonstrations (`make_windows`, policies.pace). With `pace_copies` K, each
    demonstration window appears K times instead, at paces drawn uniformly between 1 and `pace.fastest` (seeded by
    `seed`), and the set carries them (`paces`) for a policy that takes the pace as an input."""
    if extra.stride < 1:
        raise ValueError(f"extra_stride must be >= 1, got {extra.stride}")
    pace = Pace.of(pace)
    replay = load_replay(data)
    frames = window_frames(replay, horizon, pad_end, pace.fastest)
    paces = None
    if pace_copies:
        if extra.paths:
            raise ValueError("a pace input trains on the demonstrations alone; drop the extra data")
        frames = np.repeat(frames, pace_copies)
        paces = np.random.default_rng(seed).uniform(1.0, pace.fastest, len(frames))
    states = replay.states[frames].copy()
    chunks = chunks_at(replay, frames, pace.speeds(states) if paces is None else paces, horizon, pad_end)  # make_windows' windows
    prev_states = previous_states(replay, frames)
    demo_windows = len(states)
    weights = [np.ones(demo_windows)]
    for path in extra.paths:
        extra_replay = load_replay(path)
        extra_states, extra_chunks = make_windows(extra_replay, horizon, pad_end, pace)
        frames = window_frames(extra_replay, horizon, pad_end, pace.fastest)
        keep = _frame_in_episode(frames, extra_replay.episode_ends) % extra.stride == 0
        extra_states, extra_chunks, frames = extra_states[keep], extra_chunks[keep], frames[keep]
        states, chunks = np.concatenate([states, extra_states]), np.concatenate([chunks, extra_chunks])
        prev_states = np.concatenate([prev_states, previous_states(extra_replay, frames)])
        labels = human_labels(path, len(extra_replay.states))
        starts_human = labels[frames] if labels is not None else None
        weights.append(
            np.ones(len(extra_states))
            if starts_human is None
            else np.where(starts_human, extra.human_weight, extra.policy_step_weight)
        )
    weights = np.concatenate(weights)
    return TrainingSet(
        states=torch.as_tensor(np.asarray(states, dtype=np.float32)),
        chunks=torch.as_tensor(np.asarray(chunks, dtype=np.float32)),
        prev_states=torch.as_tensor(np.asarray(prev_states, dtype=np.float32)),
        paces=None if paces is None else torch.as_tensor(paces, dtype=torch.float32),
        demonstrations=replay,
        demo_windows=demo_windows,
        # all ones samples exactly as before the weights existed (plain permutations, same draws)
        weights=None if np.all(weights == 1.0) else torch.as_tensor(weights, dtype=torch.float64),
    )


def previous_states(replay: Replay, frames: np.ndarray) -> np.ndarray:
    """The state one step before each of `frames` (global indices), or the frame's own at its episode's start, as an env reports them."""
    first = _frame_in_episode(frames, replay.episode_ends) == 0
    return replay.states[np.where(first, frames, frames - 1)]


def _frame_in_episode(frames: np.ndarray, episode_ends: np.ndarray) -> np.ndarray:
    """Each global frame index's offset from the start of its episode."""
    ends = np.asarray(episode_ends, dtype=np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    return frames - starts[np.searchsorted(ends, frames, side="right")]


def window_starts(episode_ends: np.ndarray, horizon: int = DEFAULT_HORIZON) -> np.ndarray:
    """Every frame t whose window t..t+horizon-1 lies inside its episode (episodes shorter than horizon give none)."""
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    ends = np.asarray(episode_ends, dtype=np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    per_episode = [np.arange(s, e - horizon + 1, dtype=np.int64) for s, e in zip(starts, ends)]
    return np.concatenate(per_episode) if per_episode else np.zeros(0, dtype=np.int64)


def _read_array(root: Any, path: Path, name: str) -> np.ndarray:
    try:
        array = root[name]
    except KeyError:
        raise DatasetError(f"{path}: missing array {name}") from None
    if not isinstance(array, zarr.Array):
        raise DatasetError(f"{path}: {name} is a group, expected an array")
    try:
        return np.asarray(array[...])
    except Exception as exc:  # a corrupt chunk surfaces as a codec or OS error
        raise DatasetError(f"{path}: cannot read {name}: {exc}") from None

"""The Push-T demonstrations: a validated replay buffer, 12-action windows inside episodes, and z-score normalization.

    replay = load_replay()                      # data/pusht_lowdim.zarr
    states, chunks = make_windows(replay)       # [23384, 5], [23384, 12, 2] on the real data
    norm = Normalizer.fit(replay.states, replay.actions)
    data = training_set("data/pusht_lowdim.zarr", action_frame="agent")  # what a training loop needs, in one call

Window t pairs the state at frame t with the actions of frames t..t+11 of the same episode.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import zarr

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATASET = REPO_ROOT / "data" / "pusht_lowdim.zarr"
STATE_DIM = 5
ACTION_DIM = 2
HORIZON = 12
# Same rule as training.policies.guard_std, so training and acting normalize alike.
MIN_STD = 1e-6
NORMALIZER_KEYS = ("state_mean", "state_std", "action_mean", "action_std")


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


def make_windows(replay: Replay, horizon: int = HORIZON, pad_end: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """States [W, 5] and action chunks [W, horizon, 2]: the state at t and actions t..t+horizon-1 of one episode.

    With `pad_end`, every frame starts a window, and chunks that would run past their episode's end
    repeat its last action (as Diffusion Policy's sampler pads), so the final frames are learned too.
    """
    starts = window_frames(replay, horizon, pad_end)
    if pad_end:
        last = np.repeat(replay.episode_ends - 1, np.diff(np.concatenate([[0], replay.episode_ends])))
        chunk_index = np.minimum(starts[:, None] + np.arange(horizon)[None, :], last[:, None])
    else:
        chunk_index = starts[:, None] + np.arange(horizon)[None, :]
    return replay.states[starts].copy(), replay.actions[chunk_index]


def window_frames(replay: Replay, horizon: int = HORIZON, pad_end: bool = False) -> np.ndarray:
    """The frame each of `make_windows`' windows starts at (every frame with `pad_end`)."""
    return np.arange(len(replay.states), dtype=np.int64) if pad_end else window_starts(replay.episode_ends, horizon)


def human_labels(path: str | Path, frames: int) -> np.ndarray | None:
    """A store's data/human as bools (True: a human gave that frame's action, as /viewer records), or None without it."""
    root = zarr.open_group(str(path), mode="r")
    if "data/human" not in root:
        return None
    labels = _read_array(root, Path(path), "data/human").reshape(-1)
    if len(labels) != frames:
        raise DatasetError(f"{path}: data/human has {len(labels)} frames but data/state has {frames}")
    return labels.astype(bool)


def training_windows(replay: Replay, horizon: int, action_frame: str, pad_end: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """States [W, 5] and the chunks [W, H, 2] a policy learns: env units, relative to the agent for action_frame="agent"."""
    states, chunks = make_windows(replay, horizon=horizon, pad_end=pad_end)
    if action_frame == "agent":
        chunks = chunks - states[:, None, :2]
    return states, chunks


@dataclass(frozen=True)
class TrainingSet:
    """Normalized training windows, resident as float32 tensors (a few MB, so no DataLoader), and their normalizer."""

    states: torch.Tensor  # [W, 5]
    chunks: torch.Tensor  # [W, H, 2]
    normalizer: Normalizer
    demo_windows: int  # the first demo_windows rows come from the demonstrations, the rest from extra data
    weights: torch.Tensor | None = None  # sampling weight per window; None: all equal (plain permutations)

    def __len__(self) -> int:
        return len(self.states)

    def epoch_order(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """`count` window indices for an epoch: a permutation, or with weights a draw with replacement in proportion to them."""
        if self.weights is None:
            return torch.randperm(len(self.states), generator=generator)[:count]
        return torch.multinomial(self.weights, count, replacement=True, generator=generator)


def training_set(data: str | Path, horizon: int = HORIZON, action_frame: str = "absolute", pad_end: bool = False,
                 extra_data: tuple[str | Path, ...] = (), normalizer: Normalizer | None = None,
                 human_weight: float = 1.0, policy_step_weight: float = 1.0, extra_stride: int = 1) -> TrainingSet:
    """The demonstrations' windows plus those of `extra_data`, normalized by `normalizer` or by statistics of the demonstrations alone.

    Extra windows whose first action a human gave (data/human) weigh `human_weight`, the others of such stores `policy_step_weight`.
    With `extra_stride` k, extra windows start only every k-th frame of an episode (a policy's decision points when k is its chunk length)."""
    if extra_stride < 1:
        raise ValueError(f"extra_stride must be >= 1, got {extra_stride}")
    replay = load_replay(data)
    states, chunks = training_windows(replay, horizon, action_frame, pad_end)
    if normalizer is None:
        # agent-frame chunks have their own statistics; absolute ones share the per-frame actions'
        normalizer = Normalizer.fit(replay.states, chunks if action_frame == "agent" else replay.actions)
    demo_windows = len(states)
    weights = [np.ones(demo_windows)]
    for extra in extra_data:
        extra_replay = load_replay(extra)
        extra_states, extra_chunks = training_windows(extra_replay, horizon, action_frame, pad_end)
        frames = window_frames(extra_replay, horizon, pad_end)
        keep = _frame_in_episode(frames, extra_replay.episode_ends) % extra_stride == 0
        extra_states, extra_chunks, frames = extra_states[keep], extra_chunks[keep], frames[keep]
        states, chunks = np.concatenate([states, extra_states]), np.concatenate([chunks, extra_chunks])
        labels = human_labels(extra, len(extra_replay.states))
        starts_human = labels[frames] if labels is not None else None
        weights.append(np.ones(len(extra_states)) if starts_human is None else np.where(starts_human, human_weight, policy_step_weight))
    weights = np.concatenate(weights)
    return TrainingSet(
        states=torch.as_tensor(np.asarray(normalizer.normalize_state(states), dtype=np.float32)),
        chunks=torch.as_tensor(np.asarray(normalizer.normalize_action(chunks), dtype=np.float32)),
        normalizer=normalizer,
        demo_windows=demo_windows,
        # all ones samples exactly as before the weights existed (plain permutations, same draws)
        weights=None if np.all(weights == 1.0) else torch.as_tensor(weights, dtype=torch.float64),
    )


def _frame_in_episode(frames: np.ndarray, episode_ends: np.ndarray) -> np.ndarray:
    """Each global frame index's offset from the start of its episode."""
    ends = np.asarray(episode_ends, dtype=np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    return frames - starts[np.searchsorted(ends, frames, side="right")]


def window_starts(episode_ends: np.ndarray, horizon: int = HORIZON) -> np.ndarray:
    """Every frame t whose window t..t+horizon-1 lies inside its episode (episodes shorter than horizon give none)."""
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    ends = np.asarray(episode_ends, dtype=np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    per_episode = [np.arange(s, e - horizon + 1, dtype=np.int64) for s, e in zip(starts, ends)]
    return np.concatenate(per_episode) if per_episode else np.zeros(0, dtype=np.int64)


@dataclass
class Normalizer:
    """Per-dimension z-score statistics of states and actions (std of constant dimensions taken as 1)."""

    state_mean: np.ndarray
    state_std: np.ndarray
    action_mean: np.ndarray
    action_std: np.ndarray

    def __post_init__(self) -> None:
        for key in NORMALIZER_KEYS:
            value = np.asarray(getattr(self, key), dtype=np.float32).reshape(-1)
            if not np.isfinite(value).all():
                raise ValueError(f"normalizer {key} must be finite, got {value.tolist()}")
            if key.endswith("_std"):
                if np.any(value < 0):
                    raise ValueError(f"normalizer {key} must be >= 0, got {value.tolist()}")
                value = np.where(value < MIN_STD, np.float32(1.0), value).astype(np.float32)
            setattr(self, key, value)
        if self.state_mean.shape != self.state_std.shape or self.action_mean.shape != self.action_std.shape:
            raise ValueError("normalizer means and stds must have matching lengths")

    @classmethod
    def fit(cls, states: np.ndarray, actions: np.ndarray) -> "Normalizer":
        """Mean and population std per dimension over all given frames (states [..., 5], actions [..., 2])."""
        states = np.asarray(states, dtype=np.float64)
        actions = np.asarray(actions, dtype=np.float64)
        states = states.reshape(-1, states.shape[-1])
        actions = actions.reshape(-1, actions.shape[-1])
        if len(states) == 0 or len(actions) == 0:
            raise ValueError("cannot fit a normalizer on no samples")
        return cls(states.mean(0), states.std(0), actions.mean(0), actions.std(0))

    def normalize_state(self, states: Any) -> Any:
        """(states - state_mean) / state_std for numpy arrays or torch tensors."""
        return (states - _like(self.state_mean, states)) / _like(self.state_std, states)

    def normalize_action(self, actions: Any) -> Any:
        """(actions - action_mean) / action_std, broadcast over leading dims."""
        return (actions - _like(self.action_mean, actions)) / _like(self.action_std, actions)

    def denormalize_action(self, actions_n: Any) -> Any:
        """actions_n * action_std + action_mean (no clipping)."""
        return actions_n * _like(self.action_std, actions_n) + _like(self.action_mean, actions_n)

    def to_dict(self) -> dict[str, list[float]]:
        """JSON-ready lists; the checkpoint card's `normalization`."""
        return {key: [float(v) for v in getattr(self, key)] for key in NORMALIZER_KEYS}

    @classmethod
    def from_dict(cls, data: Any) -> "Normalizer":
        """Inverse of to_dict; ValueError naming the bad key."""
        if not isinstance(data, dict):
            raise ValueError(f"normalizer must be an object with {list(NORMALIZER_KEYS)}, got {type(data).__name__}")
        values = {}
        for key in NORMALIZER_KEYS:
            value = data.get(key)
            if not isinstance(value, list) or not value or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value
            ):
                raise ValueError(f"normalizer {key} must be a non-empty list of finite numbers, got {value!r}")
            values[key] = np.asarray(value, dtype=np.float32)
        return cls(**values)

    def save(self, path: str | Path) -> None:
        """Write the statistics as JSON."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=2) + "\n", encoding="utf-8")

    @classmethod
    def load(cls, path: str | Path) -> "Normalizer":
        """Read statistics written by save(); ValueError naming the file on any problem."""
        path = Path(path)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ValueError(f"{path}: normalizer file not found") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: not a valid normalizer JSON file: {exc}") from None
        try:
            return cls.from_dict(data)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None


def add_state_noise(states_n: Any, std: float, generator: torch.Generator | np.random.Generator | None = None) -> Any:
    """Normalized states plus N(0, std²) noise (a torch tensor with a torch generator, or a numpy array with a numpy one)."""
    if std < 0:
        raise ValueError(f"noise std must be >= 0, got {std}")
    if std == 0:
        return states_n
    if isinstance(states_n, torch.Tensor):
        noise = torch.randn(states_n.shape, generator=generator, device=states_n.device, dtype=states_n.dtype)
        return states_n + std * noise
    rng = generator if isinstance(generator, np.random.Generator) else np.random.default_rng()
    return states_n + np.asarray(std * rng.standard_normal(np.shape(states_n)), dtype=np.asarray(states_n).dtype)


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


def _like(stats: np.ndarray, x: Any) -> Any:
    """`stats` as the same kind of array as `x` (torch tensor on its device and dtype, or numpy)."""
    if isinstance(x, torch.Tensor):
        return torch.as_tensor(stats, dtype=x.dtype, device=x.device)
    return stats

"""A policy's one conversion between env units and its model's units: z-scores and the action frame.

Every policy owns a `Normalizer` (`policy.normalizer`); its loss and its acting both go through it, so
training and acting cannot convert differently. The statistics are buffers of the policy that its
state_dict leaves out: the checkpoint's card carries them (`normalization`) and loading puts them back.

This module imports only torch, numpy and the torch-free `policies.card` and `pusht.spec`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from policies.card import NORMALIZATION_KEYS, check_normalization
from pusht.spec import ACTION_DIM, MIN_STD, STATE_DIM

ACTION_FRAMES = ("absolute", "agent")
""""agent": the model's chunks are relative to the agent's position (the state's first ACTION_DIM values)"""


class Normalizer(nn.Module):
    """Per-dimension state and action statistics and the action frame: env units in, model units out, and back.

    The statistics start as NaN, so a policy that was never fitted or loaded fails loudly instead of
    training or acting on garbage; a std below MIN_STD (a constant dimension) is taken as 1.
    """

    def __init__(self, state_dim: int = STATE_DIM, action_dim: int = ACTION_DIM, action_frame: str = "absolute") -> None:
        super().__init__()
        if action_frame not in ACTION_FRAMES:
            raise ValueError(f"action_frame must be one of {ACTION_FRAMES}, got {action_frame!r}")
        self.state_dim, self.action_dim, self.action_frame = state_dim, action_dim, action_frame
        for key in NORMALIZATION_KEYS:
            dim = state_dim if key.startswith("state") else action_dim
            self.register_buffer(key, torch.full((dim,), float("nan")), persistent=False)

    state_mean: torch.Tensor
    state_std: torch.Tensor
    action_mean: torch.Tensor
    action_std: torch.Tensor

    @property
    def is_set(self) -> bool:
        """Whether statistics were fitted or loaded."""
        return bool(all(torch.isfinite(getattr(self, key)).all() for key in NORMALIZATION_KEYS))

    def require(self) -> None:
        """ValueError unless the statistics are set."""
        if not self.is_set:
            raise ValueError(
                "the policy has no normalization yet: fit it (policy.normalizer.fit_demonstrations), set it (policy.normalizer.set) or load a checkpoint"
            )

    def set(self, statistics: Any) -> "Normalizer":
        """Take the statistics of a card's `normalization` dict (lists, arrays or tensors) or of another Normalizer; returns self."""
        if isinstance(statistics, Normalizer):
            statistics = statistics.to_dict()
        if not isinstance(statistics, dict):
            raise ValueError(f"normalization must be a dict with {list(NORMALIZATION_KEYS)}, got {type(statistics).__name__}")
        lists = {key: _float_list(statistics.get(key)) for key in NORMALIZATION_KEYS}
        check_normalization(lists, {"state_dim": self.state_dim, "action_dim": self.action_dim})
        for key in NORMALIZATION_KEYS:
            value = torch.tensor(lists[key], dtype=torch.float32)
            if key.endswith("_std"):
                value = torch.where(value < MIN_STD, torch.ones_like(value), value)
            getattr(self, key).copy_(value)
        return self

    def to_dict(self) -> dict[str, list[float]]:
        """The statistics as JSON-ready lists: the card's `normalization`."""
        self.require()
        return {key: getattr(self, key).tolist() for key in NORMALIZATION_KEYS}

    @classmethod
    def fit(cls, states: Any, actions: Any, action_frame: str = "absolute") -> "Normalizer":
        """A normalizer of the mean and population std per dimension of states [..., S] and actions [..., A] (already in `action_frame`)."""
        states, actions = np.asarray(states, dtype=np.float64), np.asarray(actions, dtype=np.float64)
        states, actions = states.reshape(-1, states.shape[-1]), actions.reshape(-1, actions.shape[-1])
        if len(states) == 0 or len(actions) == 0:
            raise ValueError("cannot fit a normalizer on no samples")
        return cls(states.shape[1], actions.shape[1], action_frame).set(
            {
                "state_mean": states.mean(0),
                "state_std": states.std(0),
                "action_mean": actions.mean(0),
                "action_std": actions.std(0),
            }
        )

    def fit_demonstrations(self, frame_states: Any, frame_actions: Any, window_states: Any, window_chunks: Any) -> "Normalizer":
        """Set the statistics of demonstrations: states over every frame; actions over every frame, or for the
        agent frame over the windows' env-unit chunks as the model sees them (relative to the agent); returns self."""
        actions = frame_actions if self.action_frame == "absolute" else self.in_frame(window_states, window_chunks)
        return self.set(Normalizer.fit(frame_states, actions, self.action_frame))

    def in_frame(self, states: Any, chunks: Any) -> Any:
        """Env-unit chunks [..., H, A] in the action frame (numpy arrays or tensors): relative to the agent in `states` [..., S] for "agent"."""
        if self.action_frame == "agent":
            return chunks - states[..., None, : self.action_dim]
        return chunks

    def state(self, state: torch.Tensor) -> torch.Tensor:
        """The model's view of env-unit states [B, S]: z-scored."""
        return (state - self.state_mean) / self.state_std

    def env_state(self, state_n: torch.Tensor) -> torch.Tensor:
        """Env-unit states [B, S] of z-scored ones: inverse of `state`."""
        return state_n * self.state_std + self.state_mean

    def chunk(self, state: torch.Tensor, chunk: torch.Tensor) -> torch.Tensor:
        """The model's view of env-unit chunks [B, H, A] taken in states [B, S]: in the frame, z-scored."""
        return (self.in_frame(state, chunk) - self.action_mean) / self.action_std

    def actions(self, state: torch.Tensor, chunk_n: torch.Tensor) -> torch.Tensor:
        """Env-unit actions (unclipped) of the model's chunks [B, H, A] in states [B, S]: inverse of `chunk`."""
        actions = chunk_n * self.action_std + self.action_mean
        if self.action_frame == "agent":
            actions = actions + state[:, None, : self.action_dim]
        return actions


def _float_list(value: Any) -> Any:
    """Plain floats from a tensor, array or sequence (anything else passes through for check_normalization to name)."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().double().reshape(-1).tolist()
    if isinstance(value, np.ndarray):
        return value.astype(np.float64).reshape(-1).tolist()
    if isinstance(value, (list, tuple)):
        return [float(v) if isinstance(v, (int, float, np.floating)) and not isinstance(v, bool) else v for v in value]
    return value

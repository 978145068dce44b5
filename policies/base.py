"""What every Push-T policy is: the `Policy` interface, the chunk policy both kinds build on, and `ActingPolicy`.

A policy owns its `Normalizer` (`policy.normalizer`, policies.normalization): `compute_loss` takes
env-unit states and demonstrated chunks, and `act` takes env-unit states and returns clipped env-unit
actions, both converting through it; only the networks in between (`forward`, `sample_actions`) work
in the model's units (z-scores, chunks in the action frame). `ActingPolicy` is `act` as a module: what
ONNX exports and the torch backend runs.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch
from torch import nn

from policies.configuration import architecture_dict
from policies.features import KEYPOINT_FEATURES, MOTION_FEATURES, motion_features, tee_keypoints
from policies.networks import StateSkipMLP, mlp
from policies.normalization import Normalizer
from policies.pace import Pace
from pusht.spec import ACTION_HIGH, ACTION_LOW, DEFAULT_NUM_STEPS


@runtime_checkable
class Policy(Protocol):
    """What every policy offers."""

    kind: str
    normalizer: Normalizer

    @property
    def architecture(self) -> dict[str, Any]:
        """The constructor kwargs; `build_policy(kind, **architecture)` rebuilds the same model."""
        ...

    def compute_loss(self, state: torch.Tensor, action_chunk: torch.Tensor, state_noise: float = 0.0) -> torch.Tensor:
        """Scalar training loss of env-unit states [B, S] and demonstrated env-unit chunks [B, H, A]."""
        ...

    def act(self, state: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int = DEFAULT_NUM_STEPS) -> torch.Tensor:
        """Clipped env-unit action chunks [B, H, A] for env-unit states [B, S]."""
        ...


class ChunkPolicy(nn.Module):
    """Shared by both policies: the normalizer, the optional sin/cos angle encoding, the MLP, loss and acting in env units."""

    kind: str

    def _init_common(self, arch: dict[str, Any]) -> int:
        """Record the validated architecture and build the normalizer; returns the encoded state width."""
        self._arch = arch
        self.horizon, self.action_dim, self.state_dim = arch["horizon"], arch["action_dim"], arch["state_dim"]
        self.action_frame = arch["action_frame"]
        self.normalizer = Normalizer(self.state_dim, self.action_dim, self.action_frame)
        self.angle_encoding = arch["angle_encoding"]
        self.prev_state = arch["prev_state"]
        self.pace_input = arch["pace_input"]
        # where a pace input acts: the card's rule (policies.pace), else the demonstrators' own pace
        self.acting_pace = Pace(*arch["acting_pace"]) if arch["acting_pace"] is not None else Pace()
        extra = (MOTION_FEATURES if self.prev_state else 0) + (1 if self.pace_input else 0)
        return self.state_dim + extra + {"raw": 0, "sincos": 1, "keypoints": 1 + KEYPOINT_FEATURES}[self.angle_encoding]

    @property
    def architecture(self) -> dict[str, Any]:
        """The constructor kwargs (JSON-ready)."""
        return architecture_dict(self._arch)

    def _init_net(self, in_dim: int, cond_dim: int, out_dim: int) -> None:
        """The MLP as `self.net`: plain, or with the encoded state fed again into every layer (`state_skip`)."""
        self.state_skip = self._arch["state_skip"]
        hidden, dropout = self._arch["hidden_dims"], self._arch["dropout"]
        self.net = (
            StateSkipMLP(in_dim, cond_dim, hidden, out_dim, dropout) if self.state_skip else mlp(in_dim, hidden, out_dim, dropout)
        )

    def _run_net(self, inputs: torch.Tensor, encoded: torch.Tensor) -> torch.Tensor:
        return self.net(inputs, encoded) if self.state_skip else self.net(inputs)

    def policy_state(
        self, state: torch.Tensor, prev_state: torch.Tensor | None = None, pace: torch.Tensor | None = None
    ) -> torch.Tensor:
        """What the network is given of env-unit states [B, S]: the normalized state; with `prev_state` in the architecture
        the motion since the previous step's states (`prev_state`; None: the episode's first step, no motion); with
        `pace_input` the chunk's pace (`pace` [B]; None: the card's `acting_pace` rule of the state)."""
        parts = [self.normalizer.state(state)]
        if self.prev_state:
            parts.append(motion_features(state, state if prev_state is None else prev_state))
        if self.pace_input:
            pace = self.acting_pace.speeds_t(state) if pace is None else pace
            parts.append(pace.reshape(-1, 1).to(state.dtype) - 1.0)
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)

    def encode_state(self, state_n: torch.Tensor) -> torch.Tensor:
        """The network's view of `policy_state` rows: unchanged ("raw"), or the angle as sin, cos of the raw angle
        ("sincos"), and with "keypoints" the tee's corners in the arena too; the motion features follow unchanged."""
        if self.angle_encoding == "raw":
            return state_n
        base, motion = state_n[:, : self.state_dim], state_n[:, self.state_dim :]
        raw = self.normalizer.env_state(base)
        angle = raw[:, -1:]
        parts = [base[:, :-1], torch.sin(angle), torch.cos(angle)]
        if self.angle_encoding == "keypoints":
            parts.append(tee_keypoints(raw[:, 2:5]))
        parts.append(motion)
        return torch.cat(parts, dim=1)

    def compute_loss(
        self,
        state: torch.Tensor,
        action_chunk: torch.Tensor,
        state_noise: float = 0.0,
        generator: torch.Generator | None = None,
        prev_state: torch.Tensor | None = None,
        pace: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The loss of env-unit states [B, S] (and the states a step before, the chunks' paces: `policy_state`) and chunks
        [B, H, A]; `state_noise`: std of Gaussian noise on the network's normalized inputs."""
        self.normalizer.require()
        state_n = self.policy_state(state, prev_state, pace)
        chunk_n = self.normalizer.chunk(state, action_chunk)  # the frame follows the clean state
        if state_noise > 0:
            state_n = state_n + state_noise * torch.randn(
                state_n.shape, generator=generator, device=state_n.device, dtype=state_n.dtype
            )
        return self.normalized_loss(state_n, chunk_n, generator=generator)

    def act(
        self,
        state: torch.Tensor,
        noise: torch.Tensor | None = None,
        num_steps: int = DEFAULT_NUM_STEPS,
        prev_state: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Env-unit actions [B, H, A], clipped to the arena, for env-unit states [B, S] (and the states a step before, where the
        architecture takes them); MSE ignores `noise` and `num_steps`."""
        chunk_n = self.sample_actions(self.policy_state(state, prev_state), noise=noise, num_steps=num_steps)
        return self.arena_actions(state, chunk_n)

    def arena_actions(self, state: torch.Tensor, chunk_n: torch.Tensor) -> torch.Tensor:
        """Env-unit actions [B, H, A], clipped to the arena, of normalized chunks [B, H, A] from env-unit states [B, S]."""
        return torch.clamp(self.normalizer.actions(state, chunk_n), ACTION_LOW, ACTION_HIGH)


class ActingPolicy(nn.Module):
    """`policy.act` as a module (what ONNX exports and the torch backend runs): env-unit states [B, S] (and flow noise) in, clipped actions out."""

    def __init__(self, policy: ChunkPolicy, num_steps: int = DEFAULT_NUM_STEPS) -> None:
        super().__init__()
        policy.normalizer.require()
        self.policy = policy
        self.kind = policy.kind
        self.num_steps = num_steps

    def forward(
        self,
        state: torch.Tensor,
        noise: torch.Tensor | None = None,
        num_steps: int | None = None,
        prev_state: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Actions [B, H, A] in env units, clipped to [0, 512]. MSE ignores `noise`; flow draws it if None."""
        return self.policy.act(state, noise, self.num_steps if num_steps is None else num_steps, prev_state)

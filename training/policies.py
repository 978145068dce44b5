"""Behavioral-cloning policies for Push-T: one interface, two models (MSE regression and flow matching).

A policy owns its `Normalizer` (`policy.normalizer`, training.normalization): `compute_loss` takes
env-unit states and demonstrated chunks, and `act` takes env-unit states and returns clipped env-unit
actions, both converting through it; only the networks in between (`forward`, `sample_actions`) work
in the model's units (z-scores, chunks in the action frame). `ActingPolicy` is `act` as a module: what
ONNX exports and the torch backend runs.

This module imports only torch, numpy and the torch-free `acting.card` and `pusht.spec`: the service
imports it without the training code.
"""

from __future__ import annotations

import math
from typing import Any, Protocol, Sequence, runtime_checkable

import torch
from torch import nn
from torch.nn import functional as F

from pusht.spec import ACTION_DIM, ACTION_HIGH, ACTION_LOW, DEFAULT_HORIZON, DEFAULT_NUM_STEPS, POLICY_KINDS, STATE_DIM
from training.features import KEYPOINT_FEATURES, MOTION_FEATURES, motion_features, tee_keypoints
from training.architecture import (
    DEFAULT_DROPOUT, DEFAULT_TIME_EMBEDDING_DIM, FLOW_ARCH_KEYS, FLOW_HIDDEN_DIMS, MSE_ARCH_KEYS, MSE_HIDDEN_DIMS,
    architecture_dict, check_architecture,
)
from training.networks import StateSkipMLP, mlp
from training.normalization import Normalizer
from training.pace import Pace

# Angular frequencies (rad per unit t) of the sinusoidal time embedding: slow enough to stay monotonic
# over t in [0, 1], fast enough to separate nearby Euler steps.
TIME_FREQ_MIN, TIME_FREQ_MAX = 1.0, 1000.0


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


def build_policy(kind: str, **architecture: Any) -> "MSEPolicy | FlowPolicy":
    """A fresh policy of `kind` ("mse" or "flow") built from its architecture kwargs (its normalizer not yet set)."""
    classes = {"mse": MSEPolicy, "flow": FlowPolicy}
    if kind not in classes:
        raise ValueError(f"unknown policy kind {kind!r}; expected one of {POLICY_KINDS}")
    allowed = set(MSE_ARCH_KEYS if kind == "mse" else FLOW_ARCH_KEYS)
    unknown = sorted(set(architecture) - allowed)
    if unknown:
        raise ValueError(f"unknown {kind} architecture keys {unknown}; expected a subset of {sorted(allowed)}")
    return classes[kind](**architecture)


class _ChunkPolicy(nn.Module):
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
        # where a pace input acts: the card's rule (training.pace), else the demonstrators' own pace
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
        self.net = StateSkipMLP(in_dim, cond_dim, hidden, out_dim, dropout) if self.state_skip else mlp(in_dim, hidden, out_dim, dropout)

    def _run_net(self, inputs: torch.Tensor, encoded: torch.Tensor) -> torch.Tensor:
        return self.net(inputs, encoded) if self.state_skip else self.net(inputs)

    def policy_state(self, state: torch.Tensor, prev_state: torch.Tensor | None = None, pace: torch.Tensor | None = None) -> torch.Tensor:
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

    def compute_loss(self, state: torch.Tensor, action_chunk: torch.Tensor, state_noise: float = 0.0,
                     generator: torch.Generator | None = None, prev_state: torch.Tensor | None = None,
                     pace: torch.Tensor | None = None) -> torch.Tensor:
        """The loss of env-unit states [B, S] (and the states a step before, the chunks' paces: `policy_state`) and chunks
        [B, H, A]; `state_noise`: std of Gaussian noise on the network's normalized inputs."""
        self.normalizer.require()
        state_n = self.policy_state(state, prev_state, pace)
        chunk_n = self.normalizer.chunk(state, action_chunk)  # the frame follows the clean state
        if state_noise > 0:
            state_n = state_n + state_noise * torch.randn(state_n.shape, generator=generator, device=state_n.device, dtype=state_n.dtype)
        return self.normalized_loss(state_n, chunk_n, generator=generator)

    def act(self, state: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int = DEFAULT_NUM_STEPS,
            prev_state: torch.Tensor | None = None) -> torch.Tensor:
        """Env-unit actions [B, H, A], clipped to the arena, for env-unit states [B, S] (and the states a step before, where the
        architecture takes them); MSE ignores `noise` and `num_steps`."""
        chunk_n = self.sample_actions(self.policy_state(state, prev_state), noise=noise, num_steps=num_steps)
        return torch.clamp(self.normalizer.actions(state, chunk_n), ACTION_LOW, ACTION_HIGH)


class MSEPolicy(_ChunkPolicy):
    """An MLP from state to a whole action chunk, trained by mean squared error on normalized actions."""

    kind = "mse"

    def __init__(
        self,
        hidden_dims: Sequence[int] = MSE_HIDDEN_DIMS,
        dropout: float = DEFAULT_DROPOUT,
        horizon: int = DEFAULT_HORIZON,
        action_dim: int = ACTION_DIM,
        state_dim: int = STATE_DIM,
        angle_encoding: str = "raw",
        state_skip: bool = False,
        action_frame: str = "absolute",
        prev_state: bool = False,
        pace_input: bool = False,
        acting_pace: Sequence[float] | None = None,
    ) -> None:
        super().__init__()
        encoded_dim = self._init_common(check_architecture(
            hidden_dims, dropout, horizon, action_dim, state_dim, angle_encoding=angle_encoding, state_skip=state_skip,
            action_frame=action_frame, prev_state=prev_state, pace_input=pace_input, acting_pace=acting_pace))
        self._init_net(encoded_dim, encoded_dim, horizon * action_dim)

    def forward(self, state_n: torch.Tensor) -> torch.Tensor:
        """The predicted normalized chunk [B, H, A] of normalized states [B, S]."""
        encoded = self.encode_state(state_n)
        return self._run_net(encoded, encoded).reshape(-1, self.horizon, self.action_dim)

    def normalized_loss(self, state_n: torch.Tensor, chunk_n: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Mean squared error between the predicted and the demonstrated normalized chunk."""
        return F.mse_loss(self(state_n), chunk_n)

    def sample_actions(self, state_n: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int = DEFAULT_NUM_STEPS) -> torch.Tensor:
        """The deterministic normalized chunk [B, H, A]; `noise` and `num_steps` are accepted for the common interface and ignored."""
        return self(state_n)


class FlowPolicy(_ChunkPolicy):
    """Straight-line conditional flow matching: an MLP of (state, noisy chunk, t) predicts the velocity x1 - x0."""

    kind = "flow"

    def __init__(
        self,
        hidden_dims: Sequence[int] = FLOW_HIDDEN_DIMS,
        dropout: float = DEFAULT_DROPOUT,
        horizon: int = DEFAULT_HORIZON,
        action_dim: int = ACTION_DIM,
        state_dim: int = STATE_DIM,
        angle_encoding: str = "raw",
        state_skip: bool = False,
        time_embedding: str = "scalar",
        time_embedding_dim: int = DEFAULT_TIME_EMBEDDING_DIM,
        action_frame: str = "absolute",
        noise_scale: float = 1.0,
        outcome_dims: Sequence[int] | None = None,
        outcome_candidates: int = 16,
        outcome_stretches: Sequence[float] = (1.0,),
        prev_state: bool = False,
        pace_input: bool = False,
        acting_pace: Sequence[float] | None = None,
    ) -> None:
        super().__init__()
        encoded_dim = self._init_common(check_architecture(
            hidden_dims, dropout, horizon, action_dim, state_dim, angle_encoding=angle_encoding, state_skip=state_skip,
            time_embedding=time_embedding, time_embedding_dim=time_embedding_dim, action_frame=action_frame,
            noise_scale=noise_scale, outcome_dims=outcome_dims, outcome_candidates=outcome_candidates,
            outcome_stretches=list(outcome_stretches), prev_state=prev_state,
            pace_input=pace_input, acting_pace=acting_pace))
        # Sampling only (training draws x0 ~ N(0, I)): starting closer to the mean trades diversity
        # for precision, chosen by rollouts on non-held-out seeds (models/README.md).
        self.noise_scale = self._arch["noise_scale"]
        self.time_embedding = time_embedding
        if time_embedding == "sinusoidal":
            freqs = torch.exp(torch.linspace(math.log(TIME_FREQ_MIN), math.log(TIME_FREQ_MAX), time_embedding_dim // 2))
            # not persistent: it follows from the architecture, so checkpoints need not carry it
            self.register_buffer("time_freqs", freqs, persistent=False)
            time_dim = time_embedding_dim
        else:
            time_dim = 1
        chunk_dim = horizon * action_dim
        self._init_net(encoded_dim + chunk_dim + time_dim, encoded_dim, chunk_dim)
        # A learned one-chunk model of the block choosing among K integrated chunks (training.finetune --algo outcome).
        self.outcome = None
        if self._arch["outcome_dims"] is not None:
            from training.outcome import OutcomeSelector

            self.outcome = OutcomeSelector((horizon, action_dim), self._arch["outcome_dims"], self._arch["outcome_candidates"],
                                           self._arch["outcome_stretches"])

    def forward(self, state_n: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Velocity [B, H, A] at noisy normalized chunks x_t [B, H, A] and times t [B] or [B, 1], given normalized states [B, S]."""
        batch = state_n.shape[0]
        encoded = self.encode_state(state_n)
        t = t.reshape(batch, 1).to(state_n.dtype)
        if self.time_embedding == "sinusoidal":
            angles = t * self.time_freqs
            t = torch.cat([torch.sin(angles), torch.cos(angles)], dim=1)
        inputs = torch.cat([encoded, x_t.reshape(batch, -1), t], dim=1)
        return self._run_net(inputs, encoded).reshape(batch, self.horizon, self.action_dim)

    def normalized_loss(self, state_n: torch.Tensor, chunk_n: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Flow-matching loss: x_t = (1 - t) x0 + t x1 with x0 ~ N(0, I), t ~ U[0, 1]; target x1 - x0."""
        x1 = chunk_n
        x0 = torch.randn(x1.shape, generator=generator, device=x1.device, dtype=x1.dtype)
        t = torch.rand((x1.shape[0], 1, 1), generator=generator, device=x1.device, dtype=x1.dtype)
        x_t = (1 - t) * x0 + t * x1
        return F.mse_loss(self(state_n, x_t, t), x1 - x0)

    def sample_actions(
        self,
        state_n: torch.Tensor,
        noise: torch.Tensor | None = None,
        num_steps: int = DEFAULT_NUM_STEPS,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Normalized chunks integrated from x0 = noise_scale * `noise` [B, H, A] (standard normal if None) in `num_steps` Euler steps."""
        if num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {num_steps}")
        shape = (state_n.shape[0], self.horizon, self.action_dim)
        if noise is None:
            noise = torch.randn(shape, generator=generator, device=state_n.device, dtype=state_n.dtype)
        elif tuple(noise.shape) != shape and not torch.jit.is_tracing() and not torch.compiler.is_compiling():
            raise ValueError(f"noise must have shape {list(shape)}, got {list(noise.shape)}")
        if self.outcome is not None:
            return self.outcome.best_chunk(self, state_n, noise, num_steps)
        return self.integrate(state_n, self.start_noise(state_n, noise), num_steps)

    def start_noise(self, state_n: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """The Euler start x0 [B, H, A] of standard-normal `noise`: scaled by noise_scale."""
        return noise if self.noise_scale == 1.0 else noise * self.noise_scale

    def integrate(self, state_n: torch.Tensor, x0: torch.Tensor, num_steps: int = DEFAULT_NUM_STEPS) -> torch.Tensor:
        """Normalized chunks [B, H, A]: the velocity integrated from x0 with `num_steps` Euler steps."""
        x = x0
        dt = 1.0 / num_steps
        # Python loop: tracing for ONNX unrolls it into num_steps copies of the network.
        for i in range(num_steps):
            t = torch.full_like(state_n[:, :1], i * dt)
            x = x + dt * self(state_n, x, t)
        return x

    def act_from_start(self, state: torch.Tensor, x0: torch.Tensor, num_steps: int = DEFAULT_NUM_STEPS,
                       prev_state: torch.Tensor | None = None) -> torch.Tensor:
        """Clipped env-unit actions [B, H, A] integrated from a given Euler start x0 (fine-tuning acts this way)."""
        chunk_n = self.integrate(self.policy_state(state, prev_state), x0, num_steps)
        return torch.clamp(self.normalizer.actions(state, chunk_n), ACTION_LOW, ACTION_HIGH)


class ActingPolicy(nn.Module):
    """`policy.act` as a module (what ONNX exports and the torch backend runs): env-unit states [B, S] (and flow noise) in, clipped actions out."""

    def __init__(self, policy: MSEPolicy | FlowPolicy, num_steps: int = DEFAULT_NUM_STEPS) -> None:
        super().__init__()
        policy.normalizer.require()
        self.policy = policy
        self.kind = policy.kind
        self.num_steps = num_steps

    def forward(self, state: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int | None = None,
                prev_state: torch.Tensor | None = None) -> torch.Tensor:
        """Actions [B, H, A] in env units, clipped to [0, 512]. MSE ignores `noise`; flow draws it if None."""
        return self.policy.act(state, noise, self.num_steps if num_steps is None else num_steps, prev_state)

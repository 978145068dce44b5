"""The flow-matching policy: a conditional velocity field over action chunks, sampled by Euler integration.

With `outcome_dims` in its architecture it is a chooser (policies.chooser): K candidates integrated from one noise,
the one a learned model of the block predicts leaves the tee closest to its goal played.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch.nn import functional as F

from policies.base import ChunkPolicy
from policies.configuration import architecture_with_defaults, check_architecture
from pusht.spec import DEFAULT_NUM_STEPS

# Angular frequencies (rad per unit t) of the sinusoidal time embedding: slow enough to stay monotonic
# over t in [0, 1], fast enough to separate nearby Euler steps.
TIME_FREQ_MIN, TIME_FREQ_MAX = 1.0, 1000.0


class FlowPolicy(ChunkPolicy):
    """Straight-line conditional flow matching: an MLP of (state, noisy chunk, t) predicts the velocity x1 - x0."""

    kind = "flow"

    def __init__(self, **architecture: Any) -> None:
        """`architecture`: keys of `FLOW_DEFAULTS` (policies.configuration), the others at their defaults."""
        super().__init__()
        encoded_dim = self._init_common(check_architecture(**architecture_with_defaults("flow", architecture)))
        arch = self._arch
        horizon, action_dim, time_embedding, time_embedding_dim = (
            arch["horizon"],
            arch["action_dim"],
            arch["time_embedding"],
            arch["time_embedding_dim"],
        )
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
            from policies.chooser import OutcomeSelector

            self.outcome = OutcomeSelector(
                (horizon, action_dim),
                self._arch["outcome_dims"],
                self._arch["outcome_candidates"],
                self._arch["outcome_stretches"],
                self._arch["value_dims"],
            )

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

    def normalized_loss(
        self, state_n: torch.Tensor, chunk_n: torch.Tensor, generator: torch.Generator | None = None
    ) -> torch.Tensor:
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

    def act_from_start(
        self, state: torch.Tensor, x0: torch.Tensor, num_steps: int = DEFAULT_NUM_STEPS, prev_state: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Clipped env-unit actions [B, H, A] integrated from a given Euler start x0 (fine-tuning acts this way)."""
        chunk_n = self.integrate(self.policy_state(state, prev_state), x0, num_steps)
        return self.arena_actions(state, chunk_n)

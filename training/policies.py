"""Behavioral-cloning policies for Push-T: one interface, two models (MSE regression and flow matching).

Policies work in NORMALIZED units (z-scored states and actions). `ActingPolicy` wraps a policy with
its normalization statistics so that env-unit states go in and clipped env-unit actions come out; it
is the module that ONNX exports and that the service's torch backend runs.

This module imports only torch and the standard library: the service imports it without the
training code.
"""

from __future__ import annotations

import math
from typing import Any, Protocol, Sequence, runtime_checkable

import torch
from torch import nn
from torch.nn import functional as F

POLICY_KINDS = ("mse", "flow")
STATE_DIM = 2 + 2 + 1  # agent x, y; block x, y; block angle
ACTION_DIM = 2
HORIZON = 12
MSE_HIDDEN_DIMS = (128, 256, 256, 512)
FLOW_HIDDEN_DIMS = (128, 256, 512, 512, 512)
DEFAULT_DROPOUT = 0.1
DEFAULT_NUM_STEPS = 10
ACTION_LOW = 0.0
ACTION_HIGH = 512.0
# A normalization std below this is treated as 1 (a constant dimension), so nothing divides by ~0.
MIN_STD = 1e-6
ARCH_KEYS = ("hidden_dims", "dropout", "horizon", "action_dim", "state_dim")


@runtime_checkable
class Policy(Protocol):
    """What every policy offers; all tensors are in normalized units."""

    kind: str

    @property
    def architecture(self) -> dict[str, Any]:
        """The constructor kwargs; `build_policy(kind, **architecture)` rebuilds the same model."""
        ...

    def compute_loss(self, state: torch.Tensor, action_chunk: torch.Tensor) -> torch.Tensor:
        """Scalar training loss of states [B, S] and demonstrated chunks [B, H, A]."""
        ...

    def sample_actions(self, state: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int = DEFAULT_NUM_STEPS) -> torch.Tensor:
        """Action chunks [B, H, A] for states [B, S]."""
        ...


def build_policy(kind: str, **architecture: Any) -> "MSEPolicy | FlowPolicy":
    """A fresh policy of `kind` ("mse" or "flow") built from its architecture kwargs."""
    classes = {"mse": MSEPolicy, "flow": FlowPolicy}
    if kind not in classes:
        raise ValueError(f"unknown policy kind {kind!r}; expected one of {POLICY_KINDS}")
    cls = classes[kind]
    allowed = set(ARCH_KEYS)
    unknown = sorted(set(architecture) - allowed)
    if unknown:
        raise ValueError(f"unknown {kind} architecture keys {unknown}; expected a subset of {sorted(allowed)}")
    return cls(**architecture)


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters (buffers excluded)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


class MSEPolicy(nn.Module):
    """An MLP from state to a whole action chunk, trained by mean squared error on normalized actions."""

    kind = "mse"

    def __init__(
        self,
        hidden_dims: Sequence[int] = MSE_HIDDEN_DIMS,
        dropout: float = DEFAULT_DROPOUT,
        horizon: int = HORIZON,
        action_dim: int = ACTION_DIM,
        state_dim: int = STATE_DIM,
    ) -> None:
        super().__init__()
        self._arch = _check_architecture(hidden_dims, dropout, horizon, action_dim, state_dim)
        self.horizon, self.action_dim, self.state_dim = horizon, action_dim, state_dim
        self.net = mlp(state_dim, self._arch["hidden_dims"], horizon * action_dim, dropout)

    @property
    def architecture(self) -> dict[str, Any]:
        """The constructor kwargs (JSON-ready)."""
        return dict(self._arch, hidden_dims=list(self._arch["hidden_dims"]))

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        """The predicted chunk [B, H, A] of normalized states [B, S]."""
        return self.net(state).reshape(-1, self.horizon, self.action_dim)

    def compute_loss(self, state: torch.Tensor, action_chunk: torch.Tensor) -> torch.Tensor:
        """Mean squared error between the predicted and the demonstrated normalized chunk."""
        return F.mse_loss(self(state), action_chunk)

    def sample_actions(self, state: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int = DEFAULT_NUM_STEPS) -> torch.Tensor:
        """The deterministic chunk [B, H, A]; `noise` and `num_steps` are accepted for the common interface and ignored."""
        return self(state)


class FlowPolicy(nn.Module):
    """Straight-line conditional flow matching: an MLP of (state, noisy chunk, t) predicts the velocity x1 - x0."""

    kind = "flow"

    def __init__(
        self,
        hidden_dims: Sequence[int] = FLOW_HIDDEN_DIMS,
        dropout: float = DEFAULT_DROPOUT,
        horizon: int = HORIZON,
        action_dim: int = ACTION_DIM,
        state_dim: int = STATE_DIM,
    ) -> None:
        super().__init__()
        self._arch = _check_architecture(hidden_dims, dropout, horizon, action_dim, state_dim)
        self.horizon, self.action_dim, self.state_dim = horizon, action_dim, state_dim
        chunk_dim = horizon * action_dim
        self.net = mlp(state_dim + chunk_dim + 1, self._arch["hidden_dims"], chunk_dim, dropout)

    @property
    def architecture(self) -> dict[str, Any]:
        """The constructor kwargs (JSON-ready)."""
        return dict(self._arch, hidden_dims=list(self._arch["hidden_dims"]))

    def forward(self, state: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Velocity [B, H, A] at noisy chunks x_t [B, H, A] and times t [B] or [B, 1], given states [B, S]."""
        batch = state.shape[0]
        inputs = torch.cat([state, x_t.reshape(batch, -1), t.reshape(batch, 1).to(state.dtype)], dim=1)
        return self.net(inputs).reshape(batch, self.horizon, self.action_dim)

    def compute_loss(self, state: torch.Tensor, action_chunk: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Flow-matching loss: x_t = (1 - t) x0 + t x1 with x0 ~ N(0, I), t ~ U[0, 1]; target x1 - x0."""
        x1 = action_chunk
        x0 = torch.randn(x1.shape, generator=generator, device=x1.device, dtype=x1.dtype)
        t = torch.rand((x1.shape[0], 1, 1), generator=generator, device=x1.device, dtype=x1.dtype)
        x_t = (1 - t) * x0 + t * x1
        return F.mse_loss(self(state, x_t, t), x1 - x0)

    def sample_actions(
        self,
        state: torch.Tensor,
        noise: torch.Tensor | None = None,
        num_steps: int = DEFAULT_NUM_STEPS,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Integrate the velocity from x0 = `noise` [B, H, A] (standard normal if None) with `num_steps` Euler steps."""
        if num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {num_steps}")
        batch = state.shape[0]
        shape = (batch, self.horizon, self.action_dim)
        if noise is None:
            noise = torch.randn(shape, generator=generator, device=state.device, dtype=state.dtype)
        elif tuple(noise.shape) != shape and not torch.jit.is_tracing() and not torch.compiler.is_compiling():
            raise ValueError(f"noise must have shape {list(shape)}, got {list(noise.shape)}")
        x = noise
        dt = 1.0 / num_steps
        # Python loop: tracing for ONNX unrolls it into num_steps copies of the network.
        for i in range(num_steps):
            t = torch.full_like(state[:, :1], i * dt)
            x = x + dt * self(state, x, t)
        return x


class ActingPolicy(nn.Module):
    """A policy with its normalization: env-unit states [B, 5] (and flow noise [B, 12, 2]) in, clipped env-unit actions out."""

    def __init__(
        self,
        policy: MSEPolicy | FlowPolicy,
        state_mean: Any,
        state_std: Any,
        action_mean: Any,
        action_std: Any,
        num_steps: int = DEFAULT_NUM_STEPS,
    ) -> None:
        super().__init__()
        self.policy = policy
        self.kind = policy.kind
        self.num_steps = num_steps
        stats = {
            "state_mean": (state_mean, policy.state_dim),
            "state_std": (state_std, policy.state_dim),
            "action_mean": (action_mean, policy.action_dim),
            "action_std": (action_std, policy.action_dim),
        }
        for name, (value, dim) in stats.items():
            tensor = torch.as_tensor(value, dtype=torch.float32).detach().clone().reshape(-1)
            if tensor.numel() != dim:
                raise ValueError(f"{name} must have {dim} values, got {tensor.numel()}")
            if not torch.isfinite(tensor).all():
                raise ValueError(f"{name} must be finite, got {tensor.tolist()}")
            if name.endswith("_std"):
                tensor = guard_std(tensor)
            self.register_buffer(name, tensor)

    def forward(self, state: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int | None = None) -> torch.Tensor:
        """Actions [B, H, A] in env units, clipped to [0, 512]. MSE ignores `noise`; flow draws it if None."""
        state_n = (state - self.state_mean) / self.state_std
        if self.kind == "flow":
            steps = self.num_steps if num_steps is None else num_steps
            chunk_n = self.policy.sample_actions(state_n, noise=noise, num_steps=steps)
        else:
            chunk_n = self.policy.sample_actions(state_n)
        actions = chunk_n * self.action_std + self.action_mean
        return torch.clamp(actions, ACTION_LOW, ACTION_HIGH)

    def normalization(self) -> dict[str, list[float]]:
        """The statistics as JSON-ready lists."""
        return {name: getattr(self, name).tolist() for name in ("state_mean", "state_std", "action_mean", "action_std")}


def guard_std(std: torch.Tensor) -> torch.Tensor:
    """`std` with entries below MIN_STD (constant dimensions) replaced by 1."""
    return torch.where(std < MIN_STD, torch.ones_like(std), std)


def mlp(in_dim: int, hidden_dims: Sequence[int], out_dim: int, dropout: float) -> nn.Sequential:
    """Linear -> ReLU -> Dropout per hidden layer, then a linear output layer."""
    layers: list[nn.Module] = []
    prev = in_dim
    for width in hidden_dims:
        layers += [nn.Linear(prev, width), nn.ReLU(), nn.Dropout(dropout)]
        prev = width
    layers.append(nn.Linear(prev, out_dim))
    return nn.Sequential(*layers)


def _check_architecture(hidden_dims: Sequence[int], dropout: float, horizon: int, action_dim: int, state_dim: int) -> dict[str, Any]:
    """Validated constructor kwargs, or a ValueError naming the bad one."""
    if isinstance(hidden_dims, (str, bytes)) or not isinstance(hidden_dims, Sequence) or len(hidden_dims) == 0:
        raise ValueError(f"hidden_dims must be a non-empty list of positive ints, got {hidden_dims!r}")
    for width in hidden_dims:
        if isinstance(width, bool) or not isinstance(width, int) or width < 1:
            raise ValueError(f"hidden_dims must be a non-empty list of positive ints, got {list(hidden_dims)!r}")
    if isinstance(dropout, bool) or not isinstance(dropout, (int, float)) or not (0 <= dropout < 1) or math.isnan(dropout):
        raise ValueError(f"dropout must be a number in [0, 1), got {dropout!r}")
    for name, value in (("horizon", horizon), ("action_dim", action_dim), ("state_dim", state_dim)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    return {
        "hidden_dims": tuple(int(w) for w in hidden_dims),
        "dropout": float(dropout),
        "horizon": horizon,
        "action_dim": action_dim,
        "state_dim": state_dim,
    }

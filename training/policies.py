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
ANGLE_ENCODINGS = ("raw", "sincos")
# "agent": chunks are predicted relative to the agent's position in the state (added back when acting).
ACTION_FRAMES = ("absolute", "agent")
TIME_EMBEDDINGS = ("scalar", "sinusoidal")
DEFAULT_TIME_EMBEDDING_DIM = 32
# Angular frequencies (rad per unit t) of the sinusoidal time embedding: slow enough to stay monotonic
# over t in [0, 1], fast enough to separate nearby Euler steps.
TIME_FREQ_MIN, TIME_FREQ_MAX = 1.0, 1000.0
_BASE_KEYS = ("hidden_dims", "dropout", "horizon", "action_dim", "state_dim")
MSE_ARCH_KEYS = _BASE_KEYS + ("angle_encoding", "state_skip", "action_frame")
FLOW_ARCH_KEYS = MSE_ARCH_KEYS + ("time_embedding", "time_embedding_dim", "noise_scale", "steering_dims", "selector_dims", "selector_candidates")
ARCH_KEYS = FLOW_ARCH_KEYS  # every key some kind accepts; each kind checks its own subset
# Variant keys and their defaults; the `architecture` dict lists a variant key only when it differs,
# so cards of the default architectures stay exactly as they were.
_VARIANT_DEFAULTS = {"angle_encoding": "raw", "state_skip": False, "action_frame": "absolute", "time_embedding": "scalar", "time_embedding_dim": DEFAULT_TIME_EMBEDDING_DIM, "noise_scale": 1.0, "steering_dims": None, "selector_dims": None, "selector_candidates": 16}


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
    allowed = set(MSE_ARCH_KEYS if kind == "mse" else FLOW_ARCH_KEYS)
    unknown = sorted(set(architecture) - allowed)
    if unknown:
        raise ValueError(f"unknown {kind} architecture keys {unknown}; expected a subset of {sorted(allowed)}")
    return cls(**architecture)


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters (buffers excluded)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


class _StateEncoding(nn.Module):
    """Shared by both policies: the optional sin/cos angle encoding and its input statistics."""

    state_dim: int

    def _init_state_encoding(self, angle_encoding: str) -> int:
        """Set up the encoding; returns the encoded state width."""
        self.angle_encoding = angle_encoding
        if angle_encoding == "raw":
            return self.state_dim
        # The model sees z-scored states; sin/cos need the raw angle, so the policy keeps the angle
        # channel's statistics as (persistent) buffers that checkpoints carry. NaN until
        # set_input_normalization: a forgotten call fails loudly instead of training on sin(z).
        self.register_buffer("angle_mean", torch.full((1,), float("nan")))
        self.register_buffer("angle_std", torch.full((1,), float("nan")))
        return self.state_dim + 1

    def set_input_normalization(self, state_mean: Any, state_std: Any) -> None:
        """Record the state normalization the inputs went through (needed by angle_encoding="sincos"; a no-op for "raw")."""
        mean = torch.as_tensor(state_mean, dtype=torch.float32).detach().reshape(-1)
        std = guard_std(torch.as_tensor(state_std, dtype=torch.float32).detach().reshape(-1))
        if mean.numel() != self.state_dim or std.numel() != self.state_dim:
            raise ValueError(f"state_mean and state_std must have {self.state_dim} values, got {mean.numel()} and {std.numel()}")
        if not (torch.isfinite(mean).all() and torch.isfinite(std).all()):
            raise ValueError(f"state normalization must be finite, got {mean.tolist()} / {std.tolist()}")
        if self.angle_encoding == "sincos":
            self.angle_mean.copy_(mean[-1:])
            self.angle_std.copy_(std[-1:])

    def check_input_normalization(self, state_mean: Any | None = None, state_std: Any | None = None) -> None:
        """Raise ValueError if a sincos policy lacks its normalization, or (when given) it differs from these statistics."""
        if self.angle_encoding != "sincos":
            return
        if not (torch.isfinite(self.angle_mean).all() and torch.isfinite(self.angle_std).all()):
            raise ValueError(
                'angle_encoding="sincos" needs the state normalization: call policy.set_input_normalization(state_mean, state_std)'
            )
        if state_mean is None or state_std is None:
            return
        mean = torch.as_tensor(state_mean, dtype=torch.float32).reshape(-1)[-1:]
        std = guard_std(torch.as_tensor(state_std, dtype=torch.float32).reshape(-1))[-1:]
        if not (torch.allclose(mean, self.angle_mean, rtol=1e-5, atol=1e-6) and torch.allclose(std, self.angle_std, rtol=1e-5, atol=1e-6)):
            raise ValueError(
                f"the policy's angle normalization (mean {self.angle_mean.item()}, std {self.angle_std.item()}) differs from the "
                f"given state normalization (mean {mean.item()}, std {std.item()})"
            )

    def _init_net(self, in_dim: int, cond_dim: int, hidden_dims: Sequence[int], out_dim: int, dropout: float, state_skip: bool) -> None:
        """The MLP as `self.net`: plain, or with the encoded state fed again into every layer (`state_skip`)."""
        self.state_skip = state_skip
        if state_skip:
            self.net = StateSkipMLP(in_dim, cond_dim, hidden_dims, out_dim, dropout)
        else:
            self.net = mlp(in_dim, hidden_dims, out_dim, dropout)

    def _run_net(self, inputs: torch.Tensor, encoded: torch.Tensor) -> torch.Tensor:
        return self.net(inputs, encoded) if self.state_skip else self.net(inputs)

    def encode_state(self, state: torch.Tensor) -> torch.Tensor:
        """The network's view of normalized states [B, S]: unchanged ("raw"), or the angle (last channel) as sin, cos of the raw angle."""
        if self.angle_encoding == "raw":
            return state
        angle = state[:, -1:] * self.angle_std + self.angle_mean
        return torch.cat([state[:, :-1], torch.sin(angle), torch.cos(angle)], dim=1)


class MSEPolicy(_StateEncoding):
    """An MLP from state to a whole action chunk, trained by mean squared error on normalized actions."""

    kind = "mse"

    def __init__(
        self,
        hidden_dims: Sequence[int] = MSE_HIDDEN_DIMS,
        dropout: float = DEFAULT_DROPOUT,
        horizon: int = HORIZON,
        action_dim: int = ACTION_DIM,
        state_dim: int = STATE_DIM,
        angle_encoding: str = "raw",
        state_skip: bool = False,
        action_frame: str = "absolute",
    ) -> None:
        super().__init__()
        self._arch = _check_architecture(hidden_dims, dropout, horizon, action_dim, state_dim)
        self._arch.update(_check_variants(angle_encoding=angle_encoding, state_skip=state_skip, action_frame=action_frame))
        self.horizon, self.action_dim, self.state_dim = horizon, action_dim, state_dim
        self.action_frame = action_frame
        encoded_dim = self._init_state_encoding(angle_encoding)
        self._init_net(encoded_dim, encoded_dim, self._arch["hidden_dims"], horizon * action_dim, dropout, state_skip)

    @property
    def architecture(self) -> dict[str, Any]:
        """The constructor kwargs (JSON-ready)."""
        return _architecture_dict(self._arch)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        """The predicted chunk [B, H, A] of normalized states [B, S]."""
        encoded = self.encode_state(state)
        return self._run_net(encoded, encoded).reshape(-1, self.horizon, self.action_dim)

    def compute_loss(self, state: torch.Tensor, action_chunk: torch.Tensor) -> torch.Tensor:
        """Mean squared error between the predicted and the demonstrated normalized chunk."""
        self.check_input_normalization()
        return F.mse_loss(self(state), action_chunk)

    def sample_actions(self, state: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int = DEFAULT_NUM_STEPS) -> torch.Tensor:
        """The deterministic chunk [B, H, A]; `noise` and `num_steps` are accepted for the common interface and ignored."""
        return self(state)


class FlowPolicy(_StateEncoding):
    """Straight-line conditional flow matching: an MLP of (state, noisy chunk, t) predicts the velocity x1 - x0."""

    kind = "flow"

    def __init__(
        self,
        hidden_dims: Sequence[int] = FLOW_HIDDEN_DIMS,
        dropout: float = DEFAULT_DROPOUT,
        horizon: int = HORIZON,
        action_dim: int = ACTION_DIM,
        state_dim: int = STATE_DIM,
        angle_encoding: str = "raw",
        state_skip: bool = False,
        time_embedding: str = "scalar",
        time_embedding_dim: int = DEFAULT_TIME_EMBEDDING_DIM,
        action_frame: str = "absolute",
        noise_scale: float = 1.0,
        steering_dims: Sequence[int] | None = None,
        selector_dims: Sequence[int] | None = None,
        selector_candidates: int = 16,
    ) -> None:
        super().__init__()
        self._arch = _check_architecture(hidden_dims, dropout, horizon, action_dim, state_dim)
        self._arch.update(
            _check_variants(
                angle_encoding=angle_encoding,
                state_skip=state_skip,
                time_embedding=time_embedding,
                time_embedding_dim=time_embedding_dim,
                action_frame=action_frame,
                noise_scale=noise_scale,
                steering_dims=steering_dims,
                selector_dims=selector_dims,
                selector_candidates=selector_candidates,
            )
        )
        self.horizon, self.action_dim, self.state_dim = horizon, action_dim, state_dim
        self.action_frame = action_frame
        # Sampling only (training draws x0 ~ N(0, I)): starting closer to the mean trades diversity
        # for precision, chosen by rollouts on non-held-out seeds (models/README.md).
        self.noise_scale = float(noise_scale)
        encoded_dim = self._init_state_encoding(angle_encoding)
        self.time_embedding = time_embedding
        if time_embedding == "sinusoidal":
            freqs = torch.exp(torch.linspace(math.log(TIME_FREQ_MIN), math.log(TIME_FREQ_MAX), time_embedding_dim // 2))
            # not persistent: it follows from the architecture, so checkpoints need not carry it
            self.register_buffer("time_freqs", freqs, persistent=False)
            time_dim = time_embedding_dim
        else:
            time_dim = 1
        chunk_dim = horizon * action_dim
        self._init_net(encoded_dim + chunk_dim + time_dim, encoded_dim, self._arch["hidden_dims"], chunk_dim, dropout, state_skip)
        # Learned start noise (training.finetune); None: x0 is noise_scale * noise, as trained.
        self.steering = None
        if self._arch["steering_dims"] is not None:
            from training.steering import NoiseSteering

            self.steering = NoiseSteering(encoded_dim, (horizon, action_dim), self._arch["steering_dims"])
        # A learned critic choosing the best of K candidate starts (training.finetune --algo qselect).
        self.selector = None
        if self._arch["selector_dims"] is not None:
            from training.selection import NoiseSelector

            self.selector = NoiseSelector(encoded_dim, (horizon, action_dim), self._arch["selector_dims"], self._arch["selector_candidates"])

    @property
    def architecture(self) -> dict[str, Any]:
        """The constructor kwargs (JSON-ready)."""
        return _architecture_dict(self._arch)

    def forward(self, state: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Velocity [B, H, A] at noisy chunks x_t [B, H, A] and times t [B] or [B, 1], given states [B, S]."""
        batch = state.shape[0]
        encoded = self.encode_state(state)
        t = t.reshape(batch, 1).to(state.dtype)
        if self.time_embedding == "sinusoidal":
            angles = t * self.time_freqs
            t = torch.cat([torch.sin(angles), torch.cos(angles)], dim=1)
        inputs = torch.cat([encoded, x_t.reshape(batch, -1), t], dim=1)
        return self._run_net(inputs, encoded).reshape(batch, self.horizon, self.action_dim)

    def compute_loss(self, state: torch.Tensor, action_chunk: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Flow-matching loss: x_t = (1 - t) x0 + t x1 with x0 ~ N(0, I), t ~ U[0, 1]; target x1 - x0."""
        self.check_input_normalization()
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
        """Integrate the velocity from x0 = noise_scale * `noise` [B, H, A] (standard normal if None) with `num_steps` Euler steps."""
        if num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {num_steps}")
        batch = state.shape[0]
        shape = (batch, self.horizon, self.action_dim)
        if noise is None:
            noise = torch.randn(shape, generator=generator, device=state.device, dtype=state.dtype)
        elif tuple(noise.shape) != shape and not torch.jit.is_tracing() and not torch.compiler.is_compiling():
            raise ValueError(f"noise must have shape {list(shape)}, got {list(noise.shape)}")
        x = self.start_noise(state, noise)
        return self.integrate(state, x, num_steps)

    def start_noise(self, state: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """The Euler start x0 [B, H, A] of standard-normal `noise`: scaled, and steered when the policy has steering."""
        if self.steering is not None:
            return self.steering(self.encode_state(state), noise, self.noise_scale)
        if self.selector is not None:
            return self.selector(self.encode_state(state), noise, self.noise_scale)
        return noise if self.noise_scale == 1.0 else noise * self.noise_scale

    def integrate(self, state: torch.Tensor, x0: torch.Tensor, num_steps: int = DEFAULT_NUM_STEPS) -> torch.Tensor:
        """Normalized chunks [B, H, A]: the velocity integrated from x0 with `num_steps` Euler steps."""
        x = x0
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
        policy.check_input_normalization(state_mean, state_std)
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
        return self._to_env_units(state, chunk_n)

    def from_start(self, state: torch.Tensor, x0: torch.Tensor) -> torch.Tensor:
        """Flow only: env-unit actions [B, H, A] integrated from a given Euler start x0 (fine-tuning acts this way)."""
        state_n = (state - self.state_mean) / self.state_std
        return self._to_env_units(state, self.policy.integrate(state_n, x0, self.num_steps))

    def _to_env_units(self, state: torch.Tensor, chunk_n: torch.Tensor) -> torch.Tensor:
        actions = chunk_n * self.action_std + self.action_mean
        if self.policy.action_frame == "agent":
            actions = actions + state[:, None, :ACTION_DIM]
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


class StateSkipMLP(nn.Module):
    """Like `mlp`, but the conditioning `cond` [B, C] is concatenated again to the input of every hidden layer after the first and of the output layer."""

    def __init__(self, in_dim: int, cond_dim: int, hidden_dims: Sequence[int], out_dim: int, dropout: float) -> None:
        super().__init__()
        self.hidden = nn.ModuleList()
        prev = in_dim
        for i, width in enumerate(hidden_dims):
            self.hidden.append(nn.Linear(prev + (cond_dim if i else 0), width))
            prev = width
        self.out = nn.Linear(prev + cond_dim, out_dim)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """Outputs [B, out_dim] of inputs [B, in_dim] and conditioning [B, cond_dim]."""
        h = x
        for i, layer in enumerate(self.hidden):
            if i:
                h = torch.cat([h, cond], dim=1)
            h = self.dropout(F.relu(layer(h)))
        return self.out(torch.cat([h, cond], dim=1))


def _architecture_dict(arch: dict[str, Any]) -> dict[str, Any]:
    """JSON-ready kwargs: the base keys always, a variant key only where it differs from its default."""
    out = {k: v for k, v in arch.items() if k not in _VARIANT_DEFAULTS or v != _VARIANT_DEFAULTS[k]}
    out["hidden_dims"] = list(arch["hidden_dims"])
    return out


def _check_variants(**variants: Any) -> dict[str, Any]:
    """Validated variant kwargs (angle_encoding, state_skip, time_embedding, time_embedding_dim, action_frame), or a ValueError naming the bad one."""
    if "noise_scale" in variants:
        scale = variants["noise_scale"]
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0 <= scale <= 10:
            raise ValueError(f"noise_scale must be a number in [0, 10], got {scale!r}")
        variants["noise_scale"] = float(scale)
    for key in ("steering_dims", "selector_dims"):
        dims = variants.get(key)
        if dims is None:
            continue
        if isinstance(dims, (str, bytes)) or not isinstance(dims, Sequence) or not dims or any(
            isinstance(w, bool) or not isinstance(w, int) or w < 1 for w in dims
        ):
            raise ValueError(f"{key} must be null or a non-empty list of positive ints, got {dims!r}")
        variants[key] = [int(w) for w in dims]
    if "selector_candidates" in variants:
        k = variants["selector_candidates"]
        if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= 256:
            raise ValueError(f"selector_candidates must be an int in [1, 256], got {k!r}")
    if variants.get("steering_dims") is not None and variants.get("selector_dims") is not None:
        raise ValueError("a flow takes steering_dims or selector_dims, not both")
    if "action_frame" in variants and variants["action_frame"] not in ACTION_FRAMES:
        raise ValueError(f"action_frame must be one of {ACTION_FRAMES}, got {variants['action_frame']!r}")
    if "angle_encoding" in variants and variants["angle_encoding"] not in ANGLE_ENCODINGS:
        raise ValueError(f"angle_encoding must be one of {ANGLE_ENCODINGS}, got {variants['angle_encoding']!r}")
    if "state_skip" in variants and not isinstance(variants["state_skip"], bool):
        raise ValueError(f"state_skip must be true or false, got {variants['state_skip']!r}")
    if "time_embedding" in variants:
        if variants["time_embedding"] not in TIME_EMBEDDINGS:
            raise ValueError(f"time_embedding must be one of {TIME_EMBEDDINGS}, got {variants['time_embedding']!r}")
        dim = variants["time_embedding_dim"]
        if isinstance(dim, bool) or not isinstance(dim, int) or dim < 2 or dim % 2:
            raise ValueError(f"time_embedding_dim must be an even int >= 2, got {dim!r}")
        if variants["time_embedding"] == "scalar" and dim != DEFAULT_TIME_EMBEDDING_DIM:
            raise ValueError('time_embedding_dim applies only to time_embedding="sinusoidal"')
    return variants


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

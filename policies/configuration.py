"""The policies' architecture kwargs: defaults, the keys each kind accepts, validation, the card's form.

`build_policy(kind, **architecture)` rebuilds a model from its card's `architecture`; a variant key is
listed there only when it differs from its default, so cards of the default architectures stay as
they were.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

from policies.normalization import ACTION_FRAMES
from pusht.spec import ACTION_DIM, DEFAULT_HORIZON, STATE_DIM

MSE_HIDDEN_DIMS = (128, 256, 256, 512)
FLOW_HIDDEN_DIMS = (128, 256, 512, 512, 512)
DEFAULT_DROPOUT = 0.1
ANGLE_ENCODINGS = ("raw", "sincos", "keypoints")
"""keypoints: sin/cos of the angle plus the tee's corners in the arena (policies.features), as Diffusion Policy's keypoint observations"""
TIME_EMBEDDINGS = ("scalar", "sinusoidal")
DEFAULT_TIME_EMBEDDING_DIM = 32
_BASE_KEYS = ("hidden_dims", "dropout", "horizon", "action_dim", "state_dim")
MSE_ARCH_KEYS = _BASE_KEYS + ("angle_encoding", "state_skip", "action_frame", "prev_state", "pace_input", "acting_pace")
FLOW_ARCH_KEYS = MSE_ARCH_KEYS + (
    "time_embedding",
    "time_embedding_dim",
    "noise_scale",
    "outcome_dims",
    "outcome_candidates",
    "outcome_stretches",
    "value_dims",
)
ARCH_KEYS = FLOW_ARCH_KEYS  # every key some kind accepts; each kind checks its own subset
_VARIANT_DEFAULTS = {
    "angle_encoding": "raw",
    "state_skip": False,
    "action_frame": "absolute",
    "time_embedding": "scalar",
    "time_embedding_dim": DEFAULT_TIME_EMBEDDING_DIM,
    "noise_scale": 1.0,
    "outcome_dims": None,
    "outcome_candidates": 16,
    "outcome_stretches": [1.0],
    "value_dims": None,
    "prev_state": False,
    "pace_input": False,
    "acting_pace": None,
}


MSE_DEFAULTS = {
    "hidden_dims": MSE_HIDDEN_DIMS,
    "dropout": DEFAULT_DROPOUT,
    "horizon": DEFAULT_HORIZON,
    "action_dim": ACTION_DIM,
    "state_dim": STATE_DIM,
    **{k: _VARIANT_DEFAULTS[k] for k in MSE_ARCH_KEYS if k in _VARIANT_DEFAULTS},
}
FLOW_DEFAULTS = {
    **MSE_DEFAULTS,
    "hidden_dims": FLOW_HIDDEN_DIMS,
    **{k: _VARIANT_DEFAULTS[k] for k in FLOW_ARCH_KEYS if k in _VARIANT_DEFAULTS},
}


def architecture_with_defaults(kind: str, architecture: dict[str, Any]) -> dict[str, Any]:
    """`architecture` over its kind's defaults; a ValueError names keys the kind does not take."""
    defaults = MSE_DEFAULTS if kind == "mse" else FLOW_DEFAULTS
    unknown = sorted(set(architecture) - set(defaults))
    if unknown:
        raise ValueError(f"unknown {kind} architecture keys {unknown}; expected a subset of {sorted(defaults)}")
    return {**defaults, **architecture}


def architecture_dict(arch: dict[str, Any]) -> dict[str, Any]:
    """JSON-ready kwargs: the base keys always, a variant key only where it differs from its default."""
    out = {k: v for k, v in arch.items() if k not in _VARIANT_DEFAULTS or v != _VARIANT_DEFAULTS[k]}
    out["hidden_dims"] = list(arch["hidden_dims"])
    return out


def check_architecture(
    hidden_dims: Sequence[int], dropout: float, horizon: int, action_dim: int, state_dim: int, **variants: Any
) -> dict[str, Any]:
    """Validated constructor kwargs (the base ones and the given variants), or a ValueError naming the bad one."""
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
    base = {
        "hidden_dims": tuple(int(w) for w in hidden_dims),
        "dropout": float(dropout),
        "horizon": horizon,
        "action_dim": action_dim,
        "state_dim": state_dim,
    }
    return {**base, **_check_variants(**variants)}


def _check_variants(**variants: Any) -> dict[str, Any]:
    """Validated variant kwargs, or a ValueError naming the bad one."""
    if "noise_scale" in variants:
        scale = variants["noise_scale"]
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0 <= scale <= 10:
            raise ValueError(f"noise_scale must be a number in [0, 10], got {scale!r}")
        variants["noise_scale"] = float(scale)
    for key in ("outcome_dims", "value_dims"):
        dims = variants.get(key)
        if dims is None:
            continue
        if (
            isinstance(dims, (str, bytes))
            or not isinstance(dims, Sequence)
            or not dims
            or any(isinstance(w, bool) or not isinstance(w, int) or w < 1 for w in dims)
        ):
            raise ValueError(f"{key} must be null or a non-empty list of positive ints, got {dims!r}")
        variants[key] = [int(w) for w in dims]
    if variants.get("value_dims") is not None and variants.get("outcome_dims") is None:
        raise ValueError("value_dims needs outcome_dims: the value ranks the end states the outcome model predicts")
    k = variants.get("outcome_candidates", 16)
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= 256:
        raise ValueError(f"outcome_candidates must be an int in [1, 256], got {k!r}")
    for key in ("outcome_stretches",):
        if key in variants:
            variants[key] = check_stretches(variants[key], key)
    if "action_frame" in variants and variants["action_frame"] not in ACTION_FRAMES:
        raise ValueError(f"action_frame must be one of {ACTION_FRAMES}, got {variants['action_frame']!r}")
    if "angle_encoding" in variants and variants["angle_encoding"] not in ANGLE_ENCODINGS:
        raise ValueError(f"angle_encoding must be one of {ANGLE_ENCODINGS}, got {variants['angle_encoding']!r}")
    for key in ("state_skip", "prev_state", "pace_input"):
        if key in variants and not isinstance(variants[key], bool):
            raise ValueError(f"{key} must be true or false, got {variants[key]!r}")
    if variants.get("acting_pace") is not None:
        rule = variants["acting_pace"]
        if (
            isinstance(rule, (str, bytes))
            or not isinstance(rule, Sequence)
            or len(rule) != 4
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in rule)
        ):
            raise ValueError(f"acting_pace must be [far, near, radius, ramp] (policies.pace), got {rule!r}")
        from policies.pace import Pace

        Pace(*map(float, rule))  # its own range checks
        variants["acting_pace"] = [float(v) for v in rule]
    if "time_embedding" in variants:
        if variants["time_embedding"] not in TIME_EMBEDDINGS:
            raise ValueError(f"time_embedding must be one of {TIME_EMBEDDINGS}, got {variants['time_embedding']!r}")
        dim = variants["time_embedding_dim"]
        if isinstance(dim, bool) or not isinstance(dim, int) or dim < 2 or dim % 2:
            raise ValueError(f"time_embedding_dim must be an even int >= 2, got {dim!r}")
        if variants["time_embedding"] == "scalar" and dim != DEFAULT_TIME_EMBEDDING_DIM:
            raise ValueError('time_embedding_dim applies only to time_embedding="sinusoidal"')
    return variants


def check_stretches(stretches: Any, name: str = "outcome_stretches") -> list[float]:
    """Chunk stretches (an outcome chooser's, or those a second pass scores): numbers in (0, 4], the first 1 (the chunks
    themselves, what near-ties fall back to); a ValueError names `name`."""
    if (
        isinstance(stretches, (str, bytes))
        or not isinstance(stretches, Sequence)
        or not stretches
        or any(isinstance(s, bool) or not isinstance(s, (int, float)) or not 0 < s <= 4 for s in stretches)
        or stretches[0] != 1
    ):
        raise ValueError(f"{name} must be a list of numbers in (0, 4] starting with 1, got {stretches!r}")
    return [float(s) for s in stretches]

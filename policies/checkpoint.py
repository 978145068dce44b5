"""Safe checkpoints: a stem DIR/NAME is NAME.safetensors (weights only) + NAME.json (the card).

The card holds everything needed to rebuild the policy and to act (kind, architecture, and the
normalization its `policy.normalizer` holds), plus how it was made (config, steps, wall time,
evaluation, git commit, ONNX export). Loading reads only safetensors and JSON, never pickle; every
problem raises `CheckpointError` naming the file.
"""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from policies.base import ActingPolicy
from policies.card import CardError, card_stem, read_card, validate_card
from policies.factory import build_policy
from policies.networks import count_parameters
from pusht.spec import DEFAULT_NUM_STEPS, POLICY_KINDS

WEIGHTS_SUFFIX = ".safetensors"
CARD_SUFFIX = ".json"


CheckpointError = CardError
"""A checkpoint file is missing, corrupt, or does not match its card (the one error of `policies.card`)."""


def save_checkpoint(stem: str | Path, policy: torch.nn.Module, normalization: Any = None, **card_fields: Any) -> dict[str, Any]:
    """Write STEM.safetensors and STEM.json; returns the card. Extra card fields (config, steps, ...) pass through.

    The card's normalization is the policy's own; `normalization` (a card-style dict), when given, is
    first set on the policy (one built fresh, without statistics yet).
    """
    stem = checkpoint_stem(stem)
    if isinstance(policy, ActingPolicy):
        policy = policy.policy
    kind = getattr(policy, "kind", None)
    if kind not in POLICY_KINDS:
        raise ValueError(f"policy must be an MSEPolicy or FlowPolicy, got {type(policy).__name__}")
    if normalization is not None:
        policy.normalizer.set(normalization)
    architecture = policy.architecture
    card: dict[str, Any] = {
        "name": stem.name,
        "kind": kind,
        "architecture": architecture,
        "num_parameters": count_parameters(policy),
        "config": {},
        "normalization": policy.normalizer.to_dict(),
        "steps": 0,
        "wall_time_s": 0.0,
        "evaluation": None,
        "git_commit": None,
        "onnx": None,
    }
    fixed = {"kind", "architecture", "num_parameters", "normalization"}
    clashes = sorted(fixed & set(card_fields))
    if clashes:
        raise ValueError(f"card fields {clashes} are derived from the policy and cannot be given")
    card.update(card_fields)
    if card["git_commit"] is None:
        card["git_commit"] = git_commit()
    text = json.dumps(card, indent=2, allow_nan=False) + "\n"  # fails early on non-JSON config values
    stem.parent.mkdir(parents=True, exist_ok=True)
    write_tensors(stem.with_suffix(WEIGHTS_SUFFIX), policy.state_dict(), {"format": "pt", "kind": kind})
    write_text_atomic(stem.with_suffix(CARD_SUFFIX), text)
    return card


def load_checkpoint(stem: str | Path) -> tuple[torch.nn.Module, dict[str, Any]]:
    """The policy (eval mode) and its card from STEM.safetensors + STEM.json."""
    stem = checkpoint_stem(stem)
    card = load_card(stem)
    weights_path = stem.with_suffix(WEIGHTS_SUFFIX)
    try:
        policy = build_policy(card["kind"], **card["architecture"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{stem.with_suffix(CARD_SUFFIX)}: bad architecture {card['architecture']!r}: {exc}") from None
    if count_parameters(policy) != card["num_parameters"]:
        raise CheckpointError(
            f"{stem.with_suffix(CARD_SUFFIX)}: num_parameters {card['num_parameters']} does not match its architecture ({count_parameters(policy)})"
        )
    weights = _read_weights(weights_path)
    expected = policy.state_dict()
    missing = sorted(set(expected) - set(weights))
    unexpected = sorted(set(weights) - set(expected))
    if {"angle_mean", "angle_std"} & set(unexpected):
        raise CheckpointError(
            f"{weights_path}: written before the policy owned its normalization (angle_mean/angle_std, copies of "
            f"the card's): convert it once with python scripts/convert_checkpoints.py {stem}"
        )
    if missing or unexpected:
        raise CheckpointError(
            f"{weights_path}: weights do not fit the card's {card['kind']} architecture (missing {missing[:5]}, unexpected {unexpected[:5]})"
        )
    for key, tensor in weights.items():
        if tuple(tensor.shape) != tuple(expected[key].shape):
            raise CheckpointError(
                f"{weights_path}: weight {key} has shape {list(tensor.shape)}, the card's architecture needs {list(expected[key].shape)}"
            )
        if not tensor.is_floating_point():
            raise CheckpointError(f"{weights_path}: weight {key} has dtype {tensor.dtype}, expected a float")
        if not torch.isfinite(tensor).all():
            raise CheckpointError(f"{weights_path}: weight {key} contains NaN or inf")
    policy.load_state_dict(weights, strict=True)
    policy.normalizer.set(card["normalization"])  # validated by read_card
    policy.eval()
    return policy, card


def load_acting_policy(stem: str | Path, num_steps: int = DEFAULT_NUM_STEPS) -> ActingPolicy:
    """The checkpoint's policy as an acting module (eval mode): env units in, clipped actions out."""
    policy, _ = load_checkpoint(stem)
    return ActingPolicy(policy, num_steps=num_steps).eval()


def load_card(stem: str | Path) -> dict[str, Any]:
    """The validated card STEM.json as a dict (`policies.card.read_card`'s rules)."""
    return read_card(checkpoint_stem(stem).with_suffix(CARD_SUFFIX)).data


def update_card(stem: str | Path, **fields: Any) -> dict[str, Any]:
    """Set top-level card fields (e.g. onnx, evaluation) and rewrite the card atomically; returns it."""
    stem = checkpoint_stem(stem)
    card = load_card(stem)
    fixed = {"kind", "architecture", "num_parameters", "normalization"}
    clashes = sorted(fixed & set(fields))
    if clashes:
        raise ValueError(f"card fields {clashes} describe the weights and cannot be updated")
    card.update(fields)
    return _rewrite_card(stem, card)


def require_state_only(card: dict[str, Any], source: str | Path, command: str) -> None:
    """ValueError unless the card's policy acts from the state alone (no `prev_state` or pace input), which `command` needs."""
    extra = [key for key in ("prev_state", "pace_input") if card["architecture"].get(key)]
    if extra:
        raise ValueError(f"{source}: the policy takes {' and '.join(extra)} beside the state, which {command} does not carry")


def set_noise_scale(stem: str | Path, noise_scale: float) -> dict[str, Any]:
    """Set a flow checkpoint's sampling `noise_scale` (in its architecture; the weights do not change); returns the card."""
    return _set_acting_key(stem, "noise_scale", float(noise_scale), 1.0)


def set_acting_pace(stem: str | Path, rule: list[float]) -> dict[str, Any]:
    """Set the `acting_pace` rule [far, near, radius, ramp] (policies.pace) of a flow with a pace input; returns the card."""
    card = load_card(checkpoint_stem(stem))
    if not card["architecture"].get("pace_input"):
        raise ValueError(f"{checkpoint_stem(stem).with_suffix(CARD_SUFFIX)}: acting_pace applies to policies with a pace input")
    return _set_acting_key(stem, "acting_pace", [float(v) for v in rule], None)


def set_outcome_candidates(stem: str | Path, candidates: int) -> dict[str, Any]:
    """Set how many candidate chunks a flow's outcome chooser integrates; returns the card.

    Its candidate maps come from a fixed seed (`policies.selection.orthogonal_maps`: the first ones are the same for
    every count), so only those maps and the card change, never a learned weight."""
    stem = checkpoint_stem(stem)
    policy, card = load_checkpoint(stem)
    if policy.kind != "flow" or policy.outcome is None:
        raise ValueError(f"{stem.with_suffix(CARD_SUFFIX)}: outcome_candidates applies to flows with an outcome chooser")
    resized = build_policy("flow", **{**card["architecture"], "outcome_candidates": candidates})  # validates the count
    missing, unexpected = resized.load_state_dict(
        {k: v for k, v in policy.state_dict().items() if k != "outcome.rotations"}, strict=False
    )
    if missing != ["outcome.rotations"] or unexpected:
        raise ValueError(f"{stem}: weights do not carry over (missing {missing[:3]}, unexpected {unexpected[:3]})")
    resized.normalizer.set(policy.normalizer)
    derived = {"kind", "architecture", "num_parameters", "normalization"}
    return save_checkpoint(stem, resized, **{k: v for k, v in card.items() if k not in derived})


def _set_acting_key(stem: str | Path, key: str, value: Any, default: Any) -> dict[str, Any]:
    """Set how a flow checkpoint acts (an architecture key the weights do not depend on), validated; returns the card."""
    stem = checkpoint_stem(stem)
    card = load_card(stem)
    path = stem.with_suffix(CARD_SUFFIX)
    if card["kind"] != "flow":
        raise ValueError(f"{path}: {key} applies to flow policies, this card is {card['kind']}")
    architecture = {k: v for k, v in card["architecture"].items() if k != key}
    if value != default:
        architecture[key] = value
    card["architecture"] = build_policy("flow", **architecture).architecture  # validates the value
    return _rewrite_card(stem, card)


def _rewrite_card(stem: Path, card: dict[str, Any]) -> dict[str, Any]:
    """Validate `card` and write it atomically as STEM.json; returns it."""
    path = stem.with_suffix(CARD_SUFFIX)
    validate_card(card, path)
    write_text_atomic(path, json.dumps(card, indent=2, allow_nan=False) + "\n")
    return card


def checkpoint_stem(stem: str | Path) -> Path:
    """`policies.card.card_stem` (DIR/NAME from DIR/NAME, .json, .onnx or .safetensors), refusing a path with no NAME."""
    path = card_stem(stem)
    if not path.name:
        raise CheckpointError(f"{stem!s}: not a checkpoint stem (expected DIR/NAME)")
    return path


def git_commit(cwd: str | Path | None = None) -> str:
    """The current commit hash (with '-dirty' if tracked code changed), or 'unknown' outside a git repo.

    models/ and records/ are left out: a recipe writes there, so the second recipe of a clean run would otherwise say dirty."""
    where = Path(cwd) if cwd is not None else Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(
            [
                "git",
                "status",
                "--porcelain",
                "--untracked-files=no",
                "--",
                ":(top)",
                ":(top,exclude)models",
                ":(top,exclude)records",
            ],
            cwd=where,
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    commit = head.stdout.strip()
    return commit + ("-dirty" if dirty.returncode == 0 and dirty.stdout.strip() else "")


def write_text_atomic(path: Path, text: str) -> None:
    """Write `text` to `path` via a temporary file and rename, so readers never see half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; cards are read by the service, maybe as another user
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_tensors(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str] | None = None) -> None:
    """Write a safetensors file via a temporary file and a rename, readable by all like the cards."""
    tmp = path.with_name(path.name + ".tmp")
    # contiguous copies: safetensors refuses shared or strided storage
    save_file({k: v.detach().to("cpu").contiguous().clone() for k, v in tensors.items()}, str(tmp), metadata=metadata)
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def read_tensors(path: Path, what: str = "safetensors file") -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """The tensors and metadata of a safetensors file; a `CheckpointError` naming it and `what` it should be otherwise."""
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            return {k: f.get_tensor(k) for k in f.keys()}, f.metadata() or {}
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise CheckpointError(f"{path}: not a readable {what}: {exc}") from None


def _read_weights(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise CheckpointError(f"{path}: weights file not found")
    return read_tensors(path)[0]

"""Inference backends: one loaded policy behind `act(states, noise, num_steps) -> actions`.

`OnnxPolicy` runs the exported `NAME.onnx` with ONNX Runtime; `TorchPolicy` runs the
`NAME.safetensors` checkpoint through `training.checkpoint` (torch is imported only there, so the
serving image needs no torch). Both take env-unit states [B, 5] float32 and standard-normal noise
[B, 12, 2] float32 (flow only) and return clipped env-unit actions [B, 12, 2].
"""

from __future__ import annotations

import json
import logging
import stat
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from service.settings import MAX_NUM_STEPS, Settings

__all__ = ["ModelLoadError", "LoadedPolicy", "OnnxPolicy", "TorchPolicy", "load_policies", "read_card"]

log = logging.getLogger("service.backends")

STATE_DIM = 5
HORIZON = 12
ACTION_DIM = 2
KINDS = ("mse", "flow")
MAX_CARD_BYTES = 16 << 20


class ModelLoadError(RuntimeError):
    """A policy file is missing or unusable; the message names the file."""


class LoadedPolicy(Protocol):
    """What the batcher and routes need from a backend."""

    name: str
    kind: str
    backend: str
    card: dict[str, Any]
    default_num_steps: int

    def check_num_steps(self, num_steps: int) -> str | None:
        """None if this backend can run `num_steps` flow steps, else the reason it cannot."""

    def act(self, states: np.ndarray, noise: np.ndarray | None, num_steps: int | None) -> np.ndarray:
        """Actions [B, 12, 2] for states [B, 5] (noise [B, 12, 2] for flow, None for mse)."""


def load_policies(settings: Settings) -> dict[str, LoadedPolicy]:
    """Load every policy card in `settings.models_dir` with the chosen backend; raise ModelLoadError naming a bad file."""
    models_dir = Path(settings.models_dir)
    if not models_dir.is_dir():
        raise ModelLoadError(f"models dir {models_dir} does not exist (set PUSHT_MODELS_DIR)")
    policies: dict[str, LoadedPolicy] = {}
    # Every *.json is a card: a file that silently failed to load would be a policy silently missing.
    for card_path in sorted(models_dir.glob("*.json")):
        card = read_card(card_path)
        if settings.backend == "onnx":
            policy: LoadedPolicy = OnnxPolicy(card_path, card, settings.ort_intra_op_threads)
        else:
            policy = TorchPolicy(card_path, card, settings.torch_threads)
        policies[policy.name] = policy
        log.info("loaded %s policy %r from %s (%s backend)", policy.kind, policy.name, card_path, settings.backend)
    if not policies:
        raise ModelLoadError(f"no policy cards (NAME.json with a 'kind') in {models_dir}")
    return policies


def read_card(path: Path) -> dict[str, Any]:
    """The policy card at `path`; raise ModelLoadError naming the file unless it is a JSON object with the required fields."""
    _require_regular_file(path, "policy card")
    try:
        with open(path, "rb") as f:  # a regular file: opening cannot block
            raw = f.read(MAX_CARD_BYTES + 1)
        if len(raw) > MAX_CARD_BYTES:
            raise ModelLoadError(f"policy card {path} is larger than {MAX_CARD_BYTES} bytes")
        card = json.loads(raw)
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        if isinstance(exc, ModelLoadError):
            raise
        reason = "JSON nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise ModelLoadError(f"cannot read policy card {path}: {reason}") from None
    if not isinstance(card, dict):
        kind = {list: "an array", str: "a string", bool: "a boolean", type(None): "null"}.get(type(card), "a number")
        raise ModelLoadError(f"policy card {path} must be a JSON object, got {kind}")
    missing = [key for key in ("name", "kind") if key not in card]
    if missing:
        raise ModelLoadError(
            f"policy card {path} lacks {missing}: every *.json in the models dir must be a policy card "
            "(name, kind, onnx, ... as training.checkpoint writes it)"
        )
    if card["kind"] not in KINDS:
        raise ModelLoadError(f"policy card {path}: kind must be one of {KINDS}, got {card['kind']!r}")
    if card["name"] != path.stem:
        # Clients address a policy by name; a card whose name disagrees with its file is ambiguous.
        raise ModelLoadError(f"policy card {path}: name {card['name']!r} does not match the file stem {path.stem!r}")
    onnx_info = card.get("onnx")
    if onnx_info is not None and not isinstance(onnx_info, dict):
        raise ModelLoadError(f"policy card {path}: 'onnx' must be an object (file, inputs, num_steps), got {onnx_info!r:.80}")
    if onnx_info and not isinstance(onnx_info.get("file", ""), str):
        raise ModelLoadError(f"policy card {path}: onnx.file must be a file name, got {onnx_info['file']!r:.80}")
    return card


def _require_regular_file(path: Path, what: str) -> None:
    """ModelLoadError unless `path` is a regular file (a FIFO or device would block or never end)."""
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise ModelLoadError(f"{what} {path} is missing or unreadable: {exc.strerror}") from None
    if not stat.S_ISREG(mode):
        raise ModelLoadError(f"{what} {path} is not a regular file")


def _card_num_steps(card_path: Path, card: dict[str, Any]) -> int:
    onnx_info = card.get("onnx") or {}
    steps = onnx_info.get("num_steps", 10)
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= MAX_NUM_STEPS:
        raise ModelLoadError(f"policy card {card_path}: onnx.num_steps must be an integer in 1..{MAX_NUM_STEPS}, got {steps!r}")
    return steps


class OnnxPolicy:
    """A policy exported to ONNX, run by ONNX Runtime with options tuned for small batches."""

    backend = "onnx"

    def __init__(self, card_path: Path, card: dict[str, Any], intra_op_threads: int = 1) -> None:
        import onnxruntime as ort

        self.card_path = card_path
        self.card = card
        self.intra_op_threads = intra_op_threads
        self.name = self.card_path.stem
        self.kind = self.card["kind"]
        self.default_num_steps = _card_num_steps(self.card_path, self.card)
        onnx_file = (self.card.get("onnx") or {}).get("file") or f"{self.name}.onnx"
        path = self.card_path.parent / Path(onnx_file).name
        _require_regular_file(path, f"policy {self.name!r}: ONNX file")
        options = ort.SessionOptions()
        # One request is a few hundred microseconds of compute: thread pools and parallel graph
        # execution cost more in wake-ups than they save, and the event loop needs the other core.
        options.intra_op_num_threads = self.intra_op_threads
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        options.log_severity_level = 3
        try:
            self._session = ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # ORT raises its own exception types for unreadable graphs
            raise ModelLoadError(f"policy {self.name!r}: cannot load ONNX file {path}: {exc}") from exc
        inputs = {i.name for i in self._session.get_inputs()}
        expected = {"state", "noise"} if self.kind == "flow" else {"state"}
        if inputs != expected:
            raise ModelLoadError(f"policy {self.name!r}: ONNX file {path} has inputs {sorted(inputs)}, expected {sorted(expected)}")
        self._output = self._session.get_outputs()[0].name
        _smoke_test(self, path)

    def check_num_steps(self, num_steps: int) -> str | None:
        """The unrolled graph has a fixed step count; other counts need the torch backend."""
        if num_steps != self.default_num_steps:
            return (
                f"num_steps={num_steps} is not available on the onnx backend: policy {self.name!r} was exported "
                f"with {self.default_num_steps} unrolled steps (use the torch backend for other values)"
            )
        return None

    def act(self, states: np.ndarray, noise: np.ndarray | None, num_steps: int | None) -> np.ndarray:
        """Actions [B, 12, 2] from one ONNX Runtime call."""
        feeds = {"state": states}
        if self.kind == "flow":
            feeds["noise"] = noise
        return self._session.run([self._output], feeds)[0]


class TorchPolicy:
    """A policy rebuilt from its safetensors checkpoint and run by torch (any num_steps)."""

    backend = "torch"

    def __init__(self, card_path: Path, card: dict[str, Any], threads: int = 1) -> None:
        self.card_path = card_path
        self.card = card
        self.threads = threads
        try:
            import torch

            from training.checkpoint import load_acting_policy
        except ImportError as exc:
            raise ModelLoadError(f"the torch backend needs torch and the training package (pip install '.[train]'): {exc}") from exc
        self._torch = torch
        if self.threads:
            torch.set_num_threads(self.threads)
        self.name = self.card_path.stem
        self.kind = self.card["kind"]
        self.default_num_steps = _card_num_steps(self.card_path, self.card)
        weights = self.card_path.with_suffix(".safetensors")
        _require_regular_file(weights, f"policy {self.name!r}: weights file")
        try:
            self._module = load_acting_policy(self.card_path.with_suffix(""))
        except Exception as exc:  # safetensors/torch raise many types for a corrupt file
            raise ModelLoadError(f"policy {self.name!r}: cannot load checkpoint {weights}: {exc}") from exc
        self._module.eval()
        _smoke_test(self, weights)

    def check_num_steps(self, num_steps: int) -> str | None:
        """Torch integrates any step count, except for a distilled flow, trained for its own count only."""
        trained = self.card.get("sampler_steps")
        if trained is not None and num_steps != trained:
            return (f"num_steps={num_steps} is not available: policy {self.name!r} was distilled to sample in {trained} "
                    f"step{'s' if trained != 1 else ''}, and other counts do not give its actions")
        return None

    def act(self, states: np.ndarray, noise: np.ndarray | None, num_steps: int | None) -> np.ndarray:
        """Actions [B, 12, 2] from one torch forward pass."""
        torch = self._torch
        with torch.inference_mode():
            state_t = torch.from_numpy(states)
            if self.kind == "flow":
                steps = self.default_num_steps if num_steps is None else num_steps
                out = self._module(state_t, torch.from_numpy(noise), steps)
            else:
                out = self._module(state_t)
        return out.numpy()


def _smoke_test(policy: LoadedPolicy, path: Path) -> None:
    """Calls at load time: catch a wrong output shape or non-finite output (broken weights), and warm the session up."""
    rng = np.random.default_rng(0)
    states = np.column_stack([rng.uniform(0, 512, (8, 4)), rng.uniform(0, 2 * np.pi, 8)]).astype(np.float32)
    states[0] = 256.0
    noise = rng.standard_normal((8, HORIZON, ACTION_DIM), dtype=np.float32) if policy.kind == "flow" else None
    try:
        out = np.asarray(policy.act(states, noise, None))
    except Exception as exc:
        raise ModelLoadError(f"policy {policy.name!r}: test inference on {path} failed: {exc}") from exc
    if out.shape != (8, HORIZON, ACTION_DIM):
        raise ModelLoadError(f"policy {policy.name!r}: {path} returns shape {list(out.shape)}, expected [B, {HORIZON}, {ACTION_DIM}]")
    if not np.isfinite(out).all():
        raise ModelLoadError(f"policy {policy.name!r}: warm-up output of {path} is not finite (NaN or inf): broken weights")

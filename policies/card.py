"""The one reader of policy cards (NAME.json beside NAME.safetensors and NAME.onnx), torch-free.

Training writes cards (`policies.checkpoint`); evaluation, export, shipping and the service read them
here, with one set of rules, and take every shape past training from the `Card` it returns.
"""

from __future__ import annotations

import json
import math
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pusht.spec import ACTION_DIM, DEFAULT_HORIZON, DEFAULT_NUM_STEPS, POLICY_KINDS, STATE_DIM

__all__ = [
    "CARD_FIELDS",
    "Card",
    "CardError",
    "MAX_CARD_BYTES",
    "MAX_NUM_STEPS",
    "NORMALIZATION_KEYS",
    "card_stem",
    "check_normalization",
    "read_card",
    "require_regular_file",
]

CARD_FIELDS = (
    "name",
    "kind",
    "architecture",
    "num_parameters",
    "config",
    "normalization",
    "steps",
    "wall_time_s",
    "evaluation",
    "git_commit",
    "onnx",
)
NORMALIZATION_KEYS = ("state_mean", "state_std", "action_mean", "action_std")
MAX_CARD_BYTES = 16 << 20
MAX_NUM_STEPS = 100
"""the most flow steps a request or a card may ask for"""


class CardError(ValueError):
    """A policy file is missing, unreadable or inconsistent; the message starts with the file's path."""


@dataclass(frozen=True)
class Card:
    """A validated card and the shapes past training read from it."""

    path: Path  # STEM.json
    data: dict[str, Any]

    @property
    def stem(self) -> Path:
        return self.path.with_suffix("")

    @property
    def name(self) -> str:
        return self.data["name"]

    @property
    def kind(self) -> str:
        return self.data["kind"]

    @property
    def architecture(self) -> dict[str, Any]:
        return self.data["architecture"]

    @property
    def horizon(self) -> int:
        return int(self.architecture.get("horizon", DEFAULT_HORIZON))

    @property
    def state_dim(self) -> int:
        return int(self.architecture.get("state_dim", STATE_DIM))

    @property
    def action_dim(self) -> int:
        return int(self.architecture.get("action_dim", ACTION_DIM))

    @property
    def sampler_steps(self) -> int | None:
        """The one step count a flow was trained to sample in (distilled or fine-tuned at it), else None (any count integrates)."""
        return self.data.get("sampler_steps")

    @property
    def num_steps(self) -> int | None:
        """Flow steps a chunk takes by default (the exported graph's, else the distilled count, else 10); None for mse."""
        if self.kind != "flow":
            return None
        return (self.data["onnx"] or {}).get("num_steps") or self.sampler_steps or DEFAULT_NUM_STEPS

    @property
    def onnx_path(self) -> Path:
        """The exported graph beside the card (its `onnx.file`, else STEM.onnx)."""
        file = (self.data["onnx"] or {}).get("file") or f"{self.path.stem}.onnx"
        return self.path.parent / Path(file).name

    @property
    def uses_noise(self) -> bool:
        """Whether a flow's actions depend on its start noise: not where the card scales it to 0 (a deterministic student)
        or an outcome chooser maps it into its candidates."""
        arch = self.architecture
        if self.kind != "flow" or arch.get("outcome_dims") is not None:
            return self.kind == "flow"
        return float(arch.get("noise_scale", 1.0)) != 0.0

    @property
    def computes(self) -> str:
        """What the policy computes: mse; flow (a flow-matching sampler); flow-chooser (a flow's candidates picked by a learned
        outcome model)."""
        arch = self.architecture
        if self.kind != "flow":
            return self.kind
        if arch.get("outcome_dims") is not None:
            return "flow-chooser"
        return "flow"

    @property
    def default(self) -> bool:
        """Whether the card asks to be the service's default policy (its recipe says `default = true`)."""
        return self.data.get("default") is True

    def network_evaluations(self, num_steps: int | None = None) -> int:
        """Network evaluations per chunk: 1 for mse; a flow's step count, and with an outcome chooser over K candidates at
        S stretches K times that plus the K x S outcome-model passes (and as many value passes, with a value)."""
        if self.kind != "flow":
            return 1
        steps = num_steps or self.num_steps
        if self.architecture.get("outcome_dims") is None:
            return steps
        candidates = int(self.architecture.get("outcome_candidates", 16))
        scored = len(self.architecture.get("outcome_stretches", [1.0])) * (2 if self.architecture.get("value_dims") else 1)
        return candidates * (steps + scored)


def card_stem(path: str | Path) -> Path:
    """DIR/NAME from DIR/NAME, DIR/NAME.json, DIR/NAME.onnx or DIR/NAME.safetensors (other suffixes are part of the name)."""
    path = Path(path)
    return path.with_suffix("") if path.suffix in (".json", ".onnx", ".safetensors") else path


def read_card(path: str | Path) -> Card:
    """The card of a stem, card, ONNX or weights path; CardError naming the file unless it is a well-formed card."""
    path = card_stem(path).with_suffix(".json")
    if not path.exists() and not path.is_symlink():
        raise CardError(f"{path}: checkpoint card not found")
    require_regular_file(path, "card")
    try:
        with open(path, "rb") as f:  # a regular file: opening cannot block
            raw = f.read(MAX_CARD_BYTES + 1)
    except OSError as exc:
        raise CardError(f"{path}: cannot read the card: {exc.strerror}") from None
    if len(raw) > MAX_CARD_BYTES:
        raise CardError(f"{path}: card is larger than {MAX_CARD_BYTES} bytes")
    try:
        data = json.loads(raw)
    except RecursionError:
        raise CardError(f"{path}: card is not valid JSON: nested too deeply") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CardError(f"{path}: card is not valid JSON: {exc}") from None
    validate_card(data, path)
    return Card(path, data)


def validate_card(card: Any, path: str | Path) -> None:
    """CardError (naming `path`) unless `card` has every field, with a known kind and sane architecture, normalization and onnx."""
    if not isinstance(card, dict):
        raise CardError(f"{path}: card must be a JSON object, got {type(card).__name__}")
    missing = [f for f in CARD_FIELDS if f not in card]
    if missing:
        raise CardError(f"{path}: card is missing fields {missing}")
    if card["kind"] not in POLICY_KINDS:
        raise CardError(f"{path}: unknown policy kind {card['kind']!r}; expected one of {POLICY_KINDS}")
    architecture = card["architecture"]
    if not isinstance(architecture, dict):
        raise CardError(f"{path}: architecture must be an object, got {architecture!r:.80}")
    for key, default in (("horizon", DEFAULT_HORIZON), ("state_dim", STATE_DIM), ("action_dim", ACTION_DIM)):
        _check_count(architecture.get(key, default), f"architecture.{key}", path, 1, 1024)
    if isinstance(card["num_parameters"], bool) or not isinstance(card["num_parameters"], int):
        raise CardError(f"{path}: num_parameters must be an int, got {card['num_parameters']!r}")
    try:
        check_normalization(card["normalization"], architecture)
    except ValueError as exc:
        raise CardError(f"{path}: {exc}") from None
    onnx = card["onnx"]
    if onnx is not None and not (isinstance(onnx, dict) and isinstance(onnx.get("file"), str)):
        raise CardError(f"{path}: onnx must be null or an object with a 'file', got {onnx!r:.80}")
    if onnx and "num_steps" in onnx:
        _check_count(onnx["num_steps"], "onnx.num_steps", path, 1, MAX_NUM_STEPS)
    if card.get("sampler_steps") is not None:
        _check_count(card["sampler_steps"], "sampler_steps", path, 1, MAX_NUM_STEPS)


def check_normalization(normalization: Any, architecture: dict[str, Any], where: str = "normalization") -> dict[str, list[float]]:
    """The four statistics lists, or ValueError unless each has the architecture's width and finite values (stds >= 0)."""
    if not isinstance(normalization, dict):
        raise ValueError(f"{where} must be an object with {list(NORMALIZATION_KEYS)}, got {normalization!r:.80}")
    dims = {"state": architecture.get("state_dim", STATE_DIM), "action": architecture.get("action_dim", ACTION_DIM)}
    for key in NORMALIZATION_KEYS:
        value = normalization.get(key)
        dim = dims[key.split("_")[0]]
        if not isinstance(value, list) or len(value) != dim:
            raise ValueError(f"{where}.{key} must be a list of {dim} numbers, got {value!r:.80}")
        for v in value:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{where}.{key} must hold finite numbers, got {value!r:.80}")
        if key.endswith("_std") and any(v < 0 for v in value):
            raise ValueError(f"{where}.{key} must be >= 0, got {value!r:.80}")
    return {key: normalization[key] for key in NORMALIZATION_KEYS}


def require_regular_file(path: Path, what: str) -> None:
    """CardError unless `path` is a regular file (a FIFO or device would block or never end)."""
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise CardError(f"{path}: {what} is missing or unreadable: {exc.strerror}") from None
    if not stat.S_ISREG(mode):
        raise CardError(f"{path}: {what} is not a regular file")


def _check_count(value: Any, name: str, path: str | Path, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise CardError(f"{path}: {name} must be an integer in {low}..{high}, got {value!r:.80}")

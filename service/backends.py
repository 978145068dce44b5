"""The models dir as loaded policies: every card NAME.json through `acting.load_policy`, checked at startup.

`acting` reads the cards (one reader, one set of rules) and runs them, with ONNX Runtime or torch
(imported only for the torch backend, so the serving image needs no torch); every shape the service
uses (chunk length, action width, step count) comes from the card. The service adds its own rules:
a card's `name` is its file stem (clients address policies by name), its states are the env's
(`pusht.spec.STATE_DIM`, what every request schema checks), it takes no previous state (no protocol
here carries one), and a warm-up call must give finite actions of the card's shape. Any problem
stops startup with one line naming the file (`ModelLoadError`).
"""

from __future__ import annotations

import logging
from pathlib import Path

from acting import CardError, Policy, load_policy
from pusht.spec import STATE_DIM
from service.settings import Settings

__all__ = ["LoadedPolicy", "ModelLoadError", "default_policy", "load_policies", "load_served_policy"]

log = logging.getLogger("service.backends")

LoadedPolicy = Policy
"""What the batcher and routes run: an `acting.Policy`."""

CARD_HINT = "every *.json in the models dir must be a policy card (name, kind, onnx, ... as policies.checkpoint writes it)"


class ModelLoadError(RuntimeError):
    """A policy file is missing or unusable; the message starts with the file's path."""


def default_policy(policies: dict[str, Policy], preferred: str = "") -> str:
    """The policy a request without a name gets: `preferred` (PUSHT_DEFAULT_POLICY) if set, else the one whose card says
    `default`, else the first name in order; ModelLoadError if `preferred` or several cards' flags leave it unclear."""
    if preferred:
        if preferred not in policies:
            raise ModelLoadError(f"PUSHT_DEFAULT_POLICY={preferred!r} is not a loaded policy; loaded: {sorted(policies)}")
        return preferred
    flagged = sorted(name for name, policy in policies.items() if policy.card.default)
    if len(flagged) > 1:
        raise ModelLoadError(f"cards {flagged} each say `default`: keep one, or set PUSHT_DEFAULT_POLICY")
    return flagged[0] if flagged else min(policies)


def load_policies(settings: Settings) -> dict[str, Policy]:
    """Load every policy card in `settings.models_dir` with the chosen backend; raise ModelLoadError naming a bad file."""
    models_dir = Path(settings.models_dir)
    if not models_dir.is_dir():
        raise ModelLoadError(f"models dir {models_dir} does not exist (set PUSHT_MODELS_DIR)")
    policies: dict[str, Policy] = {}
    # Every *.json is a card: a file that silently failed to load would be a policy silently missing.
    for card_path in sorted(models_dir.glob("*.json")):
        policy = load_served_policy(card_path, settings)
        policies[policy.name] = policy
        log.info(
            "loaded %s policy %r from %s (%s backend, chunks of %d)",
            policy.kind,
            policy.name,
            card_path,
            settings.backend,
            policy.horizon,
        )
    if not policies:
        raise ModelLoadError(f"no policy cards (NAME.json with a 'kind') in {models_dir}")
    return policies


def load_served_policy(card_path: Path, settings: Settings) -> Policy:
    """One card's policy, loaded, checked against the service's rules and warmed up; ModelLoadError naming the file."""
    threads = settings.ort_intra_op_threads if settings.backend == "onnx" else settings.torch_threads
    try:
        policy = load_policy(card_path, backend=settings.backend, threads=threads)
        if policy.card.name != card_path.stem:
            # Clients address a policy by name; a card whose name disagrees with its file is ambiguous.
            raise CardError(f"{card_path}: name {policy.card.name!r} does not match the file stem {card_path.stem!r}")
        if policy.state_dim != STATE_DIM:
            raise CardError(
                f"{card_path}: architecture.state_dim is {policy.state_dim}; the service serves Push-T "
                f"states of {STATE_DIM} numbers"
            )
        if policy.takes_prev_state:
            raise CardError(f"{card_path}: the policy takes prev_state, which no protocol of the service carries")
        policy.check_outputs()  # wrong shapes or broken weights stop startup; also warms the session up
    except CardError as exc:
        message = str(exc)
        if message.startswith(f"{card_path}: card is missing fields") or message.startswith(f"{card_path}: card must be"):
            message = f"{message}: {CARD_HINT}"
        raise ModelLoadError(message) from None
    except Exception as exc:  # the torch backend's checkpoint loader raises many types for a corrupt file
        where = card_path.with_suffix(".safetensors") if settings.backend == "torch" else card_path
        raise ModelLoadError(f"{where}: cannot load the {settings.backend} policy: {type(exc).__name__}: {exc}") from exc
    return policy

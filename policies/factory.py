"""`build_policy`: a fresh policy of a kind from its architecture (the card's `kind` and `architecture`)."""

from __future__ import annotations

from typing import Any

from policies.flow import FlowPolicy
from policies.mse import MSEPolicy
from pusht.spec import POLICY_KINDS

__all__ = ["build_policy"]


def build_policy(kind: str, **architecture: Any) -> "MSEPolicy | FlowPolicy":
    """A fresh policy of `kind` ("mse" or "flow") built from its architecture kwargs (its normalizer not yet set)."""
    classes = {"mse": MSEPolicy, "flow": FlowPolicy}
    if kind not in classes:
        raise ValueError(f"unknown policy kind {kind!r}; expected one of {POLICY_KINDS}")
    return classes[kind](**architecture)

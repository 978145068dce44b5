"""What the lifespan loads and the routes use: settings, policies, their batchers, metrics, readiness."""

from __future__ import annotations

from dataclasses import dataclass, field

from acting import Policy
from service.batching import Batcher
from service.metrics import Metrics
from service.settings import Settings


@dataclass
class ServiceState:
    """Per-app state, kept on `app.state.service`; `ready` turns True once every policy is loaded."""

    settings: Settings
    metrics: Metrics
    policies: dict[str, Policy] = field(default_factory=dict)
    batchers: dict[str, Batcher] = field(default_factory=dict)
    default_policy: str = ""  # what a request without a policy name gets (service.backends.default_policy)
    ready: bool = False

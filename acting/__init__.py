"""One way to act: a card's policy as `Policy.act(states, ...) -> actions`, for ONNX Runtime or torch.

Evaluation, collection, shipping and the service all load policies here (`load_policy`) and read cards
here (`read_card`); see docs/design.md. Importing this package imports no torch.
"""

from acting.card import Card, CardError, read_card
from acting.policy import Policy, load_policy, rollout_act

__all__ = ["Card", "CardError", "Policy", "load_policy", "read_card", "rollout_act"]

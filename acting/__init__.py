"""One way to act: a card's policy as `Policy.act(states, ...) -> actions`, for ONNX Runtime or torch.

Evaluation, collection, shipping and the service all load policies here (`load_policy`) and read cards
here (`read_card`); see docs/design.md. Importing this package imports no torch.
"""

from acting.loading import BACKENDS, load_policy, rollout_act
from acting.policy import Policy
from policies.card import Card, CardError, read_card

__all__ = ["BACKENDS", "Card", "CardError", "Policy", "load_policy", "read_card", "rollout_act"]

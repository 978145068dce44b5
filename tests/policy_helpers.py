"""Helpers shared by the policy tests: real windows, fitted normalizers, a short training loop."""

from __future__ import annotations

import torch

from policies.base import ActingPolicy


def fitted(policy, data):
    """`policy` with its normalizer fitted on the demonstrations, as training does."""
    policy.normalizer.set(data.statistics(policy.action_frame))
    return policy


def acting_with(policy, state_mean, state_std, action_mean, action_std) -> ActingPolicy:
    policy.normalizer.set(
        {
            "state_mean": list(map(float, state_mean)),
            "state_std": list(map(float, state_std)),
            "action_mean": list(map(float, action_mean)),
            "action_std": list(map(float, action_std)),
        }
    )
    return ActingPolicy(policy).eval()


def loss_before_and_after_training(policy, states, chunks, steps: int) -> tuple[float, float]:
    """Evaluation loss (dropout off, the same x0 and t draws) before and after `steps` Adam steps on one batch."""

    def eval_loss() -> float:
        policy.eval()
        with torch.no_grad():
            extra = {"generator": torch.Generator().manual_seed(1)} if policy.kind == "flow" else {}
            return float(policy.compute_loss(states, chunks, **extra))

    before = eval_loss()
    policy.train()
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)
    for _ in range(steps):
        optimizer.zero_grad()
        loss = policy.compute_loss(states, chunks)
        assert torch.isfinite(loss)
        loss.backward()
        optimizer.step()
    return before, eval_loss()

"""`load_policy`: a card's policy on ONNX Runtime or torch; `rollout_act`: a policy as the rollout runner's act function."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from acting.onnx_backend import OnnxPolicy
from acting.policy import Policy
from acting.torch_backend import TorchPolicy
from policies.card import read_card
from pusht.seeding import row_noise

BACKENDS = ("onnx", "torch")


def load_policy(model: str | Path, backend: str | None = None, threads: int = 1, num_steps: int | None = None) -> Policy:
    """The policy of an ONNX file (card beside it) or a checkpoint stem / card; backend: onnx for .onnx files, else torch.

    `num_steps` sets the flow step count of every call that gives none (ValueError where the backend cannot run it)."""
    path = Path(model)
    backend = backend or ("onnx" if path.suffix == ".onnx" else "torch")
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; expected one of {BACKENDS}")
    card = read_card(path)  # a missing or broken card is named before any backend loads
    if backend == "onnx":
        policy: Policy = OnnxPolicy(card, threads)
    else:
        policy = TorchPolicy(card, threads)
    if num_steps is not None and policy.kind == "flow":
        problem = policy.check_num_steps(num_steps)
        if problem is not None:
            raise ValueError(problem)
        policy.default_num_steps = num_steps
    return policy


def rollout_act(policy: Policy, noise_scale: float = 1.0, fixed_noise: int | None = None):
    """The rollout runner's act function (states, one request seed per row) -> actions: row i's noise from seeds[i], or
    with `fixed_noise` every row's from that one seed (a flow as a deterministic map of the state)."""
    if not 0 <= noise_scale <= 10:
        raise ValueError(f"noise_scale must be in [0, 10], got {noise_scale}")
    start = None if fixed_noise is None else row_noise([fixed_noise], policy.horizon, policy.action_dim)

    def act(states: np.ndarray, seeds: list[int], prev_states: np.ndarray | None = None) -> np.ndarray:
        if start is not None:
            return policy.act(states, prev_states, noise=np.repeat(start, len(states), axis=0), noise_scale=noise_scale)
        return policy.act(states, prev_states, seeds=seeds, noise_scale=noise_scale)

    return act

"""Seeds and noise of a rollout: each episode's randomness comes from its own seed only.

Rule: episode seed e resets the env with `reset(seed=e)`; that episode's decision d (0 at reset, then
1, 2, ...) asks the policy with request seed `decision_seed(e, d)`, and a flow policy starts that
row's sampling from `chunk_noise(decision_seed(e, d), 1)[0]` (`row_noise` of a batch's seeds). So an
episode's actions do not depend on which episodes share its batch, nor on how many envs run at once.

Batch shape matters too: ONNX Runtime's and torch's CPU matrix products round the rows of a full
group of four differently (last bit) from the last 1-3 rows, and the contact dynamics grow such bits
into different episodes. Every model call therefore runs a batch padded to a multiple of
`BATCH_MULTIPLE` rows (`pad_rows`), which makes each row's actions independent of its batch (measured
for batches of 1 to 250 rows, 1 or 2 threads, both shipped models, both backends).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

__all__ = ["BATCH_MULTIPLE", "MAX_SEED", "chunk_noise", "decision_seed", "episode_seeds", "pad_rows", "row_noise"]

MAX_SEED = 2**63
BATCH_MULTIPLE = 4
"""Model calls run batches padded to a multiple of this many rows (see the module docstring)."""


def episode_seeds(seed: int, n: int) -> list[int]:
    """The `n` consecutive episode seeds `[seed, seed + 1, ..., seed + n - 1]`."""
    check_seed_value("seed", seed)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    return list(range(int(seed), int(seed) + int(n)))


def decision_seed(seed: int, decision_index: int) -> int:
    """The request seed of decision `decision_index` of episode `seed`, in [0, 2**63).

    XOR of the two words of `SeedSequence([seed, decision_index]).generate_state(2, uint64)`, top bit cleared.
    """
    check_seed_value("seed", seed)
    check_seed_value("decision_index", decision_index)
    words = np.random.SeedSequence([int(seed), int(decision_index)]).generate_state(2, np.uint64)
    return int(words[0] ^ words[1]) & (MAX_SEED - 1)


def chunk_noise(seed: int, batch: int, horizon: int = 12, action_dim: int = 2) -> np.ndarray:
    """Flow's standard-normal start for a request seed: `default_rng(seed).standard_normal(shape, float32)`, [batch, horizon, action_dim]."""
    check_seed_value("seed", seed)
    for name, value in (("batch", batch), ("horizon", horizon), ("action_dim", action_dim)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    rng = np.random.default_rng(int(seed))
    return rng.standard_normal((int(batch), int(horizon), int(action_dim)), dtype=np.float32)


def row_noise(seeds: Sequence[int], horizon: int = 12, action_dim: int = 2) -> np.ndarray:
    """Per-row noise: row i is `chunk_noise(seeds[i], 1, horizon, action_dim)[0]`, so it depends on its own seed only.

    float32 [len(seeds), horizon, action_dim]; the service applies this to a request's `seeds`.
    """
    if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__len__") or len(seeds) == 0:
        raise ValueError("seeds must be a non-empty sequence of integers")
    return np.concatenate([chunk_noise(int(s) if isinstance(s, np.integer) else s, 1, horizon, action_dim) for s in seeds])


def pad_rows(array: np.ndarray, multiple: int = BATCH_MULTIPLE) -> np.ndarray:
    """`array` with its last row repeated until its length is a multiple of `multiple` (unchanged if it is)."""
    missing = -len(array) % multiple
    if missing == 0:
        return array
    # Filled in place: half the time of concatenate + repeat, on every model call of the service.
    padded = np.empty((len(array) + missing, *array.shape[1:]), dtype=array.dtype)
    padded[: len(array)] = array
    padded[len(array) :] = array[-1]
    return padded


def check_seed_value(name: str, value: Any) -> None:
    """Raise ValueError naming `name` unless `value` is an integer in [0, 2**63)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if not 0 <= int(value) < MAX_SEED:
        raise ValueError(f"{name} must be in [0, 2**63), got {value}")

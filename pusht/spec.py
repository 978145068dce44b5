"""The fixed names every package shares: dimensions, policy kinds, action bounds, success, seed ranges.

Shapes a policy chooses (its chunk length, its step count) come from its card; these are what no card
changes. `pusht` imports nothing of the project's, so `training`, `service`, `clients` and `bench`
all import these from here.
"""

from __future__ import annotations

__all__ = [
    "ACTION_DIM",
    "ACTION_HIGH",
    "ACTION_LOW",
    "DEFAULT_HORIZON",
    "DEFAULT_NUM_STEPS",
    "FINETUNE_EVAL_SEED",
    "HELD_OUT_RANGES",
    "HELD_OUT_SEED",
    "MIN_STD",
    "POLICY_KINDS",
    "RESERVED_SEEDS",
    "STATE_DIM",
    "SUCCESS_COVERAGE",
    "TRAIN_EVAL_SEED",
    "TUNING_SEED",
    "UNUSED_SEED",
]

STATE_DIM = 5
"""agent x, y; block x, y; block angle (rad)"""
ACTION_DIM = 2
"""the agent's target x, y"""
ACTION_LOW, ACTION_HIGH = 0.0, 512.0
"""every action is clipped to this range, in env units (pixels)"""

POLICY_KINDS = ("mse", "flow")
DEFAULT_HORIZON = 12
"""actions per chunk where a card does not say (every shipped card says 12)"""
DEFAULT_NUM_STEPS = 10
"""flow Euler steps where a card does not say"""
MIN_STD = 1e-6
"""a normalization std below this (a constant dimension) is replaced by 1"""

SUCCESS_COVERAGE = 0.95
"""an episode succeeds once the block covers more than this fraction of the goal (as gym-pusht)"""

# Episode seed ranges: scores on one range never choose anything scored on another.
TRAIN_EVAL_SEED = 100_000
"""training's periodic evaluation, and its `best` checkpoint (100000..)"""
HELD_OUT_SEED = 200_000
"""held-out scores (200000..); nothing is chosen on them"""
TUNING_SEED = 300_000
"""choices of settings (noise scale, step count, ...) (300000..)"""
FINETUNE_EVAL_SEED = 400_000
"""fine-tuning's periodic evaluation (400000..)"""
UNUSED_SEED = 600_000
"""1,000 further held-out episodes (600000..600999)"""
HELD_OUT_RANGES = (range(HELD_OUT_SEED, HELD_OUT_SEED + 500), range(UNUSED_SEED, UNUSED_SEED + 1000))
"""every held-out episode seed (the 100 and 500 episodes from 200000, the 1,000 from 600000): never trained or collected on"""
RESERVED_SEEDS = range(100_000, 1_000_000)
"""every evaluation range above: collection and training episodes draw seeds outside it"""

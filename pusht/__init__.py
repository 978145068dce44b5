"""Push-T: a gymnasium env that reproduces gym-pusht 0.1.8 (state observations) faster, and its rollout runner.

`import pusht` registers `pusht/PushT-v0` (300 steps per episode) with gymnasium.
"""

from __future__ import annotations

import gymnasium

from pusht.env import MAX_EPISODE_STEPS, PushTEnv
from pusht.geometry import coverage
from pusht.spec import SUCCESS_COVERAGE

__all__ = ["ENV_ID", "MAX_EPISODE_STEPS", "SUCCESS_COVERAGE", "PushTEnv", "coverage"]

ENV_ID = "pusht/PushT-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="pusht.env:PushTEnv", max_episode_steps=MAX_EPISODE_STEPS)

"""`training.finetune --algo outcome`: fit the outcome model of a flow's candidate chooser on simulated chunks (DAgger-style).

At each decision every env's state gets K x S candidate chunks from the frozen flow (fresh noise through
the selector's K maps, each chunk at the S stretches). In `label_envs` of the envs each candidate is simulated one chunk ahead from
the present state (`ChunkVectorEnv.lookahead`: training only), and (state, chunk, end state) joins the
replay. The envs then play the chunk the current model chooses (a random candidate with probability
`explore`, and always before `learning_starts` labels), so the model keeps learning on the states its
own choices lead to. After each decision, `updates_per_decision` minibatches of model regression.
"""

from __future__ import annotations

import numpy as np
import torch

from training.chunk_env import ChunkVectorEnv
from training.finetune_config import FinetuneConfig
from training.noise_rl import NoiseAgent, Resumable
from training.replay import ReplayBuffer

__all__ = ["OutcomeFit"]


class OutcomeFit(Resumable):
    """Supervised fitting of `policy.outcome.model` on one-chunk lookaheads of the flow's own candidates."""

    FIELDS = {"enc": 0, "x0": 0, "end": 0}  # state [5], chunk [H * A] in env units, state after the chunk [5]

    def __init__(self, agent: NoiseAgent, cfg: FinetuneConfig, generator: torch.Generator) -> None:
        self.agent, self.cfg, self.generator = agent, cfg, generator
        self.selector = agent.policy.outcome
        self.opt = torch.optim.Adam(self.selector.model.parameters(), lr=cfg.critic_lr)
        self.replay = ReplayBuffer(cfg.buffer_size, agent.policy.state_dim, agent.chunk_shape[0] * agent.chunk_shape[1], self.FIELDS)
        self.rng = np.random.default_rng(cfg.seed)

    def parts(self) -> tuple[dict, dict, dict]:
        """(modules, optimizers, replays) by name."""
        return {"outcome": self.selector.model}, {"outcome": self.opt}, {"labels": self.replay}

    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """As `Resumable.state`, plus the numpy stream that picks labelled envs and exploring ones."""
        tensors, extra = super().state()
        return tensors, {**extra, "numpy_rng": self.rng.bit_generator.state}

    def load_state(self, tensors: dict[str, torch.Tensor], extra: dict) -> None:
        """Restore what `state` saved."""
        super().load_state(tensors, extra)
        self.rng.bit_generator.state = extra["numpy_rng"]

    def iterate(self, envs: ChunkVectorEnv, finished_max: list, finished_success: list) -> dict:
        """`rollout_decisions` decisions in every env, each followed by the updates; returns figures for the log."""
        agent, cfg, losses = self.agent, self.cfg, []
        for _ in range(cfg.rollout_decisions):
            states = torch.as_tensor(envs.obs, dtype=torch.float32)
            noise = torch.randn((envs.num_envs, *agent.chunk_shape), generator=self.generator)
            with torch.no_grad():
                _, actions = self.selector.candidate_chunks(agent.policy, agent.policy.policy_state(states), noise, agent.num_steps)
                chosen = self.selector.choose(states, actions).numpy()
            self._label(envs, states, actions.numpy())
            explore = self.rng.random(envs.num_envs) < cfg.explore
            if self.replay.size < cfg.learning_starts:
                explore[:] = True
            chosen[explore] = self.rng.integers(self.selector.choices, size=int(explore.sum()))
            result = envs.step(actions.numpy()[np.arange(envs.num_envs), chosen])
            finished_max.extend(result.finished_max_reward)
            finished_success.extend(result.finished_success)
            if self.replay.size >= cfg.batch_size:
                losses.extend(self._update() for _ in range(cfg.updates_per_decision))
        return {"outcome_loss": float(np.mean(losses)) if losses else None, "labels": self.replay.size}

    def _label(self, envs: ChunkVectorEnv, states: torch.Tensor, actions: np.ndarray) -> None:
        rows = self.rng.permutation(envs.num_envs)[: self.cfg.label_envs]
        k = self.selector.choices
        ends = np.concatenate([envs.lookahead(int(i), actions[i]).next_obs for i in rows])
        self.replay.add(enc=states[rows].repeat_interleave(k, dim=0), x0=torch.as_tensor(actions[rows]).flatten(0, 1),
                        end=torch.as_tensor(ends, dtype=torch.float32))

    def _update(self) -> float:
        batch = self.replay.sample(self.cfg.batch_size, self.generator)
        loss = self.selector.model.loss(batch["enc"], batch["x0"].reshape(-1, *self.agent.chunk_shape), batch["end"])
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return float(loss.detach())

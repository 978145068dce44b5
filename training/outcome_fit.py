"""`training.finetune --algo outcome`: fit the outcome model of a flow's candidate chooser on simulated chunks (DAgger-style).

At each decision every env's state gets K x S candidate chunks from the frozen flow (fresh noise through
the selector's K maps, each chunk at the S stretches). In `label_envs` of the envs each candidate is simulated one chunk ahead from
the present state (`ChunkVectorEnv.lookahead`: training only), and (state, chunk, end state) joins the
replay. The envs then play the chunk the current model chooses (a random candidate with probability
`explore`, and always before `learning_starts` labels), so the model keeps learning on the states its
own choices lead to. After each decision, `updates_per_decision` minibatches of model regression.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from training.chunk_env import ChunkVectorEnv
from training.finetune_config import FinetuneConfig
from training.replay import ReplayBuffer

__all__ = ["FlowChooser", "OutcomeFit", "Resumable"]


class Resumable:
    """What a resumable checkpoint of a learner holds: its modules, optimizers and replays, by name. A learner's
    `trained` (policy, normalization, acting) is what its run saves and evaluates."""

    def parts(self) -> tuple[dict, dict, dict]:
        """(modules, optimizers, replays) by name."""
        raise NotImplementedError

    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """Tensors and JSON that `load_state` takes back."""
        from training.run import pack_optimizer

        modules, optimizers, replays = self.parts()
        tensors = {f"{name}.{k}": v for name, module in modules.items() for k, v in module.state_dict().items()}
        extra: dict = {"optimizers": {}, "replays": {}}
        for name, optimizer in optimizers.items():
            packed, extra["optimizers"][name] = pack_optimizer(optimizer, prefix=f"opt.{name}")
            tensors.update(packed)
        for name, replay in replays.items():
            packed, extra["replays"][name] = replay.state(prefix=f"replay.{name}")
            tensors.update(packed)
        return tensors, extra

    def save_outputs(self, run_dir: Path) -> None:
        """What the learner leaves in its run folder when the run finishes, beside the checkpoint: nothing by default."""

    def load_state(self, tensors: dict[str, torch.Tensor], extra: dict) -> None:
        """Restore what `state` saved."""
        from training.run import unpack_optimizer

        modules, optimizers, replays = self.parts()
        for name, module in modules.items():
            module.load_state_dict({k[len(name) + 1 :]: v for k, v in tensors.items() if k.startswith(name + ".")})
        for name, optimizer in optimizers.items():
            unpack_optimizer(optimizer, tensors, extra["optimizers"][name], prefix=f"opt.{name}")
        for name, replay in replays.items():
            replay.load_state(f"replay.{name}", tensors, extra["replays"][name])


class FlowChooser:
    """The frozen flow with a fresh (or warm) outcome chooser: what the fit trains and evaluates."""

    def __init__(self, base: torch.nn.Module, base_card: dict, cfg: FinetuneConfig) -> None:
        from policies.base import ActingPolicy
        from policies.factory import build_policy

        added = _chooser_architecture(base_card["architecture"], cfg)
        self.policy = build_policy("flow", **{**base_card["architecture"], **added})
        # the candidate maps follow from the candidate count (a fixed seed), so a warm start takes them as configured
        missing, unexpected = self.policy.load_state_dict(
            {k: v for k, v in base.state_dict().items() if k != "outcome.rotations"}, strict=False
        )
        self.policy.normalizer.set(base.normalizer)
        if unexpected or any(not k.startswith("outcome.") for k in missing):
            raise ValueError(
                f"{cfg.chooser_stem()}: weights do not carry over (missing {missing[:3]}, unexpected {unexpected[:3]})"
            )
        # The flow stays frozen because only the outcome model is optimized: no loss reaches the flow (rollouts
        # run without grad), and leaving requires_grad alone keeps the card's parameter count whole.
        self.policy.eval()
        self.normalization = self.policy.normalizer.to_dict()
        self.num_steps = cfg.flow_num_steps
        self.acting = ActingPolicy(self.policy, num_steps=cfg.flow_num_steps)
        self.noise_scale = self.policy.noise_scale
        self.chunk_shape = (self.policy.horizon, self.policy.action_dim)


def _chooser_architecture(arch: dict, cfg: FinetuneConfig) -> dict:
    """What the fit adds to the init's architecture: its outcome chooser as configured, for `--algo value` (which
    starts from an outcome chooser, kept as it is) a value model, for `--algo dagger` (the chooser teaches) and `--algo
    ppo` (a plain flow) nothing."""
    if cfg.algo in ("value", "dagger") and arch.get("outcome_dims") is None:
        raise ValueError(f"{cfg.chooser_stem()}: --algo {cfg.algo} starts from an outcome chooser (a flow with outcome_dims)")
    if cfg.algo == "dagger":
        return {}  # the chooser teaches as it is
    if cfg.algo == "ppo":
        if arch.get("outcome_dims") is not None:
            raise ValueError(f"{cfg.init}: --algo ppo fine-tunes a plain flow, not an outcome chooser")
        return {}
    if cfg.algo == "value":
        if arch.get("value_dims") is not None and list(arch["value_dims"]) != cfg.value_dims_list():
            raise ValueError(f"{cfg.init}: its value has value_dims {arch['value_dims']}; --value-dims must match")
        return {"value_dims": cfg.value_dims_list()}
    # An outcome chooser may start another outcome fit (its model warm, its stretches and candidates as configured).
    if arch.get("outcome_dims") is not None and list(arch["outcome_dims"]) != cfg.outcome_dims_list():
        raise ValueError(
            f"{cfg.init}: its outcome chooser has outcome_dims {arch['outcome_dims']}; --outcome-dims must match to start from it"
        )
    return {
        "outcome_dims": cfg.outcome_dims_list(),
        "outcome_candidates": cfg.candidates,
        "outcome_stretches": cfg.stretches_list(),
    }  # a value the init has stays, as it was fitted


class OutcomeFit(Resumable):
    """Supervised fitting of `policy.outcome.model` on one-chunk lookaheads of the flow's own candidates."""

    FIELDS = {"enc": 0, "x0": 0, "end": 0}  # state [5], chunk [H * A] in env units, state after the chunk [5]

    def __init__(self, agent: FlowChooser, cfg: FinetuneConfig, generator: torch.Generator) -> None:
        self.agent, self.cfg, self.generator = agent, cfg, generator
        self.trained = agent
        self.selector = agent.policy.outcome
        self.opt = torch.optim.Adam(self.selector.model.parameters(), lr=cfg.critic_lr)
        self.replay = ReplayBuffer(
            cfg.buffer_size, agent.policy.state_dim, agent.chunk_shape[0] * agent.chunk_shape[1], self.FIELDS
        )
        self.rng = np.random.default_rng(cfg.seed)
        self.episodes_before = 0  # started before a resume: the envs go on at the next training seed
        self.envs: ChunkVectorEnv | None = None  # built at the first iteration, after any resume

    def parts(self) -> tuple[dict, dict, dict]:
        """(modules, optimizers, replays) by name."""
        return {"outcome": self.selector.model}, {"outcome": self.opt}, {"labels": self.replay}

    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """As `Resumable.state`, plus the episodes started and the numpy stream that picks labelled envs and exploring ones."""
        tensors, extra = super().state()
        return tensors, {**extra, "episodes_started": self.episodes, "numpy_rng": self.rng.bit_generator.state}

    def load_state(self, tensors: dict[str, torch.Tensor], extra: dict) -> None:
        """Restore what `state` saved."""
        super().load_state(tensors, extra)
        self.episodes_before = int(extra["episodes_started"])
        self.rng.bit_generator.state = extra["numpy_rng"]

    @property
    def episodes(self) -> int:
        """Episodes started so far: a resumed run never replays an episode seed."""
        return self.episodes_before + (self.envs.episodes_started if self.envs is not None else 0)

    def iterate(self, finished_max: list, finished_success: list) -> dict:
        """`rollout_decisions` decisions in every env, each followed by the updates; returns figures for the log."""
        agent, cfg, losses = self.agent, self.cfg, []
        if self.envs is None:
            self.envs = ChunkVectorEnv(cfg.num_envs, cfg.train_seed_start + self.episodes_before)
        envs = self.envs
        for _ in range(cfg.rollout_decisions):
            states = torch.as_tensor(envs.obs, dtype=torch.float32)
            noise = torch.randn((envs.num_envs, *agent.chunk_shape), generator=self.generator)
            with torch.no_grad():
                _, actions = self.selector.candidate_chunks(
                    agent.policy, agent.policy.policy_state(states), noise, agent.num_steps
                )
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
        return {"episodes": self.episodes, "outcome_loss": float(np.mean(losses)) if losses else None, "labels": self.replay.size}

    def _label(self, envs: ChunkVectorEnv, states: torch.Tensor, actions: np.ndarray) -> None:
        rows = self.rng.permutation(envs.num_envs)[: self.cfg.label_envs]
        k = self.selector.choices
        ends = np.concatenate([envs.lookahead(int(i), actions[i]).next_obs for i in rows])
        self.replay.add(
            enc=states[rows].repeat_interleave(k, dim=0),
            x0=torch.as_tensor(actions[rows]).flatten(0, 1),
            end=torch.as_tensor(ends, dtype=torch.float32),
        )

    def _update(self) -> float:
        batch = self.replay.sample(self.cfg.batch_size, self.generator)
        loss = self.selector.model.loss(batch["enc"], batch["x0"].reshape(-1, *self.agent.chunk_shape), batch["end"])
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return float(loss.detach())

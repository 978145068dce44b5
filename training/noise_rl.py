"""The noise-space learners behind `training.finetune`: the agent (a flow with fresh steering or selector) and one adapter per algorithm.

Each adapter's `iterate(envs, finished_max, finished_success)` plays some decisions in the chunk-level
envs, learns from them, appends the results of episodes that ended, and returns figures for the log.
"""

from __future__ import annotations

import numpy as np
import torch

from training.chunk_env import ChunkVectorEnv
from training.finetune_config import IMITATION_FLOW, FinetuneConfig
from training.ppo import Critic, Rollout, ppo_update

__all__ = ["ALGORITHMS", "NoiseAgent", "Resumable"]


class Resumable:
    """What a resumable checkpoint of an adapter holds: its modules, optimizers and replays, by name."""

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


class NoiseAgent:
    """The flow with fresh steering, as both algorithms see it: observations in, start noises and actions out."""

    def __init__(self, base: torch.nn.Module, base_card: dict, cfg: FinetuneConfig) -> None:
        from training.policies import ActingPolicy, build_policy

        arch = base_card["architecture"]
        learned = [key for key in ("steering_dims", "selector_dims", "outcome_dims") if arch.get(key) is not None]
        # An outcome chooser may start another outcome fit (its model warm, its stretches and candidates as configured).
        warm = cfg.algo == "outcome" and learned == ["outcome_dims"]
        if learned and not warm:
            raise ValueError(f"{cfg.init}: this flow was fine-tuned already ({learned[0]} in its architecture); fine-tune a plain flow "
                             f"(--init {IMITATION_FLOW} is the one inside the outcome chooser)")
        if warm and list(arch["outcome_dims"]) != cfg.outcome_dims_list():
            raise ValueError(f"{cfg.init}: its outcome chooser has outcome_dims {arch['outcome_dims']}; --outcome-dims must match to start from it")
        if cfg.algo == "qselect":
            added = {"selector_dims": cfg.critic_dims_list(), "selector_candidates": cfg.candidates}
        elif cfg.algo == "outcome":
            added = {"outcome_dims": cfg.outcome_dims_list(), "outcome_candidates": cfg.candidates, "outcome_stretches": cfg.stretches_list()}
        else:
            added = {"steering_dims": cfg.steering_dims_list()}
        self.policy = build_policy("flow", **{**base_card["architecture"], **added})
        # the candidate maps follow from the candidate count (a fixed seed), so a warm start takes them as configured
        missing, unexpected = self.policy.load_state_dict({k: v for k, v in base.state_dict().items() if k != "outcome.rotations"}, strict=False)
        self.policy.normalizer.set(base.normalizer)
        if unexpected or any(not k.startswith(("steering.", "selector.", "outcome.")) for k in missing):
            raise ValueError(f"{cfg.init}: weights do not carry over (missing {missing[:3]}, unexpected {unexpected[:3]})")
        # The flow stays frozen because only the steering is optimized: no loss reaches the flow (rollouts
        # run without grad), and leaving requires_grad alone keeps the card's parameter count whole.
        self.policy.eval()
        self.normalization = self.policy.normalizer.to_dict()
        self.num_steps = cfg.flow_num_steps
        self.acting = ActingPolicy(self.policy, num_steps=cfg.flow_num_steps)
        self.steering = self.policy.steering
        self.noise_scale = self.policy.noise_scale
        self.chunk_shape = (self.policy.horizon, self.policy.action_dim)
        self.encoded_dim = self.policy.encode_state(torch.zeros(1, self.policy.state_dim)).shape[1]

    @torch.no_grad()
    def encode(self, state: torch.Tensor) -> torch.Tensor:
        """The policy's view [N, S'] of env-unit states [N, 5]: normalized, the angle as sin and cos."""
        return self.policy.encode_state(self.policy.normalizer.state(state))

    @torch.no_grad()
    def observe(self, envs: ChunkVectorEnv) -> tuple[torch.Tensor, torch.Tensor]:
        """The encoded states [N, S'] and clocks [N] of the envs."""
        encoded = self.encode(torch.as_tensor(envs.obs, dtype=torch.float32))
        return encoded, torch.as_tensor(envs.time_fraction(), dtype=torch.float32)

    @torch.no_grad()
    def act(self, envs: ChunkVectorEnv, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, np.ndarray]:
        """Encoded states, clocks, sampled starts x0 [N, H, A] and their env-unit chunks [N, H, A]."""
        encoded, clock = self.observe(envs)
        noise = torch.randn((envs.num_envs, *self.chunk_shape), generator=generator)
        x0 = self.steering(encoded, noise, self.noise_scale)
        return encoded, clock, x0, self.chunks(envs, x0)

    @torch.no_grad()
    def chunks(self, envs: ChunkVectorEnv, x0: torch.Tensor) -> np.ndarray:
        """The env-unit chunks [N, H, A] the flow integrates from starts x0 in the envs' states."""
        return self.policy.act_from_start(torch.as_tensor(envs.obs, dtype=torch.float32), x0, self.num_steps).numpy()


def _chunk_reward(result, cfg: FinetuneConfig) -> torch.Tensor:
    """The change of the env's reward (a potential) plus the success bonus, per env."""
    return torch.as_tensor(result.reward_end - result.reward_start + cfg.success_bonus * result.success, dtype=torch.float32)


class _PPO(Resumable):
    """On-policy: `rollout_decisions` chunks in every env, then clipped-surrogate epochs."""

    def __init__(self, agent: NoiseAgent, cfg: FinetuneConfig, generator: torch.Generator) -> None:
        self.agent, self.cfg, self.generator = agent, cfg, generator
        self.critic = Critic(agent.encoded_dim, cfg.critic_dims_list())
        self.actor_opt = torch.optim.Adam(agent.steering.parameters(), lr=cfg.lr)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr)

    def parts(self) -> tuple[dict, dict, dict]:
        """(modules, optimizers, replays) by name."""
        return ({"steering": self.agent.steering, "critic": self.critic},
                {"actor": self.actor_opt, "critic": self.critic_opt}, {})

    def iterate(self, envs: ChunkVectorEnv, finished_max: list, finished_success: list) -> dict:
        """One rollout and update; returns figures for the log."""
        agent = self.agent
        out = {k: [] for k in ("encoded", "time_fraction", "x0", "log_prob", "value", "reward", "done")}
        with torch.no_grad():
            for _ in range(self.cfg.rollout_decisions):
                encoded, clock, x0, actions = agent.act(envs, self.generator)
                log_prob, _ = agent.steering.log_prob(encoded, x0, agent.noise_scale)
                result = envs.step(actions)
                finished_max.extend(result.finished_max_reward)
                finished_success.extend(result.finished_success)
                for key, value in (("encoded", encoded), ("time_fraction", clock), ("x0", x0), ("log_prob", log_prob),
                                   ("value", self.critic(encoded, clock)), ("reward", _chunk_reward(result, self.cfg)),
                                   ("done", torch.as_tensor(result.done, dtype=torch.float32))):
                    out[key].append(value)
            last_value = self.critic(*agent.observe(envs))
        rollout = Rollout(**{k: torch.stack(v) for k, v in out.items()}, last_value=last_value)
        return ppo_update(agent.steering, self.critic, self.actor_opt, self.critic_opt, rollout, agent.noise_scale,
                          self.cfg.ppo_settings(), self.generator)


class _QSelect(Resumable):
    """Approximate policy iteration in the noise space; acting picks the best of K candidate starts by Q.

    V(state, clock) regresses the Monte Carlo returns of recent episodes; Q(state, x0) regresses
    r + gamma V(next state), a target that, the env being deterministic, hardly varies for a given
    state and start, unlike the return itself. With `label_candidates`, some visited states also get
    that target for fresh candidate starts, each simulated one chunk ahead from the state (training
    only: the served policy never simulates), so Q sees side by side what each start would do.
    Episodes are played with the current selection (plain flow sampling until `learning_starts`).
    """

    FIELDS = {"enc": 0, "clock": 1, "x0": 0, "reward": 1, "done": 1, "next_enc": 0, "next_clock": 1}

    def __init__(self, agent: NoiseAgent, cfg: FinetuneConfig, generator: torch.Generator) -> None:
        from training.replay import ReplayBuffer

        self.agent, self.cfg, self.generator = agent, cfg, generator
        self.selector = agent.policy.selector
        self.value = Critic(agent.encoded_dim, cfg.critic_dims_list())
        self.opt = torch.optim.Adam([*self.selector.q.parameters(), *self.value.parameters()], lr=cfg.critic_lr)
        noise_dim = agent.chunk_shape[0] * agent.chunk_shape[1]
        self.played = ReplayBuffer(cfg.buffer_size, agent.encoded_dim, noise_dim, {**self.FIELDS, "ret": 1})
        self.labels = ReplayBuffer(cfg.buffer_size, agent.encoded_dim, noise_dim, self.FIELDS) if cfg.label_candidates else None
        self.pending: list[list[dict[str, torch.Tensor]]] = [[] for _ in range(cfg.num_envs)]

    def parts(self) -> tuple[dict, dict, dict]:
        """(modules, optimizers, replays) by name."""
        replays = {"played": self.played, **({"labels": self.labels} if self.labels is not None else {})}
        return {"selector": self.selector, "value": self.value}, {"critics": self.opt}, replays

    @property
    def selecting(self) -> bool:
        """Whether Q has seen enough transitions to choose."""
        return self.played.size >= self.cfg.learning_starts

    def iterate(self, envs: ChunkVectorEnv, finished_max: list, finished_success: list) -> dict:
        """`rollout_decisions` decisions in every env, each followed by the updates; returns figures for the log."""
        agent, losses = self.agent, []
        for _ in range(self.cfg.rollout_decisions):
            encoded, clock = agent.observe(envs)
            if self.labels is not None:
                self._label(envs, encoded, clock)
            noise = torch.randn((envs.num_envs, *agent.chunk_shape), generator=self.generator)
            with torch.no_grad():
                x0 = self.selector(encoded, noise, agent.noise_scale) if self.selecting else agent.noise_scale * noise
            result = envs.step(agent.chunks(envs, x0))
            finished_max.extend(result.finished_max_reward)
            finished_success.extend(result.finished_success)
            reward = _chunk_reward(result, self.cfg)
            next_encoded, next_clock = agent.observe(envs)  # an ended env restarted: done cuts its bootstrap
            for i in range(envs.num_envs):
                self.pending[i].append({"enc": encoded[i], "clock": clock[i], "x0": x0[i], "reward": reward[i],
                                        "done": torch.tensor(float(result.done[i])), "next_enc": next_encoded[i], "next_clock": next_clock[i]})
                if result.done[i]:
                    self._store(self.pending[i])
                    self.pending[i] = []
            if self.played.size >= self.cfg.batch_size:
                for _ in range(self.cfg.updates_per_decision):
                    losses.append(self._update())
        q_loss, v_loss = np.mean(losses, axis=0) if losses else (None, None)
        return {"q_loss": q_loss and float(q_loss), "v_loss": v_loss and float(v_loss), "selecting": self.selecting,
                "replay": self.played.size, "labels": self.labels.size if self.labels is not None else 0}

    def _label(self, envs: ChunkVectorEnv, encoded: torch.Tensor, clock: torch.Tensor) -> None:
        agent, k = self.agent, self.cfg.label_candidates
        rows = torch.randperm(envs.num_envs, generator=self.generator)[: self.cfg.label_envs]
        m = len(rows)
        starts = agent.noise_scale * torch.randn((m * k, *agent.chunk_shape), generator=self.generator)
        states = torch.as_tensor(envs.obs[rows.numpy()], dtype=torch.float32).repeat_interleave(k, dim=0)
        with torch.no_grad():
            chunks = agent.policy.act_from_start(states, starts, agent.num_steps).numpy().reshape(m, k, *agent.chunk_shape)
        steps = [envs.lookahead(int(i), chunks[j]) for j, i in enumerate(rows)]
        next_obs = np.concatenate([s.next_obs for s in steps])
        next_enc = agent.encode(torch.as_tensor(next_obs, dtype=torch.float32))
        self.labels.add(enc=encoded[rows].repeat_interleave(k, dim=0), clock=clock[rows].repeat_interleave(k), x0=starts,
                        reward=torch.cat([_chunk_reward(s, self.cfg) for s in steps]),
                        done=torch.as_tensor(np.concatenate([s.done for s in steps]), dtype=torch.float32),
                        next_enc=next_enc, next_clock=torch.as_tensor(np.concatenate([s.next_time_fraction for s in steps]), dtype=torch.float32))

    def _store(self, episode: list[dict[str, torch.Tensor]]) -> None:
        running = 0.0
        for step in reversed(episode):
            running = float(step["reward"]) + self.cfg.gamma * running
            step["ret"] = torch.tensor(running)
        batch = {k: torch.stack([step[k] for step in episode]) for k in (*self.FIELDS, "ret")}
        self.played.add(**batch)
        if self.labels is not None:
            self.labels.add(**{k: batch[k] for k in self.FIELDS})

    def _update(self) -> tuple[float, float]:
        played = self.played.sample(self.cfg.batch_size, self.generator)
        v_loss = 0.5 * (self.value(played["enc"], played["clock"][:, 0]) - played["ret"][:, 0]).pow(2).mean()
        b = self.labels.sample(self.cfg.batch_size, self.generator) if self.labels is not None else played
        with torch.no_grad():
            target = b["reward"][:, 0] + self.cfg.gamma * (1 - b["done"][:, 0]) * self.value(b["next_enc"], b["next_clock"][:, 0])
        q_loss = 0.5 * (self.selector.value(b["enc"], b["x0"].reshape(-1, *self.agent.chunk_shape)) - target).pow(2).mean()
        self.opt.zero_grad(set_to_none=True)
        (q_loss + v_loss).backward()
        self.opt.step()
        return float(q_loss.detach()), float(v_loss.detach())


ALGORITHMS = {"ppo": _PPO, "qselect": _QSelect}

"""Fine-tune beyond imitation: PPO in a frozen flow's noise space (DSRL), on the env's reward.

    python -m training.finetune --init models/flow --name flow-dsrl

A steering network (`training.steering`) picks the flow's start noise from the state; the flow's
weights never change. One decision is one 12-action chunk executed open loop in `num_envs` envs
(`training.chunk_env`), on training seeds disjoint from every evaluation and held-out range. Reward
of a chunk: the change of the env's reward (coverage / 0.95, a potential, so the optimum is that of
the success reward alone) plus `success_bonus` when the block lands; the episode then ends, so
finishing early pays. Periodic evaluation uses `training.evaluate` on seeds 400000.. (never held out).
Each checkpoint is a flow checkpoint with `steering_dims` in its architecture: export, ship, the
service and the client take it as they take any flow.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from training.chunk_env import ChunkVectorEnv
from training.finetune_config import FinetuneConfig, parse_config
from training.ppo import Critic, Rollout, ppo_update

__all__ = ["finetune", "main"]


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    cfg = parse_config(argv)
    try:
        finetune(cfg)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def finetune(cfg: FinetuneConfig) -> Path:
    """Run one fine-tuning as configured; returns the run folder."""
    from training.checkpoint import git_commit, load_checkpoint, save_checkpoint
    from training.evaluate import evaluate_policy

    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    base, base_card = load_checkpoint(cfg.init)
    if base_card["kind"] != "flow":
        raise ValueError(f"{cfg.init} is a {base_card['kind']} checkpoint; noise-space fine-tuning needs a flow")
    agent = _Steered(base, base_card, cfg)
    generator = torch.Generator().manual_seed(cfg.seed)
    algorithm = {"ppo": _PPO, "sac": _SAC, "qselect": _QSelect}[cfg.algo](agent, cfg, generator)

    run_dir = Path(cfg.out_dir) / cfg.name
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")
    print(f"config: {json.dumps(cfg.to_dict())}", file=sys.stderr)
    log = _Log(run_dir)
    card = {"name": "flow", "config": cfg.to_dict(), "git_commit": git_commit(), "init": str(cfg.init)}
    envs = ChunkVectorEnv(cfg.num_envs, cfg.train_seed_start)
    start = time.perf_counter()
    bar = _progress_bar(cfg.iterations, cfg.progress)

    def evaluate(iteration: int) -> dict:
        summary = evaluate_policy(agent.acting, "flow", episodes=cfg.eval_episodes, seed=cfg.eval_seed, num_steps=cfg.flow_num_steps)
        record = {"type": "eval", "step": iteration, "mean_max_reward": summary.mean_max_reward,
                  "mean_max_reward_ci95": list(summary.mean_max_reward_ci95), "success_rate": summary.success_rate,
                  "success_rate_ci95": list(summary.success_rate_ci95), "seeds": [summary.seeds[0], summary.seeds[-1]],
                  "episodes": len(summary.episodes)}
        log.write(record)
        return record

    def checkpoint(iteration: int, evaluation: dict | None) -> None:
        save_checkpoint(str(run_dir / "last"), agent.policy, agent.normalization, **card, steps=iteration,
                        wall_time_s=time.perf_counter() - start, evaluation=evaluation, finished=iteration == cfg.iterations)

    last_eval = evaluate(0) if cfg.eval_every > 0 else None
    finished_max: list[float] = []
    finished_success: list[bool] = []
    for iteration in range(1, cfg.iterations + 1):
        stats = algorithm.iterate(envs, finished_max, finished_success)
        if iteration % cfg.log_every == 0 or iteration == cfg.iterations:
            record = {"type": "train", "step": iteration, "decisions": iteration * cfg.num_envs * cfg.rollout_decisions,
                      "episodes": envs.episodes_started,
                      "episode_max_reward": float(np.mean(finished_max)) if finished_max else None,
                      "episode_success": float(np.mean(finished_success)) if finished_success else None,
                      "wall_time_s": time.perf_counter() - start, **stats}
            if agent.steering is not None:
                record["std"] = float(agent.steering.std().mean().detach())
            log.write(record)
            finished_max.clear()
            finished_success.clear()
            bar.set_postfix(success=record["episode_success"])
        if cfg.eval_every > 0 and (iteration % cfg.eval_every == 0 or iteration == cfg.iterations):
            last_eval = evaluate(iteration)
            checkpoint(iteration, last_eval)
            log.plot()
        bar.update(1)
    bar.close()
    checkpoint(cfg.iterations, last_eval)
    log.plot()
    print(f"run dir: {run_dir}", file=sys.stderr)
    return run_dir


class _Steered:
    """The flow with fresh steering, as both algorithms see it: observations in, start noises and actions out."""

    def __init__(self, base: torch.nn.Module, base_card: dict, cfg: FinetuneConfig) -> None:
        from training.policies import ActingPolicy, build_policy

        if cfg.algo == "qselect":
            added = {"selector_dims": cfg.critic_dims_list(), "selector_candidates": cfg.candidates}
        else:
            added = {"steering_dims": cfg.steering_dims_list()}
        self.policy = build_policy("flow", **{**base_card["architecture"], **added})
        missing, unexpected = self.policy.load_state_dict(base.state_dict(), strict=False)
        if unexpected or any(not k.startswith(("steering.", "selector.")) for k in missing):
            raise ValueError(f"{cfg.init}: weights do not carry over (missing {missing[:3]}, unexpected {unexpected[:3]})")
        # The flow stays frozen because only the steering is optimized: no loss reaches the flow (rollouts
        # run without grad), and leaving requires_grad alone keeps the card's parameter count whole.
        self.policy.eval()
        self.normalization = base_card["normalization"]
        self.acting = ActingPolicy(self.policy, num_steps=cfg.flow_num_steps, **self.normalization)
        self.steering = self.policy.steering
        self.noise_scale = self.policy.noise_scale
        self.chunk_shape = (self.policy.horizon, self.policy.action_dim)
        self.encoded_dim = self.policy.encode_state(torch.zeros(1, self.policy.state_dim)).shape[1]

    @torch.no_grad()
    def observe(self, envs: ChunkVectorEnv) -> tuple[torch.Tensor, torch.Tensor]:
        """The encoded states [N, S'] and clocks [N] of the envs."""
        state = torch.as_tensor(envs.obs, dtype=torch.float32)
        encoded = self.policy.encode_state((state - self.acting.state_mean) / self.acting.state_std)
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
        return self.acting.from_start(torch.as_tensor(envs.obs, dtype=torch.float32), x0).numpy()


def _chunk_reward(result, cfg: FinetuneConfig) -> torch.Tensor:
    """The change of the env's reward (a potential) plus the success bonus, per env."""
    return torch.as_tensor(result.reward_end - result.reward_start + cfg.success_bonus * result.success, dtype=torch.float32)


class _PPO:
    """On-policy: `rollout_decisions` chunks in every env, then clipped-surrogate epochs."""

    def __init__(self, agent: _Steered, cfg: FinetuneConfig, generator: torch.Generator) -> None:
        self.agent, self.cfg, self.generator = agent, cfg, generator
        self.critic = Critic(agent.encoded_dim, cfg.critic_dims_list())
        self.actor_opt = torch.optim.Adam(agent.steering.parameters(), lr=cfg.lr)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr)

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


class _SAC:
    """Off-policy: each decision of every env goes to a replay; `updates_per_decision` updates follow each one."""

    def __init__(self, agent: _Steered, cfg: FinetuneConfig, generator: torch.Generator) -> None:
        from training.sac import ReplayBuffer, SACLearner

        self.agent, self.cfg, self.generator = agent, cfg, generator
        self.learner = SACLearner(agent.steering, agent.encoded_dim, agent.noise_scale, cfg.sac_settings(agent.chunk_shape),
                                  cfg.critic_dims_list())
        self.replay = ReplayBuffer(cfg.buffer_size, agent.encoded_dim, agent.chunk_shape[0] * agent.chunk_shape[1])

    def iterate(self, envs: ChunkVectorEnv, finished_max: list, finished_success: list) -> dict:
        """`rollout_decisions` decisions, each followed by its updates; returns the last update's figures."""
        stats: dict = {}
        for _ in range(self.cfg.rollout_decisions):
            encoded, clock, x0, actions = self.agent.act(envs, self.generator)
            result = envs.step(actions)
            finished_max.extend(result.finished_max_reward)
            finished_success.extend(result.finished_success)
            # an env that ended restarted at once: its next state is a fresh episode's, but done cuts the bootstrap
            next_encoded, next_clock = self.agent.observe(envs)
            self.replay.add(enc=encoded, clock=clock, x0=x0, reward=_chunk_reward(result, self.cfg),
                            done=torch.as_tensor(result.done, dtype=torch.float32), next_enc=next_encoded, next_clock=next_clock)
            if self.replay.size < self.cfg.batch_size:
                continue
            for _ in range(self.cfg.updates_per_decision):
                batch = self.replay.sample(self.cfg.batch_size, self.generator)
                stats = self.learner.update(batch, update_actor=self.replay.size >= self.cfg.learning_starts, generator=self.generator)
        return stats


class _QSelect:
    """Approximate policy iteration in the noise space; acting picks the best of K candidate starts by Q.

    V(state, clock) regresses the Monte Carlo returns of recent episodes; Q(state, x0) regresses
    r + gamma V(next state), a target that, the env being deterministic, hardly varies for a given
    state and start, unlike the return itself. Episodes are played with the current selection (plain
    flow sampling until `learning_starts` transitions are in).
    """

    FIELDS = {"enc": 0, "clock": 1, "x0": 0, "reward": 1, "done": 1, "next_enc": 0, "next_clock": 1, "ret": 1}

    def __init__(self, agent: _Steered, cfg: FinetuneConfig, generator: torch.Generator) -> None:
        from training.sac import ReplayBuffer

        self.agent, self.cfg, self.generator = agent, cfg, generator
        self.selector = agent.policy.selector
        self.value = Critic(agent.encoded_dim, cfg.critic_dims_list())
        self.opt = torch.optim.Adam([*self.selector.q.parameters(), *self.value.parameters()], lr=cfg.critic_lr)
        self.replay = ReplayBuffer(cfg.buffer_size, agent.encoded_dim, agent.chunk_shape[0] * agent.chunk_shape[1], self.FIELDS)
        self.pending: list[list[dict[str, torch.Tensor]]] = [[] for _ in range(cfg.num_envs)]

    @property
    def selecting(self) -> bool:
        """Whether Q has seen enough transitions to choose."""
        return self.replay.size >= self.cfg.learning_starts

    def iterate(self, envs: ChunkVectorEnv, finished_max: list, finished_success: list) -> dict:
        """`rollout_decisions` decisions in every env, each followed by the updates; returns figures for the log."""
        agent, losses = self.agent, []
        for _ in range(self.cfg.rollout_decisions):
            encoded, clock = agent.observe(envs)
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
            if self.replay.size >= self.cfg.batch_size:
                for _ in range(self.cfg.updates_per_decision):
                    losses.append(self._update())
        q_loss, v_loss = np.mean(losses, axis=0) if losses else (None, None)
        return {"q_loss": q_loss and float(q_loss), "v_loss": v_loss and float(v_loss), "selecting": self.selecting, "replay": self.replay.size}

    def _store(self, episode: list[dict[str, torch.Tensor]]) -> None:
        running = 0.0
        for step in reversed(episode):
            running = float(step["reward"]) + self.cfg.gamma * running
            step["ret"] = torch.tensor(running)
        self.replay.add(**{k: torch.stack([step[k] for step in episode]) for k in self.FIELDS})

    def _update(self) -> tuple[float, float]:
        b = self.replay.sample(self.cfg.batch_size, self.generator)
        v_loss = 0.5 * (self.value(b["enc"], b["clock"][:, 0]) - b["ret"][:, 0]).pow(2).mean()
        with torch.no_grad():
            target = b["reward"][:, 0] + self.cfg.gamma * (1 - b["done"][:, 0]) * self.value(b["next_enc"], b["next_clock"][:, 0])
        q_loss = 0.5 * (self.selector.value(b["enc"], b["x0"].reshape(-1, *self.agent.chunk_shape)) - target).pow(2).mean()
        self.opt.zero_grad(set_to_none=True)
        (q_loss + v_loss).backward()
        self.opt.step()
        return float(q_loss.detach()), float(v_loss.detach())


class _Log:
    """log.jsonl and learning_curve.png of a fine-tuning run."""

    def __init__(self, run_dir: Path) -> None:
        self.path = run_dir / "log.jsonl"
        self.path.write_text("")
        self.records: list[dict] = []

    def write(self, record: dict) -> None:
        self.records.append(record)
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")

    def plot(self) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        train = [r for r in self.records if r["type"] == "train" and r["episode_success"] is not None]
        evals = [r for r in self.records if r["type"] == "eval"]
        fig, ax = plt.subplots(figsize=(7, 4))
        ax.plot([r["step"] for r in train], [r["episode_success"] for r in train], lw=1, alpha=0.6, label="training episodes: success")
        if evals:
            steps = [r["step"] for r in evals]
            ax.plot(steps, [r["success_rate"] for r in evals], "s-", label="evaluation: success")
            ax.fill_between(steps, [r["success_rate_ci95"][0] for r in evals], [r["success_rate_ci95"][1] for r in evals], alpha=0.2)
            ax.plot(steps, [r["mean_max_reward"] for r in evals], "o-", label="evaluation: mean max reward")
            first, last = evals[0]["seeds"]
            ax.set_title(f"noise-space PPO (evaluation: {evals[0]['episodes']} episodes, seeds {first}..{last})")
        ax.set(xlabel="PPO iteration", ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right")
        fig.tight_layout()
        fig.savefig(self.path.with_name("learning_curve.png"), dpi=100)
        plt.close(fig)


def _progress_bar(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc="finetune", unit="it", disable=not enabled, file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())

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
    from training.policies import ActingPolicy, build_policy

    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    base, base_card = load_checkpoint(cfg.init)
    if base_card["kind"] != "flow":
        raise ValueError(f"{cfg.init} is a {base_card['kind']} checkpoint; noise-space fine-tuning needs a flow")
    architecture = {**base_card["architecture"], "steering_dims": cfg.steering_dims_list()}
    policy = build_policy("flow", **architecture)
    missing, unexpected = policy.load_state_dict(base.state_dict(), strict=False)
    if unexpected or any(not k.startswith("steering.") for k in missing):
        raise ValueError(f"{cfg.init}: weights do not carry over (missing {missing[:3]}, unexpected {unexpected[:3]})")
    # The flow stays frozen because only the steering is optimized: PPO's loss never reaches the flow
    # (rollouts run without grad), and leaving requires_grad alone keeps the card's parameter count whole.
    policy.eval()  # the frozen flow has no dropout at acting time; steering has none
    normalization = base_card["normalization"]
    acting = ActingPolicy(policy, num_steps=cfg.flow_num_steps, **normalization)
    steering = policy.steering
    noise_scale = policy.noise_scale
    encoded_dim = policy.encode_state(torch.zeros(1, policy.state_dim)).shape[1]
    critic = Critic(encoded_dim, cfg.critic_dims_list())
    actor_opt = torch.optim.Adam(steering.parameters(), lr=cfg.lr)
    critic_opt = torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr)

    run_dir = Path(cfg.out_dir) / cfg.name
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")
    print(f"config: {json.dumps(cfg.to_dict())}", file=sys.stderr)
    log = _Log(run_dir)
    card = {"name": "flow", "config": cfg.to_dict(), "git_commit": git_commit(), "init": str(cfg.init)}

    envs = ChunkVectorEnv(cfg.num_envs, cfg.train_seed_start)
    state_mean = torch.tensor(normalization["state_mean"], dtype=torch.float32)
    state_std = acting.state_std
    generator = torch.Generator().manual_seed(cfg.seed)
    recent_max, recent_success = [], []
    start = time.perf_counter()
    bar = _progress_bar(cfg.iterations, cfg.progress)

    def evaluate(iteration: int) -> dict:
        summary = evaluate_policy(acting, "flow", episodes=cfg.eval_episodes, seed=cfg.eval_seed, num_steps=cfg.flow_num_steps)
        record = {"type": "eval", "step": iteration, "mean_max_reward": summary.mean_max_reward,
                  "mean_max_reward_ci95": list(summary.mean_max_reward_ci95), "success_rate": summary.success_rate,
                  "success_rate_ci95": list(summary.success_rate_ci95), "seeds": [summary.seeds[0], summary.seeds[-1]],
                  "episodes": len(summary.episodes)}
        log.write(record)
        return record

    last_eval = evaluate(0) if cfg.eval_every > 0 else None
    for iteration in range(1, cfg.iterations + 1):
        rollout = _collect(envs, policy, acting, critic, state_mean, state_std, noise_scale, cfg, generator, recent_max, recent_success)
        stats = ppo_update(steering, critic, actor_opt, critic_opt, rollout, noise_scale, cfg.ppo_settings(), generator)
        if iteration % cfg.log_every == 0 or iteration == cfg.iterations:
            record = {"type": "train", "step": iteration, "decisions": iteration * cfg.num_envs * cfg.rollout_decisions,
                      "episodes": envs.episodes_started, "return": float(rollout.reward.sum() / max(1.0, float(rollout.done.sum()))),
                      "episode_max_reward": float(np.mean(recent_max)) if recent_max else None,
                      "episode_success": float(np.mean(recent_success)) if recent_success else None,
                      "std": float(steering.std().mean().detach()), "wall_time_s": time.perf_counter() - start, **stats}
            log.write(record)
            recent_max.clear()
            recent_success.clear()
            bar.set_postfix(success=record["episode_success"], std=round(record["std"], 3))
        if cfg.eval_every > 0 and (iteration % cfg.eval_every == 0 or iteration == cfg.iterations):
            last_eval = evaluate(iteration)
            save_checkpoint(str(run_dir / "last"), policy, normalization, **card, steps=iteration,
                            wall_time_s=time.perf_counter() - start, evaluation=last_eval, finished=iteration == cfg.iterations)
            log.plot()
        bar.update(1)
    bar.close()
    save_checkpoint(str(run_dir / "last"), policy, normalization, **card, steps=cfg.iterations,
                    wall_time_s=time.perf_counter() - start, evaluation=last_eval, finished=True)
    log.plot()
    print(f"run dir: {run_dir}", file=sys.stderr)
    return run_dir


@torch.no_grad()
def _collect(envs, policy, acting, critic, state_mean, state_std, noise_scale, cfg, generator, recent_max, recent_success) -> Rollout:
    """`rollout_decisions` chunks in every env with the current steering; returns the time-major rollout."""
    steps, n = cfg.rollout_decisions, envs.num_envs
    horizon, action_dim = policy.horizon, policy.action_dim
    out = {k: [] for k in ("encoded", "time_fraction", "x0", "log_prob", "value", "reward", "done")}
    for _ in range(steps):
        state = torch.as_tensor(envs.obs, dtype=torch.float32)
        encoded = policy.encode_state((state - state_mean) / state_std)
        clock = torch.as_tensor(envs.time_fraction(), dtype=torch.float32)
        noise = torch.randn((n, horizon, action_dim), generator=generator)
        x0 = policy.steering(encoded, noise, noise_scale)
        log_prob, _ = policy.steering.log_prob(encoded, x0, noise_scale)
        actions = acting(state, noise).numpy()  # the same x0: acting steers the same noise the same way
        result = envs.step(actions)
        reward = result.reward_end - result.reward_start + cfg.success_bonus * result.success
        recent_max.extend(result.finished_max_reward)
        recent_success.extend(result.finished_success)
        for key, value in (("encoded", encoded), ("time_fraction", clock), ("x0", x0), ("log_prob", log_prob),
                           ("value", critic(encoded, clock)), ("reward", torch.as_tensor(reward, dtype=torch.float32)),
                           ("done", torch.as_tensor(result.done, dtype=torch.float32))):
            out[key].append(value)
    state = torch.as_tensor(envs.obs, dtype=torch.float32)
    encoded = policy.encode_state((state - state_mean) / state_std)
    last_value = critic(encoded, torch.as_tensor(envs.time_fraction(), dtype=torch.float32))
    return Rollout(**{k: torch.stack(v) for k, v in out.items()}, last_value=last_value)


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

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
from training.noise_rl import ALGORITHMS, NoiseAgent

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
    agent = NoiseAgent(base, base_card, cfg)
    generator = torch.Generator().manual_seed(cfg.seed)
    algorithm = ALGORITHMS[cfg.algo](agent, cfg, generator)

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

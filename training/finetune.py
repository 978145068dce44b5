"""Fine-tune beyond imitation: an outcome chooser among a frozen flow's chunks, or a plain flow's own weights (dagger, ppo).

    python -m training.finetune --init runs/recipes/imitation-KEY/last --name flow-outcome --iterations 160 ...
    (the recipe stage `run = "finetune"` runs this: recipes/flow-chooser.toml)

`training.outcome_fit` fits a one-chunk model of the block on simulated lookaheads of the flow's own
candidate chunks (each also at `--stretches`, faster); the served flow then plays the candidate it
predicts closest to the goal. `--init` may be such a chooser, whose model the fit goes on fitting; with
`--algo value` (`training.value_fit`) the chooser's value of time is fitted on its own episodes, and the
chooser then plays the candidate whose predicted end state it values most. The flow's weights never change, except
in `--algo dagger` (`training.dagger_fit`), which teaches a copy of them (or the plain flow `--init`, when
`--dagger-teacher` names the chooser) the chooser's picks, and in `--algo ppo` (`training.ppo_fit`), which fine-tunes
the plain flow `--init` in the env on a return that rewards finishing early. One decision is one 12-action chunk
executed open loop in `num_envs` envs (`training.chunk_env`, `pusht.rollout`), on training seeds disjoint from every
evaluation and held-out range. Periodic evaluation uses `training.evaluate` on seeds 400000.. (never held out). Each
checkpoint is a flow checkpoint, with `outcome_dims` in its architecture but for the plain flows of dagger and ppo:
export, ship, the service and the client take it as they take any flow (one fitted for other than 10 Euler steps
records them as its `sampler_steps`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from policies.checkpoint import git_commit, load_checkpoint, require_state_only, save_checkpoint
from pusht.spec import DEFAULT_NUM_STEPS
from training.dagger_fit import DaggerFit
from training.evaluate import evaluate_policy
from training.finetune_config import RESUMABLE_CHANGES, FinetuneConfig, parse_config
from training.outcome_fit import FlowChooser, OutcomeFit
from training.ppo_fit import PPOFit
from training.run import Run, RunError, RunStopped, pack_rng, unpack_rng
from training.value_fit import ValueFit

__all__ = ["finetune", "main"]


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: 0 when finished, 2 on a bad setting, 128 + N when stopped by signal N."""
    cfg = parse_config(argv)
    try:
        return finetune(cfg).exit_code()
    except (RunError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def finetune(cfg: FinetuneConfig):
    """Run (or resume) one fine-tuning as configured; returns its `training.run.Run` (folder in `.dir`)."""
    job = _FineTuning(cfg)
    iteration = job.first - 1
    try:
        for iteration in range(job.first, cfg.iterations + 1):
            job.iterate(iteration)
            if job.run.stop_requested:
                break
        else:
            job.finish()
    except RunStopped:
        job.save(iteration)
    finally:
        job.bar.close()
        job.run.close()
    if job.run.stop_requested:
        print(
            f"stopped by {job.run.stop_signal} after iteration {iteration} of {cfg.iterations}; continue with the same "
            f"command and --resume (state in {job.run.dir})",
            file=sys.stderr,
        )
    return job.run


class _FineTuning:
    """One fine-tuning's state: the chooser, its fit (`algorithm`, whose `trained` is saved and evaluated), the run
    folder."""

    def __init__(self, cfg: FinetuneConfig) -> None:
        self.cfg = cfg
        torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        stem = cfg.chooser_stem()
        base, base_card = load_checkpoint(stem)
        if base_card["kind"] != "flow":
            raise ValueError(f"{stem} is a {base_card['kind']} checkpoint; fine-tuning needs a flow")
        require_state_only(base_card, stem, "fine-tuning")
        self.agent = FlowChooser(base, base_card, cfg)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        learner = {"outcome": OutcomeFit, "value": ValueFit, "dagger": DaggerFit, "ppo": PPOFit}[cfg.algo]
        self.algorithm = learner(self.agent, cfg, self.generator)
        self.run = Run.start(
            cfg.out_dir, cfg.name, cfg.to_dict(), resume=cfg.resume, overwrite=cfg.overwrite, may_change=RESUMABLE_CHANGES
        )
        self.card = {
            "name": "flow",
            "config": cfg.to_dict(),
            "git_commit": git_commit(),
            "init": str(cfg.init),
            **({"teacher": cfg.dagger_teacher} if cfg.dagger_teacher else {}),
            **({"sampler_steps": cfg.flow_num_steps} if cfg.flow_num_steps != DEFAULT_NUM_STEPS else {}),
            "reproduce": {"finetune": cfg.command()},
        }
        self.first = 1
        state = self.run.load_state()
        if state is not None:
            step, tensors, extra = state
            self.algorithm.load_state(tensors, extra)
            unpack_rng(tensors, {"main": self.generator})
            self.first = step + 1
            self.run.log({"type": "resume", "step": step})
        self.bar = _progress_bar(cfg.iterations, cfg.progress, self.first - 1)
        self.finished_max: list[float] = []
        self.finished_success: list[bool] = []
        if self.first == 1 and cfg.eval_every > 0:
            self.evaluate(0)

    def iterate(self, iteration: int) -> None:
        """One outcome-fit iteration, its log record, the periodic evaluation and resumable state."""
        cfg, run = self.cfg, self.run
        stats = self.algorithm.iterate(self.finished_max, self.finished_success)
        if iteration % cfg.log_every == 0 or iteration == cfg.iterations:
            record = {
                "type": "train",
                "step": iteration,
                "episode_max_reward": float(np.mean(self.finished_max)) if self.finished_max else None,
                "episode_success": float(np.mean(self.finished_success)) if self.finished_success else None,
                "wall_time_s": run.elapsed_s,
                **stats,
            }
            run.log(record)
            self.finished_max.clear()
            self.finished_success.clear()
            self.bar.set_postfix(success=record["episode_success"])
        self.bar.update(1)
        if cfg.eval_every > 0 and iteration % cfg.eval_every == 0 and iteration < cfg.iterations:
            with run.interruptible():  # a stop must not wait for a long evaluation
                self.evaluate(iteration)
        if run.stop_requested or (iteration < cfg.iterations and iteration % cfg.checkpoint_every == 0):
            self.save(iteration)

    def evaluate(self, iteration: int) -> dict:
        cfg = self.cfg
        summary = evaluate_policy(self.algorithm.trained.acting, episodes=cfg.eval_episodes, seed=cfg.eval_seed)
        record = {
            "type": "eval",
            "step": iteration,
            "mean_max_reward": summary.mean_max_reward,
            "mean_max_reward_ci95": list(summary.mean_max_reward_ci95),
            "success_rate": summary.success_rate,
            "success_rate_ci95": list(summary.success_rate_ci95),
            "mean_steps_to_success": summary.mean_steps_to_success,
            "seeds": [summary.seeds[0], summary.seeds[-1]],
            "episodes": len(summary.episodes),
        }
        self.run.log(record)
        return record

    def save(self, iteration: int, finished: bool = False) -> None:
        run = self.run
        evaluation = next((r for r in reversed(run.records) if r["type"] == "eval"), None)
        save_checkpoint(
            str(run.dir / "last"),
            self.algorithm.trained.policy,
            self.algorithm.trained.normalization,
            **self.card,
            steps=iteration,
            wall_time_s=run.elapsed_s,
            evaluation=evaluation,
            finished=finished,
        )
        if not finished:
            tensors, extra = self.algorithm.state()
            run.save_state(iteration, {**tensors, **pack_rng({"main": self.generator})}, extra)
        _plot(run.records, run.dir / "learning_curve.png")

    def finish(self) -> None:
        cfg = self.cfg
        if cfg.eval_every > 0:
            self.evaluate(cfg.iterations)
        self.save(cfg.iterations, finished=True)
        self.algorithm.save_outputs(self.run.dir)
        self.run.finish(cfg.iterations)
        print(f"done: {cfg.iterations} iterations in {self.run.elapsed_s:.0f} s; outputs in {self.run.dir}", file=sys.stderr)


def _plot(records: list[dict], path: Path) -> None:
    """The learning curve: training episodes' success and periodic evaluation with its interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    train = [r for r in records if r["type"] == "train" and r.get("episode_success") is not None]
    evals = [r for r in records if r["type"] == "eval"]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(
        [r["step"] for r in train], [r["episode_success"] for r in train], lw=1, alpha=0.6, label="training episodes: success"
    )
    if evals:
        steps = [r["step"] for r in evals]
        ax.plot(steps, [r["success_rate"] for r in evals], "s-", label="evaluation: success")
        ax.fill_between(steps, [r["success_rate_ci95"][0] for r in evals], [r["success_rate_ci95"][1] for r in evals], alpha=0.2)
        ax.plot(steps, [r["mean_max_reward"] for r in evals], "o-", label="evaluation: mean max reward")
        first, last = evals[0]["seeds"]
        ax.set_title(f"fine-tuning (evaluation: {evals[0]['episodes']} episodes, seeds {first}..{last})")
    ax.set(xlabel="iteration", ylim=(0, 1.02))
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _progress_bar(total: int, enabled: bool, done: int):
    from tqdm import tqdm

    return tqdm(total=total, initial=done, desc="finetune", unit="it", disable=not enabled, file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())

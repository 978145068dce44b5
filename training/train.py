"""Train an MSE or flow-matching behavioral-cloning policy on the Push-T demonstrations.

    python -m training.train --policy flow --name flow-200k
    torchrun --nproc_per_node=2 -m training.train --policy mse --threads 1

Outputs in OUT_DIR/NAME: config.json, log.jsonl (train and eval records), learning_curve.png and the
checkpoints `last` (the final weights) and `best` (best evaluation mean max reward), each a
safetensors file with its JSON card. Under torchrun (gloo), every rank trains on its own slice of
each global batch; only rank 0 logs, evaluates and saves.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from training.config import TrainConfig, parse_config


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: parse the config and train."""
    cfg = parse_config(argv)
    try:
        train(cfg)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def train(cfg: TrainConfig) -> Path:
    """Run one training as configured; returns the run folder."""
    from training.checkpoint import git_commit, load_checkpoint, save_checkpoint
    from training.data import Normalizer, load_replay
    from training.policies import ActingPolicy, build_policy

    ctx = _Distributed.start()
    try:
        if cfg.batch_size % ctx.world_size:
            raise ValueError(f"batch_size {cfg.batch_size} is not divisible by the {ctx.world_size} DDP ranks")
        torch.set_num_threads(cfg.threads or max(1, (os.cpu_count() or 1) // ctx.world_size))
        torch.manual_seed(cfg.seed + ctx.rank)
        np.random.seed(cfg.seed + ctx.rank)
        if not cfg.name:
            # every rank must agree on the folder, so only rank 0 picks the timestamp
            cfg.name = ctx.broadcast_str(f"{cfg.policy}-{datetime.now():%Y%m%d-%H%M%S}")
        run_dir = Path(cfg.out_dir) / cfg.name
        if ctx.is_main:
            if cfg.eval_every >= 0:
                from training.evaluate import env_factory

                env_factory(cfg.eval_env)()  # fail now, not after hours of training, if the env is missing
            run_dir.mkdir(parents=True, exist_ok=True)
            (run_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")
            print(f"config: {json.dumps(cfg.to_dict())}", file=sys.stderr)
            print(f"run dir: {run_dir}  world size: {ctx.world_size}  threads: {torch.get_num_threads()}", file=sys.stderr)

        replay = load_replay(cfg.data)
        if cfg.init:
            policy, init_card = load_checkpoint(cfg.init)
            if init_card["kind"] != cfg.policy:
                raise ValueError(f"{cfg.init} is a {init_card['kind']} checkpoint, not {cfg.policy}")
        else:
            policy = build_policy(cfg.policy, **{"dropout": cfg.dropout, **cfg.architecture_overrides()})
        states, chunks = training_windows(replay, cfg.horizon, policy.action_frame, cfg.pad_episode_end)
        if cfg.init:
            # the exported graph bakes the normalization in, so a fine-tuned policy keeps its base's
            normalizer = Normalizer.from_dict(init_card["normalization"])
        elif policy.action_frame == "agent":
            normalizer = Normalizer.fit(replay.states, chunks)
        else:
            normalizer = Normalizer.fit(replay.states, replay.actions)
        # the normalization comes from the demonstrations alone; extra data only adds windows
        demo_windows = len(states)
        for extra in filter(None, (path.strip() for path in cfg.extra_data.split(","))):
            extra_states, extra_chunks = training_windows(load_replay(extra), cfg.horizon, policy.action_frame, cfg.pad_episode_end)
            states, chunks = np.concatenate([states, extra_states]), np.concatenate([chunks, extra_chunks])
        normalization = normalizer.to_dict()
        if ctx.is_main:
            print(f"windows: {len(states)} ({demo_windows} demonstration, {len(states) - demo_windows} extra)", file=sys.stderr)
        # The whole dataset is a few MB: keep it resident as normalized tensors, no DataLoader.
        states_n = torch.as_tensor(np.asarray(normalizer.normalize_state(states), dtype=np.float32))
        chunks_n = torch.as_tensor(np.asarray(normalizer.normalize_action(chunks), dtype=np.float32))
        num_windows = len(states_n)
        if num_windows < cfg.batch_size:
            raise ValueError(f"{cfg.data} has {num_windows} windows, fewer than batch_size {cfg.batch_size}")

        # sin/cos angle encoding needs the raw angle back from the normalized state; a no-op otherwise
        policy.set_input_normalization(normalizer.state_mean, normalizer.state_std)
        policy.train()
        model: nn.Module = _LossModule(policy)
        if ctx.world_size > 1:
            model = nn.parallel.DistributedDataParallel(model)
        # fused: 10-20% faster per step than foreach on CPU for these MLPs (measured)
        optimizer = torch.optim.AdamW(policy.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, fused=True)
        if ctx.is_main:
            num_parameters = sum(p.numel() for p in policy.parameters())
            print(f"{cfg.policy} policy: {num_parameters} parameters, architecture {policy.architecture}", file=sys.stderr)

        log = _RunLog(run_dir, enabled=ctx.is_main)
        # kind, architecture, num_parameters and normalization are derived by save_checkpoint itself
        card = {"name": cfg.policy, "config": cfg.to_dict(), "git_commit": git_commit()}
        best_reward = -math.inf
        local_batch = cfg.batch_size // ctx.world_size
        batches_per_epoch = num_windows // cfg.batch_size
        permutation_rng = torch.Generator().manual_seed(cfg.seed)  # same on every rank
        bar = _progress_bar(cfg.steps, enabled=ctx.is_main and cfg.progress)

        start = time.perf_counter()
        interval_start, interval_loss, interval_steps = time.perf_counter(), 0.0, 0
        interval_eval_s = 0.0  # evaluation time inside the interval, kept out of ms_per_step
        batch_in_epoch = batches_per_epoch  # forces a fresh permutation at step 0
        for step in range(1, cfg.steps + 1):
            if batch_in_epoch == batches_per_epoch:
                # each global batch is split in rank-sized slices: rank r takes slice r
                order = torch.randperm(num_windows, generator=permutation_rng)[: batches_per_epoch * cfg.batch_size]
                order = order.view(batches_per_epoch, cfg.batch_size)[:, ctx.rank * local_batch : (ctx.rank + 1) * local_batch]
                batch_in_epoch = 0
            idx = order[batch_in_epoch]
            batch_in_epoch += 1

            progress = (step - 1) / cfg.steps
            lr = cfg.lr * 0.5 * (1.0 + math.cos(math.pi * progress))
            for group in optimizer.param_groups:
                group["lr"] = lr
            noise_std = state_noise_std(cfg, progress)
            state_batch = states_n[idx]
            if noise_std > 0:
                state_batch = state_batch + noise_std * torch.randn_like(state_batch)

            loss = model(state_batch, chunks_n[idx])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

            loss_value = loss.item()
            if not math.isfinite(loss_value):
                raise ValueError(f"loss became {loss_value} at step {step}; lower --lr or check the data")
            interval_loss += loss_value
            interval_steps += 1
            if bar is not None:
                bar.update(1)
                if step % 20 == 0:
                    bar.set_postfix(loss=f"{loss_value:.4f}", refresh=False)

            if step % cfg.log_every == 0 or step == cfg.steps:
                ms = 1000 * (time.perf_counter() - interval_start - interval_eval_s) / interval_steps
                mean_loss = ctx.mean(interval_loss / interval_steps)  # over all ranks' slices
                log.write({"type": "train", "step": step, "loss": mean_loss, "lr": lr,
                           "state_noise": noise_std, "ms_per_step": ms})
                interval_loss, interval_steps, interval_eval_s = 0.0, 0, 0.0
                interval_start = time.perf_counter()

            evaluate_now = cfg.eval_every >= 0 and (
                step == cfg.steps or (cfg.eval_every > 0 and step % cfg.eval_every == 0)
            )
            if evaluate_now:
                eval_start = time.perf_counter()
                if ctx.is_main:
                    evaluation = _evaluate(policy, normalization, cfg, ActingPolicy, step)
                    log.write({"type": "eval", **evaluation})
                    if evaluation["mean_max_reward"] > best_reward:
                        best_reward = evaluation["mean_max_reward"]
                        save_checkpoint(str(run_dir / "best"), policy, normalization, **card, steps=step,
                                        wall_time_s=time.perf_counter() - start, evaluation=evaluation)
                    # `last` is rewritten at every evaluation, so a crashed run still leaves recent weights
                    save_checkpoint(str(run_dir / "last"), policy, normalization, **card, steps=step,
                                    wall_time_s=time.perf_counter() - start, evaluation=evaluation)
                    log.plot()
                    if bar is not None:
                        bar.set_postfix(loss=f"{loss_value:.4f}", eval=f"{evaluation['mean_max_reward']:.3f}")
                ctx.barrier()
                interval_eval_s += time.perf_counter() - eval_start

        if bar is not None:
            bar.close()
        if ctx.is_main:
            last_eval = log.last_eval if cfg.eval_every >= 0 else None
            save_checkpoint(str(run_dir / "last"), policy, normalization, **card, steps=cfg.steps,
                            wall_time_s=time.perf_counter() - start, evaluation=last_eval)
            log.plot()
            print(f"done: {cfg.steps} steps in {time.perf_counter() - start:.0f} s; outputs in {run_dir}", file=sys.stderr)
        ctx.barrier()
        return run_dir
    finally:
        ctx.stop()


def training_windows(replay: Any, horizon: int, action_frame: str, pad_end: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """States [W, 5] and the chunks [W, H, 2] a policy learns: in env units, relative to the agent for action_frame="agent"."""
    from training.data import make_windows

    states, chunks = make_windows(replay, horizon=horizon, pad_end=pad_end)
    if action_frame == "agent":
        chunks = chunks - states[:, None, :2]
    return states, chunks


def state_noise_std(cfg: TrainConfig, progress: float) -> float:
    """The std of the Gaussian noise on normalized training states at a fraction `progress` of training."""
    start, end = cfg.state_noise_start, cfg.state_noise_end
    if cfg.state_noise_schedule == "constant":
        return start
    if cfg.state_noise_schedule == "linear":
        return start + (end - start) * progress
    return end + (start - end) * 0.5 * (1.0 + math.cos(math.pi * progress))


class _LossModule(nn.Module):
    """Wraps a policy so DDP's forward hook sees the loss computation (policies expose compute_loss)."""

    def __init__(self, policy: nn.Module) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, state: torch.Tensor, chunk: torch.Tensor) -> torch.Tensor:
        return self.policy.compute_loss(state, chunk)


def _evaluate(policy: nn.Module, normalization: dict, cfg: TrainConfig, acting_cls: Any, step: int) -> dict[str, Any]:
    from training.evaluate import evaluate_policy

    policy.eval()
    try:
        summary = evaluate_policy(
            acting_cls(policy, num_steps=cfg.flow_num_steps, **normalization),
            cfg.policy,
            episodes=cfg.eval_episodes,
            seed=cfg.eval_seed,
            num_envs=cfg.eval_num_envs or None,
            env=cfg.eval_env,
            action_horizon=cfg.action_horizon,
            max_steps=cfg.eval_max_steps,
            num_steps=cfg.flow_num_steps,
        )
    finally:
        policy.train()
    return {
        "step": step,
        "env": cfg.eval_env,
        "episodes": len(summary.episodes),
        "mean_max_reward": summary.mean_max_reward,
        "mean_max_reward_ci95": list(summary.mean_max_reward_ci95),
        "success_rate": summary.success_rate,
        "success_rate_ci95": list(summary.success_rate_ci95),
        "mean_length": summary.mean_length,
        "action_horizon": summary.action_horizon,
        "max_steps": summary.max_steps,
        "seeds": summary.seeds,
        "wall_time_s": summary.wall_time_s,
    }


class _RunLog:
    """log.jsonl and learning_curve.png of one run (no-ops on non-main ranks)."""

    def __init__(self, run_dir: Path, enabled: bool) -> None:
        self.enabled = enabled
        self.path = run_dir / "log.jsonl"
        self.records: list[dict[str, Any]] = []
        if enabled:
            self.path.write_text("")

    def write(self, record: dict[str, Any]) -> None:
        if not self.enabled:
            return
        self.records.append(record)
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")

    @property
    def last_eval(self) -> dict[str, Any] | None:
        evals = [r for r in self.records if r["type"] == "eval"]
        return {k: v for k, v in evals[-1].items() if k != "type"} if evals else None

    def plot(self) -> None:
        if not self.enabled:
            return
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        train = [r for r in self.records if r["type"] == "train"]
        evals = [r for r in self.records if r["type"] == "eval"]
        fig, (ax_loss, ax_eval) = plt.subplots(1, 2, figsize=(11, 4))
        ax_loss.plot([r["step"] for r in train], [r["loss"] for r in train], lw=1)
        ax_loss.set(xlabel="step", ylabel="training loss", title="loss", yscale="log")
        ax_loss.grid(alpha=0.3)
        if evals:
            steps = [r["step"] for r in evals]
            ax_eval.plot(steps, [r["mean_max_reward"] for r in evals], "o-", label="mean max reward")
            ax_eval.fill_between(steps, [r["mean_max_reward_ci95"][0] for r in evals],
                                 [r["mean_max_reward_ci95"][1] for r in evals], alpha=0.2)
            ax_eval.plot(steps, [r["success_rate"] for r in evals], "s-", label="success rate")
            ax_eval.legend(loc="upper left")
            first = evals[0]["seeds"]
            ax_eval.set_title(f"evaluation ({len(first)} episodes, seeds {first[0]}..{first[-1]})")
        else:
            ax_eval.set_title("evaluation (none yet)")
        last_step = max([r["step"] for r in self.records], default=1)
        ax_eval.set(xlabel="step", ylim=(0, 1), xlim=(0, last_step * 1.02))
        ax_eval.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(self.path.with_name("learning_curve.png"), dpi=100)
        plt.close(fig)


@dataclass
class _Distributed:
    """The process group under torchrun (gloo), or a single process."""

    rank: int = 0
    world_size: int = 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @classmethod
    def start(cls) -> _Distributed:
        world_size = int(os.environ.get("WORLD_SIZE", "1"))
        if world_size <= 1:
            return cls()
        # evaluation on rank 0 can take minutes while the others wait at a barrier
        dist.init_process_group("gloo", timeout=timedelta(hours=2))
        return cls(rank=dist.get_rank(), world_size=dist.get_world_size())

    def barrier(self) -> None:
        if self.world_size > 1:
            dist.barrier()

    def mean(self, value: float) -> float:
        if self.world_size == 1:
            return value
        box = torch.tensor([value], dtype=torch.float64)
        dist.all_reduce(box)
        return box.item() / self.world_size

    def broadcast_str(self, value: str) -> str:
        if self.world_size == 1:
            return value
        box = [value]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    def stop(self) -> None:
        if self.world_size > 1 and dist.is_initialized():
            dist.destroy_process_group()


def _progress_bar(total: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc="train", unit="step", file=sys.stderr, mininterval=0.5)


if __name__ == "__main__":
    sys.exit(main())

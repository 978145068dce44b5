"""Few-step flow by distillation: a student regresses the teacher's many-step sampling map in 1 or 2 Euler steps.

    python -m training.distill --teacher models/flow --student-steps 1 --name flow-distill-1step

The teacher's sampler is a deterministic map from (state, start noise) to a chunk. The student, a
flow of the same architecture initialized with the teacher's weights, learns to reach the same chunk
from the same start in `student_steps` Euler steps (knowledge distillation of the ODE, Luhman and
Luhman 2021; rectified-flow reflow trains on the same pairs). Pairs are drawn once, before training:
states from the demonstrations and any `--extra-states` stores (states the policy visits), each with
fresh start noises. The student's card records its step count (`sampler_steps`), so export, evaluation and the service
run it with that many network evaluations.
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from training.cli import build_parser, command_line, option

PROG = "python -m training.distill"
RESUMABLE_CHANGES = ("progress", "threads")


@dataclass
class DistillConfig:
    """Everything that defines a distillation run."""

    teacher: str = option("models/flow", "flow checkpoint stem to distil (its noise_scale and steps define the map)")
    teacher_steps: int = option(10, "Euler steps of the teacher's sampler")
    student_steps: int = option(1, "Euler steps (network evaluations) of the student")
    name: str = option("flow-distill", "run name; outputs go to OUT_DIR/NAME")
    out_dir: str = option("runs", "parent folder of run folders")
    data: str = option("data/pusht_lowdim.zarr", "demonstrations whose states are distilled")
    extra_states: str = option("", "comma-separated zarr stores whose states join (e.g. policy rollouts)")
    pairs: int = option(400_000, "(state, start noise, teacher chunk) triples drawn before training")
    steps: int = option(40_000, "optimizer steps")
    batch_size: int = option(256, "batch size")
    lr: float = option(1e-4, "AdamW peak learning rate (cosine decay to 0)")
    eval_episodes: int = option(200, "episodes of the final evaluation")
    eval_seed: int = option(400_000, "first evaluation episode seed (never a held-out one)")
    log_every: int = option(200, "write a log record every N steps")
    seed: int = option(0, "seed of the pairs and of the batch order")
    threads: int = option(1, "torch intra-op threads")
    progress: bool = option(True, "show a tqdm progress bar on stderr")

    def __post_init__(self) -> None:
        for name in ("teacher_steps", "student_steps", "pairs", "steps", "batch_size", "eval_episodes", "log_every", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")

    def to_dict(self) -> dict:
        """A JSON-ready dict of every field."""
        return asdict(self)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: 0 when finished, 2 on a bad setting."""
    from training.run import RunError

    parser = build_parser(DistillConfig, PROG, __doc__.splitlines()[0])
    args = parser.parse_args(argv)
    try:
        cfg = DistillConfig(**vars(args))
    except ValueError as exc:
        parser.error(str(exc))
    try:
        distill(cfg)
    except (RunError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def distill(cfg: DistillConfig):
    """Draw the pairs, train the student, evaluate it, save `last`; returns the Run."""
    from tqdm import tqdm

    from training.checkpoint import git_commit, load_checkpoint, require_state_only, save_checkpoint
    from training.curves import plot_learning_curve
    from training.data import load_replay
    from training.evaluate import evaluate_policy
    from training.policies import ActingPolicy, build_policy
    from training.run import Run

    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    teacher, card = load_checkpoint(cfg.teacher)
    if card["kind"] != "flow":
        raise ValueError(f"{cfg.teacher} is a {card['kind']} checkpoint; only a flow has steps to distil")
    require_state_only(card, cfg.teacher, "distillation")
    teacher.eval()
    student = build_policy("flow", **card["architecture"])
    student.load_state_dict(teacher.state_dict())
    student.normalizer.set(teacher.normalizer)
    states = np.concatenate([load_replay(p).states for p in [cfg.data, *filter(None, cfg.extra_states.split(","))]])
    run = Run.start(cfg.out_dir, cfg.name, cfg.to_dict(), may_change=RESUMABLE_CHANGES)
    try:
        generator = torch.Generator().manual_seed(cfg.seed)
        rows = torch.randint(0, len(states), (cfg.pairs,), generator=generator)
        s = teacher.normalizer.state(torch.as_tensor(states, dtype=torch.float32)[rows])
        noise = torch.randn((cfg.pairs, student.horizon, student.action_dim), generator=generator)
        with torch.no_grad():
            target = torch.cat([teacher.sample_actions(s[i : i + 4096], noise[i : i + 4096], cfg.teacher_steps) for i in range(0, cfg.pairs, 4096)])
        run.log({"type": "pairs", "step": 0, "pairs": cfg.pairs, "states": len(states), "elapsed_s": run.elapsed_s})
        optimizer = torch.optim.AdamW(student.parameters(), lr=cfg.lr, weight_decay=0.0)
        student.train()
        bar = tqdm(total=cfg.steps, desc="distill", disable=not cfg.progress, file=sys.stderr)
        running, start = 0.0, time.perf_counter()
        for step in range(1, cfg.steps + 1):
            for group in optimizer.param_groups:
                group["lr"] = cfg.lr * 0.5 * (1 + np.cos(np.pi * (step - 1) / cfg.steps))
            idx = torch.randint(0, cfg.pairs, (cfg.batch_size,), generator=generator)
            loss = torch.nn.functional.mse_loss(student.sample_actions(s[idx], noise[idx], cfg.student_steps), target[idx])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            running += float(loss.detach())
            if step % cfg.log_every == 0:
                run.log({"type": "train", "step": step, "loss": running / cfg.log_every, "ms_per_step": 1e3 * (time.perf_counter() - start) / step})
                running = 0.0
            bar.update(1)
            if run.stop_requested:
                raise ValueError(f"stopped by {run.stop_signal} at step {step}; distillation is short: start it again with another --name")
        bar.close()
        student.eval()
        summary = evaluate_policy(ActingPolicy(student, num_steps=cfg.student_steps), episodes=cfg.eval_episodes,
                                  seed=cfg.eval_seed)
        evaluation = {"step": cfg.steps, **{k: v for k, v in summary.scores().items() if k != "wall_time_s"}}
        run.log({"type": "eval", **evaluation, "seeds": summary.seeds})
        plot_learning_curve(run.records, run.dir / "learning_curve.png")
        reproduce = {"distill": command_line(DistillConfig, PROG, cfg.to_dict(), always=("teacher", "name", "student_steps"))}
        save_checkpoint(str(run.dir / "last"), student, name="flow", config=cfg.to_dict(), git_commit=git_commit(),
                        steps=cfg.steps, wall_time_s=run.elapsed_s, evaluation=evaluation, finished=True, reproduce=reproduce,
                        sampler_steps=cfg.student_steps, teacher=str(cfg.teacher))
        run.finish(cfg.steps)
    finally:
        run.close()
    print(f"done: {cfg.steps} steps in {run.elapsed_s:.0f} s; {summary.scores()}; outputs in {run.dir}", file=sys.stderr)
    return run


if __name__ == "__main__":
    sys.exit(main())

"""The scoring pass of a multichoice student: which of its K hypotheses to play, learned from the teacher's outcome model.

A multichoice student's hypotheses hold a better policy than its own scores play: the teacher's outcome
model, choosing among them, plays within a few points of the chooser. That choice is a jump, but what the
model predicts for each hypothesis (where it leaves the block) is smooth in the state, so a second network
pass (`OnePassChooser.changes`, `--scorer-dims`) regresses it, all K at once; the goal distances follow
exactly, and the nearest plays. The
hypotheses stay frozen; the labels cost K outcome-model passes a state and no flow integration, so
the scorer learns from every state the run holds and then, DAgger-style, from the states of episodes it
plays itself (`--scorer-rounds`); after each round the run keeps them all (its pairs file, states only), so that
the next run can start where this one went (`--states-from`).
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

__all__ = ["hypothesis_changes", "save_states", "train_scorer"]

LABEL_BATCH = 4096
JITTER = torch.tensor([3.0, 3.0, 3.0, 3.0, 0.03])
"""how far `--scorer-jitter`'s copies of a visited state lie from it, one standard deviation (px, px, px, px, rad)"""


def train_scorer(student, teacher, state_n: torch.Tensor, run, cfg, generator: torch.Generator) -> dict:
    """Train `student.onepass.scorer` on where the teacher's outcome model says the student's hypotheses leave the block at the
    network inputs `state_n` [N, S'] (then `cfg.scorer_rounds` rounds of its own episodes' states); returns the last evaluation."""
    from training.distill_data import PAIRS_FILE, decision_pairs
    from training.evaluate import evaluate_policy
    from training.policies import ActingPolicy

    head = student.onepass
    changes = hypothesis_changes(student, teacher, state_n)
    optimizer = torch.optim.AdamW(head.scorer.parameters(), lr=cfg.scorer_lr, weight_decay=0.0)
    seed = cfg.round_seed + cfg.teacher_episodes + cfg.rounds * cfg.round_episodes  # after the generator's episodes
    evaluation: dict = {}
    for round_ in range(cfg.scorer_rounds + 1):
        if round_:
            visited, _, scores = decision_pairs(ActingPolicy(student.eval(), 1), cfg.round_episodes, seed)
            seed += cfg.round_episodes
            visited = torch.as_tensor(visited)
            # moved copies cost labels, not episodes: the pass learns around the states it goes to, not at points
            moved = [visited + torch.randn(visited.shape, generator=generator) * JITTER for _ in range(cfg.scorer_jitter)]
            new = teacher.policy_state(torch.cat([visited, *moved]))
            state_n, changes = torch.cat([state_n, new]), torch.cat([changes, hypothesis_changes(student, teacher, new)])
            run.log({"type": "scorer_round", "step": round_, "round": round_, "states": len(state_n), "elapsed_s": run.elapsed_s,
                     **{f"played_{k}": v for k, v in scores.items()}})
            save_states(run.dir / PAIRS_FILE, state_n, cfg.teacher)
        steps = cfg.scorer_steps if round_ == 0 else cfg.scorer_steps // 2
        lr = cfg.scorer_lr if round_ == 0 else cfg.scorer_lr / 3
        _fit(student, state_n, changes, optimizer, steps, lr, run, cfg, generator, round_)
        student.eval()
        summary = evaluate_policy(ActingPolicy(student, 1), episodes=cfg.eval_episodes, seed=cfg.eval_seed)
        evaluation = {"scorer_round": round_, **{k: v for k, v in summary.scores().items() if k != "wall_time_s"}}
        run.log({"type": "scorer_eval", "step": round_, **evaluation})
    return evaluation


def save_states(path, state_n: torch.Tensor, teacher: str) -> None:
    """Keep the network inputs [N, S'] the second pass learned from (a run's pairs file with states only), so that another
    run can start from them (`--states-from`)."""
    from safetensors.torch import save_file

    save_file({"state_n": state_n.contiguous()}, str(path), metadata={"teacher": str(teacher), "labels": "states"})


@torch.no_grad()
def hypothesis_changes(student, teacher, state_n: torch.Tensor) -> torch.Tensor:
    """[N, K * S, 3]: where the teacher's outcome model says each of the student's K hypotheses at the inputs `state_n` [N, S']
    leaves the block at each stretch the second pass scores (its network's output: a move in the block's frame and a turn, scaled)."""
    head, model, out = student.onepass, teacher.outcome.model, []
    for i in range(0, len(state_n), LABEL_BATCH // len(head.scorer_stretches)):
        rows_n = state_n[i : i + LABEL_BATCH // len(head.scorer_stretches)]
        state, actions = head.scored_actions(student, rows_n, head(student, rows_n)[0])
        out.append(model.net(model.features(state, actions)).reshape(len(rows_n), head.scored, 3))
    return torch.cat(out)


def _fit(student, state_n, changes, optimizer, steps: int, lr: float, run, cfg, generator: torch.Generator, round_: int) -> None:
    """`steps` optimizer steps of `OnePassChooser.scorer_loss` on random batches (cosine from `lr`), logged as "scorer" records."""
    from tqdm import tqdm

    head = student.onepass
    head.scorer.train()
    running, start = 0.0, time.perf_counter()
    for step in tqdm(range(1, steps + 1), desc=f"scorer {round_}", disable=not cfg.progress, file=sys.stderr):
        for group in optimizer.param_groups:
            group["lr"] = lr * 0.5 * (1 + np.cos(np.pi * (step - 1) / steps))
        rows = torch.randint(0, len(state_n), (cfg.batch_size,), generator=generator)
        with torch.no_grad():
            chunks_n, _ = head(student, state_n[rows])
        loss = head.scorer_loss(student, state_n[rows], chunks_n, changes[rows])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        running += float(loss.detach())
        if step % cfg.log_every == 0:
            run.log({"type": "scorer", "step": step, "round": round_, "loss": running / cfg.log_every,
                     "ms_per_step": 1e3 * (time.perf_counter() - start) / step})
            running = 0.0
        if run.stop_requested:
            raise ValueError(f"stopped by {run.stop_signal} at scorer step {step}; start it again with another --name")

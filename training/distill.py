"""Few-step flow by distillation: a student regresses the teacher's many-step sampling map in 1 or 2 Euler steps.

    python -m training.distill --teacher models/flow --student-steps 1 --name flow-distill-1step

The teacher's sampler is a deterministic map from (state, start noise) to a chunk: a flow's Euler
integration, or with an outcome chooser the chunk it picks among its candidates. The student, a plain
flow of the teacher's architecture initialized with its flow's weights, learns to reach the same chunk
from the same start in `student_steps` Euler steps (knowledge distillation of the ODE, Luhman and
Luhman 2021; rectified-flow reflow trains on the same pairs). Pairs: states from the demonstrations and
any `--extra-states` stores, each with a fresh start noise; the decision states of `--teacher-episodes`
episodes the teacher plays; then, for each of `--rounds`, the decision states of episodes the student
plays, each with the noise it played (DAgger: the teacher labels where the student goes), `--steps`
more steps each. The student's card records its step count (`sampler_steps`), so export, evaluation
and the service run it with that many network evaluations.

`--student one-pass` distils an outcome chooser from one fixed start noise (`--fixed-noise`) into
`training.onepass.OnePassChooser`: one network pass regresses all the chooser's candidates and their
scores, and the choice among them stays an exact argmin (no steps; the card says `onepass_dims`).
`--student multichoice` trains the same head as K hypotheses of the chooser's one chosen chunk and which
one to play (`OnePassChooser.multichoice_loss`); it takes `--outcome-weight` like a flow student. With
`--top M` each state's label is the chooser's M best chunks (from fresh start noises: its modes, not one
pick), and `--scorer-dims` adds a second pass that learns which hypothesis the teacher's outcome model
would play (`training.distill_scorer`; 2 network evaluations) to a trained student (`--steps 0 --init CARD`).
"""

from __future__ import annotations

import sys
import time
from functools import partial
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from training.cli import build_parser, command_line
from training.distill_config import DEFAULT_MULTICHOICE_DIMS, DEFAULT_ONEPASS_DIMS, DistillConfig

__all__ = ["DistillConfig", "distill", "main", "outcome_term", "student_of"]

PROG = "python -m training.distill"
RESUMABLE_CHANGES = ("progress", "threads")
CHOOSER_KEYS = ("outcome_dims", "outcome_candidates", "outcome_stretches")
"""Architecture keys of an outcome chooser, which a flow student does not take (it samples one chunk); a one-pass student
keeps the candidates and stretches."""
OUTCOME_PRUNE_STATES = 4096
"""demonstration states on which --scorer-outcome ranks the outcome model's units, where the second pass is narrower"""


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
    """Label the pairs, train the student (then DAgger rounds: play, label, train on), evaluate it, save `last`; returns the Run."""
    from training.checkpoint import git_commit, save_checkpoint
    from training.curves import plot_learning_curve
    from training.data import load_replay
    from training.distill_data import PAIRS_FILE, Pairs, decision_pairs
    from training.evaluate import evaluate_policy
    from training.policies import ActingPolicy
    from training.run import Run

    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    teacher, student = _teacher_and_student(cfg)
    run = Run.start(cfg.out_dir, cfg.name, cfg.to_dict(), may_change=RESUMABLE_CHANGES)
    try:
        generator = torch.Generator().manual_seed(cfg.seed)
        # drawn even when the pairs come from another run: the generator's later draws (the batch order) stay as recorded
        states = np.concatenate([load_replay(p).states for p in [cfg.data, *filter(None, cfg.extra_states.split(","))]])
        rows = torch.randint(0, len(states), (cfg.pairs,), generator=generator).numpy()
        noise = torch.randn((cfg.pairs, student.horizon, student.action_dim), generator=generator).numpy()
        pairs = Pairs(teacher, cfg.teacher, cfg.teacher_steps, cfg.progress, fixed_noise=cfg.fixed_noise, choices=cfg.student == "one-pass",
                      top=cfg.top)
        reproduce = {"distill": command_line(DistillConfig, PROG, cfg.to_dict(), always=("teacher", "name", "student_steps"))}
        save = partial(save_checkpoint, name="flow", config=cfg.to_dict(), git_commit=git_commit(), reproduce=reproduce,
                       sampler_steps=cfg.student_steps if cfg.student == "flow" else None, teacher=str(cfg.teacher))  # a one-pass student has no steps
        total = cfg.steps * (cfg.rounds + 1)
        if cfg.steps:
            if cfg.pairs_from:
                pairs.load(Path(cfg.pairs_from) / PAIRS_FILE)
            elif cfg.states_from:
                pairs.relabel(Path(cfg.states_from) / PAIRS_FILE, cfg.pairs, generator)
            else:
                pairs.add(states[rows], noise, "demonstrations")
                if cfg.teacher_episodes:
                    pairs.add(*decision_pairs(ActingPolicy(teacher, cfg.teacher_steps), cfg.teacher_episodes, cfg.round_seed)[:2], "teacher")
            run.log({"type": "pairs", "step": 0, "round": 0, "pairs": len(pairs), "elapsed_s": run.elapsed_s})
            optimizer = torch.optim.AdamW(student.parameters(), lr=cfg.lr, weight_decay=0.0)
        for round_ in range(cfg.rounds + 1 if cfg.steps else 0):
            if round_:
                seed = cfg.round_seed + cfg.teacher_episodes + (round_ - 1) * cfg.round_episodes
                visited, noise, scores = decision_pairs(ActingPolicy(student.eval(), cfg.student_steps), cfg.round_episodes, seed)
                pairs.add(visited, noise, f"round {round_}")
                run.log({"type": "round", "step": round_ * cfg.steps, "round": round_, "pairs": len(pairs),
                         "elapsed_s": run.elapsed_s, **{f"played_{k}": v for k, v in scores.items()}})
            _train(student, teacher, optimizer, pairs, run, cfg, generator, first=round_ * cfg.steps, total=total)
            student.eval()
            summary = evaluate_policy(ActingPolicy(student, num_steps=cfg.student_steps), episodes=cfg.eval_episodes, seed=cfg.eval_seed)
            evaluation = {"step": (round_ + 1) * cfg.steps, **{k: v for k, v in summary.scores().items() if k != "wall_time_s"}}
            run.log({"type": "eval", "round": round_, **evaluation})
            if round_ or not cfg.pairs_from:  # new labels to keep
                pairs.save(run.dir / PAIRS_FILE)
            finished = round_ == cfg.rounds
            save(str(run.dir / ("last" if finished else f"round{round_}")), student, steps=(round_ + 1) * cfg.steps,
                 wall_time_s=run.elapsed_s, evaluation=evaluation, finished=finished)
        if cfg.scorer_dims or cfg.ranker_dims:  # the hypotheses of a trained student (--init) stay; the second pass or the ranker learns
            from training.distill_scorer import train_scorer

            where = student.policy_state(torch.as_tensor(states[rows]))
            if cfg.states_from:  # states of another run's pairs: where its students went
                where = torch.cat([where, pairs.saved_states(Path(cfg.states_from) / PAIRS_FILE)])
            evaluation = train_scorer(student, teacher, where, run, cfg, generator)
        elif cfg.scorer_outcome:  # the outcome model itself chooses among the trained student's hypotheses: nothing to learn
            summary = evaluate_policy(ActingPolicy(student.eval(), 1), episodes=cfg.eval_episodes, seed=cfg.eval_seed)
            evaluation = {"scorer_round": 0, **{k: v for k, v in summary.scores().items() if k != "wall_time_s"}}
            run.log({"type": "scorer_eval", "step": 0, **evaluation})
        if cfg.second_pass:
            save(str(run.dir / "last"), student, steps=0, wall_time_s=run.elapsed_s, evaluation=evaluation, finished=True)
        plot_learning_curve(run.records, run.dir / "learning_curve.png")
        run.finish(total)
    finally:
        run.close()
    print(f"done: {total} steps in {run.elapsed_s:.0f} s; {evaluation}; outputs in {run.dir}", file=sys.stderr)
    return run


def _teacher_and_student(cfg: DistillConfig) -> tuple[torch.nn.Module, torch.nn.Module]:
    """The teacher (frozen) and the student to train, checked against each other before any work."""
    from training.checkpoint import load_checkpoint, require_state_only

    teacher, card = load_checkpoint(cfg.teacher)
    if card["kind"] != "flow":
        raise ValueError(f"{cfg.teacher} is a {card['kind']} checkpoint; only a flow has steps to distil")
    require_state_only(card, cfg.teacher, "distillation")
    if card.get("sampler_steps") not in (None, cfg.teacher_steps):
        raise ValueError(f"{cfg.teacher} was itself distilled to sample in {card['sampler_steps']} steps; "
                         f"give --teacher-steps {card['sampler_steps']} or distil its own teacher ({card.get('teacher')})")
    needs = "--outcome-weight" if cfg.outcome_weight else "a one-pass student" if cfg.student == "one-pass" else "a second pass"
    if (cfg.outcome_weight or cfg.student == "one-pass" or cfg.second_pass) and teacher.outcome is None:
        raise ValueError(f"{needs} needs a teacher with an outcome chooser; {cfg.teacher} has none")
    teacher.eval().requires_grad_(False)
    noise_scale = 0.0 if cfg.fixed_noise >= 0 else None
    if cfg.student == "one-pass":
        student = student_of(teacher, noise_scale, onepass_dims=cfg.student_hidden_dims or DEFAULT_ONEPASS_DIMS)
    elif cfg.student == "multichoice":  # deterministic whatever the labels' noise: it never reads its start noise
        outcome = cfg.scorer_outcome  # the outcome model's widths unless narrower ones are given, each hypothesis alone
        scorer_dims = cfg.scorer_dims or (",".join(map(str, teacher.architecture["outcome_dims"])) if outcome else "")
        student = student_of(teacher, 0.0, onepass_dims=cfg.student_hidden_dims or DEFAULT_MULTICHOICE_DIMS, hypotheses=cfg.hypotheses,
                             scorer_dims=scorer_dims, scorer_shared=cfg.scorer_shared or outcome, scorer_stretches=cfg.scored_stretches(),
                             scorer_context=cfg.scorer_context and not outcome, scorer_top=cfg.scorer_top, ranker_dims=cfg.ranker_dims)
    else:
        student = student_of(teacher, noise_scale, hidden_dims=cfg.student_hidden_dims)
    if cfg.init:
        start, start_card = load_checkpoint(cfg.init)
        # with --scorer-dims the hypotheses come from --init and the second pass is trained: its own if it has this one
        second = (("onepass_scorer_dims", "onepass_scorer_shared", "onepass_scorer_context", "onepass_scorer_stretches", "onepass_scorer_top",
                   "onepass_ranker_dims") if cfg.second_pass else ())
        if start_card.get("teacher") != cfg.teacher or _without(start.architecture, second) != _without(student.architecture, second):
            raise ValueError(f"--init {cfg.init} is not a student of {cfg.teacher} with this run's architecture "
                             f"(its teacher: {start_card.get('teacher')})")
        if cfg.second_pass:  # a second pass (a ranker) of the same widths keeps its layers (but the last, if it scores other stretches)
            def alike(*keys: str) -> bool:
                return all(start.architecture.get(k) == student.architecture.get(k) for k in keys)

            same = {"onepass.scorer.": alike("onepass_scorer_dims", "onepass_scorer_shared", "onepass_scorer_context"),
                    "onepass.ranker.": alike("onepass_ranker_dims")}
            own = student.state_dict()
            kept = {k: v for k, v in start.state_dict().items() if k in own and (
                all(not k.startswith(part) or (alike and own[k].shape == v.shape) for part, alike in same.items()))}
            student.load_state_dict({**student.state_dict(), **kept})
            if cfg.scorer_outcome:  # pruned where narrower, by its units' activity on the hypotheses at demonstration states
                from training.data import load_replay
                from training.distill_scorer import outcome_scorer

                demonstrations = load_replay(cfg.data).states
                picked = demonstrations[:: max(1, len(demonstrations) // OUTCOME_PRUNE_STATES)]
                outcome_scorer(student, teacher, student.policy_state(torch.as_tensor(picked)))
        else:
            student = start
    return teacher, student


def outcome_term(student, teacher, state_n: torch.Tensor, chunk_n: torch.Tensor, cfg: DistillConfig) -> torch.Tensor:
    """The teacher's outcome model's distance to the goal (its root with `outcome_root`) after the student's normalized chunks
    [B, H, A] from the inputs `state_n`, summed over `outcome_chunks` chunks the student plays on in the model."""
    from pusht.spec import ACTION_HIGH, ACTION_LOW
    from training.outcome import goal_corner_distance

    state = teacher.normalizer.env_state(state_n[:, : teacher.state_dim])
    total = chunk_n.new_zeros(())
    for ahead in range(cfg.outcome_chunks):
        if ahead:
            chunk_n = student.sample_actions(student.policy_state(state), torch.randn_like(chunk_n), cfg.student_steps)
        actions = torch.clamp(teacher.normalizer.actions(state, chunk_n), ACTION_LOW, ACTION_HIGH)
        pose = teacher.outcome.model(state, actions)
        distance = goal_corner_distance(pose)
        total = total + (distance.clamp_min(1e-6).sqrt() if cfg.outcome_root else distance).mean()
        # the agent ends a chunk near its last target (PD control), the block where the model predicts
        state = torch.cat([actions[:, -1], pose], dim=1)
    return total


def student_of(teacher: torch.nn.Module, noise_scale: float | None = None, hidden_dims: str = "", onepass_dims: str = "",
               hypotheses: int | None = None, scorer_dims: str = "", scorer_shared: bool = False,
               scorer_stretches: Sequence[float] = (1.0,), scorer_context: bool = True, scorer_top: int = 0,
               ranker_dims: str = "") -> torch.nn.Module:
    """A plain flow of the teacher's architecture and normalization (and `noise_scale` if given) with its flow's weights,
    or with comma-separated `hidden_dims` a fresh network of those widths; an outcome chooser's own parts stay behind.
    With comma-separated `onepass_dims`: the teacher's flow with a fresh one-pass chooser of those widths over its
    candidates and stretches (`training.onepass`), or with `hypotheses` a multiple-choice head of that many unstretched chunks
    (and with `scorer_dims` its second pass, scoring each at `scorer_stretches`, shared with or without `scorer_context`,
    all of them or the `scorer_top` best-scored by the first pass, or by a ranker of `ranker_dims` on its last hidden layer)."""
    from training.policies import build_policy

    dropped = ("outcome_dims",) if onepass_dims else CHOOSER_KEYS
    arch = {k: v for k, v in teacher.architecture.items() if k not in dropped}
    if noise_scale is not None:
        arch["noise_scale"] = noise_scale
    if hidden_dims:
        arch["hidden_dims"] = _widths(hidden_dims)
    if onepass_dims:
        arch["onepass_dims"] = _widths(onepass_dims)
    if hypotheses:
        arch.update(outcome_candidates=hypotheses, outcome_stretches=[1.0])
    if scorer_dims:
        arch["onepass_scorer_dims"] = _widths(scorer_dims)
        if scorer_shared:
            arch["onepass_scorer_shared"] = True
            arch["onepass_scorer_context"] = scorer_context
        if scorer_top:
            arch["onepass_scorer_top"] = scorer_top
        if ranker_dims:
            arch["onepass_ranker_dims"] = _widths(ranker_dims)
        if list(scorer_stretches) != [1.0]:
            arch["onepass_scorer_stretches"] = [float(s) for s in scorer_stretches]
    student = build_policy("flow", **arch)
    if not hidden_dims:
        weights = {k: v for k, v in teacher.state_dict().items() if not k.startswith("outcome.")}
        weights.update({k: v for k, v in student.state_dict().items() if k.startswith("onepass.")})  # fresh
        student.load_state_dict(weights)
    student.normalizer.set(teacher.normalizer)
    return student


def _without(architecture: dict, keys: tuple[str, ...]) -> dict:
    return {k: v for k, v in architecture.items() if k not in keys}


def _widths(text: str) -> list[int]:
    return [int(width) for width in text.split(",")]


def _train(student, teacher, optimizer, pairs, run, cfg: DistillConfig, generator: torch.Generator, first: int, total: int) -> None:
    """`cfg.steps` optimizer steps from step `first` of a cosine schedule over `total`: the student's chunk in
    `student_steps` Euler steps against the teacher's, mean squared error in normalized units (plus, with an
    outcome weight, `outcome_term`: the teacher's predicted distance to the goal after the student's chunks); a one-pass student's
    `OnePassChooser.loss`; a multichoice student's `OnePassChooser.multichoice_loss` (and the outcome term on its played chunk)."""
    from tqdm import tqdm

    student.train()
    running, running_outcome, start = 0.0, 0.0, time.perf_counter()
    for step in tqdm(range(first + 1, first + cfg.steps + 1), desc="distill", disable=not cfg.progress, file=sys.stderr):
        for group in optimizer.param_groups:
            group["lr"] = cfg.lr * 0.5 * (1 + np.cos(np.pi * (step - 1) / total))
        batch = pairs.batch(cfg.batch_size, generator)
        if cfg.student == "multichoice":
            state_n, _, target = batch
            loss, chunk_n = student.onepass.multichoice_loss(student, state_n, target, cfg.relax)
        elif cfg.student == "one-pass":
            loss = student.onepass.loss(student, *batch)
        else:
            state_n, noise, target = batch
            chunk_n = student.sample_actions(state_n, noise, cfg.student_steps)
            loss = torch.nn.functional.mse_loss(chunk_n, target)
        running += float(loss.detach())
        if cfg.outcome_weight:
            outcome = outcome_term(student, teacher, state_n, chunk_n, cfg)
            running_outcome += float(outcome.detach())
            loss = loss + cfg.outcome_weight * outcome
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step % cfg.log_every == 0:
            record = {"type": "train", "step": step, "loss": running / cfg.log_every,
                      "ms_per_step": 1e3 * (time.perf_counter() - start) / (step - first)}
            if cfg.outcome_weight:
                record["outcome_distance"] = running_outcome / cfg.log_every
            run.log(record)
            running, running_outcome = 0.0, 0.0
        if run.stop_requested:
            raise ValueError(f"stopped by {run.stop_signal} at step {step}; distillation is short: start it again with another --name")


if __name__ == "__main__":
    sys.exit(main())

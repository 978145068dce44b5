"""Experiment: a multiple-choice student of the chooser (one MLP pass: K hypothesis chunks and which one to play).

    .venv/bin/python scripts/multichoice_student.py --k 8 --outcome-weight 3 --rounds 5 --save runs/mc/k8.safetensors

The 2-step student regresses the one chunk the chooser picks and averages where the pick jumps; the
one-pass head regresses all the chooser's candidates and scores. This sits between: K hypotheses trained
winner-takes-all on the chooser's chunk (relaxed: the losers get `--relax` of the loss, so none dies),
logits trained by cross-entropy toward the winner, and at acting time the argmax hypothesis (multiple
choice learning, Guzman-Rivera et al. 2012; BeT's mode-plus-offset idea). With `--outcome-weight` the
teacher's outcome model scores the played hypothesis as in `training.distill`. Pairs: a distillation
run's saved chunk labels (`--pairs`; from the fixed noise 12345, or with `--fixed-noise -1` from fresh
noises: the stochastic chooser, whose chunks differ from one label to the next, so the hypotheses spread
over its modes), then `--rounds` DAgger rounds (the student plays 1,000 training-seed episodes, the
chooser labels their decision states). `--scorer` adds a second pass that scores the K hypotheses at
once and chooses instead of the logits (2 network evaluations). Prints one JSON line per stage.
`training.distill --student multichoice` is the product path of the plain variant (a card that exports
and serves); the stochastic labels and the scorer live only here, as experiments.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from torch import nn
from safetensors.torch import load_file, save_file
from torch.nn import functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pusht.spec import ACTION_HIGH, ACTION_LOW  # noqa: E402
from training.checkpoint import load_checkpoint  # noqa: E402
from training.distill_data import Pairs, decision_pairs  # noqa: E402
from training.evaluate import evaluate_policy  # noqa: E402
from training.distill import DistillConfig, outcome_term  # noqa: E402
from training.networks import silu_mlp  # noqa: E402
from training.onepass import CHOICE_WEIGHT, EXTRA_FEATURES, head_features, score_target, winner_takes_all  # noqa: E402

TEACHER = "records/flow-outcome16-stretch/last"
FIXED_NOISE = 12345


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--pairs", default="runs/distill-fixed-root-more/pairs.safetensors", help="chunk labels of the chooser from noise 12345")
    parser.add_argument("--fixed-noise", type=int, default=FIXED_NOISE, help="the labels' one start noise (-1: labels from fresh noises, the stochastic chooser)")
    parser.add_argument("--k", type=int, default=8, help="hypotheses")
    parser.add_argument("--hidden", default="512,512,512", help="comma-separated hidden widths")
    parser.add_argument("--steps", type=int, default=20000, help="optimizer steps before the rounds")
    parser.add_argument("--round-steps", type=int, default=10000, help="optimizer steps after each round's labels")
    parser.add_argument("--lr", type=float, default=1e-3, help="peak learning rate (cosine to 0; a third of it in the rounds)")
    parser.add_argument("--relax", type=float, default=0.05, help="share of the loss on the losing hypotheses")
    parser.add_argument("--outcome-weight", type=float, default=0.0, help="weight of the outcome model's root goal distance after the played hypothesis")
    parser.add_argument("--choice", choices=("nearest", "outcome"), default="nearest",
                        help="what the logits learn: the hypothesis nearest the chooser's chunk, or the one the teacher's outcome model predicts ends closest to the goal")
    parser.add_argument("--rounds", type=int, default=0, help="DAgger rounds")
    parser.add_argument("--round-seed", type=int, default=28_100_000, help="first training seed of the rounds' episodes")
    parser.add_argument("--eval-episodes", type=int, default=200, help="episodes of each evaluation")
    parser.add_argument("--eval-seed", type=int, default=400_000, help="first evaluation seed (never a held-out one)")
    parser.add_argument("--init", default=None, help="start from these saved weights (.safetensors), then train --steps (0: evaluate them)")
    parser.add_argument("--save", default=None, help="save the student's weights here (.safetensors) after each stage")
    parser.add_argument("--scorer", default="", help="comma-separated hidden widths of a second pass that scores the K hypotheses at once "
                                                     "(state features + all K chunks -> K scores, regressing the teacher's outcome model's "
                                                     "goal distances); it, not the logits, then chooses what plays")
    parser.add_argument("--relabel", type=int, default=0, help="with --fixed-noise -1: label this many random states of --pairs (any "
                                                                 "labels) anew from fresh noises instead of loading its labels")
    parser.add_argument("--play", choices=("choice", "sampled", "outcome"), default="choice",
                        help="what plays in the evaluations: the student's choice (scorer, else argmax logit); a hypothesis drawn from "
                             "the softmax of the logits (Gumbel-max from the env's start noise); or, as a diagnostic costing K more "
                             "evaluations, the one the teacher's outcome model predicts ends closest to the goal")
    parser.add_argument("--card", default=None, help="at the end, write the student (no scorer) as a flow card at this stem: a one-pass "
                                                   "head with K candidates whose scores are the negated logits (exports and serves as any flow)")
    parser.add_argument("--init-scorer", default=None, help="start the scorer from these saved weights (.safetensors)")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    torch.manual_seed(0)
    teacher, _ = load_checkpoint(TEACHER)
    teacher.eval().requires_grad_(False)
    pairs = Pairs(teacher, TEACHER, 10, fixed_noise=args.fixed_noise)
    if args.relabel:
        relabel(pairs, Path(args.pairs), args.relabel)
        if args.save:
            pairs.save(Path(args.save).with_suffix(".pairs.safetensors"))
    else:
        pairs.load(Path(args.pairs))
    student = MultiChoice(teacher, args.k, [int(w) for w in args.hidden.split(",")], [int(w) for w in args.scorer.split(",") if w])
    generator = torch.Generator().manual_seed(0)
    if args.init:
        student.net.load_state_dict(load_file(args.init))
    if args.init_scorer:
        student.scorer.load_state_dict(load_file(args.init_scorer))
    train(student, teacher, pairs, args, generator, args.steps, args.lr)
    for round_ in range(args.rounds):
        visited, noise, played = decision_pairs(Acting(student), 1000, args.round_seed + round_ * 1000)
        print(json.dumps({"round": round_ + 1, "played_success_rate": played["success_rate"], "states": len(visited)}), flush=True)
        pairs.add(visited, noise, f"round {round_ + 1}")
        if args.save:
            pairs.save(Path(args.save).with_suffix(".pairs.safetensors"))
        train(student, teacher, pairs, args, generator, args.round_steps, args.lr / 3)
    if args.card:
        write_card(student, teacher, args.card, args.hidden)
    return 0


class MultiChoice(nn.Module):
    """MLP(encoded state, tee corners, agent in the block's frame) -> K normalized chunks [B, K, H, A] and K logits."""

    def __init__(self, flow: nn.Module, k: int, hidden: list[int], scorer: list[int] | None = None) -> None:
        super().__init__()
        self.flow, self.k, self.shape = [flow], k, (flow.horizon, flow.action_dim)  # a list: the flow's weights stay out
        encoded = flow.encode_state(torch.zeros(1, flow.state_dim)).shape[1]
        self.net = silu_mlp(encoded + EXTRA_FEATURES, hidden, k * self.shape[0] * self.shape[1] + k)
        self.scorer = silu_mlp(encoded + EXTRA_FEATURES + k * self.shape[0] * self.shape[1], scorer, k) if scorer else None

    def scores(self, state_n: torch.Tensor, chunks_n: torch.Tensor) -> torch.Tensor:
        """The second pass: K scores [B, K] (lower: predicted closer to the goal) of the hypotheses [B, K, H, A]."""
        return self.scorer(torch.cat([head_features(self.flow[0], state_n), chunks_n.flatten(1)], dim=1))

    def choose(self, state_n: torch.Tensor, chunks_n: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
        """Index [B] of the hypothesis that plays: the best-scored with a scorer, else the argmax logit."""
        if self.scorer is None:
            return logits.argmax(dim=1)
        with torch.no_grad():
            return self.scores(state_n, chunks_n).argmin(dim=1)

    def forward(self, state_n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.net(head_features(self.flow[0], state_n))
        split = self.k * self.shape[0] * self.shape[1]
        return out[:, :split].reshape(-1, self.k, *self.shape), out[:, split:]


class Acting(nn.Module):
    """The student as the torch acting module `evaluate_policy` takes; `play` as `--play` says (the noise only read by "sampled")."""

    def __init__(self, student: MultiChoice, play: str = "choice") -> None:
        super().__init__()
        self.student, self.policy, self.num_steps, self.play = student, student.flow[0], 1, play

    @torch.no_grad()
    def forward(self, state, noise=None, num_steps=None, prev_state=None):
        flow, student = self.policy, self.student
        state_n = flow.policy_state(state)
        chunks, logits = student(state_n)
        if self.play == "sampled":
            uniform = (0.5 * (1 + torch.erf(noise.flatten(1)[:, : student.k] / 2**0.5))).clamp(1e-6, 1 - 1e-6)
            index = (logits - torch.log(-torch.log(uniform))).argmax(dim=1)
        elif self.play == "outcome":
            index = best_by_outcome(flow, state_n, chunks)
        else:
            index = student.choose(state_n, chunks, logits)
        return torch.clamp(flow.normalizer.actions(state, chunks[torch.arange(len(chunks)), index]), ACTION_LOW, ACTION_HIGH)


def write_card(student: MultiChoice, teacher: nn.Module, stem: str, hidden: str) -> None:
    """The student as `training.distill --student multichoice` would save it: the teacher's flow with a one-pass head of
    the same trunk (`hidden` widths), whose K scores are the negated logits (the argmin plays the argmax hypothesis)."""
    from training.checkpoint import git_commit, save_checkpoint
    from training.distill import student_of

    if student.scorer is not None:
        raise SystemExit("--card writes a one-pass student; a scorer's second pass has no card yet")
    card = student_of(teacher, 0.0, onepass_dims=hidden, hypotheses=student.k)
    weights = {name: tensor.clone() for name, tensor in student.net.state_dict().items()}
    last = max(int(name.split(".")[0]) for name in weights)
    split = student.k * student.shape[0] * student.shape[1]
    for suffix in ("weight", "bias"):
        weights[f"{last}.{suffix}"][split:] *= -1
    card.onepass.net.load_state_dict(weights)
    save_checkpoint(stem, card, name="flow", teacher=TEACHER, sampler_steps=None, git_commit=git_commit(),
                    config={"script": "scripts/multichoice_student.py", "argv": sys.argv[1:]})
    print(f"card: {stem}.json", file=sys.stderr)


def relabel(pairs: Pairs, path: Path, count: int) -> None:
    """Label `count` random states saved at `path` anew, each from a fresh start noise (seeded: the same states and noises every run)."""
    from safetensors import safe_open

    if pairs.fixed_noise >= 0:
        raise SystemExit("--relabel labels from fresh noises: give --fixed-noise -1")
    with safe_open(str(path), framework="pt") as f:
        state_n = f.get_tensor("state_n")
    generator = torch.Generator().manual_seed(1)
    rows = torch.randperm(len(state_n), generator=generator)[:count]
    pairs.add_inputs(state_n[rows], torch.randn(len(rows), pairs.teacher.horizon, pairs.teacher.action_dim, generator=generator), "relabelled states")


def train(student: MultiChoice, teacher: nn.Module, pairs: Pairs, args: argparse.Namespace, generator: torch.Generator,
          steps: int, lr: float) -> None:
    """`steps` optimizer steps (cosine from `lr`), then an evaluation printed as one JSON line."""
    optimizer = torch.optim.AdamW(student.parameters(), lr=lr, weight_decay=0.0)
    outcome = DistillConfig(outcome_weight=args.outcome_weight, outcome_root=True)  # the root distance after the played chunk
    student.train()
    for step in range(1, steps + 1):
        for group in optimizer.param_groups:
            group["lr"] = lr * 0.5 * (1 + np.cos(np.pi * (step - 1) / steps))
        state_n, _, target = pairs.batch(256, generator)
        chunks, logits = student(state_n)
        loss, winner = winner_takes_all(chunks, target, args.relax)
        choice = winner if args.choice == "nearest" else best_by_outcome(teacher, state_n, chunks.detach())
        loss = loss + CHOICE_WEIGHT * F.cross_entropy(logits, choice)
        if args.outcome_weight:
            played = chunks[torch.arange(len(chunks)), student.choose(state_n, chunks, logits)]
            loss = loss + args.outcome_weight * outcome_term(None, teacher, state_n, played, outcome)
        if student.scorer is not None:  # on the hypotheses as they stand: the generator learns nothing from the scorer
            detached = chunks.detach()
            distance = outcome_distances(teacher, state_n, detached)
            scores = student.scores(state_n, detached)
            loss = loss + F.mse_loss(scores, score_target(distance)) + CHOICE_WEIGHT * F.cross_entropy(-scores, distance.argmin(dim=1))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    student.eval()
    if args.save:
        save_file(student.net.state_dict(), args.save)
        if student.scorer is not None:
            save_file(student.scorer.state_dict(), str(Path(args.save).with_suffix(".scorer.safetensors")))
    scores = evaluate_policy(Acting(student, args.play), episodes=args.eval_episodes, seed=args.eval_seed).scores()
    print(json.dumps({"steps": steps, **{k: scores[k] for k in ("success_rate", "success_rate_ci95", "mean_max_reward", "mean_length")}}), flush=True)


def best_by_outcome(teacher: nn.Module, state_n: torch.Tensor, chunks_n: torch.Tensor) -> torch.Tensor:
    """Index [B] of the hypothesis [B, K, H, A] (normalized) the teacher's outcome model predicts leaves the block closest to the goal."""
    return outcome_distances(teacher, state_n, chunks_n).argmin(dim=1)


@torch.no_grad()
def outcome_distances(teacher: nn.Module, state_n: torch.Tensor, chunks_n: torch.Tensor) -> torch.Tensor:
    """[B, K]: the teacher's outcome model's goal distance after each hypothesis [B, K, H, A] (normalized)."""
    b, k = chunks_n.shape[:2]
    state = teacher.normalizer.env_state(state_n[:, : teacher.state_dim]).repeat_interleave(k, dim=0)
    actions = torch.clamp(teacher.normalizer.actions(state, chunks_n.reshape(b * k, *chunks_n.shape[2:])), ACTION_LOW, ACTION_HIGH)
    return teacher.outcome.goal_distance(state, actions).reshape(b, k)


if __name__ == "__main__":
    sys.exit(main())

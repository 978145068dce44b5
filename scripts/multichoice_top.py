"""Experiment: a multiple-choice student on the chooser's M best chunks per state (label, then train).

    .venv/bin/python scripts/multichoice_top.py label --states runs/mc/k8-rand-r2.pairs.safetensors,runs/mc/k8-r5.pairs.safetensors \
        --count 64000 --top 4 --out runs/mc/topm4-64k.safetensors
    .venv/bin/python scripts/multichoice_top.py train --labels runs/mc/topm4-64k.safetensors --k 16 \
        --init runs/mc/k8-rand.safetensors --save runs/mc/k16-topm.safetensors

`pick --card STEM [--stretches 1,1.3,1.6]`: a multichoice card's hypotheses (each also at those stretches) chosen by the
teacher's outcome model (a diagnostic, K x S more evaluations). `label`: each of `--count` random saved states, one
fresh start noise each, gets the chooser's `--top` best (candidate, stretch) chunks by its outcome model (as
`training.distill --top`). `train`: K hypotheses (`--init`'s first ones copied to fill K) learn them winner-takes-all,
each label pulling its nearest hypothesis, half of each batch from `--extra` single-chunk fresh-noise labels; then the teacher's outcome
model choosing among the K (a diagnostic) and the argmax logit play 1,000 episodes. `training.distill
--student multichoice --top M` is the product path (from scratch: no --init, no --extra).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch.nn import functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from multichoice_student import TEACHER, Acting, MultiChoice  # noqa: E402
from training.checkpoint import load_checkpoint  # noqa: E402
from training.distill_data import teacher_top  # noqa: E402
from training.evaluate import evaluate_policy  # noqa: E402
from training.onepass import CHOICE_WEIGHT, winner_takes_all  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    label = sub.add_parser("label", help="the chooser's best chunks of saved states", formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    label.add_argument("--states", required=True, help="comma-separated saved pairs (.safetensors with state_n)")
    label.add_argument("--count", type=int, default=64000, help="random states to label")
    label.add_argument("--top", type=int, default=4, help="best chunks per state")
    label.add_argument("--seed", type=int, default=3, help="seed of the states drawn and their start noises")
    label.add_argument("--out", required=True, help="where the labels go (.safetensors: state_n, targets)")
    train = sub.add_parser("train", help="K hypotheses on those labels", formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    train.add_argument("--labels", required=True, help="`label`'s output")
    train.add_argument("--extra", default="runs/mc/k8-rand-r2.pairs.safetensors", help="single-chunk labels for half of each batch ('' for none)")
    train.add_argument("--k", type=int, default=16, help="hypotheses")
    train.add_argument("--init", default="", help="a student's saved weights (.safetensors) whose hypotheses are copied to fill K")
    train.add_argument("--init-k", type=int, default=8, help="the hypotheses of --init")
    train.add_argument("--steps", type=int, default=15000, help="optimizer steps")
    train.add_argument("--lr", type=float, default=5e-4, help="peak learning rate (cosine to 0)")
    train.add_argument("--relax", type=float, default=0.05, help="share of the loss on the hypotheses not nearest a label")
    train.add_argument("--save", required=True, help="where the weights go (.safetensors)")
    train.add_argument("--eval-episodes", type=int, default=1000, help="episodes of each evaluation (400000..)")
    train.add_argument("--threads", type=int, default=2, help="torch threads")
    pick = sub.add_parser("pick", help="a card's hypotheses chosen by the outcome model", formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    pick.add_argument("--card", required=True, help="a multichoice student's checkpoint stem")
    pick.add_argument("--episodes", type=int, default=1000, help="episodes")
    pick.add_argument("--seed", type=int, default=400_000, help="first episode seed (never a held-out one)")
    pick.add_argument("--stretches", default="1", help="comma-separated stretches each hypothesis is also offered at (training.outcome.stretch)")
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    teacher, _ = load_checkpoint(TEACHER)
    teacher.eval().requires_grad_(False)
    if args.command == "label":
        torch.set_num_threads(2)
        return label_states(teacher, args)
    if args.command == "pick":
        torch.set_num_threads(2)
        return outcome_pick(teacher, args)
    torch.set_num_threads(args.threads)
    return train_student(teacher, args)


def outcome_pick(teacher, args: argparse.Namespace) -> int:
    """Play the card's hypotheses as the teacher's outcome model picks them; print the scores (one JSON line)."""
    from pusht.spec import ACTION_HIGH, ACTION_LOW
    from training.architecture import check_stretches
    from training.outcome import stretch

    student, _ = load_checkpoint(args.card)
    student.eval()
    factors = check_stretches([float(s) for s in args.stretches.split(",")])

    class Pick(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.policy, self.num_steps = student, 1

        @torch.no_grad()
        def forward(self, state, noise=None, num_steps=None, prev_state=None):
            state_n = student.policy_state(state)
            rows, actions = student.onepass.hypothesis_actions(student, state_n, student.onepass(student, state_n)[0])  # [B * K, ...]
            options = torch.stack([torch.clamp(stretch(rows, actions, f), ACTION_LOW, ACTION_HIGH) for f in factors], dim=1)
            options = options.reshape(len(state), -1, *actions.shape[1:])  # [B, K * S, H, A]: each hypothesis at each stretch
            distance = teacher.outcome.goal_distance(rows.repeat_interleave(len(factors), dim=0), options.reshape(-1, *actions.shape[1:]))
            best = distance.reshape(len(state), -1).argmin(dim=1)
            return options[torch.arange(len(state)), best]

    scores = evaluate_policy(Pick(), episodes=args.episodes, seed=args.seed).scores()
    print(json.dumps({"card": args.card, "play": "outcome", "stretches": factors, **{k: scores[k] for k in ("success_rate", "success_rate_ci95", "mean_max_reward", "mean_length")}}))
    return 0


def label_states(teacher, args: argparse.Namespace) -> int:
    """Write `args.count` random saved states with the chooser's `args.top` best chunks from one fresh noise each."""
    state_n = torch.cat([load_file(path)["state_n"] for path in args.states.split(",")])
    generator = torch.Generator().manual_seed(args.seed)
    state_n = state_n[torch.randperm(len(state_n), generator=generator)[: args.count]]
    noise = torch.randn(len(state_n), teacher.horizon, teacher.action_dim, generator=generator)
    targets = teacher_top(teacher, state_n, noise, 10, args.top, progress=True)
    save_file({"state_n": state_n.contiguous(), "targets": targets.contiguous()}, args.out)
    print(f"wrote {len(state_n)} states x {args.top} to {args.out}", file=sys.stderr)
    return 0


def train_student(teacher, args: argparse.Namespace) -> int:
    """Train K hypotheses on the labels, save them, print the outcome model's pick's and the argmax's scores (JSON lines)."""
    student = MultiChoice(teacher, args.k, [512, 512, 512])
    horizon, action_dim = student.shape
    if args.init:  # hypotheses init_k.. copy the first ones: winner-takes-all splits them apart
        weights = load_file(args.init)
        last = max(int(name.split(".")[0]) for name in weights)
        split, reps = args.init_k * horizon * action_dim, -(-args.k // args.init_k)
        for suffix in ("weight", "bias"):
            old = weights[f"{last}.{suffix}"]
            ones = [1] * (old.dim() - 1)
            weights[f"{last}.{suffix}"] = torch.cat([old[:split].repeat(reps, *ones)[: args.k * horizon * action_dim],
                                                     old[split:].repeat(reps, *ones)[: args.k]])
        student.net.load_state_dict(weights)
    labels = load_file(args.labels)
    states, targets = labels["state_n"], labels["targets"]
    extra = load_file(args.extra) if args.extra else None
    generator = torch.Generator().manual_seed(0)
    optimizer = torch.optim.AdamW(student.parameters(), lr=args.lr, weight_decay=0.0)
    start = time.time()
    student.train()
    for step in range(1, args.steps + 1):
        for group in optimizer.param_groups:
            group["lr"] = args.lr * 0.5 * (1 + np.cos(np.pi * (step - 1) / args.steps))
        rows = torch.randint(0, len(states), (256,), generator=generator)
        state_n, target = states[rows], targets[rows]
        if extra is not None:  # the single labels repeated to the labels' count
            more = torch.randint(0, len(extra["state_n"]), (128,), generator=generator)
            state_n = torch.cat([state_n[:128], extra["state_n"][more]])
            target = torch.cat([target[:128], extra["target"][more][:, None].expand(-1, targets.shape[1], -1, -1)])
        chunks, logits = student(state_n)
        loss, nearest = winner_takes_all(chunks, target, args.relax)
        loss = loss + CHOICE_WEIGHT * F.cross_entropy(logits, nearest)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step % 2500 == 0:
            print(json.dumps({"step": step, "loss": round(float(loss), 4), "s": round(time.time() - start)}), flush=True)
    student.eval()
    save_file(student.net.state_dict(), args.save)
    for play in ("outcome", "choice"):
        scores = evaluate_policy(Acting(student, play), episodes=args.eval_episodes, seed=400_000).scores()
        print(json.dumps({"play": play, **{k: scores[k] for k in ("success_rate", "success_rate_ci95", "mean_max_reward", "mean_length")}}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Where a one-pass student loses to its chooser: its candidates, or its scores? Each half swapped for the teacher's.

    .venv/bin/python scripts/onepass_diagnostics.py --student runs/onepass-dagger/last --episodes 200

Plays three policies on the same seeds (from one fixed start noise, as the student was labelled):
`student` (its own candidates and scores), `student-candidates` (its candidates, scored by the teacher's
outcome model at the chooser's stretches) and `student-scores` (the teacher's own 64 candidates, chosen
by the student's scores). One JSON line each. Costs the teacher's 896 network evaluations per decision
in the last two.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pusht.seeding import chunk_noise  # noqa: E402
from pusht.spec import ACTION_HIGH, ACTION_LOW  # noqa: E402
from training.checkpoint import load_checkpoint  # noqa: E402
from training.evaluate import evaluate_policy  # noqa: E402
from training.outcome import nearest, stretch  # noqa: E402
from training.policies import ActingPolicy  # noqa: E402

MODES = ("student", "student-candidates", "student-scores")


def main(argv: list[str] | None = None) -> int:
    """Play the three policies and print one JSON line each."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--student", required=True, help="checkpoint stem of a one-pass student (training.distill --student one-pass)")
    parser.add_argument("--episodes", type=int, default=200, help="episodes per policy")
    parser.add_argument("--seed", type=int, default=400000, help="first episode seed (not a held-out one)")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES), help="policies to play")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    student, card = load_checkpoint(args.student)
    if student.onepass is None:
        parser.error(f"{args.student} is not a one-pass student (its card has no onepass_dims)")
    teacher, _ = load_checkpoint(card["teacher"])
    fixed = torch.as_tensor(chunk_noise(int(card["config"]["fixed_noise"]), 1, student.horizon, student.action_dim))
    for mode in args.modes:
        module = ActingPolicy(student.eval(), 1) if mode == "student" else _Swapped(student.eval(), teacher.eval(), fixed, mode)
        summary = evaluate_policy(module, episodes=args.episodes, seed=args.seed)
        scores = summary.scores()
        print(json.dumps({"mode": mode, **{k: scores[k] for k in ("success_rate", "success_rate_ci95", "mean_max_reward", "mean_length", "seeds")}}))
    return 0


class _Swapped(nn.Module):
    """An ActingPolicy-like module: half the student's decision, half the teacher's."""

    def __init__(self, student: nn.Module, teacher: nn.Module, fixed: torch.Tensor, mode: str) -> None:
        super().__init__()
        self.policy, self.teacher, self.fixed, self.mode, self.num_steps = student, teacher, fixed, mode, 1

    @torch.no_grad()
    def forward(self, state, noise=None, num_steps=None, prev_state=None):
        student, teacher, chooser = self.policy, self.teacher, self.teacher.outcome
        state_n = student.policy_state(state)
        candidates, scores = student.onepass(student, state_n)
        rows = torch.arange(len(state))
        if self.mode == "student-candidates":
            states = state.repeat_interleave(chooser.candidates, 0)
            raw = student.normalizer.actions(states, candidates.flatten(0, 1))
            every = torch.cat([torch.clamp(stretch(states, raw, s), ACTION_LOW, ACTION_HIGH).reshape(*candidates.shape)
                               for s in chooser.stretches], dim=1)
            return every[rows, nearest(chooser.distances(state, every))]
        chunks_n, _ = chooser.scored_candidates(teacher, teacher.policy_state(state), self.fixed.expand(len(state), -1, -1), 10)
        return torch.clamp(teacher.normalizer.actions(state, chunks_n[rows, scores.argmin(dim=1)]), ACTION_LOW, ACTION_HIGH)


if __name__ == "__main__":
    sys.exit(main())

"""Where a scoring student's second pass loses its choice: its pick against the teacher's outcome model's, on states it learned from and on fresh ones.

    .venv/bin/python scripts/choice_regret.py --card records/distill-mc16-shared192/student --episodes 300 --seed 31900000

Among the student's own hypotheses, the outcome model's nearest is the target; the second pass's pick costs its
regret (the difference of their `score_target`s: a tenth is a tenth of a standardized log distance). Reported on
`--states` demonstration states (what every second pass first learns from), the same moved by a few pixels, and the
decision states of `--episodes` episodes the student plays from `--seed` (training seeds: where it goes, unseen).
One JSON line per set: the agreement, the regret's mean and 90th percentile, the squared error of the predicted changes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from training.checkpoint import load_checkpoint  # noqa: E402
from training.data import load_replay  # noqa: E402
from training.distill_data import decision_pairs  # noqa: E402
from training.distill_scorer import hypothesis_changes  # noqa: E402
from training.onepass import score_target  # noqa: E402
from training.policies import ActingPolicy  # noqa: E402

TEACHER = "records/flow-outcome16-stretch/last"
MOVED = torch.tensor([3.0, 3.0, 3.0, 3.0, 0.03])
"""how far the moved demonstration states lie from theirs (px, px, px, px, rad), one standard deviation"""


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: one JSON line per state set."""
    parser = argparse.ArgumentParser(prog="python scripts/choice_regret.py", description=__doc__.splitlines()[0])
    parser.add_argument("--card", required=True, help="checkpoint stem of a scoring student (a multichoice student with a second pass)")
    parser.add_argument("--teacher", default=TEACHER, help="the outcome chooser whose model labels the hypotheses")
    parser.add_argument("--states", type=int, default=5000, help="demonstration states drawn")
    parser.add_argument("--episodes", type=int, default=300, help="episodes the student plays for fresh states")
    parser.add_argument("--seed", type=int, default=31_900_000, help="their first seed (training seeds, never held-out ones)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    student, _ = load_checkpoint(args.card)
    teacher, _ = load_checkpoint(args.teacher)
    if student.onepass is None or student.onepass.scorer is None:
        print(f"error: {args.card} has no second pass (onepass_scorer_dims in its architecture)", file=sys.stderr)
        return 2
    student.eval()
    teacher.eval()
    shown = load_replay("data/pusht_lowdim.zarr").states
    drawn = torch.as_tensor(shown[np.random.default_rng(0).integers(0, len(shown), args.states)])
    moved = drawn + torch.randn(drawn.shape, generator=torch.Generator().manual_seed(1)) * MOVED
    visited, _, scores = decision_pairs(ActingPolicy(student, 1), args.episodes, args.seed)
    for name, states in (("demonstrations", drawn), ("demonstrations moved", moved), ("its own episodes", torch.as_tensor(visited))):
        print(json.dumps({"card": args.card, "states": name, **regret(student, teacher, student.policy_state(states))}))
    print(json.dumps({"card": args.card, "played": {k: scores[k] for k in ("episodes", "seeds", "success_rate")}}))
    return 0


@torch.no_grad()
def regret(student, teacher, state_n: torch.Tensor) -> dict:
    """The second pass's pick against the outcome model's among the student's hypotheses at the inputs `state_n`."""
    head = student.onepass
    labels = hypothesis_changes(student, teacher, state_n)
    predicted = head.changes(student, state_n, head(student, state_n)[0])
    target = score_target(head.goal_distances(student, state_n, labels))
    pick = score_target(head.goal_distances(student, state_n, predicted)).argmin(dim=1)
    lost = target.gather(1, pick[:, None])[:, 0] - target.min(dim=1).values
    return {"n": len(state_n), "agreement": round(float((pick == target.argmin(dim=1)).float().mean()), 3),
            "regret_mean": round(float(lost.mean()), 4), "regret_p90": round(float(lost.quantile(0.9)), 4),
            "change_mse": round(float((predicted - labels).pow(2).mean()), 4)}


if __name__ == "__main__":
    sys.exit(main())

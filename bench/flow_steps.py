"""In-process cost of one chunk at batch 1, ONNX Runtime on 1 thread: several exported flows timed side by side.

    .venv/bin/python bench/flow_steps.py --models models/flow.onnx runs/flow-distill-1step/last.onnx

The models are timed in alternating rounds (each round calls every model `--calls` times on the same
states and noises), so machine noise hits all of them alike; medians over rounds are printed, with
each model's ratio to the first. Run it with the cores quiet.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository's packages, installed or not

from acting import read_card  # noqa: E402
from acting.onnx_backend import onnx_session  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Time the models and print one JSON line per model."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument(
        "--models",
        nargs="+",
        required=True,
        help="exported flows (ONNX files, each with its card beside it) of one shape; the first is the baseline",
    )
    parser.add_argument("--rounds", type=int, default=15, help="alternating rounds")
    parser.add_argument("--calls", type=int, default=200, help="calls per model per round")
    parser.add_argument("--batch", type=int, default=1, help="rows per call")
    args = parser.parse_args(argv)
    cards = [read_card(m) for m in args.models]
    shapes = {(c.kind, c.state_dim, c.horizon, c.action_dim) for c in cards}
    if len(shapes) != 1 or cards[0].kind != "flow":
        parser.error(f"the models must be flows of one shape (kind, state_dim, horizon, action_dim), got {sorted(shapes)}")
    card = cards[0]
    sessions = [onnx_session(m, threads=1) for m in args.models]
    rng = np.random.default_rng(0)
    low = [50, 50, 100, 100, 0] if card.state_dim == 5 else [0] * card.state_dim
    high = [450, 450, 400, 400, 6.28] if card.state_dim == 5 else [512] * card.state_dim
    feeds = {
        "state": rng.uniform(low, high, (args.batch, card.state_dim)).astype(np.float32),
        "noise": rng.standard_normal((args.batch, card.horizon, card.action_dim)).astype(np.float32),
    }
    for session in sessions:  # warm-up
        for _ in range(50):
            session.run(["actions"], feeds)
    per_call = [[] for _ in sessions]
    for _ in range(args.rounds):
        for times, session in zip(per_call, sessions):
            start = time.perf_counter()
            for _ in range(args.calls):
                session.run(["actions"], feeds)
            times.append((time.perf_counter() - start) / args.calls)
    base = float(np.median(per_call[0]))
    for model, times in zip(args.models, per_call):
        median = float(np.median(times))
        print(
            json.dumps(
                {
                    "model": model,
                    "batch": args.batch,
                    "ms_per_chunk_median": round(median * 1e3, 4),
                    "ms_per_chunk_min_round": round(min(times) * 1e3, 4),
                    "ratio_to_first": round(median / base, 3),
                }
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Diagnostics of the policies' pace, outside the served contract: resampled chunks, and two flows gated by goal distance.

    python scripts/pace_diagnostics.py resample --model models/flow.onnx --speed 1.5
    python scripts/pace_diagnostics.py gate --far runs/flow-speed2.0-padend-150k/last.onnx --far-noise-scale 0.3 \
        --near models/flow.onnx --radius 2.0
    python scripts/pace_diagnostics.py phases --model models/flow.onnx --max-steps 900
    python scripts/pace_diagnostics.py acting-pace --model runs/flow-paceinput2.5-padend-150k/last --rule 2 1 2 0 --noise-scale 0.3

`resample` plays each chunk `speed` times as fast (linear interpolation between its actions) and so
executes only floor(11 / speed) + 1 actions of it before asking again; `gate` takes, per row, the far
flow's chunk when the block is at least `radius` goal units from the goal (training.pace) and the near
flow's otherwise, all 12 actions executed. Neither is a shippable policy (the first breaks the
12-actions-open-loop rule, the second runs two networks); they measure what pace is worth. `phases`
plays one flow as served and reports where its episodes spend their steps: the median step at which
the block first covers 0.3 and 0.9 of the goal, and of success. `acting-pace` plays a flow with a pace
input as served, at another acting rule (a copy of the checkpoint with that rule and start-noise scale,
exported to ONNX in a temporary folder: what `training.ship --acting-pace` would ship). Prints one JSON line, with the scores
as training.evaluate prints them. Tuning seeds only (default 300000).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from acting import load_policy, rollout_act
from pusht.rollout import run_episodes
from training.cli import HelpFormatter
from training.pace import goal_distance


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(prog="python scripts/pace_diagnostics.py", description=__doc__.splitlines()[0], formatter_class=HelpFormatter)
    sub = parser.add_subparsers(dest="mode", required=True)
    resample = sub.add_parser("resample", help="one flow, each chunk played SPEED times as fast", formatter_class=HelpFormatter)
    resample.add_argument("--model", required=True, help="ONNX file or checkpoint stem")
    resample.add_argument("--speed", type=float, required=True, help="pace multiplier (executes floor(11 / speed) + 1 actions per chunk)")
    resample.add_argument("--noise-scale", type=float, default=1.0, help="start-noise multiplier on top of the card's")
    gate = sub.add_parser("gate", help="two flows, chosen per row by the block's goal distance", formatter_class=HelpFormatter)
    gate.add_argument("--far", required=True, help="the flow acting at least RADIUS goal units from the goal")
    gate.add_argument("--near", required=True, help="the flow acting closer")
    gate.add_argument("--radius", type=float, default=2.0, help="goal distance (40 px + 0.6 rad per unit) that separates them")
    gate.add_argument("--far-noise-scale", type=float, default=1.0, help="start-noise multiplier of the far flow")
    gate.add_argument("--near-noise-scale", type=float, default=1.0, help="start-noise multiplier of the near flow")
    phases = sub.add_parser("phases", help="one flow as served: when its episodes first reach coverage 0.3, 0.9 and success", formatter_class=HelpFormatter)
    phases.add_argument("--model", required=True, help="ONNX file or checkpoint stem")
    phases.add_argument("--noise-scale", type=float, default=1.0, help="start-noise multiplier on top of the card's")
    phases.add_argument("--max-steps", type=int, default=300, help="episode step limit")
    paced = sub.add_parser("acting-pace", help="a flow with a pace input, as served at another acting rule", formatter_class=HelpFormatter)
    paced.add_argument("--model", required=True, help="checkpoint stem of a flow with a pace input")
    paced.add_argument("--rule", type=float, nargs=4, required=True, metavar=("FAR", "NEAR", "RADIUS", "RAMP"), help="the acting rule (training.pace)")
    paced.add_argument("--noise-scale", type=float, default=1.0, help="the sampling noise_scale to set in the copy")
    for p in (resample, gate, phases, paced):
        p.add_argument("--episodes", type=int, default=1000, help="episodes (seeds seed..seed+episodes-1)")
        p.add_argument("--seed", type=int, default=300000, help="first episode seed (use tuning seeds, never held-out ones)")
    args = parser.parse_args(argv)
    seeds = list(range(args.seed, args.seed + args.episodes))
    if args.mode == "acting-pace":
        summary, extra = run_episodes(rollout_act(paced_copy(args.model, args.rule, args.noise_scale)), seeds, num_envs=100), {}
    elif args.mode == "phases":
        summary = run_episodes(rollout_act(load_policy(args.model), args.noise_scale), seeds, num_envs=100, max_steps=args.max_steps,
                               record_trajectories=True)
        extra = phase_steps(summary)
    else:
        act, action_horizon = resampled(args) if args.mode == "resample" else gated(args)
        summary, extra = run_episodes(act, seeds, num_envs=100, action_horizon=action_horizon), {}
    print(json.dumps({"mode": args.mode, **{k: v for k, v in vars(args).items() if k != "mode"}, **summary.scores(), **extra}))
    return 0


def phase_steps(summary) -> dict:
    """Median first steps of coverage > 0.3 and > 0.9 over the episodes that reach them, and of success; counts beside."""
    from pusht.geometry import coverage

    firsts: dict[str, list[int]] = {"0.3": [], "0.9": [], "success": []}
    for trajectory, episode in zip(summary.trajectories, summary.episodes):
        covered = [coverage(float(s[2]), float(s[3]), float(s[4])) for s in trajectory.states]
        for key in ("0.3", "0.9"):
            # a trajectory holds the state before each step, not the one a success ends on: a push that covers from
            # under 0.9 to success in its last step reached 0.9 there too
            step = next((t for t, c in enumerate(covered) if c > float(key)), episode.length if episode.success else None)
            if step is not None:
                firsts[key].append(step)
        if episode.success:
            firsts["success"].append(episode.length)
    return {f"median_first_step_{k}": float(np.median(v)) if v else None for k, v in firsts.items()} | {
        f"episodes_reaching_{k}": len(v) for k, v in firsts.items()}


def paced_copy(stem: str, rule: list[float], noise_scale: float):
    """The ONNX policy of a copy of checkpoint `stem` acting at `rule` and `noise_scale`, in a temporary folder."""
    import shutil
    import tempfile
    from pathlib import Path

    from training.checkpoint import checkpoint_stem, set_acting_pace, set_noise_scale
    from training.export import export_onnx

    source = checkpoint_stem(stem)
    copy = Path(tempfile.mkdtemp(prefix="acting-pace-")) / "policy"
    for suffix in (".safetensors", ".json"):
        shutil.copyfile(source.with_suffix(suffix), copy.with_suffix(suffix))
    try:
        set_acting_pace(copy, rule)
        set_noise_scale(copy, noise_scale)
        export_onnx(copy)
        return load_policy(copy.with_suffix(".onnx"))  # ONNX Runtime holds the graph in memory: the copy can go
    finally:
        shutil.rmtree(copy.parent)


def resampled(args: argparse.Namespace):
    """The act function playing chunks `args.speed` times as fast, and how many actions of each it executes."""
    policy = load_policy(args.model)
    base = rollout_act(policy, args.noise_scale)
    horizon = policy.card.horizon
    executed = int(np.floor((horizon - 1) / args.speed + 1e-9)) + 1
    positions = args.speed * np.arange(executed)
    below = np.floor(positions).astype(np.int64)
    above = np.minimum(below + 1, horizon - 1)
    weight = (positions - below)[None, :, None]

    def act(states: np.ndarray, seeds: list[int]) -> np.ndarray:
        chunks = base(states, seeds)
        return (1 - weight) * chunks[:, below] + weight * chunks[:, above]

    return act, executed


def gated(args: argparse.Namespace):
    """The act function taking the far flow's chunk away from the goal and the near flow's close to it (whole chunks)."""
    far = rollout_act(load_policy(args.far), args.far_noise_scale)
    near = rollout_act(load_policy(args.near), args.near_noise_scale)

    def act(states: np.ndarray, seeds: list[int]) -> np.ndarray:
        use_far = goal_distance(states) >= args.radius
        return np.where(use_far[:, None, None], far(states, seeds), near(states, seeds))

    return act, None


if __name__ == "__main__":
    sys.exit(main())

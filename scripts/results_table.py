"""Print the markdown table of every recorded training run's held-out scores (records/*/).

    python scripts/results_table.py [--records-dir records] [--models-dir models] [--env pusht]

One row per run and checkpoint (final, best), from the cards that `python -m training.ship` wrote,
so the numbers in models/README.md come from a command. A run shipped as models/NAME.* says so.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository's packages, installed or not

from acting import CardError, read_card  # noqa: E402  (the one card reader)

DEFAULT_ARCH_KEYS = ("hidden_dims", "horizon", "action_dim", "state_dim")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records-dir", default="records", help="folder of the run records that training.ship writes")
    parser.add_argument("--models-dir", default="models", help="folder of the shipped policies")
    parser.add_argument("--env", nargs="+", default=["pusht", "gym-pusht"], help="envs whose scores to list")
    args = parser.parse_args(argv)
    models = Path(args.models_dir)
    records = sorted(p for p in Path(args.records_dir).glob("*") if (p / "last.json").is_file())
    if not records:
        print(f"error: no run records (*/last.json) in {args.records_dir}", file=sys.stderr)
        return 2
    try:
        return _table(records, models, args.env)
    except CardError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def _table(records: list[Path], models: Path, envs: list[str]) -> int:
    shipped = {}
    for path in models.glob("*.json"):
        card = read_card(path).data
        shipped[Path(card.get("run", "")).name] = path.stem

    print("| run | kind | changes from the recipe | checkpoint | steps | train time | env "
          "| mean max reward (95% CI) | success (95% CI) | held-out seeds | shipped as |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for record in records:
        for label in ("final", "best"):
            path = record / ("last.json" if label == "final" else "best.json")
            if not path.is_file():
                continue
            card = read_card(path).data
            for env, score in (card.get("heldout_evaluation") or {}).items():
                if env not in envs:
                    continue
                print(
                    f"| {record.name} | {card['kind']} | {_changes(card)} | {label} | {card['steps']:,} "
                    f"| {card['wall_time_s'] / 60:.0f} min | {env} | {_with_ci(score, 'mean_max_reward')} "
                    f"| {_with_ci(score, 'success_rate', percent=True)} | {score['seeds'][0]}..{score['seeds'][1]} "
                    f"| {shipped.get(record.name, '') if label == 'final' else ''} |"
                )
    return 0


def _changes(card: dict) -> str:
    """The architecture and config choices that differ from the published recipe, in a few words."""
    arch = {k: v for k, v in card["architecture"].items() if k not in DEFAULT_ARCH_KEYS}
    config = card.get("config", {})
    parts = [f"{k}={v}" for k, v in arch.items() if not (k == "dropout" and v == 0.1)]
    noise = (config.get("state_noise_start"), config.get("state_noise_end"), config.get("state_noise_schedule"))
    if "state_noise_start" in config and noise != (0.05, 0.05, "constant"):
        parts.append(f"state noise {noise[0]}->{noise[1]} {noise[2]}")
    if config.get("pad_episode_end"):
        parts.append("end-padded windows")
    if config.get("pace_copies"):
        parts.append(f"each window {config['pace_copies']} times at paces 1..{config['action_speed']:g}x, the pace an input")
    elif config.get("action_speed", 1.0) != 1.0:
        near = config.get("action_speed_near") or config["action_speed"]
        ramp = f", rising over {config['speed_ramp']:g}" if config.get("speed_ramp") else ""
        where = f" ({near:g}x within {config['speed_radius']:g} of the goal{ramp})" if near != config["action_speed"] else ""
        parts.append(f"chunks at {config['action_speed']:g}x the demonstrations' pace{where}")
    if config.get("lr", 3e-4) != 3e-4:
        parts.append(f"lr {config['lr']:g}")
    if config.get("seed", 0):
        parts.append(f"seed {config['seed']}")
    if config.get("init"):
        parts.append(f"fine-tuned from {config['init']}")
    if config.get("extra_data"):
        parts.append(f"plus the episodes in {config['extra_data']}")
    return ", ".join(parts) or "none"


def _with_ci(score: dict, key: str, percent: bool = False) -> str:
    low, high = score[f"{key}_ci95"]
    if percent:
        return f"{100 * score[key]:.0f} % ({100 * low:.0f}..{100 * high:.0f})"
    return f"{score[key]:.3f} ({low:.3f}..{high:.3f})"


if __name__ == "__main__":
    sys.exit(main())

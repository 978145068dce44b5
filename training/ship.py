"""Record a finished training run's held-out scores and, optionally, ship its final checkpoint as `models/NAME`.

    python -m training.ship --run runs/flow-agentframe-padend-150k --name flow   # record and ship
    python -m training.ship --run runs/mse-recipe-200k                           # record only

Only a finished run is taken (its `last` card says `finished`). Every run gets a compact record in
`records/RUN/`: the cards of its final (`last.json`) and best (`best.json`) checkpoints, each with
`heldout_evaluation` (scores on held-out episode seeds, never used in training, in every requested
env), its learning curve and its log (`log.jsonl.gz`). With `--name`, the final checkpoint becomes
`models/NAME.{safetensors,json,onnx}` (scored through its ONNX export, what the service runs), the
record keeps the best checkpoint's weights, and the first held-out episode goes to
`models/NAME_rollout.gif`. A shipped policy that scores better on the same held-out seeds stays unless
`--force`. One JSON line is printed per evaluation.
"""

from __future__ import annotations

import argparse
import gzip
import json
import shutil
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from policies.checkpoint import (
    CheckpointError,
    load_card,
    set_acting_pace,
    set_noise_scale,
    set_outcome_candidates,
    update_card,
    write_text_atomic,
)
from pusht.spec import HELD_OUT_SEED
from training.config import HelpFormatter, command_line
from training.evaluate import ENVS, evaluate_policy, load_model, report, write_gif
from training.export import export_onnx

SHIPPED_SUFFIXES = (".safetensors", ".onnx", ".json")  # the card last: the service finds a policy by its card


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        lines = ship(
            ShipConfig(
                Path(args.run),
                args.name,
                Path(args.models_dir),
                Path(args.records_dir),
                args.episodes,
                args.seed,
                args.envs,
                args.note,
                args.force,
                args.noise_scale,
                args.acting_pace,
                args.outcome_candidates,
            )
        )
        for line in lines:
            print(json.dumps(line))
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def _parser() -> argparse.ArgumentParser:
    """The command line."""
    parser = argparse.ArgumentParser(
        prog="python -m training.ship", description=__doc__.splitlines()[0], formatter_class=HelpFormatter
    )
    parser.add_argument("--run", required=True, help="the finished run folder written by training.train (has last.* and best.*)")
    parser.add_argument(
        "--name", default=None, help="ship the final checkpoint as MODELS_DIR/NAME (e.g. flow, mse); omit to only record the run"
    )
    parser.add_argument("--models-dir", default="models", help="where shipped policies live")
    parser.add_argument("--records-dir", default="records", help="where run records live")
    parser.add_argument("--episodes", type=int, default=100, help="held-out episodes")
    parser.add_argument("--seed", type=int, default=HELD_OUT_SEED, help="first held-out episode seed")
    parser.add_argument("--envs", nargs="+", choices=ENVS, default=list(ENVS), help="envs to score in")
    parser.add_argument(
        "--noise-scale",
        type=float,
        default=None,
        help="flow: set the sampling noise_scale of the run's final and best checkpoints first (chosen on non-held-out seeds)",
    )
    parser.add_argument(
        "--acting-pace",
        type=float,
        nargs=4,
        default=None,
        metavar=("FAR", "NEAR", "RADIUS", "RAMP"),
        help="flow with a pace input: set the pace it acts at by goal distance (policies.pace), like --noise-scale",
    )
    parser.add_argument(
        "--outcome-candidates",
        type=int,
        default=None,
        metavar="K",
        help="flow with an outcome chooser: set how many candidate chunks it integrates, like --noise-scale",
    )
    parser.add_argument("--note", default="", help="what changed from the published recipe and why (stored in the card)")
    parser.add_argument(
        "--force", action="store_true", help="replace MODELS_DIR/NAME even if it scores better on the held-out seeds"
    )
    return parser


@dataclass
class ShipConfig:
    """What `ship` records and ships (the command's options): `noise_scale`, `acting_pace` and `outcome_candidates` (flow)
    are first set on the run's final and best checkpoints, so every score and export uses them."""

    run: Path
    name: str | None
    models_dir: Path = Path("models")
    records_dir: Path = Path("records")
    episodes: int = 100
    seed: int = HELD_OUT_SEED
    envs: list[str] = field(default_factory=lambda: list(ENVS))
    note: str = ""
    force: bool = False
    noise_scale: float | None = None
    acting_pace: list[float] | None = None
    outcome_candidates: int | None = None


def ship(cfg: ShipConfig) -> list[dict[str, Any]]:
    """Record `cfg.run` in `cfg.records_dir`, ship its final checkpoint as `models_dir/name` if named; returns the reports."""
    run, name, models_dir, episodes, seed, envs = cfg.run, cfg.name, cfg.models_dir, cfg.episodes, cfg.seed, cfg.envs
    check_finished(run)
    has_best = (run / "best.json").is_file()
    for checkpoint in ("last", "best") if has_best else ("last",):
        _apply_acting_settings(run / checkpoint, cfg)
    record = cfg.records_dir / run.name
    extra = {"recipe_changes": cfg.note} if cfg.note else {}
    reports: list[dict[str, Any]] = []
    staging = None
    try:
        if name is None:
            final = score_heldout(run / "last", run / "last", episodes, seed, envs, reports, "final")[0]
        else:
            # the candidate is built and scored aside, so a refused or failed ship leaves models/ as it was
            models_dir.mkdir(parents=True, exist_ok=True)
            staging = Path(tempfile.mkdtemp(prefix=f".ship-{name}-", dir=models_dir))
            staged = staging / name
            shutil.copyfile(run / "last.safetensors", staged.with_suffix(".safetensors"))
            card = load_card(run / "last") | extra
            card.update(name=name, run=str(record), reproduce=reproduce_commands(card, run, name))
            write_text_atomic(staged.with_suffix(".json"), json.dumps(card, indent=2, allow_nan=False) + "\n")
            export_onnx(staged)
            final, frames = score_heldout(
                staged.with_suffix(".onnx"), models_dir / f"{name}.onnx", episodes, seed, envs, reports, "final", gif=True
            )
            check_replacement(models_dir / name, final[envs[0]], envs[0], cfg.force)
        best = score_heldout(run / "best", run / "best", episodes, seed, envs, reports, "best")[0] if has_best else None

        write_record(run, record, final, best, extra, keep_best_weights=name is not None)
        if staging is not None:
            update_card(staged, heldout_evaluation=final)
            for suffix in SHIPPED_SUFFIXES:
                staged.with_suffix(suffix).replace((models_dir / name).with_suffix(suffix))
            write_gif(frames, models_dir / f"{name}_rollout.gif")
    finally:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
    return reports


def _apply_acting_settings(stem: Path, cfg: ShipConfig) -> None:
    """Write the ship stage's acting settings (those it sets) into the checkpoint's card."""
    if cfg.noise_scale is not None:
        set_noise_scale(stem, cfg.noise_scale)
    if cfg.acting_pace is not None:
        set_acting_pace(stem, cfg.acting_pace)
    if cfg.outcome_candidates is not None:
        set_outcome_candidates(stem, cfg.outcome_candidates)


def check_finished(run: Path) -> dict[str, Any]:
    """The run's `last` card; ValueError unless the run finished (cards from before the flag: steps == configured steps)."""
    if not (run / "last.json").is_file() or not (run / "last.safetensors").is_file():
        raise FileNotFoundError(f"{run / 'last.json'} or its weights are missing: is {run} a training run folder?")
    card = load_card(run / "last")
    target = card["config"].get("steps")
    if not card.get("finished", card["steps"] == target):
        raise ValueError(
            f"{run} is not finished (its last checkpoint is at step {card['steps']:,} of {target:,}): "
            "continue it with its training command and --resume before shipping"
        )
    return card


def check_replacement(stem: Path, new: dict[str, Any], env: str, force: bool) -> None:
    """ValueError (both scores in it) if the policy shipped at `stem` scores better than `new` on the same seeds, or cannot be compared."""
    if not stem.with_suffix(".json").is_file() or force:
        return
    try:
        old = (load_card(stem).get("heldout_evaluation") or {}).get(env)
    except CheckpointError:
        old = None
    label = f"{new['mean_max_reward']:.3f} mean max reward, {100 * new['success_rate']:.0f} % success"
    if old is None or old.get("seeds") != new["seeds"]:
        seeds = "no held-out score" if old is None else f"seeds {old['seeds'][0]}..{old['seeds'][1]}"
        raise ValueError(
            f"{stem} ({seeds} in {env}) cannot be compared with this run ({label}, seeds "
            f"{new['seeds'][0]}..{new['seeds'][1]}): not replaced; --force replaces it"
        )
    if old["mean_max_reward"] > new["mean_max_reward"]:
        raise ValueError(
            f"{stem} scores {old['mean_max_reward']:.3f} mean max reward, {100 * old['success_rate']:.0f} % success "
            f"in {env} (seeds {new['seeds'][0]}..{new['seeds'][1]}), this run {label}: not replaced; "
            "--force replaces it, and without --name the run is only recorded"
        )


def write_record(
    run: Path, record: Path, final: dict[str, Any], best: dict[str, Any] | None, extra: dict[str, Any], keep_best_weights: bool
) -> None:
    """records/RUN: the final and best cards with their held-out scores, the learning curve, the compressed log."""
    if record.exists():
        shutil.rmtree(record)
    record.mkdir(parents=True)
    for label, scores in (("last", final), ("best", best)):
        if scores is None:
            continue
        card = load_card(run / label) | (extra if label == "last" else {}) | {"heldout_evaluation": scores}
        write_text_atomic(record / f"{label}.json", json.dumps(card, indent=2, allow_nan=False) + "\n")
    if (run / "learning_curve.png").is_file():
        shutil.copyfile(run / "learning_curve.png", record / "learning_curve.png")
    if (run / "log.jsonl").is_file():
        # mtime=0: the same log gives the same bytes, so re-recording a run does not churn git
        (record / "log.jsonl.gz").write_bytes(gzip.compress((run / "log.jsonl").read_bytes(), mtime=0))
    if keep_best_weights and best is not None:
        shutil.copyfile(run / "best.safetensors", record / "best.safetensors")


def reproduce_commands(card: dict[str, Any], run: Path, name: str) -> list[str]:
    """The training (or fine-tuning) command that made the run and the ship command that made `models/NAME`."""
    # a fine-tuned run's card carries its own command; its config is not a training.train config
    made = None
    if isinstance(card.get("reproduce"), dict):
        made = card["reproduce"].get("finetune") or card["reproduce"].get("distill")
    ship_command = f"python -m training.ship --run {run} --name {name}"
    scale = card["architecture"].get("noise_scale")
    if scale is not None:
        ship_command += f" --noise-scale {scale:g}"
    rule = card["architecture"].get("acting_pace")
    if rule is not None:
        ship_command += " --acting-pace " + " ".join(f"{v:g}" for v in rule)
    candidates, fitted = card["architecture"].get("outcome_candidates", 16), (card.get("config") or {}).get("candidates")
    if card["architecture"].get("outcome_dims") is not None and fitted is not None and candidates != fitted:
        ship_command += f" --outcome-candidates {candidates}"  # chosen at shipping, as the noise scale
    return [made or command_line(card["config"]), ship_command]


def score_heldout(
    model: Path,
    label: Path,
    episodes: int,
    seed: int,
    envs: list[str],
    reports: list[dict[str, Any]],
    checkpoint: str,
    gif: bool = False,
) -> tuple[dict[str, Any], list[Any]]:
    """Held-out scores of `model` per env (reports appended, named `label`) and the first env's first-episode frames if `gif`."""
    scores, frames = {}, []
    policy = load_model(model)
    for env in envs:
        record_frames = gif and env == envs[0]
        summary = evaluate_policy(policy, episodes=episodes, seed=seed, env=env, record_frames=record_frames)
        if record_frames:
            frames = summary.frames
        scores[env] = report(summary, model=str(label), kind=policy.kind, env=env)
        reports.append({"checkpoint": checkpoint, **scores[env]})
    return scores, frames


if __name__ == "__main__":
    sys.exit(main())

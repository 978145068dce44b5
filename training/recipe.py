"""Run a recipe: the ordered stages that make one shipped policy, from the demonstrations to `models/`.

    python -m training.recipe recipes/flow.toml
    python -m training.recipe recipes/flow.toml --scale 0.01 --out-dir runs/smoke --models-dir runs/smoke/models \\
        --records-dir runs/smoke/records                      # a smoke run in minutes; models/ untouched

A recipe file (TOML) names the policy it ships and lists its `[[stage]]`s. Each stage has a `name`, a
`run` (train, finetune, collect or ship), optionally `from` (the stage whose checkpoint it takes; default
the previous one; a train stage starts fresh unless it names one) and `acting` (sampling settings written
on its output checkpoint, such as noise_scale), and only the settings that differ from that command's
defaults. A collect stage plays its source's episodes (training.collect) and keeps the successful ones; a
train stage's `extra_from` lists collect stages whose episodes it learns from beside the demonstrations. A stage's output is cached in
OUT_DIR/STAGE-KEY, KEY a hash of its settings and its inputs: a second run is all cached, a
changed stage reruns with the stages after it. A stopped stage (SIGTERM, SIGINT) resumes on the next
run. The shipped card cites the recipe file and its sha256, the commit, and every stage's wall time.

With --reuse-shipped, a stage whose output already ships (a card in MODELS_DIR lists the same key just before its
ship stage) is restored from MODELS_DIR instead of run, and the stages only it needs are not run either: a fresh clone
then runs only what the shipped policies do not hold. The card marks those stages `restored_from`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from training.cli import HelpFormatter
from training.recipe_file import Recipe, RecipeError, Stage, load_recipe

if TYPE_CHECKING:
    from training.recipe_reuse import ShippedStages

__all__ = ["Recipe", "RecipeError", "Stage", "load_recipe", "main", "run_recipe"]

# per stage kind: the settings --scale shrinks (counts of steps, iterations, episodes and the intervals between them)
SCALED = {
    "train": ("steps", "eval_every", "eval_episodes", "checkpoint_every", "log_every"),
    "finetune": (
        "iterations",
        "eval_every",
        "eval_episodes",
        "checkpoint_every",
        "learning_starts",
        "log_every",
        "value_episodes",
        "value_updates",
        "dagger_episodes",
        "dagger_updates",
        "ppo_warmup",
    ),
    "collect": ("episodes",),
    "ship": ("episodes",),
}
DONE_FILE = "stage.json"


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: 0 when every stage finished, 2 on a bad recipe or setting, 128 + N when stopped by signal N."""
    parser = argparse.ArgumentParser(
        prog="python -m training.recipe", description=__doc__.splitlines()[0], formatter_class=HelpFormatter
    )
    parser.add_argument("recipe", help="the recipe file, e.g. recipes/flow.toml")
    parser.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="multiply every stage's steps, iterations and episodes by this (0.01: a smoke run)",
    )
    parser.add_argument("--out-dir", default="runs/recipes", help="where stage outputs are cached")
    parser.add_argument("--models-dir", default="models", help="where the ship stage writes the policy")
    parser.add_argument("--records-dir", default="records", help="where the ship stage writes the run's small evidence")
    parser.add_argument("--threads", type=int, default=None, help="torch threads of every stage (default: each stage's own)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument(
        "--reuse-shipped",
        action="store_true",
        help="restore a stage whose output ships in MODELS_DIR (same key) instead of running it and what only it needs",
    )
    args = parser.parse_args(argv)
    if not 0 < args.scale <= 1:
        parser.error(f"--scale must be in (0, 1], got {args.scale}")
    try:
        recipe = load_recipe(Path(args.recipe))
        options = RunOptions(
            Path(args.out_dir),
            Path(args.models_dir),
            Path(args.records_dir),
            args.scale,
            args.threads,
            not args.no_progress,
            args.reuse_shipped,
        )
        results = run_recipe(recipe, options)
    except (RecipeError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(summary_table(results))
    stopped = [r for r in results if r.exit_code]
    if stopped:
        print(f"stopped in stage {stopped[0].stage}; run the same command again to resume it", file=sys.stderr)
        return stopped[0].exit_code
    return 0


@dataclass
class RunOptions:
    """Where a recipe run writes and how much of each stage it runs."""

    out_dir: Path
    models_dir: Path
    records_dir: Path
    scale: float = 1.0
    threads: int | None = None
    progress: bool = True
    reuse_shipped: bool = False

    def stage_dir(self, name: str, key: str) -> Path:
        """A stage's output folder: recipes that share a stage (same key) share it."""
        return self.out_dir / f"{name}-{key}"


@dataclass
class StageResult:
    """What a stage left: its folder, its cache key, its wall time, whether it was cached, its score."""

    stage: str
    run: str
    key: str
    dir: Path
    wall_time_s: float
    cached: bool
    score: dict[str, Any] | None
    exit_code: int = 0
    restored_from: dict[str, str] | None = None
    """the shipped policy (and its commit) whose card gave this stage's output, under --reuse-shipped"""

    def as_card(self) -> dict[str, Any]:
        card = {
            "name": self.stage,
            "run": self.run,
            "key": self.key,
            "wall_time_s": round(self.wall_time_s, 1),
            "score": self.score,
        }
        return card | ({"restored_from": self.restored_from} if self.restored_from else {})


def run_recipe(recipe: Recipe, options: RunOptions) -> list[StageResult]:
    """Run (or take from the cache, or from the shipped policies) every stage in order; stops after a stage that was
    stopped by a signal."""
    from policies.checkpoint import git_commit
    from training.recipe_reuse import ShippedStages

    commit = git_commit()
    keys = stage_keys(recipe, options.scale)
    shipped = ShippedStages.read(options.models_dir) if options.reuse_shipped else ShippedStages()
    needed = _needed(recipe, keys, options, shipped)
    results: dict[str, StageResult] = {}
    for index, stage in enumerate(recipe.stages, 1):
        key = keys[stage.name]
        stage_dir = options.stage_dir(stage.name, key)
        print(f"[{index}/{len(recipe.stages)}] {stage.name} ({stage.run}) -> {stage_dir}", file=sys.stderr, flush=True)
        if stage.name not in needed:
            print("  not needed: the stages after it are restored from the shipped policies", file=sys.stderr)
            results[stage.name] = shipped.result(stage, key, stage_dir)
            continue
        result = _cached(stage, key, stage_dir, options.models_dir / f"{recipe.policy}.json") or shipped.restore(
            recipe, stage, key, stage_dir
        )
        if result is None:
            from training.recipe_stages import StageContext

            before = list(results.values())
            result = _run_stage(
                StageContext(recipe, stage, scaled(stage, options.scale), stage_dir, options, before, commit, key)
            )
        results[stage.name] = result
        if result.exit_code:
            break
    return list(results.values())


def stage_keys(recipe: Recipe, scale: float) -> dict[str, str]:
    """Every stage's cache key, in order (a key hashes its inputs' keys)."""
    keys: dict[str, str] = {}
    shipped = {"policy": recipe.policy, "description": recipe.description, "default": recipe.default}
    for stage in recipe.stages:
        keys[stage.name] = stage_key(stage, scaled(stage, scale), keys, scale, shipped if stage.run == "ship" else None)
    return keys


def _needed(recipe: Recipe, keys: dict[str, str], options: RunOptions, shipped: ShippedStages) -> set[str]:
    """The stages to run or take from the cache: all of them, but under --reuse-shipped those whose every reader is
    cached or restored (and whose own record the shipped cards keep)."""
    names = [s.name for s in recipe.stages]
    if not options.reuse_shipped:
        return set(names)
    needed = {names[-1]}
    for stage in reversed(recipe.stages):
        key = keys[stage.name]
        if stage.name not in needed and key in shipped.records:
            continue
        needed.add(stage.name)
        done = _done_record(stage, key, options.stage_dir(stage.name, key), options.models_dir / f"{recipe.policy}.json")
        if done is None and shipped.acting(recipe, stage, key) is None:
            needed.update(stage.inputs)
    return needed


def scaled(stage: Stage, scale: float) -> dict[str, Any]:
    """The stage's settings with its counts multiplied by `scale` (at least 1 each)."""
    from training.collect import CollectConfig
    from training.config import TrainConfig
    from training.finetune_config import FinetuneConfig

    defaults = {"train": TrainConfig, "finetune": FinetuneConfig, "collect": CollectConfig}.get(stage.run)
    settings = dict(stage.settings)
    if scale == 1:
        return settings
    for name in SCALED[stage.run]:
        value = settings.get(name, _default(defaults, name) if defaults else SHIP_DEFAULTS[name])
        if value > 0:
            settings[name] = max(1, round(value * scale))
    return settings


SHIP_DEFAULTS = {"episodes": 500}


def _default(cls: type, name: str) -> Any:
    return next(f.default for f in fields(cls) if f.name == name)


def stage_key(
    stage: Stage, settings: dict[str, Any], keys: dict[str, str], scale: float, shipped: dict[str, Any] | None = None
) -> str:
    """A hash of what the stage computes from: its kind, settings, acting settings and its inputs (the keys of the
    stages it reads, the data; for ship also what the recipe says of the policy it ships)."""
    inputs: dict[str, Any] = {"from": keys[stage.source] if stage.source else None}
    if stage.extra_sources:
        inputs["extra"] = [keys[name] for name in stage.extra_sources]
    if stage.teacher:
        inputs["teacher"] = keys[stage.teacher]
    if shipped is not None:
        inputs["shipped"] = shipped
    if stage.run == "train":
        inputs["data"] = tree_sha256(Path(settings.get("data", "data/pusht_lowdim.zarr")))
    text = json.dumps(
        {"run": stage.run, "settings": settings, "acting": stage.acting, "inputs": inputs, "scale": scale}, sort_keys=True
    )
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def tree_sha256(path: Path) -> str:
    """sha256 over a file or a folder's files (relative names and bytes), so a changed dataset changes the stage keys."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: the training data is missing")
    digest = hashlib.sha256()
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    for file in files:
        digest.update(str(file.relative_to(path) if file != path else file.name).encode())
        digest.update(file.read_bytes())
    return digest.hexdigest()


def _cached(stage: Stage, key: str, stage_dir: Path, shipped_card: Path) -> StageResult | None:
    """The stage's result if its folder holds a finished run of the same key (ship: and the shipped card is its output)."""
    record = _done_record(stage, key, stage_dir, shipped_card)
    if record is None:
        return None
    print(f"  cached ({record['wall_time_s']:.0f} s when it ran)", file=sys.stderr)
    restored = record.get("restored_from")
    return StageResult(stage.name, stage.run, key, stage_dir, record["wall_time_s"], True, record.get("score"), 0, restored)


def _done_record(stage: Stage, key: str, stage_dir: Path, shipped_card: Path) -> dict[str, Any] | None:
    done = stage_dir / DONE_FILE
    if not done.is_file():
        return None
    record = json.loads(done.read_text())
    if record.get("key") != key:
        return None
    if stage.run == "ship" and not _shipped_by(shipped_card, key):
        return None
    return record


def _shipped_by(card: Path, key: str) -> bool:
    try:
        stages = json.loads(card.read_text()).get("stages") or [{}]
    except (OSError, ValueError):
        return False
    return stages[-1].get("key") == key


def _run_stage(context: Any) -> StageResult:
    """Run one stage that is not cached; a stage that finished leaves its DONE_FILE."""
    from training import recipe_stages

    stage, stage_dir, key, commit = context.stage, context.stage_dir, context.key, context.commit
    runner = {
        "train": recipe_stages.train,
        "finetune": recipe_stages.finetune,
        "collect": recipe_stages.collect,
        "ship": recipe_stages.ship,
    }[stage.run]
    started = time.perf_counter()
    outcome = runner(context)
    wall = outcome.wall_time_s if outcome.wall_time_s is not None else time.perf_counter() - started
    result = StageResult(stage.name, stage.run, key, stage_dir, wall, False, outcome.score, outcome.exit_code)
    if not outcome.exit_code:
        record = {
            "key": key,
            "stage": stage.name,
            "run": stage.run,
            "wall_time_s": wall,
            "score": outcome.score,
            "git_commit": commit,
        }
        (stage_dir / DONE_FILE).write_text(json.dumps(record, indent=2) + "\n")
    return result


def summary_table(results: list[StageResult]) -> str:
    """The end-of-run table: stage, kind, wall time, cached or run, score."""
    lines = ["| stage | run | wall time | cached | score |", "| --- | --- | --- | --- | --- |"]
    for r in results:
        status = "stopped" if r.exit_code else ("restored" if r.restored_from else "cached" if r.cached else "ran")
        lines.append(f"| {r.stage} | {r.run} | {r.wall_time_s:.0f} s | {status} | {format_score(r.score)} |")
    total = sum(r.wall_time_s for r in results)
    lines.append(f"| total | | {total:.0f} s | | |")
    return "\n".join(lines)


def format_score(score: dict[str, Any] | None) -> str:
    if not score:
        return "-"
    first, last = score["seeds"]
    return (
        f"{100 * score['success_rate']:.1f} % success, {score['mean_max_reward']:.3f} mean max reward "
        f"({score['episodes']} episodes, seeds {first}..{last}{', ' + score['env'] if 'env' in score else ''})"
    )


if __name__ == "__main__":
    sys.exit(main())

"""The recipe runner's stages: train, finetune, collect and ship, each run from a recipe's settings into its stage folder.

Each takes a `StageContext` and returns a `StageOutcome` (score, wall time, exit code). Train and finetune
are the run lifecycle of `training.train` and `training.finetune`: a folder with a resumable state is
resumed, a finished one is taken as it is. Collect writes its source's successful episodes (training.collect). Ship scores a copy of its source checkpoint on held-out seeds,
writes MODELS_DIR/POLICY and RECORDS_DIR/POLICY, and makes the card cite the recipe.
"""

from __future__ import annotations

import json
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from policies.checkpoint import load_card, set_noise_scale, set_outcome_candidates, update_card

__all__ = ["StageContext", "StageOutcome", "collect", "finetune", "set_acting", "ship", "train"]

RECIPE_COMMAND = "python -m training.recipe"


@dataclass
class StageContext:
    """What a stage runs with: the recipe, its settings (scaled), its input folder, its own folder, the run options."""

    recipe: Any
    stage: Any
    settings: dict[str, Any]
    stage_dir: Path
    options: Any
    before: list[Any]
    """the results of the stages before this one, in order"""
    commit: str
    key: str

    def input_dir(self, name: str | None) -> Path | None:
        """The folder of the earlier stage `name` (None for None)."""
        return next(r.dir for r in self.before if r.stage == name) if name else None

    @property
    def source_dir(self) -> Path | None:
        return self.input_dir(self.stage.source)

    @property
    def extra_dirs(self) -> list[Path]:
        """the folders of the collect stages a train stage learns from"""
        return [self.input_dir(name) for name in self.stage.extra_sources]

    def run_options(self) -> dict[str, Any]:
        """The settings the runner owns: folder, resume or start afresh, threads, progress bar."""
        state = self.stage_dir / "state.json"
        resume = state.is_file() and not json.loads(state.read_text()).get("finished")
        extra = {"threads": self.options.threads} if self.options.threads else {}
        return {
            "name": self.stage_dir.name,
            "out_dir": str(self.stage_dir.parent),
            "resume": resume,
            "overwrite": self.stage_dir.exists() and not resume,
            "progress": self.options.progress,
            **extra,
        }

    def config(self, cls: type, **inputs: Any) -> Any:
        """The stage's command config: its settings, then its inputs and the runner's options over them (--threads
        replaces a stage's own threads)."""
        return cls(**{**self.settings, **inputs, **self.run_options()})


@dataclass
class StageOutcome:
    """A stage's score (its last evaluation, or held-out scores for ship), its wall time, and 128 + N if stopped by signal N."""

    score: dict[str, Any] | None
    wall_time_s: float | None
    exit_code: int = 0


def train(ctx: StageContext) -> StageOutcome:
    """Imitation (`training.train`) on the demonstrations and any collected episodes; fresh, or from the source's checkpoint."""
    from training.collect import EPISODES_STORE
    from training.config import TrainConfig
    from training.train import train as run_train

    inputs = {"extra_data": ",".join(str(d / EPISODES_STORE) for d in ctx.extra_dirs)}
    if ctx.source_dir is not None:
        inputs["init"] = str(ctx.source_dir / "last")
    if not _finished(ctx.stage_dir):
        run = run_train(ctx.config(TrainConfig, **inputs))
        if run.stop_requested:
            return StageOutcome(None, None, run.exit_code())
    return _finish(ctx)


def finetune(ctx: StageContext) -> StageOutcome:
    """Beyond imitation (`training.finetune`) from the source stage's final checkpoint (a dagger stage's student; its
    `teacher` stage's checkpoint labels)."""
    from training.finetune import finetune as run_finetune
    from training.finetune_config import FinetuneConfig

    inputs = {"init": str(ctx.source_dir / "last")}
    if ctx.stage.teacher:
        inputs["dagger_teacher"] = str(ctx.input_dir(ctx.stage.teacher) / "last")
    if not _finished(ctx.stage_dir):
        run = run_finetune(ctx.config(FinetuneConfig, **inputs))
        if run.stop_requested:
            return StageOutcome(None, None, run.exit_code())
    return _finish(ctx)


def collect(ctx: StageContext) -> StageOutcome:
    """The source's successful episodes (`training.collect`) in STAGE_DIR/episodes.zarr; scored by the collection's success."""
    from training.collect import EPISODES_STORE, CollectConfig
    from training.collect import collect as run_collect

    started = time.perf_counter()
    ctx.stage_dir.mkdir(parents=True, exist_ok=True)
    cfg = CollectConfig(
        str(ctx.source_dir / "last"), ctx.stage_dir / EPISODES_STORE, **ctx.settings, progress=ctx.options.progress
    )
    line = run_collect(cfg)
    (ctx.stage_dir / "collect.json").write_text(json.dumps(line, indent=2) + "\n")
    return StageOutcome(_score(line), time.perf_counter() - started)


def ship(ctx: StageContext) -> StageOutcome:
    """Export and score a copy of the source's final checkpoint on held-out seeds; write it to MODELS_DIR/POLICY with its card."""
    from pusht.spec import HELD_OUT_SEED
    from training.ship import ShipConfig
    from training.ship import ship as ship_run

    started = time.perf_counter()
    settings = {"episodes": 500, "envs": ["pusht", "gym-pusht"], "seed": HELD_OUT_SEED} | ctx.settings
    copy = ctx.stage_dir / ctx.recipe.policy
    if ctx.stage_dir.exists():
        shutil.rmtree(ctx.stage_dir)
    copy.mkdir(parents=True)
    for name in ("last.safetensors", "last.json", "learning_curve.png", "log.jsonl"):
        if (ctx.source_dir / name).is_file():
            shutil.copyfile(ctx.source_dir / name, copy / name)
    set_acting(copy / "last", ctx.stage.acting)
    reports = ship_run(
        ShipConfig(
            copy,
            ctx.recipe.policy,
            ctx.options.models_dir,
            ctx.options.records_dir,
            settings["episodes"],
            settings["seed"],
            settings["envs"],
            note=ctx.recipe.description,
            force=True,
        )
    )
    final = {r["env"]: r for r in reports if r["checkpoint"] == "final"}
    score = final.get("gym-pusht") or next(iter(final.values()))
    wall = time.perf_counter() - started
    stages = [r.as_card() for r in ctx.before] + [
        {"name": ctx.stage.name, "run": "ship", "key": ctx.key, "wall_time_s": round(wall, 1), "score": _score(score)}
    ]
    fields = {
        "recipe": {"file": _relative(ctx.recipe.path), "sha256": ctx.recipe.sha256},
        "git_commit": ctx.commit,
        "stages": stages,
        "stages_wall_time_s": round(sum(s["wall_time_s"] for s in stages), 1),
        "reproduce": f"{RECIPE_COMMAND} {_relative(ctx.recipe.path)}",
        "run": f"{ctx.options.records_dir.name}/{ctx.recipe.policy}",
        "default": ctx.recipe.default,
    }
    if ctx.options.scale != 1:
        fields["recipe"]["scale"] = ctx.options.scale
    labels = {str(r.dir): f"<recipe stage {r.stage}>" for r in ctx.before} | {str(copy): f"<recipe stage {ctx.stage.name}>"}
    for stem in (ctx.options.models_dir / ctx.recipe.policy, ctx.options.records_dir / ctx.recipe.policy / "last"):
        update_card(stem, **fields)
        _scrub_paths(stem.with_suffix(".json"), labels, str(ctx.options.out_dir))
    return StageOutcome(_score(score), wall)


def _finished(stage_dir: Path) -> bool:
    card = stage_dir / "last.json"
    return card.is_file() and bool(json.loads(card.read_text()).get("finished"))


def _finish(ctx: StageContext) -> StageOutcome:
    stem = ctx.stage_dir / "last"
    for checkpoint in ("last", "best"):
        if (ctx.stage_dir / f"{checkpoint}.json").is_file():
            set_acting(ctx.stage_dir / checkpoint, ctx.stage.acting)
    card = load_card(stem)
    return StageOutcome(_score(card.get("evaluation")), float(card["wall_time_s"]))


def set_acting(stem: Path, acting: dict[str, Any]) -> None:
    """Write a stage's `acting` settings (noise_scale, outcome_candidates) on a checkpoint."""
    if "noise_scale" in acting:
        set_noise_scale(stem, acting["noise_scale"])
    if "outcome_candidates" in acting:
        set_outcome_candidates(stem, acting["outcome_candidates"])


def _score(evaluation: dict[str, Any] | None) -> dict[str, Any] | None:
    """The part of an evaluation record a summary shows: success, mean max reward, episodes, first and last seed, env."""
    if not evaluation:
        return None
    seeds = evaluation["seeds"]
    score = {
        "success_rate": evaluation["success_rate"],
        "mean_max_reward": round(evaluation["mean_max_reward"], 4),
        "episodes": evaluation.get("episodes", len(seeds)),
        "seeds": [seeds[0], seeds[-1]],
    }
    if "env" in evaluation:
        score["env"] = evaluation["env"]
    return score


def _relative(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def _scrub_paths(card_path: Path, labels: dict[str, str], out_dir: str) -> None:
    """Replace the stage folders a card names (which no clone has) by the recipe stages that made them."""
    text = card_path.read_text()
    for path in sorted(labels, key=len, reverse=True):
        text = text.replace(path, labels[path])
    text = re.sub(re.escape(out_dir) + r"(?=[\"/])", "<recipe out-dir>", text)
    card_path.write_text(text)

"""A recipe file (TOML): the policy it ships and its `[[stage]]`s, parsed and checked before anything runs."""

from __future__ import annotations

import hashlib
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

__all__ = ["Recipe", "RecipeError", "Stage", "load_recipe"]

STAGE_RUNS = ("train", "finetune", "collect", "ship")
ACTING_KEYS = ("noise_scale", "outcome_candidates")
# settings a stage never takes from the recipe: the runner owns them
RUNNER_OWNED = (
    "name",
    "out_dir",
    "resume",
    "overwrite",
    "progress",
    "init",
    "dagger_teacher",
    "extra_data",
    "run",
    "models_dir",
    "records_dir",
    "model",
    "out",
)


@dataclass
class Stage:
    """One step of a recipe: what runs, on which earlier stage's checkpoint, with which settings."""

    name: str
    run: str
    settings: dict[str, Any]
    source: str | None = None
    acting: dict[str, Any] = field(default_factory=dict)
    extra_sources: tuple[str, ...] = ()
    """collect stages whose episodes a train stage learns from beside the demonstrations"""
    teacher: str | None = None
    """the stage whose chooser labels a dagger stage's student (the student is then `source`'s plain flow)"""

    @property
    def inputs(self) -> tuple[str, ...]:
        """Every earlier stage whose output this one reads."""
        return tuple(name for name in (self.source, *self.extra_sources, self.teacher) if name)


@dataclass
class Recipe:
    """A shipped policy's stages, read from a recipe file."""

    path: Path
    policy: str
    description: str
    stages: list[Stage]
    default: bool = False

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.path.read_bytes()).hexdigest()


class RecipeError(ValueError):
    """A recipe file that cannot be run: the message names the file and the problem."""


def load_recipe(path: Path) -> Recipe:
    """Parse and check a recipe file; RecipeError naming the file and the problem."""
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise RecipeError(f"{path}: recipe file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RecipeError(f"{path}: not valid TOML: {exc}") from None
    unknown = set(data) - {"policy", "description", "default", "stage"}
    if unknown:
        raise RecipeError(f"{path}: unknown top-level keys {sorted(unknown)} (policy, description, default, stage)")
    if not isinstance(data.get("default", False), bool):
        raise RecipeError(f"{path}: `default` must be true or false")
    if not isinstance(data.get("policy"), str) or not data["policy"]:
        raise RecipeError(f'{path}: needs `policy = "NAME"`, the name it ships as')
    raw = data.get("stage")
    if not isinstance(raw, list) or not raw:
        raise RecipeError(f"{path}: needs at least one [[stage]]")
    stages: list[Stage] = []
    for index, table in enumerate(raw):
        stages.append(_parse_stage(path, index, dict(table), [s.name for s in stages]))
    runs = {s.name: s.run for s in stages}
    for stage in stages:
        if any(runs[name] != "collect" for name in stage.extra_sources):
            raise RecipeError(
                f"{path}: stage {stage.name}: `extra_from` names only collect stages, got {list(stage.extra_sources)}"
            )
    if stages[-1].run != "ship":
        raise RecipeError(f'{path}: the last stage must be `run = "ship"`')
    return Recipe(path, data["policy"], str(data.get("description", "")), stages, data.get("default", False))


def _parse_stage(path: Path, index: int, table: dict[str, Any], earlier: list[str]) -> Stage:
    where = f"{path}: stage {index + 1}"
    name, run = table.pop("name", None), table.pop("run", None)
    if not isinstance(name, str) or not name.replace("-", "").replace("_", "").isalnum():
        raise RecipeError(f"{where}: needs a `name` of letters, digits, - and _")
    if name in earlier:
        raise RecipeError(f"{where}: the name {name!r} is used twice")
    if run not in STAGE_RUNS:
        raise RecipeError(f"{where} ({name}): `run` must be one of {STAGE_RUNS}, got {run!r}")
    source = table.pop("from", None if run == "train" or not earlier else earlier[-1])
    if (run != "train" or source is not None) and source not in earlier:
        raise RecipeError(f"{where} ({name}): `from` must name an earlier stage, got {source!r}")
    extra = table.pop("extra_from", [])
    if extra and (run != "train" or not isinstance(extra, list) or not set(extra) <= set(earlier)):
        raise RecipeError(f"{where} ({name}): `extra_from` is a train stage's list of earlier collect stages, got {extra!r}")
    teacher = table.pop("teacher", None)
    if teacher is not None and (run != "finetune" or table.get("algo") != "dagger" or teacher not in earlier):
        raise RecipeError(
            f"{where} ({name}): `teacher` names the earlier stage whose chooser labels a dagger stage, got {teacher!r}"
        )
    acting = table.pop("acting", {})
    if not isinstance(acting, dict) or set(acting) - set(ACTING_KEYS):
        raise RecipeError(f"{where} ({name}): `acting` takes only {ACTING_KEYS}")
    owned = sorted(set(table) & set(RUNNER_OWNED))
    if owned:
        raise RecipeError(f"{where} ({name}): {owned} are set by the recipe runner, not the recipe")
    allowed = _settings_fields(run)
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise RecipeError(f'{where} ({name}): unknown settings for `run = "{run}"`: {unknown}')
    return Stage(name, run, table, source, acting, tuple(extra), teacher)


def _settings_fields(run: str) -> set[str]:
    if run == "train":
        from training.config import TrainConfig

        return {f.name for f in fields(TrainConfig)}
    if run == "finetune":
        from training.finetune_config import FinetuneConfig

        return {f.name for f in fields(FinetuneConfig)}
    if run == "collect":
        from training.collect import CollectConfig

        return {f.name for f in fields(CollectConfig)} - {"progress"}
    return {"episodes", "envs", "seed"}

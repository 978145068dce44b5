"""`--reuse-shipped`: a recipe stage whose output already ships in MODELS_DIR is restored from there, not run again.

A shipped card lists the stages that made it, each with its key; the stage just before its ship stage is the one whose
output the shipped weights are, but for the `acting` settings the ship stage wrote over them, which are read from the
recipe that shipped the card and set back as the stages before had them.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from training.recipe import DONE_FILE, StageResult
from training.recipe_file import Recipe, Stage

__all__ = ["ShippedStages"]


@dataclass
class ShippedStages:
    """What the shipped cards say of the stages that made them: each stage's record by key, and which stage's output
    each shipped policy is (the one before its ship stage) with the `acting` its ship stage wrote over it."""

    records: dict[str, dict[str, Any]] = field(default_factory=dict)
    outputs: dict[str, tuple[Path, dict[str, Any], dict[str, Any]]] = field(default_factory=dict)

    @classmethod
    def read(cls, models_dir: Path) -> ShippedStages:
        shipped = cls()
        for path in sorted(models_dir.glob("*.json")):
            card = json.loads(path.read_text())
            stages = card.get("stages") or []
            if len(stages) < 2 or stages[-1].get("run") != "ship":
                continue
            origin = {"policy": path.stem, "git_commit": card.get("git_commit", "")}
            for record in stages[:-1]:  # a stage the card itself restored keeps the card that ran it
                shipped.records.setdefault(record["key"], {"restored_from": origin} | record)
            ship_acting = _ship_acting(card)
            if ship_acting is not None:
                shipped.outputs[stages[-2]["key"]] = (path, origin, ship_acting)
        return shipped

    def acting(self, recipe: Recipe, stage: Stage, key: str) -> dict[str, Any] | None:
        """The acting settings that make the shipped policy the stage's output again (the ship stage's, undone by the
        latest `acting` of the stage and those it comes from); None if no shipped policy is its output."""
        if key not in self.outputs:
            return None
        by_name = {s.name: s for s in recipe.stages}
        chain, name = {}, stage.name
        while name:  # the stage, then its source, ...: the first to set a key set it last
            chain = by_name[name].acting | chain
            name = by_name[name].source
        changed = self.outputs[key][2]
        return {k: chain[k] for k in changed} if set(changed) <= set(chain) else None

    def result(self, stage: Stage, key: str, stage_dir: Path) -> StageResult:
        """A stage that is not run: its record as the shipped card keeps it."""
        record = self.records[key]
        return StageResult(
            stage.name, stage.run, key, stage_dir, record["wall_time_s"], True, record["score"], 0, record["restored_from"]
        )

    def restore(self, recipe: Recipe, stage: Stage, key: str, stage_dir: Path) -> StageResult | None:
        """The stage's output copied from the shipped policy that is it, marked done; None if none is."""
        acting = self.acting(recipe, stage, key)
        if acting is None:
            return None
        from training.recipe_stages import set_acting

        card_path, origin, _ = self.outputs[key]
        stage_dir.mkdir(parents=True, exist_ok=True)
        for suffix in (".safetensors", ".json"):
            shutil.copyfile(card_path.with_suffix(suffix), stage_dir / f"last{suffix}")
        set_acting(stage_dir / "last", acting)
        result = self.result(stage, key, stage_dir)
        record = {"key": key, "stage": stage.name, "run": stage.run, "wall_time_s": result.wall_time_s}
        record |= {"score": result.score, "git_commit": origin["git_commit"], "restored_from": result.restored_from}
        (stage_dir / DONE_FILE).write_text(json.dumps(record, indent=2) + "\n")
        print(f"  restored from {card_path}" + (f", acting {acting}" if acting else ""), file=sys.stderr)
        return result


def _ship_acting(card: dict[str, Any]) -> dict[str, Any] | None:
    """The `acting` of the ship stage that wrote the card, from its recipe as it was (at the card's commit, or as the
    file is now: whichever has the sha256 the card cites); None if neither has."""
    recipe = card.get("recipe") or {}
    if "file" not in recipe:
        return None
    path = Path(recipe["file"])
    text = path.read_bytes() if path.is_file() else b""
    if hashlib.sha256(text).hexdigest() != recipe.get("sha256"):  # changed since: ask git for it as it was
        text = _shown(card.get("git_commit", ""), recipe["file"])
    if hashlib.sha256(text).hexdigest() != recipe.get("sha256"):
        return None
    return tomllib.loads(text.decode())["stage"][-1].get("acting", {})


def _shown(commit: str, file: str) -> bytes:
    """`git show COMMIT:FILE` (a card's '-dirty' commit taken as its clean one); b"" if git cannot show it."""
    try:
        shown = subprocess.run(["git", "show", f"{commit.removesuffix('-dirty')}:{file}"], capture_output=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return b""
    return shown.stdout if shown.returncode == 0 else b""

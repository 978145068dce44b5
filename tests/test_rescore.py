"""training.rescore on a copy of the shipped MSE policy and its record: the cards get training.evaluate's scores."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from PIL import Image

from training.evaluate import main as evaluate_main
from training.rescore import main as rescore_main

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture()
def shipped_copy(tmp_path, monkeypatch) -> Path:
    """tmp/models/mse.* and tmp/records/RUN (the card names its record relative to the repo root)."""
    card = json.loads((REPO / "models" / "mse.json").read_text())
    (tmp_path / "models").mkdir()
    for suffix in (".json", ".onnx", ".safetensors"):
        shutil.copyfile(REPO / "models" / f"mse{suffix}", tmp_path / "models" / f"mse{suffix}")
    shutil.copytree(REPO / card["run"], tmp_path / card["run"])
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_rescore_writes_the_evaluations_scores_into_every_card(shipped_copy, capsys):
    assert rescore_main(["--name", "mse", "--episodes", "2", "--seed", "300000", "--envs", "pusht"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["checkpoint"] for line in lines] == ["final", "best"]

    card = json.loads((shipped_copy / "models" / "mse.json").read_text())
    record = shipped_copy / card["run"]
    assert evaluate_main(["--model", "models/mse.onnx", "--episodes", "2", "--seed", "300000", "--no-progress"]) == 0
    expected = json.loads(capsys.readouterr().out)
    timing = ("wall_time_s",)
    for got in (card["heldout_evaluation"]["pusht"], json.loads((record / "last.json").read_text())["heldout_evaluation"]["pusht"]):
        assert {k: v for k, v in got.items() if k not in timing} == {k: v for k, v in expected.items() if k not in timing}
    best = json.loads((record / "best.json").read_text())["heldout_evaluation"]["pusht"]
    assert best["seeds"] == [300000, 300001] and best["model"].endswith("best")
    with Image.open(shipped_copy / "models" / "mse_rollout.gif") as gif:
        assert gif.info["duration"] == 100


def test_rescore_names_a_missing_policy(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert rescore_main(["--name", "nosuch", "--episodes", "2"]) == 2
    assert "nosuch.json" in capsys.readouterr().err

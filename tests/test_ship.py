"""training.ship on a real (tiny) training run: the record, the shipped files and their held-out scores."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from training.checkpoint import load_card
from training.ship import main as ship_main
from training.train import main as train_main

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "data" / "pusht_lowdim.zarr"


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs")
    args = ["--policy", "flow", "--name", "tiny", "--out-dir", str(out), "--data", str(DATA), "--steps", "40",
            "--batch-size", "32", "--eval-every", "0", "--eval-episodes", "2", "--eval-max-steps", "12", "--no-progress",
            "--arch", '{"hidden_dims": [32, 32], "action_frame": "agent"}']
    assert train_main(args) == 0
    return out / "tiny"


@pytest.mark.slow
def test_ship_records_scores_and_ships_with_a_noise_scale(run, tmp_path, capsys):
    models = tmp_path / "models"
    code = ship_main(["--run", str(run), "--name", "tiny", "--models-dir", str(models), "--episodes", "2",
                      "--envs", "pusht", "--noise-scale", "0.5", "--note", "a test"])
    assert code == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["checkpoint"] for line in lines] == ["final", "best"]
    assert all(line["seeds"] == [200000, 200001] for line in lines)

    shipped = load_card(models / "tiny")
    assert shipped["architecture"]["noise_scale"] == 0.5 and shipped["architecture"]["action_frame"] == "agent"
    assert shipped["onnx"]["file"] == "tiny.onnx" and (models / "tiny.onnx").is_file()
    train_command, ship_command = shipped["reproduce"]
    assert train_command.startswith("python -m training.train --policy flow --name tiny") and "--steps 40" in train_command
    assert ship_command == f"python -m training.ship --run {run} --name tiny --noise-scale 0.5"
    assert shipped["heldout_evaluation"]["pusht"]["mean_max_reward"] == lines[0]["mean_max_reward"]
    assert (models / "tiny_rollout.gif").stat().st_size > 1000
    record = models / "runs" / "tiny"
    assert load_card(record / "last")["recipe_changes"] == "a test"
    assert load_card(record / "best")["heldout_evaluation"]["pusht"]["episodes"] == 2
    assert (record / "best.safetensors").is_file() and (record / "log.jsonl").is_file()


def test_ship_of_an_unfinished_run_is_a_clear_error(tmp_path, capsys):
    assert ship_main(["--run", str(tmp_path / "nothing"), "--models-dir", str(tmp_path / "models")]) == 2
    err = capsys.readouterr().err
    assert "nothing" in err and "Traceback" not in err

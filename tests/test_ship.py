"""training.ship on a real (tiny) training run: the record, the shipped files and their held-out scores."""

from __future__ import annotations

import gzip
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from policies.checkpoint import load_card
from training.ship import main as ship_main
from training.train import main as train_main

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "data" / "pusht_lowdim.zarr"


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs")
    args = [
        "--policy",
        "flow",
        "--name",
        "tiny",
        "--out-dir",
        str(out),
        "--data",
        str(DATA),
        "--steps",
        "40",
        "--batch-size",
        "32",
        "--eval-every",
        "0",
        "--eval-episodes",
        "2",
        "--eval-max-steps",
        "12",
        "--no-progress",
        "--arch",
        '{"hidden_dims": [32, 32], "action_frame": "agent"}',
    ]
    assert train_main(args) == 0
    return out / "tiny"


@pytest.mark.slow
def test_ship_records_scores_and_ships_with_a_noise_scale(run, tmp_path, capsys):
    models, records = tmp_path / "models", tmp_path / "records"
    code = ship_main(
        [
            "--run",
            str(run),
            "--name",
            "tiny",
            "--models-dir",
            str(models),
            "--records-dir",
            str(records),
            "--episodes",
            "2",
            "--envs",
            "pusht",
            "--noise-scale",
            "0.5",
            "--note",
            "a test",
        ]
    )
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
    record = records / "tiny"
    assert shipped["run"] == str(record) and shipped["finished"] is True
    assert load_card(record / "last")["recipe_changes"] == "a test"
    assert load_card(record / "best")["heldout_evaluation"]["pusht"]["episodes"] == 2
    assert sorted(p.name for p in record.iterdir()) == [
        "best.json",
        "best.safetensors",
        "last.json",
        "learning_curve.png",
        "log.jsonl.gz",
    ]
    log = [json.loads(line) for line in gzip.decompress((record / "log.jsonl.gz").read_bytes()).splitlines()]
    assert log == [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert sorted(p.name for p in models.iterdir()) == ["tiny.json", "tiny.onnx", "tiny.safetensors", "tiny_rollout.gif"]


@pytest.mark.slow
def test_ship_keeps_a_better_shipped_policy_unless_forced(run, tmp_path, capsys):
    """The real shipped flow (its held-out score on seeds 200000..200499) against the 40-step run on the same seeds."""
    models, records = tmp_path / "models", tmp_path / "records"
    models.mkdir()
    for suffix in (".json", ".onnx", ".safetensors"):
        shutil.copyfile(REPO / "models" / f"flow{suffix}", models / f"p{suffix}")
    before = {p.name: p.read_bytes() for p in models.iterdir()}
    common = ["--run", str(run), "--name", "p", "--models-dir", str(models), "--records-dir", str(records), "--envs", "pusht"]
    assert ship_main([*common, "--episodes", "500"]) == 2
    err = capsys.readouterr().err
    shipped = load_card(models / "p")["heldout_evaluation"]["pusht"]["mean_max_reward"]
    assert len(err.strip().splitlines()) == 1 and err.startswith(f"error: {models / 'p'} scores {shipped:.3f} mean max reward"), (
        err
    )
    assert "this run 0." in err and "--force replaces it" in err
    assert ship_main([*common, "--episodes", "2"]) == 2  # scored on other seeds: no comparison, no replacement
    assert "cannot be compared" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in models.iterdir()} == before and not records.exists()

    assert ship_main([*common, "--episodes", "2", "--force"]) == 0
    assert load_card(models / "p")["steps"] == 40 and (records / "tiny" / "last.json").is_file()
    assert sorted(p.name for p in models.iterdir()) == ["p.json", "p.onnx", "p.safetensors", "p_rollout.gif"]


@pytest.mark.slow
def test_ship_refuses_an_unfinished_run(tmp_path, capsys):
    args = [
        "--policy",
        "mse",
        "--name",
        "cut",
        "--out-dir",
        str(tmp_path),
        "--data",
        str(DATA),
        "--steps",
        "100000",
        "--batch-size",
        "32",
        "--eval-every",
        "-1",
        "--checkpoint-every",
        "10",
        "--no-progress",
        "--arch",
        '{"hidden_dims": [32]}',
    ]
    proc = subprocess.Popen([sys.executable, "-m", "training.train", *args], cwd=REPO, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not (tmp_path / "cut" / "last.json").is_file() and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.kill()  # as a crash or an out-of-memory kill would
    proc.wait(timeout=30)
    assert ship_main(["--run", str(tmp_path / "cut"), "--name", "cut", "--models-dir", str(tmp_path / "models")]) == 2
    err = capsys.readouterr().err
    assert "is not finished (its last checkpoint is at step" in err and "of 100,000" in err and "--resume" in err
    assert not (tmp_path / "models" / "cut.json").exists()


def test_ship_of_an_unfinished_run_is_a_clear_error(tmp_path, capsys):
    assert ship_main(["--run", str(tmp_path / "nothing"), "--models-dir", str(tmp_path / "models")]) == 2
    err = capsys.readouterr().err
    assert "nothing" in err and "Traceback" not in err

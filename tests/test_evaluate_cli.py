"""`python -m training.evaluate` as a user runs it: torch-free on ONNX files, per-episode records, GIFs, --help."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from PIL import Image

from pusht.rollout import card_id

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "models"
# Makes `import torch` (and safetensors) fail in a subprocess as on a machine with only the serve and client extras.
NO_TORCH = "import sys; sys.modules['torch'] = None; sys.modules['safetensors'] = None; "


def evaluate(*args: str, prelude: str = "", importtime: bool = False) -> subprocess.CompletedProcess:
    """Run training.evaluate in a fresh interpreter, optionally after `prelude` (Python code)."""
    code = prelude + "from training.evaluate import main; sys.exit(main(sys.argv[1:]))"
    cmd = [sys.executable] + (["-X", "importtime"] if importtime else []) + ["-c", "import sys; " + code, *args]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)


def imported_modules(stderr: str) -> set[str]:
    """Module names from `python -X importtime` lines."""
    return {line.rsplit("|", 1)[1].strip() for line in stderr.splitlines() if line.startswith("import time:") and "|" in line}


def test_onnx_evaluation_imports_no_torch_and_writes_records_and_gif(tmp_path):
    out, gif = tmp_path / "episodes.jsonl", tmp_path / "first.gif"
    done = evaluate(
        "--model",
        str(SHIPPED / "mse.onnx"),
        "--episodes",
        "3",
        "--num-envs",
        "2",
        "--seed",
        "300000",
        "--max-steps",
        "36",
        "--out",
        str(out),
        "--gif",
        str(gif),
        "--no-progress",
        importtime=True,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    modules = imported_modules(done.stderr)
    assert "onnxruntime" in modules and "torch" not in modules and "policies.checkpoint" not in modules
    summary = json.loads(done.stdout)
    assert summary["seeds"] == [300000, 300002] and summary["episodes"] == 3

    card = json.loads((SHIPPED / "mse.json").read_text())
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["seed"] for r in records] == [300000, 300001, 300002]
    assert {r["policy"] for r in records} == {"mse"}
    assert {r["card"] for r in records} == {card_id("mse", card["git_commit"], card["steps"])}
    assert set(records[0]) == {"policy", "card", "seed", "max_reward", "success", "length", "final_coverage"}
    assert round(sum(r["max_reward"] for r in records) / 3, 4) == summary["mean_max_reward"]

    with Image.open(gif) as image:  # every step one frame, shown 1/10 s: real speed
        assert image.n_frames == records[0]["length"] + 1 and image.info["duration"] == 100
    assert f"gif: wrote {gif}" in done.stderr and f"to {out}" in done.stderr


def test_onnx_evaluation_runs_without_torch_and_a_checkpoint_names_the_extra():
    done = evaluate(
        "--model", str(SHIPPED / "flow.onnx"), "--episodes", "2", "--max-steps", "24", "--no-progress", prelude=NO_TORCH
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads(done.stdout)["kind"] == "flow"

    done = evaluate("--model", str(SHIPPED / "flow"), "--no-progress", prelude=NO_TORCH)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "torch is not installed" in lines[0] and ".[train]" in lines[0]
    assert "flow.onnx" in lines[0]  # and the way out that needs no torch


def test_help_shows_defaults_once_and_none_for_required_flags():
    done = subprocess.run(
        [sys.executable, "-m", "training.evaluate", "--help"], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0
    text = " ".join(done.stdout.split())
    assert "(default: None)" not in text and "(default: 200000)" in text and "(default: 100)" in text
    options = text.split(" --")[1:]
    assert all(option.count("(default") <= 1 for option in options)

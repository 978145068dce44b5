"""scripts/pace_diagnostics.py on the shipped flow: at pace 1, or gated with itself, it is the flow as training.evaluate plays it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SCRIPT = [sys.executable, "scripts/pace_diagnostics.py"]


def _run(*args: str) -> dict:
    done = subprocess.run([*SCRIPT, *args, "--episodes", "4", "--seed", "300000"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


@pytest.fixture(scope="module")
def evaluated() -> dict:
    done = subprocess.run([sys.executable, "-m", "training.evaluate", "--model", "models/flow.onnx", "--episodes", "4", "--seed", "300000",
                           "--no-progress"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_pace_one_and_a_flow_gated_with_itself_are_the_flow(evaluated):
    same = ("mean_max_reward", "success_rate", "mean_length")
    resampled = _run("resample", "--model", "models/flow.onnx", "--speed", "1")
    gated = _run("gate", "--far", "models/flow.onnx", "--near", "models/flow.onnx", "--radius", "2")
    for result in (resampled, gated):
        assert result["action_horizon"] == 12 and {k: result[k] for k in same} == {k: evaluated[k] for k in same}


def test_a_faster_pace_executes_fewer_actions():
    assert _run("resample", "--model", "models/flow.onnx", "--speed", "1.5")["action_horizon"] == 8


def test_phases_count_the_steps_to_each_coverage(evaluated):
    result = _run("phases", "--model", "models/flow.onnx")
    assert result["success_rate"] == evaluated["success_rate"]
    assert result["episodes_reaching_success"] == round(4 * evaluated["success_rate"]) <= result["episodes_reaching_0.9"] <= result["episodes_reaching_0.3"]
    if result["episodes_reaching_success"]:
        assert result["median_first_step_0.3"] <= result["median_first_step_0.9"] <= result["median_first_step_success"]


def test_help():
    done = subprocess.run([*SCRIPT, "gate", "--help"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "--radius" in done.stdout and "(default: 2.0)" in done.stdout

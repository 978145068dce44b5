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


def test_acting_pace_plays_the_copy_as_its_own_export_would(tmp_path):
    import torch

    from training.checkpoint import save_checkpoint
    from training.data import load_replay
    from training.export import export_onnx
    from training.normalization import Normalizer
    from training.policies import build_policy

    replay = load_replay()
    torch.manual_seed(0)
    stem = tmp_path / "paced"
    policy = build_policy("flow", pace_input=True, acting_pace=[2.0, 1.0, 2.0, 0.0], noise_scale=0.3)
    save_checkpoint(stem, policy, Normalizer.fit(replay.states, replay.actions).to_dict())
    export_onnx(stem)
    done = subprocess.run([sys.executable, "-m", "training.evaluate", "--model", str(stem.with_suffix(".onnx")), "--episodes", "4",
                           "--seed", "300000", "--no-progress"], cwd=REPO, capture_output=True, text=True, timeout=300)
    served = json.loads(done.stdout)
    copy = _run("acting-pace", "--model", str(stem), "--rule", "2", "1", "2", "0", "--noise-scale", "0.3")
    assert {k: copy[k] for k in ("mean_max_reward", "mean_length")} == {k: served[k] for k in ("mean_max_reward", "mean_length")}
    assert json.loads(stem.with_suffix(".json").read_text())["architecture"]["acting_pace"] == [2.0, 1.0, 2.0, 0.0]  # the source is untouched


def test_help():
    done = subprocess.run([*SCRIPT, "gate", "--help"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "--radius" in done.stdout and "(default: 2.0)" in done.stdout

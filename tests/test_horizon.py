"""Shapes come from the card: a flow trained with `--horizon 16` exports, evaluates and serves chunks of 16,
and scores over HTTP exactly as in process."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.service_fixtures import UvicornProcess

REPO = Path(__file__).resolve().parent.parent
HORIZON = 16
SEED = 100000
EPISODES = ["--episodes", "3", "--max-steps", "64", "--seed", str(SEED), "--no-progress"]


@pytest.fixture(scope="module")
def h16_models(tmp_path_factory) -> Path:
    """A short real training run with 16-action chunks, put in a models dir as the policy `h16` (weights, card, ONNX)."""
    from policies.checkpoint import load_checkpoint, save_checkpoint
    from training.export import export_onnx

    runs = tmp_path_factory.mktemp("runs")
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "training.train",
            "--policy",
            "flow",
            "--name",
            "h16",
            "--out-dir",
            str(runs),
            "--steps",
            "200",
            "--horizon",
            str(HORIZON),
            "--eval-every",
            "-1",
            "--arch",
            '{"hidden_dims": [64, 64]}',
            "--no-progress",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    policy, card = load_checkpoint(runs / "h16" / "last")
    models = tmp_path_factory.mktemp("models")
    save_checkpoint(models / "h16", policy, card["normalization"], steps=card["steps"], git_commit="test", config=card["config"])
    export_onnx(models / "h16")
    return models


@pytest.mark.slow
def test_horizon_16_trains_exports_evaluates_and_serves(h16_models: Path, tmp_path: Path) -> None:
    import acting
    from training.evaluate import evaluate_policy

    onnx, torch_policy = acting.load_policy(h16_models / "h16.onnx"), acting.load_policy(h16_models / "h16")
    assert onnx.horizon == torch_policy.horizon == HORIZON
    states = np.full((5, 5), 256.0, dtype=np.float32)
    a, b = onnx.act(states, seeds=range(5)), torch_policy.act(states, seeds=range(5))
    assert a.shape == (5, HORIZON, 2)
    np.testing.assert_allclose(a, b, atol=1e-3)
    in_process = evaluate_policy(onnx, episodes=3, seed=SEED, max_steps=64)
    assert in_process.decisions == 4  # 64 steps in chunks of 16, executed whole

    evaluated = subprocess.run(
        [
            sys.executable,
            "-m",
            "training.evaluate",
            "--model",
            str(h16_models / "h16.onnx"),
            "--num-envs",
            "2",
            "--out",
            str(tmp_path / "local.jsonl"),
            *EPISODES,
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert evaluated.returncode == 0, evaluated.stderr[-2000:]
    with UvicornProcess({"PUSHT_MODELS_DIR": str(h16_models)}) as server:
        listed = {p["name"]: p for p in httpx.get(f"{server.url}/policies", timeout=10).json()["policies"]}
        assert listed["h16"]["horizon"] == HORIZON
        answer = httpx.post(f"{server.url}/act", json={"policy": "h16", "state": [256.0] * 5, "seed": 3}, timeout=10)
        assert answer.status_code == 200, answer.text
        assert np.asarray(answer.json()["actions"]).shape == (HORIZON, 2)
        client = subprocess.run(
            [
                sys.executable,
                "clients/rollout.py",
                "--url",
                server.url,
                "--policy",
                "h16",
                "--num-envs",
                "3",
                "--out",
                str(tmp_path / "http.jsonl"),
                *EPISODES,
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=300,
        )
    assert client.returncode == 0, client.stderr[-2000:]
    local = [json.loads(line) for line in (tmp_path / "local.jsonl").read_text().splitlines()]
    http = [json.loads(line) for line in (tmp_path / "http.jsonl").read_text().splitlines()]
    assert http == local and len(local) == 3
    assert [r["max_reward"] for r in local] == [e.max_reward for e in in_process.episodes]

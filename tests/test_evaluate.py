"""Evaluation: the act-function rule (flow noise from each row's seed), checkpoints and ONNX files through `acting`, the CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import acting
from policies.card import Card
from policies.checkpoint import load_acting_policy, save_checkpoint
from policies.factory import build_policy
from policies.normalization import Normalizer
from pusht.rollout import decision_seed, row_noise
from training.data import load_replay
from training.evaluate import evaluate_policy, main

REPO = Path(__file__).resolve().parent.parent
SHARED_DATA = REPO.parent / "shared" / "data" / "pusht" / "pusht_cchi_v7_replay.zarr"
SHIPPED = REPO / "models"
REPORT_FIELDS = {
    "model",
    "kind",
    "env",
    "episodes",
    "seeds",
    "mean_max_reward",
    "mean_max_reward_ci95",
    "success_rate",
    "success_rate_ci95",
    "mean_length",
    "wall_time_s",
}


@pytest.fixture(scope="module")
def normalization() -> dict:
    own = REPO / "data" / "pusht_lowdim.zarr"
    replay = load_replay(own if (own / "meta" / "episode_ends").exists() else SHARED_DATA)
    return Normalizer.fit(replay.states, replay.actions).to_dict()


@pytest.fixture(scope="module", params=["mse", "flow"])
def checkpoint(request, tmp_path_factory, normalization) -> tuple[Path, str]:
    """An untrained but real checkpoint of each kind (small network: this tests plumbing, not skill)."""
    torch.manual_seed(0)
    policy = build_policy(request.param, hidden_dims=[64, 64])
    stem = tmp_path_factory.mktemp("ckpt") / request.param
    save_checkpoint(stem, policy, normalization, name=request.param, steps=0)
    return stem, request.param


class RecordingPolicy(acting.Policy):
    """An `acting.Policy` (card in memory) that walks the agent to the block and records the states and noise it was given."""

    def __init__(self, kind: str = "flow", horizon: int = 12):
        super().__init__(
            Card(Path("fake.json"), {"name": "fake", "kind": kind, "architecture": {"horizon": horizon}, "onnx": None})
        )
        self.states: list[np.ndarray] = []
        self.noises: list[np.ndarray | None] = []

    def _run(self, states, prev_states, noise, num_steps):
        self.states.append(states.copy())
        self.noises.append(None if noise is None else noise.copy())
        return np.repeat(states[:, None, 2:4], self.horizon, axis=1)


def test_flow_noise_comes_from_each_rows_own_seed():
    policy = RecordingPolicy()
    summary = evaluate_policy(policy, episodes=3, seed=42, num_envs=3, max_steps=24)
    assert summary.decisions == 2 and summary.seeds == [42, 43, 44]
    assert len(policy.noises) == 2 and summary.action_horizon == 12  # the card's horizon by default
    for d, noise in enumerate(policy.noises):
        assert noise.shape == (4, 12, 2)  # padded to a multiple of four rows with the last row
        np.testing.assert_array_equal(noise[:3], row_noise([decision_seed(e, d) for e in (42, 43, 44)]))
        np.testing.assert_array_equal(noise[3], noise[2])
        assert policy.states[d].shape == (4, 5)
        np.testing.assert_array_equal(policy.states[d][3], policy.states[d][2])


def test_noise_scale_multiplies_the_request_noise():
    policy = RecordingPolicy()
    evaluate_policy(policy, episodes=2, seed=42, num_envs=2, max_steps=12, noise_scale=0.6)
    expected = 0.6 * row_noise([decision_seed(42, 0), decision_seed(43, 0)])
    np.testing.assert_allclose(policy.noises[0][:2], expected, rtol=1e-6)
    with pytest.raises(ValueError, match="noise_scale"):
        evaluate_policy(policy, episodes=1, seed=0, max_steps=12, noise_scale=-1.0)


def test_mse_gets_no_noise():
    policy = RecordingPolicy("mse")
    evaluate_policy(policy, episodes=2, seed=0, max_steps=12)
    assert policy.noises == [None]


def test_action_horizon_defaults_to_the_cards_chunk_and_may_not_exceed_it():
    policy = RecordingPolicy(horizon=16)
    summary = evaluate_policy(policy, episodes=1, seed=0, max_steps=32)
    assert summary.action_horizon == 16 and summary.decisions == 2
    assert policy.noises[0].shape == (4, 16, 2) and all(n.shape == (4, 16, 2) for n in policy.noises)
    np.testing.assert_array_equal(policy.noises[0][:1], row_noise([decision_seed(0, 0)], 16, 2))
    assert evaluate_policy(RecordingPolicy(horizon=16), episodes=1, seed=0, max_steps=32, action_horizon=8).decisions == 4
    with pytest.raises(ValueError, match="action_horizon 17 exceeds the policy's chunk of 16"):
        evaluate_policy(policy, episodes=1, seed=0, action_horizon=17)


class StillPolicy(RecordingPolicy):
    """Holds the agent where it is: never moves the block, so never succeeds."""

    def _run(self, states, prev_states, noise, num_steps):
        return np.repeat(states[:, None, :2], self.horizon, axis=1)


@pytest.mark.parametrize("env", ["pusht", "gym-pusht"])
def test_max_steps_beyond_the_envs_own_300_steps_is_played_in_both_envs(env):
    summary = evaluate_policy(StillPolicy(), episodes=2, seed=0, num_envs=2, env=env, max_steps=336)
    assert [e.length for e in summary.episodes] == [336, 336] and summary.decisions == 28


def test_torch_checkpoint_is_deterministic_per_seed(checkpoint):
    stem, kind = checkpoint
    policy = acting.load_policy(stem)
    assert policy.kind == kind and policy.backend == "torch"
    runs = [evaluate_policy(policy, episodes=4, seed=200000, num_envs=2, max_steps=36).to_dict() for _ in range(2)]
    for run in runs:
        run.pop("wall_time_s")
    assert runs[0] == runs[1]
    assert runs[0]["seeds"] == [200000, 200001, 200002, 200003] and runs[0]["decisions"] == 6
    # the in-memory module that training evaluates scores exactly as its checkpoint
    module = evaluate_policy(load_acting_policy(stem), episodes=4, seed=200000, num_envs=2, max_steps=36).to_dict()
    module.pop("wall_time_s")
    assert module == runs[0]


@pytest.mark.slow
def test_onnx_and_checkpoint_score_the_same(checkpoint, tmp_path):
    from training.export import export_onnx

    stem, kind = checkpoint
    onnx_path = tmp_path / f"{kind}.onnx"
    export_onnx(stem, onnx_path)
    # the card beside the ONNX file says its kind
    (tmp_path / f"{kind}.json").write_text(stem.with_suffix(".json").read_text())
    onnx_policy = acting.load_policy(onnx_path)
    torch_policy = acting.load_policy(stem)
    assert onnx_policy.kind == kind and onnx_policy.backend == "onnx"
    a = evaluate_policy(onnx_policy, episodes=3, seed=100000, max_steps=48)
    b = evaluate_policy(torch_policy, episodes=3, seed=100000, max_steps=48)
    for x, y in zip(a.episodes, b.episodes, strict=True):
        assert x.seed == y.seed and x.length == y.length
        assert x.max_reward == pytest.approx(y.max_reward, abs=1e-3)

    from policies.checkpoint import update_card

    update_card(tmp_path / kind, onnx={"file": onnx_path.name, "inputs": ["state"], "num_steps": 10})
    if kind == "flow":
        with pytest.raises(ValueError, match="unrolls 10 flow steps"):
            acting.load_policy(onnx_path, num_steps=20)
        assert acting.load_policy(onnx_path, num_steps=10).default_num_steps == 10
        assert acting.load_policy(stem, num_steps=20).default_num_steps == 20  # torch runs any count
    else:
        assert acting.load_policy(onnx_path, num_steps=20).kind == "mse"  # MSE has no steps to disagree on


@pytest.mark.slow
def test_cli_prints_one_json_line(checkpoint, tmp_path):
    stem, kind = checkpoint
    gif = tmp_path / "episode.gif"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "training.evaluate",
            "--model",
            str(stem),
            "--episodes",
            "3",
            "--num-envs",
            "2",
            "--seed",
            "200000",
            "--max-steps",
            "24",
            "--gif",
            str(gif),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.strip().splitlines()
    assert len(lines) == 1
    report = json.loads(lines[0])
    assert REPORT_FIELDS <= set(report)
    assert report["kind"] == kind and report["env"] == "pusht" and report["episodes"] == 3
    assert report["seeds"] == [200000, 200002]
    lo, hi = report["mean_max_reward_ci95"]
    assert lo <= report["mean_max_reward"] <= hi
    assert gif.read_bytes()[:6] in (b"GIF87a", b"GIF89a")


def test_cli_on_the_reference_env(checkpoint, capsys):
    stem, kind = checkpoint
    assert main(["--model", str(stem), "--episodes", "2", "--max-steps", "12", "--env", "gym-pusht", "--no-progress"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["env"] == "gym-pusht" and report["kind"] == kind


def test_cli_errors_name_the_problem(checkpoint, tmp_path, capsys):
    stem, _ = checkpoint
    (tmp_path / "garbage.json").write_text(stem.with_suffix(".json").read_text())
    (tmp_path / "garbage.onnx").write_bytes(b"not onnx")
    assert main(["--model", str(tmp_path / "garbage.onnx"), "--no-progress"]) == 2
    assert "garbage.onnx: not a loadable ONNX model" in capsys.readouterr().err
    assert main(["--model", str(tmp_path / "missing"), "--no-progress"]) == 2
    assert "missing.json" in capsys.readouterr().err
    assert main(["--model", str(tmp_path / "missing.onnx"), "--no-progress"]) == 2
    assert "missing.onnx" in capsys.readouterr().err
    (tmp_path / "bad.json").write_text(json.dumps(json.loads(stem.with_suffix(".json").read_text()) | {"kind": "gan"}))
    assert main(["--model", str(tmp_path / "bad"), "--no-progress"]) == 2
    assert "bad.json: unknown policy kind 'gan'; expected one of ('mse', 'flow')" in capsys.readouterr().err
    (tmp_path / "bad.onnx").write_bytes(b"not onnx")
    assert main(["--model", str(tmp_path / "bad.onnx"), "--no-progress"]) == 2
    assert "bad.json: unknown policy kind 'gan'" in capsys.readouterr().err  # the card is read before the graph
    (tmp_path / "fields.json").write_text('{"kind": "mse"}')
    assert main(["--model", str(tmp_path / "fields"), "--no-progress"]) == 2
    assert "fields.json: card is missing fields" in capsys.readouterr().err
    assert main(["--model", str(SHIPPED / "mse.onnx"), "--out", str(tmp_path), "--no-progress"]) == 2
    assert "--out" in capsys.readouterr().err


def test_evaluate_policy_rejects_bad_arguments():
    policy = RecordingPolicy("mse")
    with pytest.raises(ValueError, match="policy must be an acting.Policy or a torch ActingPolicy, got function"):
        evaluate_policy(lambda states, noise: states, episodes=1)
    with pytest.raises(ValueError, match="env"):
        evaluate_policy(policy, episodes=1, env="mujoco")
    with pytest.raises(ValueError, match="positive"):
        evaluate_policy(policy, episodes=0)
    with pytest.raises(ValueError, match="action_horizon must be a positive integer"):
        evaluate_policy(policy, episodes=1, action_horizon=0)


@pytest.mark.parametrize("name", ["mse", "flow"])
def test_shipped_policy_episodes_do_not_depend_on_num_envs(name):
    """Each episode depends on its own seed only: the same results alone, in batches of 3 or all 8 at once."""
    policy = acting.load_policy(SHIPPED / f"{name}.onnx")
    assert policy.kind == name
    runs = {n: evaluate_policy(policy, episodes=8, seed=300000, num_envs=n).episodes for n in (1, 3, 8)}
    assert runs[1] == runs[3] == runs[8]
    torch_policy = acting.load_policy(SHIPPED / name)  # the torch backend too, on fewer steps
    short = {n: evaluate_policy(torch_policy, episodes=5, seed=300000, num_envs=n, max_steps=96).episodes for n in (1, 5)}
    assert short[1] == short[5]

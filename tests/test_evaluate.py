"""Evaluation: the act-function rule (flow noise from each row's seed), checkpoints and ONNX files, the CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pusht.rollout import decision_seed, row_noise
from training.checkpoint import save_checkpoint
from training.data import Normalizer, load_replay
from training.evaluate import evaluate_policy, load_actor, main
from training.policies import build_policy

REPO = Path(__file__).resolve().parent.parent
SHARED_DATA = REPO.parent / "shared" / "data" / "pusht" / "pusht_cchi_v7_replay.zarr"
SHIPPED = REPO / "models"
REPORT_FIELDS = {"model", "kind", "env", "episodes", "seeds", "mean_max_reward", "mean_max_reward_ci95",
                 "success_rate", "success_rate_ci95", "mean_length", "wall_time_s"}


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


class RecordingActor:
    """A numpy actor that walks the agent to the block and records the noise it was given."""

    _numpy_actor = True

    def __init__(self):
        self.noises: list[np.ndarray | None] = []

    def __call__(self, states, noise):
        self.noises.append(None if noise is None else noise.copy())
        return np.repeat(states[:, None, 2:4], 12, axis=1)


def test_flow_noise_comes_from_each_rows_own_seed():
    actor = RecordingActor()
    summary = evaluate_policy(actor, "flow", episodes=3, seed=42, num_envs=3, max_steps=24)
    assert summary.decisions == 2 and summary.seeds == [42, 43, 44]
    for d, noise in enumerate(actor.noises):
        assert noise.shape == (4, 12, 2)  # padded to a multiple of four rows with the last row
        np.testing.assert_array_equal(noise[:3], row_noise([decision_seed(e, d) for e in (42, 43, 44)]))
        np.testing.assert_array_equal(noise[3], noise[2])


def test_noise_scale_multiplies_the_request_noise():
    actor = RecordingActor()
    evaluate_policy(actor, "flow", episodes=2, seed=42, num_envs=2, max_steps=12, noise_scale=0.6)
    expected = 0.6 * row_noise([decision_seed(42, 0), decision_seed(43, 0)])
    np.testing.assert_allclose(actor.noises[0][:2], expected, rtol=1e-6)
    with pytest.raises(ValueError, match="noise_scale"):
        evaluate_policy(actor, "flow", episodes=1, seed=0, max_steps=12, noise_scale=-1.0)


def test_mse_gets_no_noise():
    actor = RecordingActor()
    evaluate_policy(actor, "mse", episodes=2, seed=0, max_steps=12)
    assert actor.noises == [None]


def test_torch_checkpoint_is_deterministic_per_seed(checkpoint):
    stem, kind = checkpoint
    actor, loaded_kind = load_actor(stem)
    assert loaded_kind == kind
    runs = [evaluate_policy(actor, kind, episodes=4, seed=200000, num_envs=2, max_steps=36).to_dict() for _ in range(2)]
    for run in runs:
        run.pop("wall_time_s")
    assert runs[0] == runs[1]
    assert runs[0]["seeds"] == [200000, 200001, 200002, 200003] and runs[0]["decisions"] == 6


@pytest.mark.slow
def test_onnx_and_checkpoint_score_the_same(checkpoint, tmp_path):
    from training.export import export_onnx

    stem, kind = checkpoint
    onnx_path = tmp_path / f"{kind}.onnx"
    export_onnx(stem, onnx_path)
    # the card beside the ONNX file says its kind
    (tmp_path / f"{kind}.json").write_text(stem.with_suffix(".json").read_text())
    onnx_actor, onnx_kind = load_actor(onnx_path)
    torch_actor, _ = load_actor(stem)
    assert onnx_kind == kind
    a = evaluate_policy(onnx_actor, kind, episodes=3, seed=100000, max_steps=48)
    b = evaluate_policy(torch_actor, kind, episodes=3, seed=100000, max_steps=48)
    for x, y in zip(a.episodes, b.episodes, strict=True):
        assert x.seed == y.seed and x.length == y.length
        assert x.max_reward == pytest.approx(y.max_reward, abs=1e-3)

    from training.checkpoint import update_card

    update_card(tmp_path / kind, onnx={"file": onnx_path.name, "inputs": ["state"], "num_steps": 10})
    if kind == "flow":
        with pytest.raises(ValueError, match="unrolls 10 flow steps"):
            load_actor(onnx_path, num_steps=20)
    else:
        assert load_actor(onnx_path, num_steps=20)[1] == "mse"  # MSE has no steps to disagree on


@pytest.mark.slow
def test_cli_prints_one_json_line(checkpoint, tmp_path):
    stem, kind = checkpoint
    gif = tmp_path / "episode.gif"
    done = subprocess.run(
        [sys.executable, "-m", "training.evaluate", "--model", str(stem), "--episodes", "3", "--num-envs", "2",
         "--seed", "200000", "--max-steps", "24", "--gif", str(gif)],
        cwd=REPO, capture_output=True, text=True, timeout=600,
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
    (tmp_path / "bad.json").write_text('{"kind": "gan"}')
    assert main(["--model", str(tmp_path / "bad"), "--no-progress"]) == 2
    assert "bad.json: card kind must be one of ('mse', 'flow'), got 'gan'" in capsys.readouterr().err
    (tmp_path / "bad.onnx").write_bytes(b"not onnx")
    assert main(["--model", str(tmp_path / "bad.onnx"), "--no-progress"]) == 2
    assert "bad.json: card kind must be one of" in capsys.readouterr().err
    (tmp_path / "fields.json").write_text('{"kind": "mse"}')
    assert main(["--model", str(tmp_path / "fields"), "--no-progress"]) == 2
    assert "fields.json: card is missing fields" in capsys.readouterr().err
    assert main(["--model", str(SHIPPED / "mse.onnx"), "--out", str(tmp_path), "--no-progress"]) == 2
    assert "--out" in capsys.readouterr().err


def test_evaluate_policy_rejects_bad_arguments():
    actor = RecordingActor()
    with pytest.raises(ValueError, match="kind"):
        evaluate_policy(actor, "diffusion", episodes=1)
    with pytest.raises(ValueError, match="env"):
        evaluate_policy(actor, "mse", episodes=1, env="mujoco")
    with pytest.raises(ValueError, match="positive"):
        evaluate_policy(actor, "mse", episodes=0)


@pytest.mark.parametrize("name", ["mse", "flow"])
def test_shipped_policy_episodes_do_not_depend_on_num_envs(name):
    """Each episode depends on its own seed only: the same results alone, in batches of 3 or all 8 at once."""
    actor, kind = load_actor(SHIPPED / f"{name}.onnx")
    runs = {n: evaluate_policy(actor, kind, episodes=8, seed=300000, num_envs=n).episodes for n in (1, 3, 8)}
    assert runs[1] == runs[3] == runs[8]
    torch_actor, _ = load_actor(SHIPPED / name)  # the torch backend too, on fewer steps
    short = {n: evaluate_policy(torch_actor, kind, episodes=5, seed=300000, num_envs=n, max_steps=96).episodes for n in (1, 5)}
    assert short[1] == short[5]

"""The weight average (train --ema-decay) and the keypoint features: what is evaluated and shipped is what they say."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from policies.factory import build_policy
from policies.features import tee_keypoints
from pusht.geometry import tee_polygons
from training.ema import WeightAverage

REPO = Path(__file__).resolve().parent.parent
IDENTITY = {"state_mean": [0.0] * 5, "state_std": [1.0] * 5, "action_mean": [0.0] * 2, "action_std": [1.0] * 2}


def test_decay_warms_up_and_is_capped():
    ema = WeightAverage(build_policy("mse", hidden_dims=[8]), max_decay=0.999)
    assert ema.decay(1) == pytest.approx(1 - 2**-0.75)
    assert ema.decay(10) < ema.decay(100) < ema.decay(10_000) == 0.999
    with pytest.raises(ValueError, match="ema decay"):
        WeightAverage(build_policy("mse", hidden_dims=[8]), max_decay=1.0)


def test_update_moves_the_average_toward_the_weights_and_keeps_the_normalizer():
    policy = build_policy("flow", hidden_dims=[8])
    policy.normalizer.set(IDENTITY)
    ema = WeightAverage(policy, max_decay=0.9)
    before = [p.detach().clone() for p in ema.module.parameters()]
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(1.0)
    ema.update(10_000)  # decay capped at 0.9: the average moves a tenth of the way
    for old, new in zip(before, ema.module.parameters()):
        torch.testing.assert_close(new, old + 0.1)
    assert ema.module.normalizer.is_set and ema.module.normalizer.to_dict() == policy.normalizer.to_dict()
    state = ema.state_dict()
    again = WeightAverage(policy, max_decay=0.9)
    again.load_state_dict(state)
    for a, b in zip(again.module.parameters(), ema.module.parameters()):
        assert torch.equal(a, b)


@pytest.mark.parametrize("pose", [(300.0, 200.0, 1.0), (120.5, 400.0, 5.9), (256.0, 256.0, np.pi / 4)])
def test_keypoints_are_the_tee_corners_the_env_draws(pose):
    got = tee_keypoints(torch.tensor([pose], dtype=torch.float64)).reshape(-1, 2) * 128 + 256
    bar, stem = tee_polygons(*pose)
    expected = np.asarray([*bar, stem[1], stem[2]])
    np.testing.assert_allclose(got.numpy(), expected, atol=1e-9)


@pytest.mark.slow
def test_an_ema_keypoint_flow_trains_exports_and_ships_its_average(tmp_path):
    """The saved checkpoint is the average, not the raw weights; it exports and acts the same in ONNX and torch."""
    import acting
    from policies.checkpoint import load_checkpoint
    from training.export import export_onnx

    arch = '{"angle_encoding": "keypoints", "state_skip": true, "dropout": 0.0, "action_frame": "agent", "hidden_dims": [32, 32]}'
    common = [
        "--policy",
        "flow",
        "--out-dir",
        str(tmp_path),
        "--steps",
        "60",
        "--eval-every",
        "-1",
        "--arch",
        arch,
        "--no-progress",
    ]
    for name, extra in (("raw", []), ("avg", ["--ema-decay", "0.99"])):
        done = subprocess.run(
            [sys.executable, "-m", "training.train", "--name", name, *common, *extra],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr[-2000:]
    raw, _ = load_checkpoint(tmp_path / "raw" / "last")
    avg, card = load_checkpoint(tmp_path / "avg" / "last")
    assert card["config"]["ema_decay"] == 0.99
    assert any(
        not torch.equal(a, b) for a, b in zip(raw.parameters(), avg.parameters())
    )  # same seed, same steps: only the average differs
    export_onnx(tmp_path / "avg" / "last")
    states = np.random.default_rng(0).uniform(0, 512, (6, 5)).astype(np.float32)
    onnx, torch_policy = acting.load_policy(tmp_path / "avg" / "last.onnx"), acting.load_policy(tmp_path / "avg" / "last")
    np.testing.assert_allclose(onnx.act(states, seeds=range(6)), torch_policy.act(states, seeds=range(6)), atol=1e-3)

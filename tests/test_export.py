"""ONNX export: the graph acts like the torch ActingPolicy, with the contract's names, dtypes and a dynamic batch."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from policies.checkpoint import CheckpointError, load_acting_policy, load_card, save_checkpoint
from policies.factory import build_policy
from policies.normalization import Normalizer
from training.data import load_replay
from training.export import export_onnx, main

KINDS = ["mse", "flow"]
REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def replay():
    return load_replay()


@pytest.fixture(scope="module", params=KINDS)
def exported(request, tmp_path_factory, replay) -> tuple[str, Path, Path]:
    """A random-weight policy with the real normalizer, saved and exported; its first action is pushed out of the arena."""
    kind = request.param
    torch.manual_seed(0)
    policy = build_policy(kind)
    with torch.no_grad():
        # step 0 of every chunk far outside [0, 512] (x high, y low), so the graph's clipping is exercised
        last = policy.net[-1]
        last.bias[0] += 20.0
        last.bias[1] -= 20.0
    norm = Normalizer.fit(replay.states, replay.actions)
    stem = tmp_path_factory.mktemp(kind) / kind
    save_checkpoint(stem, policy, norm.to_dict())
    out = stem.with_suffix(".onnx")
    export_onnx(stem, out)
    return kind, stem, out


def _inputs(kind: str, replay, batch: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    feeds = {"state": replay.states[rng.choice(len(replay.states), batch, replace=False)].astype(np.float32)}
    if kind == "flow":
        feeds["noise"] = rng.standard_normal((batch, 12, 2)).astype(np.float32)
    return feeds


@pytest.mark.parametrize("batch", [1, 37])
def test_onnx_matches_torch(exported, replay, batch: int) -> None:
    kind, stem, out = exported
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    feeds = _inputs(kind, replay, batch, seed=batch)
    got = session.run(["actions"], feeds)[0]
    acting = load_acting_policy(stem)
    with torch.inference_mode():
        want = acting(*(torch.from_numpy(feeds[name]) for name in ("state", "noise") if name in feeds)).numpy()
    assert got.dtype == np.float32 and got.shape == (batch, 12, 2)
    assert np.abs(got - want).max() < 1e-3
    # clipping happens inside the graph
    assert np.all(got[:, 0, 0] == 512.0) and np.all(got[:, 0, 1] == 0.0)
    assert got.min() >= 0.0 and got.max() <= 512.0


def test_onnx_signature(exported) -> None:
    kind, _, out = exported
    model = onnx.load(str(out))
    onnx.checker.check_model(model, full_check=True)
    assert next(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) >= 17
    assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in model.graph.initializer)
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    inputs = {i.name: i for i in session.get_inputs()}
    assert list(inputs) == (["state", "noise"] if kind == "flow" else ["state"])
    assert inputs["state"].type == "tensor(float)" and inputs["state"].shape[1:] == [5]
    assert isinstance(inputs["state"].shape[0], str)  # symbolic: any batch
    if kind == "flow":
        assert inputs["noise"].type == "tensor(float)" and inputs["noise"].shape[1:] == [12, 2]
        assert inputs["noise"].shape[0] == inputs["state"].shape[0]
    (output,) = session.get_outputs()
    assert output.name == "actions" and output.type == "tensor(float)" and output.shape[1:] == [12, 2]


def test_card_records_the_export(exported) -> None:
    kind, stem, out = exported
    card = load_card(stem)
    assert card["onnx"] == {
        "file": out.name,
        "inputs": ["state", "noise"] if kind == "flow" else ["state"],
        "outputs": ["actions"],
        "num_steps": 10,
        "opset": card["onnx"]["opset"],
        "batch_invariant": card["onnx"]["batch_invariant"],
    }
    model = onnx.load(str(out))
    assert card["onnx"]["opset"] == next(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) >= 17


def test_onnx_is_deterministic_and_flow_follows_its_noise(exported, replay) -> None:
    kind, _, out = exported
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    feeds = _inputs(kind, replay, 8, seed=0)
    first = session.run(["actions"], feeds)[0]
    assert np.array_equal(first, session.run(["actions"], feeds)[0])
    if kind == "flow":
        feeds["noise"] = feeds["noise"] + 1.0
        assert not np.allclose(first[:, 1:], session.run(["actions"], feeds)[0][:, 1:])


def test_a_rows_actions_do_not_depend_on_its_batch_padded_or_not(exported, replay) -> None:
    # The export records whether each row's actions are the same alone as in batches (float32 products may round a full
    # group of four rows differently from fewer); acting runs such a graph unpadded, any other padded to four rows.
    from acting import load_policy

    kind, stem, out = exported
    policy = load_policy(out)
    assert policy.batch_multiple == (1 if load_card(stem)["onnx"]["batch_invariant"] else 4)
    feeds = _inputs(kind, replay, 37, seed=5)
    together = policy.act(feeds["state"], noise=feeds.get("noise"))
    alone = [policy.act(feeds["state"][i : i + 1], noise=None if kind == "mse" else feeds["noise"][i : i + 1]) for i in range(37)]
    np.testing.assert_array_equal(np.concatenate(alone), together)


def test_export_of_a_missing_checkpoint_names_it(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match=r"ghost\.json: checkpoint card not found"):
        export_onnx(tmp_path / "ghost")
    assert main(["--models-dir", str(tmp_path), "--names", "ghost"]) == 2


def test_cli_help() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "training.export", "--help"], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0 and "--models-dir" in result.stdout and "--checkpoint" in result.stdout


@pytest.mark.slow
def test_cli_exports_a_models_folder(tmp_path: Path) -> None:
    torch.manual_seed(0)
    norm = {"state_mean": [256.0] * 5, "state_std": [100.0] * 5, "action_mean": [256.0] * 2, "action_std": [100.0] * 2}
    save_checkpoint(tmp_path / "mse", build_policy("mse", hidden_dims=[32]), norm)
    assert main(["--models-dir", str(tmp_path), "--names", "mse"]) == 0
    assert (tmp_path / "mse.onnx").is_file()
    assert json.loads((tmp_path / "mse.json").read_text())["onnx"]["file"] == "mse.onnx"


@pytest.mark.slow
def test_export_elsewhere_leaves_the_card_alone(tmp_path: Path) -> None:
    norm = {"state_mean": [256.0] * 5, "state_std": [100.0] * 5, "action_mean": [256.0] * 2, "action_std": [100.0] * 2}
    save_checkpoint(tmp_path / "ckpt" / "flow", build_policy("flow", hidden_dims=[16]), norm)
    out = tmp_path / "elsewhere" / "f.onnx"
    assert main(["--checkpoint", str(tmp_path / "ckpt" / "flow"), "--out", str(out)]) == 0
    assert out.is_file() and load_card(tmp_path / "ckpt" / "flow")["onnx"] is None


def test_a_flow_of_16_action_chunks_exports_and_verifies_in_its_own_shapes(tmp_path: Path) -> None:
    """Shapes come from the checkpoint: state [B, 5], noise and actions [B, 16, 2]; acting's ONNX and torch backends agree."""
    import acting

    torch.manual_seed(0)
    norm = {"state_mean": [256.0] * 5, "state_std": [100.0] * 5, "action_mean": [256.0] * 2, "action_std": [100.0] * 2}
    save_checkpoint(tmp_path / "h16", build_policy("flow", hidden_dims=[16], horizon=16), norm)
    info = export_onnx(tmp_path / "h16")
    assert info["num_steps"] == 10 and info["card_updated"] and info["max_abs_diff"] < 1e-3
    session = ort.InferenceSession(str(tmp_path / "h16.onnx"), providers=["CPUExecutionProvider"])
    assert {i.name: i.shape[1:] for i in session.get_inputs()} == {"state": [5], "noise": [16, 2]}
    assert session.get_outputs()[0].shape[1:] == [16, 2]
    onnx_policy, torch_policy = acting.load_policy(tmp_path / "h16.onnx"), acting.load_policy(tmp_path / "h16")
    assert onnx_policy.horizon == torch_policy.horizon == 16
    states = np.array(
        [[222.0, 97.0, 222.0, 222.0, 0.8], [300.0, 400.0, 250.0, 260.0, 3.1], [50.0, 60.0, 70.0, 80.0, 5.0]], np.float32
    )
    got = onnx_policy.act(states, seeds=[1, 2, 3])
    assert got.shape == (3, 16, 2)
    np.testing.assert_allclose(got, torch_policy.act(states, seeds=[1, 2, 3]), atol=1e-3)


def test_default_num_steps_is_a_distilled_flows_own_count(tmp_path: Path) -> None:
    from policies.checkpoint import update_card
    from training.export import default_num_steps

    norm = {"state_mean": [256.0] * 5, "state_std": [100.0] * 5, "action_mean": [256.0] * 2, "action_std": [100.0] * 2}
    save_checkpoint(tmp_path / "f", build_policy("flow", hidden_dims=[16]), norm)
    assert default_num_steps(tmp_path / "f") == 10
    update_card(tmp_path / "f", sampler_steps=2)
    assert default_num_steps(tmp_path / "f") == default_num_steps(tmp_path / "f.json") == 2
    with pytest.raises(ValueError, match="num_steps must be >= 1"):
        export_onnx(tmp_path / "f", num_steps=0)

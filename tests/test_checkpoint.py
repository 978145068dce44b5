"""Checkpoints: save then load acts identically; every broken file gives a CheckpointError naming it."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from policies.base import ActingPolicy
from policies.card import CARD_FIELDS
from policies.checkpoint import (
    CheckpointError,
    git_commit,
    load_acting_policy,
    load_card,
    load_checkpoint,
    save_checkpoint,
    set_acting_pace,
    set_noise_scale,
    update_card,
)
from policies.factory import build_policy
from policies.flow import FlowPolicy
from policies.mse import MSEPolicy
from policies.normalization import Normalizer

REPO = Path(__file__).resolve().parent.parent

KINDS = ["mse", "flow"]
# float32 values: the card records the statistics the policy's normalizer holds
NORMALIZATION = {
    "state_mean": [229.125, 293.25, 246.5, 272.375, 1.8125],
    "state_std": [101.875, 96.5, 63.875, 65.875, 1.78125],
    "action_mean": [228.25, 294.0],
    "action_std": [101.625, 96.0],
}


def _save(tmp_path: Path, kind: str, **kwargs) -> tuple[Path, torch.nn.Module]:
    torch.manual_seed(0)
    policy = build_policy(kind, **kwargs)
    stem = tmp_path / kind
    save_checkpoint(
        stem, policy, NORMALIZATION, config={"lr": 3e-4}, steps=123, wall_time_s=4.5, evaluation={"seeds": [100000, 100099]}
    )
    return stem, policy


@pytest.mark.parametrize("kind", KINDS)
def test_save_load_gives_identical_outputs(tmp_path: Path, kind: str) -> None:
    stem, policy = _save(tmp_path, kind)
    loaded, card = load_checkpoint(stem)
    assert type(loaded) is type(policy) and not loaded.training
    for key, value in policy.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value)
    policy.eval()
    state, noise = torch.randn(9, 5), torch.randn(9, 12, 2)
    assert torch.equal(loaded.sample_actions(state, noise=noise), policy.sample_actions(state, noise=noise))

    acting = load_acting_policy(stem)
    reference = ActingPolicy(policy).eval()  # save_checkpoint gave it NORMALIZATION
    env_state = torch.rand(9, 5) * 512
    assert torch.equal(acting(env_state, noise), reference(env_state, noise))


@pytest.mark.parametrize("kind", KINDS)
def test_card_fields(tmp_path: Path, kind: str) -> None:
    stem, policy = _save(tmp_path, kind)
    card = json.loads(stem.with_suffix(".json").read_text())
    assert set(CARD_FIELDS) <= set(card)
    assert card["name"] == kind and card["kind"] == kind
    assert card["num_parameters"] == {"mse": 243_480, "flow": 706_200}[kind]
    assert card["architecture"] == policy.architecture
    assert card["normalization"] == NORMALIZATION
    assert card["config"] == {"lr": 3e-4} and card["steps"] == 123 and card["wall_time_s"] == 4.5
    assert card["evaluation"] == {"seeds": [100000, 100099]} and card["onnx"] is None
    assert isinstance(card["git_commit"], str) and card["git_commit"]


@pytest.mark.parametrize("suffix", ["", ".json", ".safetensors"])
def test_stem_with_or_without_extension(tmp_path: Path, suffix: str) -> None:
    stem, _ = _save(tmp_path, "mse")
    policy, card = load_checkpoint(str(stem) + suffix)
    assert isinstance(policy, MSEPolicy) and card["name"] == "mse"


def test_custom_architecture_round_trips(tmp_path: Path) -> None:
    stem, policy = _save(tmp_path, "flow", hidden_dims=[64, 32], dropout=0.0)
    loaded, card = load_checkpoint(stem)
    assert isinstance(loaded, FlowPolicy) and card["architecture"]["hidden_dims"] == [64, 32]
    assert loaded.architecture == policy.architecture


def test_normalizer_object_and_numpy_statistics_are_accepted(tmp_path: Path) -> None:
    import numpy as np

    norm = Normalizer().set({k: np.asarray(v) for k, v in NORMALIZATION.items()})
    card = save_checkpoint(tmp_path / "m", MSEPolicy(), norm.to_dict())
    assert card["normalization"]["action_std"] == pytest.approx(NORMALIZATION["action_std"], rel=1e-6)
    card = save_checkpoint(tmp_path / "n", MSEPolicy(), norm)
    assert len(card["normalization"]["state_mean"]) == 5


def test_save_rejects_bad_normalization(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="state_std must be a list of 5"):
        save_checkpoint(tmp_path / "x", MSEPolicy(), dict(NORMALIZATION, state_std=[1.0, 2.0]))
    with pytest.raises(ValueError, match="action_mean must be a list of 2"):
        save_checkpoint(tmp_path / "x", MSEPolicy(), {k: v for k, v in NORMALIZATION.items() if k != "action_mean"})


def test_update_card_keeps_it_valid(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "mse")
    update_card(stem, evaluation={"mean_max_reward": 0.5})
    assert load_card(stem)["evaluation"] == {"mean_max_reward": 0.5}
    with pytest.raises(ValueError, match="architecture"):
        update_card(stem, architecture={})
    with pytest.raises(CheckpointError, match="onnx"):
        update_card(stem, onnx="mse.onnx")
    assert load_card(stem)["onnx"] is None  # the failed update left the card as it was


def test_set_noise_scale_changes_sampling_only(tmp_path: Path) -> None:
    stem, policy = _save(tmp_path, "flow")
    weights_before = (tmp_path / "flow.safetensors").read_bytes()
    card = set_noise_scale(stem, 0.7)
    assert card["architecture"]["noise_scale"] == 0.7 and load_card(stem)["architecture"]["noise_scale"] == 0.7
    assert (tmp_path / "flow.safetensors").read_bytes() == weights_before
    scaled, _ = load_checkpoint(stem)
    policy.eval()
    state, noise = torch.randn(4, 5), torch.randn(4, 12, 2)
    torch.testing.assert_close(scaled.sample_actions(state, noise=noise), policy.sample_actions(state, noise=0.7 * noise))
    assert "noise_scale" not in set_noise_scale(stem, 1.0)["architecture"]  # the default is not listed
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="noise_scale"):
            set_noise_scale(stem, bad)
    mse_stem, _ = _save(tmp_path, "mse")
    with pytest.raises(ValueError, match="flow"):
        set_noise_scale(mse_stem, 0.7)


def test_set_acting_pace_needs_a_pace_input_and_a_valid_rule(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "flow")
    with pytest.raises(ValueError, match="pace input"):
        set_acting_pace(stem, [2.0, 1.0, 2.0, 0.0])
    paced = tmp_path / "paced"
    save_checkpoint(paced, FlowPolicy(pace_input=True), NORMALIZATION)
    assert set_acting_pace(paced, [2.0, 1.0, 2.0, 0.0])["architecture"]["acting_pace"] == [2.0, 1.0, 2.0, 0.0]
    assert load_checkpoint(paced)[0].acting_pace.far == 2.0
    with pytest.raises(ValueError, match="pace far must be in"):
        set_acting_pace(paced, [9.0, 1.0, 2.0, 0.0])
    assert load_card(paced)["architecture"]["acting_pace"] == [2.0, 1.0, 2.0, 0.0]  # unchanged by the refused value


def test_git_commit_outside_a_repo(tmp_path: Path) -> None:
    assert git_commit(tmp_path) == "unknown"


# --- broken checkpoints: each error names the file and the problem ---


def test_missing_card(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match=r"nothing\.json: checkpoint card not found"):
        load_checkpoint(tmp_path / "nothing")


def test_missing_weights(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "mse")
    stem.with_suffix(".safetensors").unlink()
    with pytest.raises(CheckpointError, match=r"mse\.safetensors: weights file not found"):
        load_checkpoint(stem)


def test_garbage_weights(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "flow")
    stem.with_suffix(".safetensors").write_bytes(b"\x00garbage" * 100)
    with pytest.raises(CheckpointError, match=r"flow\.safetensors: not a readable safetensors file"):
        load_checkpoint(stem)


@pytest.mark.parametrize("keep", [0.5, 0.01])
def test_truncated_weights(tmp_path: Path, keep: float) -> None:
    stem, _ = _save(tmp_path, "flow")
    path = stem.with_suffix(".safetensors")
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(CheckpointError, match=r"flow\.safetensors: not a readable safetensors file"):
        load_checkpoint(stem)


def test_pickle_is_never_loaded(tmp_path: Path) -> None:
    stem, policy = _save(tmp_path, "mse")
    torch.save(policy.state_dict(), stem.with_suffix(".safetensors"))  # a pickle under the safetensors name
    with pytest.raises(CheckpointError, match=r"mse\.safetensors: not a readable safetensors file"):
        load_checkpoint(stem)


def test_invalid_json_card(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "mse")
    stem.with_suffix(".json").write_text('{"name": "mse", ')
    with pytest.raises(CheckpointError, match=r"mse\.json: card is not valid JSON"):
        load_checkpoint(stem)


def test_card_not_an_object(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "mse")
    stem.with_suffix(".json").write_text("[1, 2]")
    with pytest.raises(CheckpointError, match=r"mse\.json: card must be a JSON object"):
        load_checkpoint(stem)


@pytest.mark.parametrize("field", ["kind", "architecture", "normalization", "steps"])
def test_card_missing_a_field(tmp_path: Path, field: str) -> None:
    stem, _ = _save(tmp_path, "mse")
    card = json.loads(stem.with_suffix(".json").read_text())
    del card[field]
    stem.with_suffix(".json").write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match=rf"mse\.json: card is missing fields \['{field}'\]"):
        load_checkpoint(stem)


def _edit_card(stem: Path, **changes) -> None:
    card = json.loads(stem.with_suffix(".json").read_text())
    card.update(changes)
    stem.with_suffix(".json").write_text(json.dumps(card))


def test_unknown_kind_in_card(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "mse")
    _edit_card(stem, kind="diffusion")
    with pytest.raises(CheckpointError, match=r"mse\.json: unknown policy kind 'diffusion'"):
        load_checkpoint(stem)


def test_wrong_kind_in_card(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "mse")
    _edit_card(stem, kind="flow")  # mse weights, flow card
    with pytest.raises(CheckpointError, match=r"mse\.(json|safetensors): .*(num_parameters|do not fit)"):
        load_checkpoint(stem)


def test_mismatched_architecture(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "flow")
    card = json.loads(stem.with_suffix(".json").read_text())
    card["architecture"]["hidden_dims"] = [128, 256, 512, 512, 256]
    card["num_parameters"] = sum(p.numel() for p in FlowPolicy(hidden_dims=[128, 256, 512, 512, 256]).parameters())
    stem.with_suffix(".json").write_text(json.dumps(card))
    with pytest.raises(
        CheckpointError, match=r"flow\.safetensors: weight net\.\d+\.\w+ has shape .* the card's architecture needs"
    ):
        load_checkpoint(stem)


def test_weights_from_another_layer_count(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "flow")
    save_file(
        {k: v.contiguous() for k, v in FlowPolicy(hidden_dims=[128, 256]).state_dict().items()},
        str(stem.with_suffix(".safetensors")),
    )
    with pytest.raises(CheckpointError, match=r"flow\.safetensors: weights do not fit the card's flow architecture"):
        load_checkpoint(stem)


def test_bad_architecture_key(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "mse")
    _edit_card(stem, architecture={"hidden_dims": [128], "width": 3})
    with pytest.raises(CheckpointError, match=r"mse\.json: bad architecture"):
        load_checkpoint(stem)


def test_num_parameters_mismatch(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "mse")
    _edit_card(stem, num_parameters=1)
    with pytest.raises(CheckpointError, match=r"mse\.json: num_parameters 1 does not match"):
        load_checkpoint(stem)


def test_bad_normalization_in_card(tmp_path: Path) -> None:
    stem, _ = _save(tmp_path, "mse")
    _edit_card(stem, normalization=dict(NORMALIZATION, action_std=[1.0]))
    with pytest.raises(CheckpointError, match=r"mse\.json: normalization\.action_std must be a list of 2"):
        load_checkpoint(stem)


def test_a_policy_without_normalization_is_not_saved(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no normalization yet"):
        save_checkpoint(tmp_path / "x", MSEPolicy())
    assert not (tmp_path / "x.json").exists()


@pytest.mark.parametrize("kind", KINDS)
def test_legacy_angle_buffers_are_refused_until_converted(tmp_path: Path, kind: str) -> None:
    """Checkpoints from before the policy owned its normalization carried angle_mean/angle_std: one conversion drops them."""
    spec = importlib.util.spec_from_file_location("convert_checkpoints", REPO / "scripts" / "convert_checkpoints.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    convert = module.convert

    stem, policy = _save(tmp_path, kind, angle_encoding="sincos")
    weights = {k: v.contiguous() for k, v in policy.state_dict().items()}
    weights["angle_mean"] = torch.tensor([NORMALIZATION["state_mean"][-1]])
    weights["angle_std"] = torch.tensor([NORMALIZATION["state_std"][-1]])
    save_file(weights, str(stem.with_suffix(".safetensors")), metadata={"format": "pt", "kind": kind})
    with pytest.raises(
        CheckpointError, match=r"safetensors: written before the policy owned its normalization.*convert_checkpoints"
    ):
        load_checkpoint(stem)
    assert convert(stem) and not convert(stem)  # converted once, then current
    state, noise = torch.rand(5, 5) * 512, torch.randn(5, 12, 2)
    assert torch.equal(load_acting_policy(stem)(state, noise), ActingPolicy(policy.eval())(state, noise))
    weights["angle_std"] = torch.tensor([2.0])  # a copy that disagrees with the card: nothing is written
    save_file(weights, str(stem.with_suffix(".safetensors")), metadata={"format": "pt", "kind": kind})
    with pytest.raises(CheckpointError, match="angle_std .* differs from the card's normalization"):
        convert(stem)


@pytest.mark.parametrize("stem", ["models/flow", "models/mse", "models/flow-chooser"])
def test_shipped_weights_are_converted(stem: str) -> None:
    policy, card = load_checkpoint(REPO / stem)
    assert policy.normalizer.to_dict() == card["normalization"]


def test_nan_weights(tmp_path: Path) -> None:
    stem, policy = _save(tmp_path, "mse")
    weights = {k: v.clone().contiguous() for k, v in policy.state_dict().items()}
    weights["net.0.weight"][0, 0] = float("nan")
    save_file(weights, str(stem.with_suffix(".safetensors")))
    with pytest.raises(CheckpointError, match=r"mse\.safetensors: weight net\.0\.weight contains NaN"):
        load_checkpoint(stem)

"""Architecture variants of both policies (angle as sin/cos, state fed to every layer, sinusoidal time): sizes, rebuilds, learning, checkpoints, ONNX."""

from __future__ import annotations

import pytest
import torch

from policies.base import ActingPolicy
from policies.factory import build_policy
from policies.networks import count_parameters
from tests.policy_helpers import acting_with as _acting
from tests.policy_helpers import fitted as _fitted
from tests.policy_helpers import loss_before_and_after_training as _loss_before_and_after_training

KINDS = ["mse", "flow"]
IDENTITY = {"state_mean": [0.0] * 5, "state_std": [1.0] * 5, "action_mean": [0.0] * 2, "action_std": [1.0] * 2}


# ---- architecture variants (angle as sin/cos, state fed to every layer, sinusoidal time) ----

FLOW_VARIANT = {"angle_encoding": "sincos", "state_skip": True, "dropout": 0.0}
MSE_VARIANT = {"angle_encoding": "sincos", "dropout": 0.0}
# one combined variant per kind exercises every new op (sin/cos, per-layer concatenation, time features)
COMBINED = {
    "mse": {"angle_encoding": "sincos", "state_skip": True, "dropout": 0.0},
    "flow": {
        "angle_encoding": "sincos",
        "state_skip": True,
        "time_embedding": "sinusoidal",
        "action_frame": "agent",
        "dropout": 0.0,
    },
}
VARIANTS = [("mse", MSE_VARIANT), ("mse", COMBINED["mse"]), ("flow", FLOW_VARIANT), ("flow", COMBINED["flow"])]


def _variant(kind: str, arch: dict, data=None, seed: int = 0):
    torch.manual_seed(seed)
    policy = build_policy(kind, **arch)
    return _fitted(policy, data) if data is not None else policy


def test_variant_parameter_counts() -> None:
    # sin/cos: one more input to the first layer (+128); flow state skip: the 6 encoded state numbers
    # again into the 4 later hidden layers and the output layer: 6 * (256 + 512 + 512 + 512 + 24)
    assert count_parameters(build_policy("mse", **MSE_VARIANT)) == 243_480 + 128 == 243_608
    assert count_parameters(build_policy("flow", **FLOW_VARIANT)) == 706_200 + 128 + 6 * 1816 == 717_224
    # sinusoidal time: 32 features instead of 1 into the first layer
    assert count_parameters(build_policy("flow", time_embedding="sinusoidal")) == 706_200 + 31 * 128


@pytest.mark.parametrize("kind, arch", VARIANTS)
def test_variant_architecture_rebuilds(kind: str, arch: dict) -> None:
    policy = build_policy(kind, **arch)
    assert {k: policy.architecture[k] for k in arch} == arch
    rebuilt = build_policy(kind, **policy.architecture)
    assert rebuilt.architecture == policy.architecture
    assert count_parameters(rebuilt) == count_parameters(policy)
    assert set(rebuilt.state_dict()) == set(policy.state_dict())


def test_default_architecture_lists_no_variant_keys() -> None:
    """Cards of the default models stay as they were, and old cards rebuild the default models."""
    for kind in KINDS:
        assert set(build_policy(kind).architecture) == {"hidden_dims", "dropout", "horizon", "action_dim", "state_dim"}
        assert not any(name.startswith("angle_") for name in build_policy(kind).state_dict())


@pytest.mark.parametrize("kind, arch", VARIANTS)
def test_the_normalization_is_not_in_the_weights(kind: str, arch: dict) -> None:
    """The card carries the statistics; the state_dict (the safetensors file) holds weights only, so no copy can disagree."""
    policy = build_policy(kind, **arch)
    assert not any(name.startswith("normalizer.") or name.startswith("angle_") for name in policy.state_dict())
    assert {name for name, _ in policy.named_buffers() if name.startswith("normalizer.")} == {
        "normalizer.state_mean",
        "normalizer.state_std",
        "normalizer.action_mean",
        "normalizer.action_std",
    }


@pytest.mark.parametrize(
    "kind, kwargs, message",
    [
        ("flow", {"angle_encoding": "degrees"}, "angle_encoding"),
        ("mse", {"state_skip": "yes"}, "state_skip"),
        ("flow", {"time_embedding": "learned"}, "time_embedding"),
        ("flow", {"time_embedding": "sinusoidal", "time_embedding_dim": 7}, "time_embedding_dim"),
        ("flow", {"time_embedding_dim": 16}, "sinusoidal"),
        ("mse", {"time_embedding": "sinusoidal"}, "unknown"),
        ("flow", {"action_frame": "block"}, "action_frame"),
    ],
)
def test_bad_variants_are_named(kind: str, kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        build_policy(kind, **kwargs)


def test_sincos_sees_the_raw_angle() -> None:
    policy = build_policy("mse", angle_encoding="sincos")
    mean, std = torch.tensor([1.0, 2.0, 3.0, 4.0, 2.5]), torch.tensor([2.0, 2.0, 2.0, 2.0, 1.5])
    policy.normalizer.set({"state_mean": mean, "state_std": std, "action_mean": [0.0] * 2, "action_std": [1.0] * 2})
    raw = torch.tensor([[10.0, 20.0, 30.0, 40.0, 0.7], [1.0, 2.0, 3.0, 4.0, 0.7 + 2 * torch.pi]])
    encoded = policy.encode_state((raw - mean) / std)
    expected_angle = torch.tensor([0.7, 0.7])
    torch.testing.assert_close(encoded[:, :4], ((raw - mean) / std)[:, :4])
    torch.testing.assert_close(encoded[:, 4], torch.sin(expected_angle), atol=1e-5, rtol=0)
    torch.testing.assert_close(encoded[:, 5], torch.cos(expected_angle), atol=1e-5, rtol=0)


def test_sincos_output_is_periodic_in_the_angle() -> None:
    mean, std = [100.0, 100.0, 100.0, 100.0, 3.0], [50.0, 50.0, 50.0, 50.0, 2.0]
    acting = _acting(_variant("flow", FLOW_VARIANT), mean, std, [256.0] * 2, [100.0] * 2)
    state = torch.tensor([[120.0, 80.0, 300.0, 250.0, 1.0]])
    noise = torch.randn(1, 12, 2)
    turned = state.clone()
    turned[0, 4] += 2 * torch.pi
    torch.testing.assert_close(acting(state, noise), acting(turned, noise), atol=1e-3, rtol=0)
    turned[0, 4] = 2.0  # a different angle must matter
    assert not torch.allclose(acting(state, noise), acting(turned, noise), atol=1e-3)


@pytest.mark.parametrize("kind", KINDS)
def test_loss_and_acting_need_the_normalization(kind: str) -> None:
    policy = build_policy(kind, **FLOW_VARIANT)
    with pytest.raises(ValueError, match="no normalization yet"):
        policy.compute_loss(torch.randn(4, 5), torch.randn(4, 12, 2))
    with pytest.raises(ValueError, match="no normalization yet"):
        ActingPolicy(policy)
    with pytest.raises(ValueError, match="state_std must be a list of 5"):
        policy.normalizer.set({**IDENTITY, "state_std": [1.0] * 4})
    policy.normalizer.set(IDENTITY)
    assert ActingPolicy(policy).policy is policy


@pytest.mark.parametrize("kind, frame", [("mse", "absolute"), ("mse", "agent"), ("flow", "agent")])
def test_loss_converts_env_units_as_acting_does(kind: str, frame: str, real_batch) -> None:
    """compute_loss(env units) is the normalized loss of the normalizer's view, frame included: the inverse of acting's conversion."""
    states, chunks, data = real_batch
    policy = _fitted(build_policy(kind, action_frame=frame, dropout=0.0), data)
    norm = policy.normalizer
    chunk_n = norm.chunk(states, chunks)
    expected_rel = chunks - states[:, None, :2] if frame == "agent" else chunks
    torch.testing.assert_close(chunk_n, (expected_rel - norm.action_mean) / norm.action_std)
    torch.testing.assert_close(norm.actions(states, chunk_n), chunks, atol=1e-3, rtol=0)
    gen = {"generator": torch.Generator().manual_seed(3)} if kind == "flow" else {}
    again = {"generator": torch.Generator().manual_seed(3)} if kind == "flow" else {}
    assert torch.equal(policy.compute_loss(states, chunks, **gen), policy.normalized_loss(norm.state(states), chunk_n, **again))


def test_state_noise_is_added_to_the_normalized_states() -> None:
    policy = build_policy("mse", dropout=0.0).eval()
    policy.normalizer.set({**IDENTITY, "state_std": [100.0] * 5})
    seen: list[torch.Tensor] = []
    policy.net.register_forward_pre_hook(lambda module, args: seen.append(args[0].clone()))
    states = torch.full((20000, 5), 300.0)
    policy.compute_loss(states, torch.zeros(20000, 12, 2), state_noise=0.05)
    assert abs(float(seen[0].mean()) - 3.0) < 0.01 and abs(float(seen[0].std()) - 0.05) < 0.002


@pytest.mark.parametrize("kind", KINDS)
def test_state_skip_reaches_the_output_layer(kind: str) -> None:
    """With every hidden layer zeroed, a skip model's output still depends on the state, a plain one's does not."""
    for skip in (True, False):
        policy = build_policy(kind, state_skip=skip, dropout=0.0).eval()
        linears = [m for m in policy.net.modules() if isinstance(m, torch.nn.Linear)]
        with torch.no_grad():
            for layer in linears[:-1]:
                layer.weight.zero_()
                layer.bias.zero_()
        states = torch.randn(2, 5)
        noise = torch.zeros(2, 12, 2)
        out = policy.sample_actions(states, noise=noise, num_steps=1)
        assert (not torch.allclose(out[0], out[1])) == skip
        if skip:
            assert [layer.in_features for layer in linears[1:]] == [w + 5 for w in policy.architecture["hidden_dims"]]


def test_sinusoidal_time_is_not_saved_but_rebuilt() -> None:
    policy = build_policy("flow", time_embedding="sinusoidal", time_embedding_dim=16).eval()
    assert "time_freqs" not in policy.state_dict()
    state, x = torch.randn(3, 5), torch.randn(3, 12, 2)
    with torch.no_grad():
        assert not torch.allclose(policy(state, x, torch.full((3,), 0.0)), policy(state, x, torch.full((3,), 0.1)))


@pytest.mark.parametrize("kind, arch", VARIANTS)
def test_variants_learn_on_real_windows(kind: str, arch: dict, real_batch) -> None:
    states, chunks, data = real_batch
    before, after = _loss_before_and_after_training(_variant(kind, arch, data), states, chunks, steps=100)
    # measured: mse 0.94 -> 0.03, flow 1.99 -> 1.14 on this batch after 100 steps
    assert after < 0.7 * before, (before, after)


@pytest.mark.parametrize("kind", KINDS)
def test_variant_checkpoint_round_trip(kind: str, real_batch, tmp_path) -> None:
    from policies.checkpoint import load_acting_policy, load_checkpoint, save_checkpoint

    _, _, data = real_batch
    policy = _variant(kind, COMBINED[kind], data).eval()
    card = save_checkpoint(tmp_path / kind, policy, git_commit="test")
    assert card["num_parameters"] == count_parameters(policy)
    assert card["architecture"] == policy.architecture
    assert card["normalization"] == policy.normalizer.to_dict()
    loaded, _ = load_checkpoint(tmp_path / kind)
    for key in card["normalization"]:
        assert torch.equal(getattr(loaded.normalizer, key), getattr(policy.normalizer, key))
    state, noise = torch.randn(6, 5), torch.randn(6, 12, 2)
    with torch.no_grad():
        assert torch.equal(loaded.sample_actions(state, noise=noise), policy.sample_actions(state, noise=noise))
    acting = load_acting_policy(tmp_path / kind)
    assert acting(torch.rand(2, 5) * 512, *([noise[:2]] if kind == "flow" else [])).shape == (2, 12, 2)


@pytest.mark.parametrize("kind", KINDS)
def test_variant_onnx_export_agrees_with_torch(kind: str, real_batch, tmp_path) -> None:
    from policies.checkpoint import save_checkpoint
    from training.export import VERIFY_ATOL, export_onnx

    _, _, data = real_batch
    save_checkpoint(tmp_path / kind, _variant(kind, COMBINED[kind], data), git_commit="test")
    info = export_onnx(tmp_path / kind, tmp_path / f"{kind}.onnx", num_steps=4)
    assert info["max_abs_diff"] <= VERIFY_ATOL

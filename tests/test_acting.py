"""The one acting interface on the shipped models (and the chooser record where steps and noise matter): no torch unless asked,
per-row seeds, batch independence, step counts, card rules."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import acting
from policies.card import CardError
from pusht.seeding import row_noise

REPO = Path(__file__).resolve().parent.parent
MODELS = REPO / "models"
STATES = np.random.default_rng(7).uniform(0, 512, (9, 5)).astype(np.float32)


def test_importing_acting_and_running_onnx_imports_no_torch():
    code = (
        "import sys, numpy as np, acting; p = acting.load_policy('models/flow.onnx'); "
        "p.act(np.full((2, 5), 256, np.float32), seeds=[1, 2]); print('torch' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "False"


@pytest.mark.parametrize(
    "folder, model",
    [
        ("shipped", "flow.onnx"),
        ("shipped", "flow"),
        ("shipped", "mse.onnx"),
        ("shipped", "mse"),
        ("chooser", "flow.onnx"),
        ("chooser", "flow"),
    ],
)
def test_a_row_depends_on_its_own_state_and_seed_only(folder, model, request):
    # a flow's rows also depend on their seeds' noise
    policy = acting.load_policy((MODELS if folder == "shipped" else request.getfixturevalue("chooser_models")) / model)
    seeds = [11, 12, 13, 14, 15, 16, 17, 18, 19]
    together = policy.act(STATES, seeds=seeds)
    assert together.shape == (9, policy.horizon, 2) and together.dtype == np.float32
    assert np.all((together >= 0) & (together <= 512))
    for i in (0, 4, 8):
        alone = policy.act(STATES[i : i + 1], seeds=seeds[i : i + 1])
        np.testing.assert_array_equal(alone[0], together[i])  # bit for bit, whatever the batch


def test_seeds_are_row_noise_and_noise_scale_multiplies_it(chooser_models):
    policy = acting.load_policy(chooser_models / "flow.onnx")  # a flow that reads its start noise
    seeds = list(range(100, 109))
    np.testing.assert_array_equal(policy.act(STATES, seeds=seeds), policy.act(STATES, noise=row_noise(seeds)))
    np.testing.assert_array_equal(
        policy.act(STATES, seeds=seeds, noise_scale=0.5), policy.act(STATES, noise=row_noise(seeds) * np.float32(0.5))
    )
    with pytest.raises(ValueError, match="one seed per state"):
        policy.act(STATES, seeds=[1, 2])
    with pytest.raises(ValueError, match="noise must have shape"):
        policy.act(STATES, noise=np.zeros((9, 16, 2), np.float32))
    with pytest.raises(ValueError, match="states must have shape"):
        policy.act(np.zeros((3, 4), np.float32))


def test_step_counts_each_backend_can_run(chooser_models):
    onnx, torch_policy = (acting.load_policy(chooser_models / m) for m in ("flow.onnx", "flow"))
    mse = acting.load_policy(MODELS / "mse.onnx")
    assert onnx.default_num_steps == torch_policy.default_num_steps == 10 and mse.default_num_steps is None
    assert onnx.check_num_steps(10) is None and "unrolls 10 flow steps" in onnx.check_num_steps(4)
    assert torch_policy.check_num_steps(4) is None
    assert "applies to flow policies" in mse.check_num_steps(4)
    # the chooser picks among K candidates at 4 stretches: each candidate takes the flow's steps, each stretch of it
    # one outcome-model pass and one value pass
    k = acting.read_card(chooser_models / "flow.json").architecture["outcome_candidates"]
    assert onnx.network_evaluations() == k * 10 + k * 4 * 2 and torch_policy.network_evaluations(4) == k * 4 + k * 4 * 2
    assert mse.network_evaluations() == 1
    with pytest.raises(ValueError, match="unrolls 10 flow steps"):
        acting.load_policy(chooser_models / "flow.onnx", num_steps=4)
    fewer = acting.load_policy(chooser_models / "flow", num_steps=4)
    np.testing.assert_array_equal(fewer.act(STATES, seeds=range(9)), torch_policy.act(STATES, seeds=range(9), num_steps=4))


@pytest.mark.parametrize("model", ["flow.onnx", "flow"])
def test_the_shipped_flow_is_a_sampler_whose_seed_changes_its_actions(model):
    policy = acting.load_policy(MODELS / model)
    assert policy.kind == "flow" and policy.card.computes == "flow" and policy.uses_noise
    assert policy.default_num_steps == policy.network_evaluations() == 10  # it integrates its velocity field in 10 Euler steps
    seeded = policy.act(STATES, seeds=range(9))
    np.testing.assert_array_equal(seeded, policy.act(STATES, seeds=range(9)))
    np.testing.assert_array_equal(seeded, policy.act(STATES, noise=row_noise(range(9))))
    assert np.abs(seeded - policy.act(STATES, seeds=range(100, 109))).max() > 1.0  # other noise, other actions


def test_a_graph_runs_unpadded_only_where_its_rows_are_the_same_alone_as_in_a_batch(tmp_path):
    # A graph runs unpadded when its export found each row the same alone as in a batch and this machine's ONNX Runtime
    # agrees on load (float32 kernels may round a group of rows otherwise on another CPU); torch always pads.
    for name in ("flow", "mse", "flow-chooser"):
        shipped = acting.load_policy(MODELS / f"{name}.onnx")
        claims = acting.read_card(MODELS / name).data["onnx"].get("batch_invariant") is True
        assert shipped.batch_multiple == (1 if claims and shipped._invariant_here() else 4)
    assert acting.load_policy(MODELS / "flow").batch_multiple == 4
    # a card that claims invariance for a graph whose rows are not is checked where it loads, so it stays padded
    card = _copy(tmp_path, "mse")
    data = json.loads(card.read_text())
    data["onnx"]["batch_invariant"] = True
    card.write_text(json.dumps(data))
    claimed = acting.load_policy(tmp_path / "mse.onnx")
    many = np.random.default_rng(8).uniform(0, 512, (37, 5)).astype(np.float32)
    alone = np.concatenate([claimed.act(many[i : i + 1]) for i in range(37)])
    np.testing.assert_array_equal(alone, claimed.act(many))


def _copy(tmp_path: Path, name: str = "flow") -> Path:
    for suffix in (".json", ".onnx"):
        shutil.copyfile(MODELS / f"{name}{suffix}", tmp_path / f"{name}{suffix}")
    return tmp_path / f"{name}.json"


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda c: c.pop("normalization"), "card is missing fields ['normalization']"),
        (lambda c: c.update(kind="gan"), "unknown policy kind 'gan'"),
        (lambda c: c["architecture"].update(horizon=0), "architecture.horizon must be an integer in 1..1024"),
        (lambda c: c["onnx"].update(num_steps=1000), "onnx.num_steps must be an integer in 1..100"),
        (lambda c: c["normalization"].update(state_std=[1.0, 1.0]), "normalization.state_std must be a list of 5 numbers"),
        (lambda c: c.update(onnx="flow.onnx"), "onnx must be null or an object"),
    ],
)
def test_one_reader_names_the_card_and_the_problem(tmp_path, edit, message):
    card_path = _copy(tmp_path)
    card = json.loads(card_path.read_text())
    edit(card)
    card_path.write_text(json.dumps(card))
    with pytest.raises(CardError) as error:
        acting.read_card(card_path)
    assert str(error.value).startswith(f"{card_path}: ") and message in str(error.value)


def test_a_graph_that_does_not_match_its_card_is_refused(tmp_path):
    _copy(tmp_path)
    shutil.copyfile(MODELS / "mse.onnx", tmp_path / "flow.onnx")  # a flow card beside an mse graph
    with pytest.raises(CardError, match="flow.onnx: has inputs \\['state'\\], a flow policy takes"):
        acting.load_policy(tmp_path / "flow.onnx")
    (tmp_path / "flow.onnx").write_bytes(b"not onnx")
    with pytest.raises(CardError, match="not a loadable ONNX model"):
        acting.load_policy(tmp_path / "flow.onnx")
    with pytest.raises(CardError, match="checkpoint card not found"):
        acting.load_policy(tmp_path / "nothing.onnx")


def test_a_flow_whose_start_noise_is_scaled_to_zero_draws_none(tmp_path):
    from policies.checkpoint import set_noise_scale

    for suffix in (".json", ".safetensors"):
        shutil.copyfile(MODELS / f"flow{suffix}", tmp_path / f"flow{suffix}")
    json_path = tmp_path / "flow.json"
    json_path.write_text(json.dumps({**json.loads(json_path.read_text()), "name": "flow"}))
    assert acting.load_policy(tmp_path / "flow").uses_noise
    set_noise_scale(tmp_path / "flow", 0.0)
    policy = acting.load_policy(tmp_path / "flow")
    assert not policy.uses_noise and acting.load_policy(MODELS / "mse").uses_noise is False
    seeded = policy.act(STATES, seeds=range(9))
    np.testing.assert_array_equal(seeded, policy.act(STATES, noise=np.zeros((9, 12, 2), np.float32)))
    np.testing.assert_array_equal(seeded, policy.act(STATES))  # no seed: the same, as nothing is drawn
    with pytest.raises(ValueError, match="seeds has 2 entries for 9 states"):
        policy.act(STATES, seeds=[1, 2])  # still checked


def test_a_rollout_with_a_fixed_noise_gives_every_row_that_seeds_noise(chooser_models):
    policy = acting.load_policy(chooser_models / "flow.onnx")
    fixed = acting.rollout_act(policy, fixed_noise=12345)
    states = np.repeat(STATES[:1], 4, axis=0)
    out = fixed(states, [1, 2, 3, 4])
    np.testing.assert_array_equal(out, np.repeat(policy.act(states[:1], seeds=[12345]), 4, axis=0))
    seeded = acting.rollout_act(policy)(states, [1, 2, 3, 4])
    assert len({row.tobytes() for row in seeded}) > 1  # per-row seeds otherwise

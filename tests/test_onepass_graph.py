"""A scoring student's lean graph acts as its module does in a fraction of the ONNX nodes, and --int8 quantizes its
hidden layers (fixed activation scales: no row depends on its batch), records how closely it follows the float32 graph,
and is refused for any other checkpoint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from acting import load_policy
from training.checkpoint import load_acting_policy, load_card, load_checkpoint, save_checkpoint
from training.distill import student_of
from training.export import _GraphModule, _torch_export, export_onnx, graph_inputs, main
from training.onepass_graph import LeanScoredChoice, lean_graph

REPO = Path(__file__).resolve().parent.parent
TEACHER = REPO / "records" / "flow-outcome16-stretch" / "last"


def _scoring_student(tmp_path: Path, stretches: tuple[float, ...] = (1.0,), shared: bool = False, context: bool = True) -> Path:
    """A random scoring student (4 hypotheses, 2 x 32 generator and scorer, scoring each at `stretches`; `shared`: a set
    network, with or without `context`) saved as a checkpoint; returns its stem."""
    torch.manual_seed(0)
    teacher, _ = load_checkpoint(TEACHER)
    student = student_of(teacher, 0.0, onepass_dims="32,32", hypotheses=4, scorer_dims="32,32", scorer_stretches=stretches,
                         scorer_shared=shared, scorer_context=context)
    with torch.no_grad():  # outputs of the order of a trained head's, so the hypotheses differ by tens of pixels
        for p in student.onepass.parameters():
            p.mul_(3.0)
    save_checkpoint(tmp_path / "student", student, steps=0, git_commit="test", evaluation=None)
    return tmp_path / "student"


def _states(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    low, high = torch.tensor([60.0, 60.0, 120.0, 120.0, 0.0]), torch.tensor([450.0, 450.0, 400.0, 400.0, 6.28])
    return low + (high - low) * torch.rand(n, 5, generator=gen), torch.randn(n, 12, 2, generator=gen)


@pytest.mark.parametrize("stretches,shared,context", [((1.0,), False, True), ((1.0, 1.3, 1.6), False, True), ((1.0,), True, True),
                                                      ((1.0, 1.3, 1.6), True, True), ((1.0,), True, False)])
def test_the_lean_graph_plays_the_modules_choice(tmp_path: Path, stretches: tuple[float, ...], shared: bool, context: bool) -> None:
    acting = load_acting_policy(_scoring_student(tmp_path, stretches, shared, context), num_steps=1).eval()
    lean = LeanScoredChoice(acting.policy).eval()
    state, noise = _states(2000, seed=1)
    with torch.no_grad():
        want, got = acting(state, noise), lean(state, noise)
    worst = (want - got).abs().amax(dim=(1, 2))
    assert float((worst > 1e-3).float().mean()) <= 0.005  # float rounding; only a near tie may pick another hypothesis
    assert lean_graph(load_checkpoint(TEACHER)[0]) is None
    if len(stretches) > 1:  # some chunks play stretched: no hypothesis is them
        with torch.no_grad():
            head = acting.policy.onepass
            state_n = acting.policy.policy_state(state)
            _, hypotheses = head.hypothesis_actions(acting.policy, state_n, head(acting.policy, state_n)[0])
        apart = (got[:, None] - hypotheses.reshape(len(state), head.candidates, 12, 2)).abs().amax(dim=(2, 3)).amin(dim=1)
        assert 0.1 < float((apart > 1e-3).float().mean()) < 0.9


def test_the_lean_export_has_under_a_third_of_the_modules_nodes(tmp_path: Path) -> None:
    stem = _scoring_student(tmp_path)
    export_onnx(stem, tmp_path / "lean.onnx")
    acting = load_acting_policy(stem, num_steps=1).eval()
    inputs = graph_inputs(acting)
    _torch_export(_GraphModule(acting, inputs).eval(), _states(4, seed=2), inputs, tmp_path / "module.onnx", 18)
    lean, module = (len(onnx.load(str(tmp_path / f"{n}.onnx")).graph.node) for n in ("lean", "module"))
    assert lean * 3 < module, (lean, module)  # 49 and 164 nodes


@pytest.mark.parametrize("shared", [False, True])
def test_int8_quantizes_the_hidden_layers_and_records_their_agreement(tmp_path: Path, capsys, shared: bool) -> None:
    stem = _scoring_student(tmp_path, shared=shared)
    export_onnx(stem, stem.with_suffix(".onnx"))
    state, noise = (t.numpy() for t in _states(256, seed=3))
    plain = load_policy(stem.with_suffix(".onnx")).act(state, noise)
    assert main(["--checkpoint", str(stem), "--int8"]) == 0
    info = load_card(stem)["onnx"]["int8"]
    # The generator after its first layer and the scoring pass's layers between its first and last (2 x 32: the one hidden
    # product); not its first layer's part on the hypotheses (signed pixels), which only --int8-parts frame takes.
    layers = ["lean.gen.1.weight", "lean.gen.2.weight", "lean.sco.1.weight"]
    assert info["layers"] == layers and "int8:" in capsys.readouterr().out
    model = onnx.load(str(stem.with_suffix(".onnx")))
    # each quantized layer is two nodes: its input to uint8 at a fixed scale, and the integer product back to float
    assert sum(n.op_type == "MatMulIntegerToFloat" for n in model.graph.node) == 3
    assert sum(n.op_type == "QuantizeLinear" for n in model.graph.node) == 3
    assert 0 <= info["median_px"] <= info["p90_px"] < 512
    policy = load_policy(stem.with_suffix(".onnx"))
    quantized = policy.act(state, noise)
    assert quantized.shape == plain.shape and np.all((quantized >= 0) & (quantized <= 512))
    assert float(np.median(np.abs(quantized - plain).reshape(256, -1).max(axis=1))) < 20.0
    # Activations have fixed scales: a row's actions do not depend on the rest of its call.
    alone = np.concatenate([policy.act(state[i : i + 1], noise[i : i + 1]) for i in range(0, 256, 17)])
    np.testing.assert_array_equal(alone, quantized[::17])
    # The torch backend plays the same int8 function (the card records each layer's input scale), not the float32 module:
    # equal but for a rare input rounded the other way.
    torch_played = load_policy(stem, backend="torch").act(state, noise)
    apart = np.abs(torch_played - quantized).reshape(256, -1).max(axis=1)
    assert float(np.mean(apart > 1e-3)) <= 0.02 and float(apart.max()) < 5.0, (np.mean(apart > 1e-3), apart.max())
    assert set(info["inputs"]) == set(layers)
    # Exported again without the flag (as `training.export` re-exports models/), the card's int8 graph comes back.
    assert main(["--checkpoint", str(stem)]) == 0
    np.testing.assert_array_equal(load_policy(stem.with_suffix(".onnx")).act(state, noise), quantized)


def test_int8_is_refused_for_a_checkpoint_without_a_scoring_pass(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="--int8 quantizes a scoring student's hidden layers"):
        export_onnx(TEACHER, tmp_path / "t.onnx", int8=True)


def test_int8_parts_quantize_only_the_layers_named_and_a_re_export_keeps_them(tmp_path: Path, capsys) -> None:
    stem = _scoring_student(tmp_path, shared=True, context=False)
    assert main(["--checkpoint", str(stem), "--int8-parts", "gen.1,frame,sco.1"]) == 0
    layers = load_card(stem)["onnx"]["int8"]["layers"]
    assert layers == ["lean.gen.1.weight", "lean.frame.weight", "lean.sco.1.weight"]
    assert main(["--checkpoint", str(stem)]) == 0  # the card's int8 graph again, the same layers
    assert load_card(stem)["onnx"]["int8"]["layers"] == layers
    assert main(["--checkpoint", str(stem), "--int8-parts", "gen,head"]) == 2
    assert "int8 parts must be gen, sco, frame" in capsys.readouterr().err

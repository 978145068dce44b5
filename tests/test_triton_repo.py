"""`training.export --triton-repo`: a model repository that Triton's own config schema accepts and that matches the graphs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest

from training.export import main
from training.triton_repo import validate_config

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def repo(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("triton")
    assert main(["--models-dir", str(REPO / "models"), "--triton-repo", str(out)]) == 0
    return out


@pytest.mark.parametrize("name, inputs", [("flow", ["state", "noise"]), ("mse", ["state"])])
def test_repository_entries_pass_tritons_schema_and_match_the_graph(repo: Path, name: str, inputs: list[str]) -> None:
    config = validate_config(repo / name)
    assert config.backend == "onnxruntime" and config.max_batch_size >= 1 and config.HasField("dynamic_batching")
    assert [t.name for t in config.input] == inputs and [list(t.dims) for t in config.output] == [[12, 2]]
    # the repository's model is the shipped one: same actions as models/NAME.onnx
    rng = np.random.default_rng(0)
    feeds = {"state": np.array([[222.0, 97.0, 222.0, 222.0, 0.8]] * 3, dtype=np.float32)}
    if name == "flow":
        feeds["noise"] = rng.standard_normal((3, 12, 2)).astype(np.float32)
    ours = ort.InferenceSession(str(repo / name / "1" / "model.onnx"), providers=["CPUExecutionProvider"]).run(
        ["actions"], feeds
    )[0]
    shipped = ort.InferenceSession(str(REPO / "models" / f"{name}.onnx"), providers=["CPUExecutionProvider"]).run(
        ["actions"], feeds
    )[0]
    np.testing.assert_allclose(ours, shipped, atol=1e-4)


def test_a_config_that_disagrees_with_its_graph_or_the_schema_is_refused(repo: Path, tmp_path: Path) -> None:
    import shutil

    from google.protobuf import text_format

    bad = tmp_path / "flow"
    shutil.copytree(repo / "flow", bad)
    text = (bad / "config.pbtxt").read_text()
    (bad / "config.pbtxt").write_text(text.replace("dims: [ 12, 2 ]\n  }\n]\ndynamic", "dims: [ 12, 3 ]\n  }\n]\ndynamic"))
    with pytest.raises(ValueError, match="outputs"):
        validate_config(bad)
    (bad / "config.pbtxt").write_text(text.replace("max_batch_size", "max_batch"))
    with pytest.raises(text_format.ParseError):
        validate_config(bad)


def test_config_shapes_come_from_the_card() -> None:
    """A flow of 16-action chunks (and any state or action width its card names) gets those dims, not 12."""
    from policies.card import Card
    from training.triton_repo import config_text

    arch = {"horizon": 16, "state_dim": 7, "action_dim": 3}
    flow = config_text("h16", Card(Path("h16.json"), {"name": "h16", "kind": "flow", "architecture": arch, "onnx": None}))
    assert flow.count("dims: [ 16, 3 ]") == 2 and "dims: [ 7 ]" in flow and 'name: "noise"' in flow and "12" not in flow
    mse = config_text("m", Card(Path("m.json"), {"name": "m", "kind": "mse", "architecture": {}, "onnx": None}))
    assert mse.count("dims: [ 12, 2 ]") == 1 and "dims: [ 5 ]" in mse and 'name: "noise"' not in mse

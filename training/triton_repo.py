"""A Triton model repository from exported policies: `REPO/NAME/1/model.onnx` and `REPO/NAME/config.pbtxt` (written by `training.export --triton-repo`).

    python -m training.export --triton-repo triton-models            # the shipped flow and mse
    docker run --rm -p 8000:8000 -v $PWD/triton-models:/models nvcr.io/nvidia/tritonserver:<version>-py3 \
        tritonserver --model-repository=/models

The config names the ONNX Runtime backend, the graph's inputs and output with their shapes (from
the card: state [5], noise [horizon, action_dim] for flow, actions [horizon, action_dim]) without the
batch dimension, which Triton's dynamic batching fills (`max_batch_size`). `validate_config` parses
the text with Triton's own model-configuration protobuf (shipped in `tritonclient`) and checks it
against the ONNX file's inputs and outputs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from policies.card import Card

__all__ = ["config_text", "validate_config", "write_config"]

MAX_BATCH_SIZE = 1024
MAX_QUEUE_DELAY_US = 100


def write_config(folder: str | Path, card: Card) -> Path:
    """Write `folder/config.pbtxt` for the policy whose ONNX graph is `folder/1/model.onnx`; the model is named after the folder."""
    path = Path(folder) / "config.pbtxt"
    path.write_text(config_text(Path(folder).name, card))
    return path


def config_text(name: str, card: Card) -> str:
    """The `config.pbtxt` of one policy, shapes from its card (`acting.read_card`)."""
    chunk = [card.horizon, card.action_dim]
    inputs = [("state", [card.state_dim])] + ([("noise", chunk)] if card.kind == "flow" else [])

    def tensor(tensor_name: str, dims: list[int]) -> str:
        return f'  {{\n    name: "{tensor_name}"\n    data_type: TYPE_FP32\n    dims: [ {", ".join(map(str, dims))} ]\n  }}'

    return "\n".join(
        [
            f'name: "{name}"',
            'backend: "onnxruntime"',
            f"max_batch_size: {MAX_BATCH_SIZE}",
            "input [\n" + ",\n".join(tensor(n, d) for n, d in inputs) + "\n]",
            "output [\n" + tensor("actions", chunk) + "\n]",
            f"dynamic_batching {{\n  max_queue_delay_microseconds: {MAX_QUEUE_DELAY_US}\n}}",
            "instance_group [\n  {\n    kind: KIND_CPU\n    count: 1\n  }\n]",
            "",
        ]
    )


def validate_config(folder: str | Path) -> Any:
    """Parse `folder/config.pbtxt` with Triton's ModelConfig protobuf and check it against `folder/1/model.onnx`; returns the message."""
    import onnx
    from google.protobuf import text_format
    from tritonclient.grpc import model_config_pb2

    folder = Path(folder)
    config = text_format.Parse((folder / "config.pbtxt").read_text(), model_config_pb2.ModelConfig())
    if config.name != folder.name:
        raise ValueError(f"{folder}/config.pbtxt: name {config.name!r} differs from its folder {folder.name!r}")
    graph = onnx.load(str(folder / "1" / "model.onnx")).graph

    def shapes(values: Any) -> dict[str, list[int]]:
        # the graph's first dimension is the dynamic batch; Triton's dims leave it out
        return {v.name: [d.dim_value for d in v.type.tensor_type.shape.dim][1:] for v in values}

    for kind, declared, actual in (("input", config.input, shapes(graph.input)), ("output", config.output, shapes(graph.output))):
        want = {t.name: list(t.dims) for t in declared}
        if want != actual:
            raise ValueError(f"{folder}/config.pbtxt: {kind}s {want} do not match the ONNX graph's {actual}")
    return config

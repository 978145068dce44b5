"""Int8 matrix products for an exported scoring student's generator (ONNX Runtime dynamic quantization).

At batch 1 a chunk's cost is reading the weights: int8 reads a quarter of the bytes. Only the generator's
layers after its first are quantized (per-channel int8 weights, activations quantized per call): its
hypotheses move by a pixel or so, and the scoring pass, kept in float32, scores the hypotheses it is
given. Quantizing the scoring pass too changes which hypothesis plays and costs success (models/README.md).
Float32 elsewhere: the first layers see pixel coordinates, which one int8 scale per call would crush.
"""

from __future__ import annotations

import logging
import re
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["GENERATOR_WEIGHT", "agreement", "quantize_generator"]

GENERATOR_WEIGHT = re.compile(r"(^|\.)gen\.[1-9][0-9]*\.weight$")
"""the initializers of `training.onepass_graph.LeanScoredChoice`'s generator layers after the first"""


def quantize_generator(path: str | Path) -> list[str]:
    """Quantize, in place, the matrix products of the ONNX file's generator layers after the first; returns their weights' names."""
    import onnx
    from onnx import helper, numpy_helper
    from onnxruntime.quantization import QuantType, quantize_dynamic

    path = Path(path)
    model = onnx.load(str(path))
    weights = {init.name: init for init in model.graph.initializer}
    nodes, chosen = [], []
    for node in model.graph.node:
        if node.op_type == "Gemm" and len(node.input) > 1 and GENERATOR_WEIGHT.search(node.input[1]):
            attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
            if attrs.get("transA", 0) or not attrs.get("transB", 0) or attrs.get("alpha", 1.0) != 1.0 or attrs.get("beta", 1.0) != 1.0:
                raise ValueError(f"{path}: {node.name} is not a plain linear layer")
            # MatMul + Add: the form the quantizer turns into an int8 product (weights transposed to [in, out]).
            name = node.input[1] + "_in_out"
            model.graph.initializer.append(numpy_helper.from_array(numpy_helper.to_array(weights[node.input[1]]).T.copy(), name))
            product = node.output[0] + "_product"
            nodes.append(helper.make_node("MatMul", [node.input[0], name], [product], name=node.name + "_matmul"))
            nodes.append(helper.make_node("Add", [product, node.input[2]], [node.output[0]], name=node.name + "_bias"))
            chosen.append(node.input[1])
            continue
        nodes.append(node)
    if not chosen:
        raise ValueError(f"{path}: no generator layers to quantize (a scoring student's lean graph has them)")
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    used = {name for node in model.graph.node for name in node.input}
    kept = [init for init in model.graph.initializer if init.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(kept)
    quiet = logging.getLogger()  # the quantizer logs advice on the root logger
    level = quiet.level
    with tempfile.TemporaryDirectory() as tmp:
        plain = Path(tmp) / "plain.onnx"
        onnx.save(model, str(plain))
        quiet.setLevel(logging.ERROR)
        try:
            quantize_dynamic(str(plain), str(path), per_channel=True, weight_type=QuantType.QInt8,
                             nodes_to_quantize=[n.name for n in nodes if n.name.endswith("_matmul")])
        finally:
            quiet.setLevel(level)
    return chosen


def agreement(reference: np.ndarray, quantized: np.ndarray) -> dict[str, float]:
    """How closely a quantized graph's actions [B, H, A] follow the float32 graph's: the median and 90th percentile over
    rows of each row's largest difference, in px (a row whose hypotheses are near a tie may choose another one)."""
    worst = np.abs(quantized - reference).reshape(len(reference), -1).max(axis=1)
    return {"median_px": round(float(np.median(worst)), 3), "p90_px": round(float(np.percentile(worst, 90)), 3)}

"""Int8 matrix products for an exported scoring student's hidden layers, quantized row by row.

At batch 1 a chunk's cost is reading the weights: int8 reads a quarter of the bytes. Quantized: the
generator's layers after its first, the scoring pass's first layer's part on the hypotheses' targets (signed
pixels in the block's frame) and its hidden layers. Float32: the parts of both first layers on the state's
ten numbers (pixel coordinates beside sines: one scale per row would crush the sines), and the scoring
pass's last, whose few outputs decide which hypothesis plays and cost nothing to keep.

Weights are int8 (7 bits of it: `WEIGHT_STEPS`) with one scale per output unit. Activations (SiLU outputs,
lifted by its floor so none is negative) get one uint8 scale per row, computed in the graph: ONNX Runtime's
dynamic quantization scales a whole call's tensor at once, so a row's actions would depend on the other rows
of its batch, which the service's contract forbids (an answer never depends on what else was in the batch).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

__all__ = ["FRAME_WEIGHT", "LAYER_WEIGHT", "SILU_FLOOR", "WEIGHT_STEPS", "agreement", "quantize_hidden"]

SILU_FLOOR = 0.2785
"""just above -min SiLU (0.27846 at -1.278): every quantized layer's input plus this is positive"""

WEIGHT_STEPS = 63
"""int8 weights use -63..63: CPUs without VNNI (AVX2) multiply uint8 by int8 in pairs summed in int16 (vpmaddubsw), which
saturates beyond 32767; 2 x 255 x 63 fits, so every CPU computes the same exact products (127 gave other actions there)"""

LAYER_WEIGHT = re.compile(r"(^|\.)(gen|sco)\.([0-9]+)\.weight$")
"""the weights of `training.onepass_graph.LeanScoredChoice`'s layers: its generator's (gen.i) and scoring pass's (sco.i)"""
FRAME_WEIGHT = re.compile(r"(^|\.)frame\.weight$")
"""the scoring pass's first layer's part on the hypotheses' targets in the block's frame (signed pixels)"""


def quantize_hidden(path: str | Path) -> list[str]:
    """Quantize, in place, the ONNX file's generator layers after the first, the scoring pass's part on the hypotheses and its
    layers between its first and last; returns their weights' names."""
    import onnx

    path = Path(path)
    model = onnx.load(str(path))
    weights = {init.name: init for init in model.graph.initializer}
    layers = {m.group(0): (m.group(2), int(m.group(3))) for name in weights if (m := LAYER_WEIGHT.search(name))}
    last_scoring = max((i for part, i in layers.values() if part == "sco"), default=-1)
    quantized = {name for name, (part, i) in layers.items() if i > 0 and (part == "gen" or i < last_scoring)}
    producers = {out: node for node in model.graph.node for out in node.output}
    nodes, added, chosen = [], [], []
    for node in model.graph.node:
        gemm = node.op_type == "Gemm" and len(node.input) >= 2
        frame = gemm and FRAME_WEIGHT.search(node.input[1]) is not None
        if frame or (gemm and _layer(node.input[1], quantized)):
            _check_linear(node, path)
            if not frame and not _silu_output(node.input[0], producers):
                raise ValueError(f"{path}: the input of {node.name} is not a SiLU's output (x * sigmoid(x)), which the quantization assumes")
            new, constants = _row_quantized_linear(node, weights, signed=frame)
            nodes.extend(new)
            added.extend(constants)
            chosen.append(node.input[1])
            continue
        nodes.append(node)
    if not chosen:
        raise ValueError(f"{path}: no hidden layers to quantize (a scoring student's lean graph has them)")
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    used = {name for node in model.graph.node for name in node.input}
    kept = [init for init in [*model.graph.initializer, *added] if init.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(kept)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return chosen


def _silu_output(name: str, producers: dict) -> bool:
    """Whether tensor `name` is x * Sigmoid(x) in the graph."""
    mul = producers.get(name)
    if mul is None or mul.op_type != "Mul":
        return False
    for a, b in (mul.input, mul.input[::-1]):
        sigmoid = producers.get(b)
        if sigmoid is not None and sigmoid.op_type == "Sigmoid" and sigmoid.input[0] == a:
            return True
    return False


def _layer(weight: str, quantized: set[str]) -> bool:
    """Whether the initializer `weight` (its name may carry a module prefix) is one of the `quantized` layers' weights."""
    m = LAYER_WEIGHT.search(weight)
    return m is not None and m.group(0) in quantized


def agreement(reference: np.ndarray, quantized: np.ndarray) -> dict[str, float]:
    """How closely a quantized graph's actions [B, H, A] follow the float32 graph's: the median and 90th percentile over
    rows of each row's largest difference, in px (a row whose hypotheses are near a tie may choose another one)."""
    worst = np.abs(quantized - reference).reshape(len(reference), -1).max(axis=1)
    return {"median_px": round(float(np.median(worst)), 3), "p90_px": round(float(np.percentile(worst, 90)), 3)}


def _check_linear(node, path: Path) -> None:
    from onnx import helper

    attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
    if attrs.get("transA", 0) or not attrs.get("transB", 0) or attrs.get("alpha", 1.0) != 1.0 or attrs.get("beta", 1.0) != 1.0:
        raise ValueError(f"{path}: {node.name} is not a plain linear layer (x @ W.T + b)")


def _row_quantized_linear(node, weights: dict, signed: bool = False) -> tuple[list, list]:
    """The nodes and constants of y = x @ W.T + b with int8 W (per output unit) and x quantized per row to uint8: a SiLU
    output lifted by SILU_FLOOR (never negative: no zero point, the shift returns through the bias), or with `signed`
    any x, scaled by its largest magnitude around 128."""
    from onnx import TensorProto, helper, numpy_helper

    p, x, y = node.name or node.input[1], node.input[0], node.output[0]
    w = numpy_helper.to_array(weights[node.input[1]]).astype(np.float64)  # [out, in]
    w_scale = np.maximum(np.abs(w).max(axis=1), 1e-12) / WEIGHT_STEPS
    w_q = np.clip(np.round(w / w_scale[:, None]), -WEIGHT_STEPS, WEIGHT_STEPS)
    has_bias = len(node.input) > 2 and node.input[2] != ""  # the exporter drops an all-zero bias
    b = numpy_helper.to_array(weights[node.input[2]]).astype(np.float64) if has_bias else np.zeros(len(w))
    lift = 0.0 if signed else SILU_FLOOR
    constants = {
        "w": w_q.astype(np.int8).T.copy(),  # [in, out]
        "w_scale": w_scale.astype(np.float32),
        # (x + lift) @ Wq.T = x @ Wq.T + lift * (row sums of Wq): subtracted here, in the dequantized weights' units
        "b": (b - lift * (w_q * w_scale[:, None]).sum(axis=1)).astype(np.float32),
        "axis": np.array([1], dtype=np.int64),
        "per_step": np.array(1.0 / (127.0 if signed else 255.0), dtype=np.float32),
    }
    if signed:
        constants |= {"mid": np.array(128.0, dtype=np.float32), "zero_point": np.array(128, dtype=np.uint8),
                      "tiny": np.array(1e-12, dtype=np.float32)}
    else:
        constants["floor"] = np.array(SILU_FLOOR, dtype=np.float32)
    c = {k: f"{p}_{k}" for k in constants}

    def t(name: str) -> str:  # the layer's intermediate tensors
        return f"{p}_{name}"

    if signed:  # an all-zero row would have no scale: the tiny floor keeps it finite
        head = [helper.make_node("Abs", [x], [t("magnitude")]),
                helper.make_node("ReduceMax", [t("magnitude"), c["axis"]], [t("largest")], keepdims=1),
                helper.make_node("Max", [t("largest"), c["tiny"]], [t("peak")])]
    else:  # a lifted SiLU output is at least 3.5e-5: its peak is never zero
        head = [helper.make_node("Add", [x, c["floor"]], [t("lifted")]),
                helper.make_node("ReduceMax", [t("lifted"), c["axis"]], [t("peak")], keepdims=1)]
    source = x if signed else t("lifted")
    nodes = [
        *head,
        helper.make_node("Mul", [t("peak"), c["per_step"]], [t("scale")]),
        helper.make_node("Div", [source, t("scale")], [t("steps")]),
        helper.make_node("Round", [t("steps")], [t("rounded")]),
        *([helper.make_node("Add", [t("rounded"), c["mid"]], [t("shifted")])] if signed else []),
        helper.make_node("Cast", [t("shifted") if signed else t("rounded")], [t("x_q")], to=TensorProto.UINT8),
        helper.make_node("MatMulInteger", [t("x_q"), c["w"], *([c["zero_point"]] if signed else [])], [t("acc")]),
        helper.make_node("Cast", [t("acc")], [t("acc_f")], to=TensorProto.FLOAT),
        helper.make_node("Mul", [t("acc_f"), t("scale")], [t("row_scaled")]),
        helper.make_node("Mul", [t("row_scaled"), c["w_scale"]], [t("product")]),
        helper.make_node("Add", [t("product"), c["b"]], [y]),
    ]
    return nodes, [numpy_helper.from_array(v, c[k]) for k, v in constants.items()]

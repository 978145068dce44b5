"""Int8 matrix products for an exported scoring student's hidden layers: weights per output unit, activations by fixed scales.

At batch 1 a chunk's cost is reading the weights and running the graph's nodes (about a microsecond each).
Quantized: the generator's layers after its first and the scoring pass's hidden layers. Float32: the parts of
both first layers on the state's numbers (pixel coordinates beside sines: one scale would crush the sines), the
scoring pass's last, whose few outputs decide which hypothesis plays and cost nothing to keep, and unless named
(`frame`) its first layer's part on the hypotheses' targets (signed pixels in the block's frame): 24 inputs, whose
int8 product costs more than its float32 one (three nodes for one).

Weights are 8-bit (`WEIGHT_STEPS`, stored as uint8 around `WEIGHT_ZERO`) with one scale per output unit. Each layer's input gets one
fixed uint8 scale and zero point, calibrated once on states (`quantize_hidden`): a layer is then two nodes
(QuantizeLinear, and ONNX Runtime's MatMulIntegerToFloat with its bias), not the eleven that scaling each row in
the graph took, and no row's actions can depend on the other rows of its batch, as the service's contract has
it. The scales span the 0.1th to 99.9th percentile of what the layer sees (`ACTIVATION_PERCENTILE`): the
largest activations are rare, and a scale wide enough for them left 67 % success where float32 plays 89 %.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

__all__ = ["ACTIVATION_PERCENTILE", "FRAME_WEIGHT", "LAYER_WEIGHT", "PARTS", "WEIGHT_STEPS", "agreement", "input_scale", "quantize_hidden",
           "quantize_weights"]

ACTIVATION_PERCENTILE = 99.9
"""a layer's input scale spans this percentile of its calibration values (and 100 minus it); beyond, values saturate"""

WEIGHT_STEPS = 127
"""weights use -127..127, stored as uint8 around a zero point of 128: ONNX Runtime multiplies uint8 by uint8 exactly on
every CPU, while uint8 by int8 on CPUs without VNNI (AVX2) sums pairs in int16 (vpmaddubsw), which saturates unless the
weights keep to -63..63, half the resolution (the outcome model's layers then choose other hypotheses)"""

LAYER_WEIGHT = re.compile(r"(^|\.)(gen|sco)\.([0-9]+)\.weight$")
"""the weights of `training.onepass_graph.LeanScoredChoice`'s layers: its generator's (gen.i) and scoring pass's (sco.i)"""
PARTS = ("gen", "sco")
"""what `quantize_hidden` takes to int8 unless told otherwise: the generator's hidden layers, the scoring pass's (`frame`
only when named)"""
FRAME_WEIGHT = re.compile(r"(^|\.)frame\.weight$")
"""the scoring pass's first layer's part on the hypotheses' targets in the block's frame (signed pixels)"""


def quantize_hidden(path: str | Path, feeds: dict[str, np.ndarray], parts: tuple[str, ...] = PARTS) -> dict[str, list[float]]:
    """Quantize, in place, the ONNX file's generator layers after the first ("gen"), the scoring pass's layers between its
    first and last ("sco") and its first layer's part on the hypotheses ("frame"), of the `parts` named, each input's scale calibrated on the
    graph's inputs `feeds`; returns each one's weight name and its input's [scale, zero point] (what `training.int8_module`
    needs to play the same graph in torch)."""
    import onnx

    unknown = [part for part in parts if not re.fullmatch(r"(gen|sco)(\.[0-9]+)?|frame", part)]
    if unknown:
        raise ValueError(f"int8 parts must be gen, sco, frame or one layer as gen.N / sco.N, got {unknown}")
    path = Path(path)
    model = onnx.load(str(path))
    weights = {init.name: init for init in model.graph.initializer}
    layers = {m.group(0): (m.group(2), int(m.group(3))) for name in weights if (m := LAYER_WEIGHT.search(name))}
    last_scoring = max((i for part, i in layers.values() if part == "sco"), default=-1)
    quantized = {name for name, (part, i) in layers.items()
                 if i > 0 and (part == "gen" or i < last_scoring) and (part in parts or f"{part}.{i}" in parts)}
    frame = "frame" in parts
    targets = [node for node in model.graph.node if node.op_type == "Gemm" and len(node.input) >= 2
               and ((frame and FRAME_WEIGHT.search(node.input[1]) is not None) or _layer(node.input[1], quantized))]
    if not targets:
        raise ValueError(f"{path}: no hidden layers to quantize (a scoring student's lean graph has them)")
    ranges = _input_ranges(model, targets, feeds)
    nodes, added, chosen = [], [], {}
    for node in model.graph.node:
        if any(node is t for t in targets):
            _check_linear(node, path)
            scale, zero = input_scale(*ranges[node.input[0]], signed=FRAME_WEIGHT.search(node.input[1]) is not None)
            new, constants = _quantized_linear(node, weights, scale, zero)
            nodes.extend(new)
            added.extend(constants)
            chosen[node.input[1]] = [scale, zero]
            continue
        nodes.append(node)
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    used = {name for node in model.graph.node for name in node.input}
    kept = [init for init in [*model.graph.initializer, *added] if init.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(kept)
    if not any(o.domain == "com.microsoft" for o in model.opset_import):
        model.opset_import.append(onnx.helper.make_opsetid("com.microsoft", 1))
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return chosen


def _input_ranges(model, targets: list, feeds: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
    """The `ACTIVATION_PERCENTILE` range (low, high) of each target layer's input when the float graph runs on `feeds`."""
    import onnx
    import onnxruntime as ort

    probe = onnx.ModelProto()
    probe.CopyFrom(model)
    names = list(dict.fromkeys(node.input[0] for node in targets))
    probe.graph.output.extend(onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, None) for name in names)
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    values = ort.InferenceSession(probe.SerializeToString(), options, providers=["CPUExecutionProvider"]).run(names, feeds)
    return {name: (float(np.percentile(v, 100 - ACTIVATION_PERCENTILE)), float(np.percentile(v, ACTIVATION_PERCENTILE)))
            for name, v in zip(names, values)}


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


def input_scale(low: float, high: float, signed: bool) -> tuple[float, int]:
    """A layer input's float32 uint8 scale and zero point over [low, high]: from 0 (a SiLU's output, at least -0.28) with a
    zero point, or with `signed` symmetric around 128."""
    if signed:
        return float(np.float32(max(abs(low), abs(high), 1e-12) / 127.0)), 128
    low = min(low, 0.0)
    scale = float(np.float32(max(high - low, 1e-12) / 255.0))
    return scale, int(round(-low / scale))


def quantize_weights(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Float weights [out, in] as int8 [out, in] in -`WEIGHT_STEPS`..`WEIGHT_STEPS` and one float32 scale per output unit."""
    w = w.astype(np.float64)
    w_scale = np.maximum(np.abs(w).max(axis=1), 1e-12) / WEIGHT_STEPS
    return np.clip(np.round(w / w_scale[:, None]), -WEIGHT_STEPS, WEIGHT_STEPS).astype(np.int8), w_scale.astype(np.float32)


WEIGHT_ZERO = 128
"""the zero point of the stored uint8 weights"""


def _quantized_linear(node, weights: dict, scale: float, zero: int) -> tuple[list, list]:
    """The nodes and constants of y = x @ W.T + b with int8 W (per output unit) and x in uint8 at `scale` around `zero`."""
    from onnx import helper, numpy_helper

    p = node.name or node.input[1]
    w_q, w_scale = quantize_weights(numpy_helper.to_array(weights[node.input[1]]))
    has_bias = len(node.input) > 2 and node.input[2] != ""  # the exporter drops an all-zero bias
    b = numpy_helper.to_array(weights[node.input[2]]) if has_bias else np.zeros(len(w_q))
    constants = {"x_scale": np.array(scale, dtype=np.float32), "x_zero": np.array(zero, dtype=np.uint8),
                 "w": (w_q.T.astype(np.int16) + WEIGHT_ZERO).astype(np.uint8), "w_scale": w_scale,
                 "w_zero": np.full(len(w_q), WEIGHT_ZERO, dtype=np.uint8), "b": b.astype(np.float32)}
    c = {k: f"{p}_{k}" for k in constants}
    nodes = [
        helper.make_node("QuantizeLinear", [node.input[0], c["x_scale"], c["x_zero"]], [f"{p}_x_q"]),
        # (x_q - zero) @ Wq times both scales, plus the bias: one contrib node of ONNX Runtime's CPU kernels
        helper.make_node("MatMulIntegerToFloat", [f"{p}_x_q", c["w"], c["x_scale"], c["w_scale"], c["x_zero"], c["w_zero"], c["b"]],
                         [node.output[0]], domain="com.microsoft"),
    ]
    return nodes, [numpy_helper.from_array(v, c[k]) for k, v in constants.items()]

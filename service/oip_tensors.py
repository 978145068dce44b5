"""OIP v2 tensors: the inference request model, its input tensors (JSON or binary data) checked, the response.

Inputs are checked as strictly as `/act` bodies: the datatype and shape of each, values finite and in
range (states within +-STATE_LIMIT, noise within +-NOISE_LIMIT, seeds in 0..2**63-1), JSON values
numbers only (no strings or booleans), binary sizes that add up to the body.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np
import orjson
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictFloat, StrictInt

from acting import Policy
from service.request_input import ServiceError
from service.schemas import MAX_SEED
from service.settings import STATE_LIMIT

__all__ = ["InferRequest", "VERSION", "answer", "input_tensors", "invalid", "model_metadata", "split_body"]

VERSION = "1"
NOISE_LIMIT = 100.0
"""Largest |noise value| accepted: the noise is standard normal, so far beyond is a client bug."""
PLATFORMS = {"onnx": "onnxruntime_onnx", "torch": "pytorch_libtorch"}

Param = StrictBool | StrictInt | StrictFloat | Annotated[str, Field(max_length=1000)]


class _Tensor(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(max_length=64)
    shape: list[Annotated[StrictInt, Field(ge=0, le=1 << 31)]] = Field(max_length=8)
    datatype: str = Field(max_length=16)
    parameters: dict[str, Param] = Field(default_factory=dict, max_length=16)
    data: list[Any] | None = None


class _Output(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(max_length=64)
    parameters: dict[str, Param] = Field(default_factory=dict, max_length=16)


class InferRequest(BaseModel):
    """An OIP v2 inference request header (the JSON before any binary tensor data)."""

    model_config = ConfigDict(extra="forbid")
    id: str | None = Field(None, max_length=256)
    parameters: dict[str, Param] = Field(default_factory=dict, max_length=16)
    inputs: list[_Tensor] = Field(min_length=1, max_length=8)
    outputs: list[_Output] | None = Field(None, max_length=8)


def invalid(loc: list[Any], msg: str) -> ServiceError:
    """A 422 naming where in the request the problem is."""
    return ServiceError(422, [{"loc": loc, "msg": msg, "type": "value_error"}])


def model_metadata(name: str, policy: Policy) -> dict[str, Any]:
    """The OIP model metadata: inputs and outputs in the policy's card shapes, with -1 for the batch dimension."""
    chunk = [-1, policy.horizon, policy.action_dim]
    inputs = [{"name": "state", "datatype": "FP32", "shape": [-1, policy.state_dim]}]
    if policy.kind == "flow":
        inputs += [{"name": "noise", "datatype": "FP32", "shape": chunk}, {"name": "seeds", "datatype": "INT64", "shape": [-1]}]
    return {
        "name": name,
        "versions": [VERSION],
        "platform": PLATFORMS.get(policy.backend, policy.backend),
        "inputs": inputs,
        "outputs": [{"name": "actions", "datatype": "FP32", "shape": chunk}],
    }


def split_body(body: bytes, header_length: str | None) -> tuple[bytes, bytes]:
    """(JSON header, binary tensor data) per the Inference-Header-Content-Length header."""
    if header_length is None:
        return body, b""
    if not header_length.isdigit() or int(header_length) > len(body):
        raise ServiceError(
            400, f"Inference-Header-Content-Length {header_length!r} must be an integer up to the body's {len(body)} bytes"
        )
    return body[: int(header_length)], body[int(header_length) :]


def input_tensors(req: InferRequest, tail: bytes, policy: Policy, max_states: int) -> dict[str, np.ndarray]:
    """The request's input tensors by name, with datatype, shape, size and values checked."""
    expected = {t["name"]: t for t in model_metadata(policy.name, policy)["inputs"]}
    out: dict[str, np.ndarray] = {}
    offset = 0
    rows = None
    for k, tensor in enumerate(req.inputs):
        loc: list[Any] = ["inputs", k]
        spec = expected.get(tensor.name)
        if spec is None:
            raise invalid(loc + ["name"], f"policy {policy.name!r} has no input {tensor.name!r}; its inputs: {sorted(expected)}")
        if tensor.name in out:
            raise invalid(loc + ["name"], f"input {tensor.name!r} is given twice")
        datatypes = ("INT64", "UINT64") if tensor.name == "seeds" else ("FP32",)
        if tensor.datatype not in datatypes:
            raise invalid(loc + ["datatype"], f"input {tensor.name!r} must be {' or '.join(datatypes)}, got {tensor.datatype!r}")
        shape = tensor.shape
        if not shape or shape[1:] != spec["shape"][1:] or not 1 <= shape[0] <= max_states or rows not in (None, shape[0]):
            dims = ", ".join(["B", *map(str, spec["shape"][1:])])
            raise invalid(
                loc + ["shape"],
                f"input {tensor.name!r} must have shape [{dims}] with B in 1..{max_states}, "
                f"the same B for every input; got {shape}",
            )
        rows = shape[0]
        dtype = np.dtype({"FP32": "<f4", "INT64": "<i8", "UINT64": "<u8"}[tensor.datatype])
        count = math.prod(tensor.shape)
        extra = set(tensor.parameters) - {"binary_data_size"}
        if extra:
            raise invalid(loc + ["parameters"], f"unknown tensor parameters {sorted(extra)}; the one known is binary_data_size")
        size = tensor.parameters.get("binary_data_size")
        if (size is None) == (tensor.data is None):
            raise invalid(loc, "give the tensor's values either as `data` or as binary data (parameters.binary_data_size)")
        if size is not None:
            if type(size) is not int or size != count * dtype.itemsize or offset + size > len(tail):
                raise invalid(
                    loc + ["parameters", "binary_data_size"],
                    f"must be {count * dtype.itemsize} bytes "
                    f"({count} x {tensor.datatype}) and within the {len(tail) - offset} binary bytes left",
                )
            array = np.frombuffer(tail, dtype=dtype, count=count, offset=offset)
            offset += size
        else:
            array = _from_json(tensor.data, count, dtype, loc + ["data"])
        out[tensor.name] = _checked(tensor.name, array.reshape(tensor.shape), loc)
    if offset != len(tail):
        raise ServiceError(400, f"{len(tail) - offset} bytes of binary data follow the header that no input claims")
    if "state" not in out:
        raise invalid(["inputs"], f"the input `state` (FP32 [B, {policy.state_dim}]) is required")
    return out


def _from_json(data: list[Any], count: int, dtype: np.dtype, loc: list[Any]) -> np.ndarray:
    """A flat array from JSON `data` (flat or nested lists of numbers, row-major)."""
    flat: list[Any] = []
    stack = [data]
    while stack:
        item = stack.pop()
        if isinstance(item, list):
            stack.extend(reversed(item))
        elif type(item) is int or (type(item) is float and dtype.kind == "f"):
            flat.append(item)
        else:
            raise invalid(loc, f"values must be JSON {'numbers' if dtype.kind == 'f' else 'integers'}, got {item!r:.40}")
        if len(flat) > count:
            break
    if len(flat) != count:
        raise invalid(loc, f"has {'more' if len(flat) > count else len(flat)} values, the shape needs {count}")
    if dtype.kind != "f":  # seeds: checked here, since a JSON integer may overflow any integer dtype
        if any(not 0 <= v <= MAX_SEED for v in flat):
            raise invalid(loc, f"seeds must be in 0..{MAX_SEED}")
        return np.asarray(flat, dtype=np.int64)
    try:
        return np.asarray(flat, dtype=np.float64)
    except OverflowError:  # an integer beyond any float: out of range like 1e999
        raise invalid(loc, "values must be finite numbers") from None


def _checked(name: str, array: np.ndarray, loc: list[Any]) -> np.ndarray:
    """A native copy of the array, once its values are in range."""
    if name == "seeds":
        if (array.dtype.kind == "i" and (array < 0).any()) or (array.dtype.kind == "u" and (array > MAX_SEED).any()):
            raise invalid(loc, f"seeds must be in 0..{MAX_SEED}")
        return array.astype(np.int64)
    limit = STATE_LIMIT if name == "state" else NOISE_LIMIT
    with np.errstate(over="ignore", invalid="ignore"):
        bad = ~np.isfinite(array) | (np.abs(array) > limit)
    if bad.any():
        raise invalid(loc, f"{name} values must be finite and within +-{limit:g}")
    return array.astype(np.float32)  # a copy: binary inputs are read-only views of the body


def answer(name: str, request_id: str | None, actions: np.ndarray, binary: bool) -> Response:
    """The OIP response: `actions` as JSON data or as binary data after the JSON header."""
    tensor: dict[str, Any] = {"name": "actions", "datatype": "FP32", "shape": list(actions.shape)}
    result: dict[str, Any] = {"model_name": name, "model_version": VERSION, "outputs": [tensor]}
    if request_id is not None:
        result["id"] = request_id
    if not binary:
        tensor["data"] = actions.ravel()
        return Response(orjson.dumps(result, option=orjson.OPT_SERIALIZE_NUMPY), media_type="application/json")
    tensor["parameters"] = {"binary_data_size": actions.nbytes}
    head = orjson.dumps(result)
    return Response(
        head + actions.astype("<f4").tobytes(),
        media_type="application/octet-stream",
        headers={"Inference-Header-Content-Length": str(len(head))},
    )

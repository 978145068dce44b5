"""The baseline for bench/service_latency.py: the plain way to serve an ONNX policy with FastAPI.

One ONNX Runtime call per request (default session options), a pydantic request model, no batching;
run with default uvicorn settings:

    BASELINE_ONNX=models/flow.onnx uvicorn bench.baseline_app:app
"""

from __future__ import annotations

import os

import numpy as np
import onnxruntime as ort
from fastapi import FastAPI
from pydantic import BaseModel

MODEL = os.environ.get("BASELINE_ONNX", "models/flow.onnx")

session = ort.InferenceSession(MODEL, providers=["CPUExecutionProvider"])
input_names = [i.name for i in session.get_inputs()]
app = FastAPI(title="baseline policy server")


class ActRequest(BaseModel):
    """One state and an optional noise seed."""

    policy: str = "flow"
    state: list[float]
    seed: int | None = None


@app.post("/act")
def act(req: ActRequest) -> dict:
    """Actions [12, 2] for one state, from one ONNX Runtime call."""
    feeds = {"state": np.asarray([req.state], dtype=np.float32)}
    if "noise" in input_names:
        feeds["noise"] = np.random.default_rng(req.seed).standard_normal((1, 12, 2), dtype=np.float32)
    actions = session.run(None, feeds)[0]
    return {"policy": req.policy, "actions": actions[0].tolist()}


@app.get("/readyz")
def readyz() -> dict:
    """Always ready once imported (the model loads at import)."""
    return {"status": "ready"}

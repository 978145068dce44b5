"""KServe Open Inference Protocol v2 (`/v2/...`) against a real server, with the official tritonclient."""

from __future__ import annotations

import asyncio
import json

import httpx
import numpy as np
import pytest

from pusht.rollout import chunk_noise
from tests.service_fixtures import SHIPPED_MODELS, UvicornProcess, iter_lines, shipped_models_available

tritonclient_http = pytest.importorskip("tritonclient.http", reason="the test extra installs tritonclient[http]")

pytestmark = pytest.mark.skipif(not shipped_models_available(), reason="needs the shipped models/flow and models/mse")

KEY = "oip-test-key"
AUTH = {"X-API-Key": KEY}
STATES = np.array(
    [[222.0, 97.0, 300.0, 300.0, 0.8], [100.0, 400.0, 250.0, 260.0, 3.1], [480.0, 30.0, 200.0, 350.0, 5.5]], dtype=np.float32
)


@pytest.fixture(scope="module")
def server():
    with UvicornProcess(
        {"PUSHT_MODELS_DIR": str(SHIPPED_MODELS), "PUSHT_API_KEY": KEY, "PUSHT_MAX_STATES": "64"}, entry="service"
    ) as srv:
        yield srv


@pytest.fixture(scope="module")
def chooser_server(chooser_models):
    """The outcome chooser record as `flow`: its actions depend on the noise, so seeds, seeds inputs and noise are told apart."""
    with UvicornProcess(
        {"PUSHT_MODELS_DIR": str(chooser_models), "PUSHT_API_KEY": KEY, "PUSHT_MAX_STATES": "64"}, entry="service"
    ) as srv:
        yield srv


def _act(url: str, body: dict) -> np.ndarray:
    response = httpx.post(f"{url}/act", json=body, headers=AUTH)
    assert response.status_code == 200, response.text
    return np.float32(response.json()["actions"])


def _tensor(name: str, array: np.ndarray, datatype: str, binary: bool = True):
    tensor = tritonclient_http.InferInput(name, list(array.shape), datatype)
    tensor.set_data_from_numpy(array, binary_data=binary)
    return tensor


@pytest.mark.parametrize("which", ["server", "chooser_server"], ids=["shipped", "chooser"])
def test_official_client_gets_the_actions_of_act(which: str, request: pytest.FixtureRequest) -> None:
    """tritonclient: health, metadata, and for seed, seeds and noise the same float32 actions as /act, binary and JSON."""
    server = request.getfixturevalue(which)
    client = tritonclient_http.InferenceServerClient(server.url.removeprefix("http://"))
    # dict(AUTH) each time: tritonclient adds Inference-Header-Content-Length to the headers dict it is given
    assert client.is_server_live() and client.is_server_ready()
    assert client.is_model_ready("flow", headers=dict(AUTH)) and not client.is_model_ready("nope")
    meta = client.get_model_metadata("flow", headers=dict(AUTH))
    assert [(i["name"], i["datatype"], i["shape"]) for i in meta["inputs"]] == [
        ("state", "FP32", [-1, 5]),
        ("noise", "FP32", [-1, 12, 2]),
        ("seeds", "INT64", [-1]),
    ]
    assert meta["outputs"] == [{"name": "actions", "datatype": "FP32", "shape": [-1, 12, 2]}]
    assert [i["name"] for i in client.get_model_metadata("mse")["inputs"]] == ["state"]
    with_seed = _act(server.url, {"policy": "flow", "states": STATES.tolist(), "seed": 7})
    with_seeds = _act(server.url, {"policy": "flow", "states": STATES.tolist(), "seeds": [11, 12, 13]})
    assert not np.array_equal(with_seed, with_seeds)  # the flow's noise comes from each row's seed
    for binary in (True, False):
        out = [tritonclient_http.InferRequestedOutput("actions", binary_data=binary)]
        state = _tensor("state", STATES, "FP32", binary)
        got = client.infer("flow", [state], parameters={"seed": 7}, outputs=out, headers=dict(AUTH)).as_numpy("actions")
        assert got.dtype == np.float32 and np.array_equal(got, with_seed)
        seeds = _tensor("seeds", np.array([11, 12, 13], dtype=np.int64), "INT64", binary)
        assert np.array_equal(
            client.infer("flow", [state, seeds], outputs=out, headers=dict(AUTH)).as_numpy("actions"), with_seeds
        )
        noise = _tensor("noise", chunk_noise(7, len(STATES)), "FP32", binary)  # the noise that seed 7 draws
        assert np.array_equal(
            client.infer("flow", [state, noise], headers=dict(AUTH), model_version="1").as_numpy("actions"), with_seed
        )
    mse = client.infer("mse", [_tensor("state", STATES[:1], "FP32")], headers=dict(AUTH)).as_numpy("actions")
    assert np.array_equal(mse, _act(server.url, {"policy": "mse", "state": STATES[0].tolist()})[None])
    # a single row equals its row of the batch: the same padded model calls as /act
    one = client.infer(
        "flow", [_tensor("state", STATES[1:2], "FP32"), _tensor("seeds", np.array([12]), "INT64")], headers=dict(AUTH)
    )
    assert np.array_equal(one.as_numpy("actions")[0], with_seeds[1])


def test_shares_model_calls_with_act(server: UvicornProcess) -> None:
    """OIP and /act requests sent together are merged into shared model calls, each answer its own."""
    bodies = []
    for i in range(24):
        state = STATES[i % 3].tolist()
        if i % 2:
            bodies.append(
                (
                    "/v2/models/flow/infer",
                    {
                        "inputs": [{"name": "state", "shape": [1, 5], "datatype": "FP32", "data": state}],
                        "parameters": {"seed": i},
                    },
                )
            )
        else:
            bodies.append(("/act", {"policy": "flow", "state": state, "seed": i}))
    for _ in range(5):  # on a loaded machine each request of a burst may arrive alone and run at once; another merges
        before = _batch_counts(server.url)
        answers = asyncio.run(_burst(server.port, bodies))
        after = _batch_counts(server.url)
        calls, requests = after[0] - before[0], after[1] - before[1]
        assert requests == len(bodies), (calls, requests)
        if calls < requests:
            break
    assert calls < requests, (calls, requests)
    for i, ((path, _), (status, body)) in enumerate(zip(bodies, answers, strict=True)):
        assert status == 200, body
        payload = json.loads(body)
        got = np.float32(payload["outputs"][0]["data"]).reshape(12, 2) if path != "/act" else np.float32(payload["actions"])
        assert np.array_equal(got, _act(server.url, {"policy": "flow", "state": STATES[i % 3].tolist(), "seed": i}))


def _batch_counts(url: str) -> tuple[float, float]:
    """(model calls, requests they merged) for flow, from /metrics; a labelled series appears at its first call, so absent is 0."""
    values = dict(line.rsplit(" ", 1) for line in iter_lines(httpx.get(f"{url}/metrics").text))
    return tuple(float(values.get(f'pusht_batch_requests_{part}{{policy="flow"}}', 0.0)) for part in ("count", "sum"))


async def _burst(port: int, requests: list[tuple[str, dict]]) -> list[tuple[int, bytes]]:
    """POST each (path, body) on its own connection, all written before any answer is read."""
    streams = await asyncio.gather(*(asyncio.open_connection("127.0.0.1", port) for _ in requests))
    for (_, writer), (path, body) in zip(streams, requests, strict=True):
        data = json.dumps(body).encode()
        writer.write(
            b"POST %s HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nX-API-Key: %s\r\nContent-Length: %d\r\n\r\n%s"
            % (path.encode(), KEY.encode(), len(data), data)
        )

    async def read(reader: asyncio.StreamReader) -> tuple[int, bytes]:
        head = await reader.readuntil(b"\r\n\r\n")
        length = next(int(line.split(b":")[1]) for line in head.split(b"\r\n") if line.lower().startswith(b"content-length:"))
        return int(head[9:12]), await reader.readexactly(length)

    try:
        return list(await asyncio.gather(*(read(reader) for reader, _ in streams)))
    finally:
        for _, writer in streams:
            writer.close()


def _state(**changes) -> dict:
    return {"name": "state", "shape": [1, 5], "datatype": "FP32", "data": [222.0, 97.0, 300.0, 300.0, 0.8], **changes}


BINARY_STATE = {"name": "state", "shape": [1, 5], "datatype": "FP32", "parameters": {"binary_data_size": 20}}
BAD = [
    # (what, path, headers, body, status, text in the error)
    ("no key", "flow", {"X-API-Key": ""}, {"inputs": [_state()]}, 401, "API key"),
    ("wrong key", "flow", {"X-API-Key": "nope"}, {"inputs": [_state()]}, 401, "API key"),
    ("browser page", "flow", {"Origin": "http://example.com"}, {"inputs": [_state()]}, 403, "web pages"),
    ("form type", "flow", {"Content-Type": "text/plain"}, {"inputs": [_state()]}, 415, "text/plain"),
    ("compressed", "flow", {"Content-Encoding": "gzip"}, {"inputs": [_state()]}, 415, "compressed"),
    ("unknown model", "nope", {}, {"inputs": [_state()]}, 404, "unknown model 'nope'"),
    ("unknown version", "flow/versions/2", {}, {"inputs": [_state()]}, 404, "version '1' only"),
    ("broken JSON", "flow", {}, b"{", 422, "Invalid JSON"),
    (
        "NaN token",
        "flow",
        {},
        b'{"inputs": [{"name": "state", "shape": [1, 5], "datatype": "FP32", "data": [1, 2, 3, 4, NaN]}]}',
        422,
        "finite",
    ),
    (
        "overflowing literal",
        "flow",
        {},
        b'{"inputs": [{"name": "state", "shape": [1, 5], "datatype": "FP32", "data": [1, 2, 3, 4, 1e999]}]}',
        422,
        "finite",
    ),
    ("huge integer", "flow", {}, {"inputs": [_state(data=[1, 2, 3, 4, 10**400])]}, 422, "finite"),
    ("no inputs", "flow", {}, {"inputs": []}, 422, "at least 1"),
    ("unknown field", "flow", {}, {"inputs": [_state()], "extra": 1}, 422, "Extra inputs"),
    ("no state", "flow", {}, {"inputs": [{"name": "seeds", "shape": [1], "datatype": "INT64", "data": [1]}]}, 422, "`state`"),
    ("unknown input", "flow", {}, {"inputs": [_state(), _state(name="prev_state")]}, 422, "no input 'prev_state'"),
    (
        "noise for mse",
        "mse",
        {},
        {"inputs": [_state(), {"name": "noise", "shape": [1, 12, 2], "datatype": "FP32", "data": [0.0] * 24}]},
        422,
        "no input 'noise'",
    ),
    ("twice", "flow", {}, {"inputs": [_state(), _state()]}, 422, "given twice"),
    ("datatype", "flow", {}, {"inputs": [_state(datatype="FP64")]}, 422, "must be FP32"),
    ("shape", "flow", {}, {"inputs": [_state(shape=[1, 4], data=[1, 2, 3, 4])]}, 422, "shape [B, 5]"),
    ("batch too large", "flow", {}, {"inputs": [_state(shape=[65, 5], data=[1.0] * 325)]}, 422, "B in 1..64"),
    (
        "rows differ",
        "flow",
        {},
        {"inputs": [_state(), {"name": "seeds", "shape": [2], "datatype": "INT64", "data": [1, 2]}]},
        422,
        "the same B",
    ),
    ("too few values", "flow", {}, {"inputs": [_state(data=[1, 2, 3])]}, 422, "has 3 values"),
    ("too many values", "flow", {}, {"inputs": [_state(data=[1, 2, 3, 4, 5, 6])]}, 422, "has more values"),
    ("string value", "flow", {}, {"inputs": [_state(data=[1, 2, 3, 4, "5"])]}, 422, "numbers"),
    ("bool value", "flow", {}, {"inputs": [_state(data=[1, 2, 3, 4, True])]}, 422, "numbers"),
    ("state out of range", "flow", {}, {"inputs": [_state(data=[1, 2, 3, 4, 1e6])]}, 422, "within +-10000"),
    (
        "noise out of range",
        "flow",
        {},
        {"inputs": [_state(), {"name": "noise", "shape": [1, 12, 2], "datatype": "FP32", "data": [1e3] * 24}]},
        422,
        "within +-100",
    ),
    (
        "negative seed",
        "flow",
        {},
        {"inputs": [_state(), {"name": "seeds", "shape": [1], "datatype": "INT64", "data": [-1]}]},
        422,
        "seeds must be in 0..",
    ),
    ("seed too large", "flow", {}, {"inputs": [_state()], "parameters": {"seed": 2**63}}, 422, "seed must be an integer"),
    (
        "seed and seeds",
        "flow",
        {},
        {"inputs": [_state(), {"name": "seeds", "shape": [1], "datatype": "INT64", "data": [1]}], "parameters": {"seed": 1}},
        422,
        "at most one",
    ),
    (
        "unknown parameter",
        "flow",
        {},
        {"inputs": [_state()], "parameters": {"priority": 1}},
        422,
        "unknown parameters ['priority']",
    ),
    (
        "num_steps",
        "flow",
        {},
        {"inputs": [_state()], "parameters": {"num_steps": 3}},
        422,
        "num_steps=3 is not available on the onnx backend",
    ),  # the graph unrolls its own 10 steps
    ("num_steps for mse", "mse", {}, {"inputs": [_state()], "parameters": {"num_steps": 10}}, 422, "no sampler steps"),
    ("unknown output", "flow", {}, {"inputs": [_state()], "outputs": [{"name": "values"}]}, 422, "the one output is `actions`"),
    ("data and binary", "flow", {}, {"inputs": [_state(parameters={"binary_data_size": 20})]}, 422, "either as `data`"),
    (
        "binary too short",
        "flow",
        {"Inference-Header-Content-Length": "HEAD"},
        (BINARY_STATE, b"\0" * 12),
        422,
        "must be 20 bytes",
    ),
    ("unclaimed bytes", "flow", {"Inference-Header-Content-Length": "HEAD"}, ({**_state()}, b"\0" * 8), 400, "no input claims"),
    (
        "header length",
        "flow",
        {"Inference-Header-Content-Length": "999"},
        {"inputs": [_state()]},
        400,
        "Inference-Header-Content-Length",
    ),
    ("body too large", "flow", {}, b"[" + b"0," * 600_000 + b"0]", 413, "exceeds the limit"),
]


@pytest.mark.parametrize(("what", "model", "headers", "body", "status", "text"), BAD, ids=[case[0] for case in BAD])
def test_bad_requests_get_clear_errors(server: UvicornProcess, what, model, headers, body, status, text) -> None:
    """Every bad request: a 4xx JSON answer with `error` (one string, what OIP clients show) naming the problem."""
    headers = {**AUTH, **headers}
    if isinstance(body, tuple):  # (JSON header, binary data): the header's length goes in Inference-Header-Content-Length
        head = json.dumps({"inputs": [body[0]]}).encode()
        headers["Inference-Header-Content-Length"] = str(len(head))
        content = head + body[1]
    else:
        content = body if isinstance(body, bytes) else json.dumps(body).encode()
    response = httpx.post(f"{server.url}/v2/models/{model}/infer", content=content, headers=headers)
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/json"
    error = response.json()["error"]
    assert isinstance(error, str) and text in error, error


def test_health_and_metadata_need_no_key(server: UvicornProcess) -> None:
    """Probes and metadata stay open as /healthz and /readyz do; infer needs the key."""
    for path, expected in (
        ("/v2/health/live", {"live": True}),
        ("/v2/health/ready", {"ready": True}),
        ("/v2/models/flow/ready", {"name": "flow", "ready": True}),
    ):
        response = httpx.get(server.url + path)
        assert (response.status_code, response.json()) == (200, expected)
    assert httpx.get(f"{server.url}/v2").json()["extensions"] == ["binary_tensor_data"]
    assert httpx.get(f"{server.url}/v2/models/mse").json()["platform"] == "onnxruntime_onnx"
    assert httpx.get(f"{server.url}/v2/models/nope").status_code == 404
    assert httpx.post(f"{server.url}/v2/models/flow/infer", json={"inputs": [_state()]}).status_code == 401

"""The openpi-compatible websocket `/openpi/{policy}` against a real server, with the official openpi-client.

openpi-client pins numpy<2 (the project runs numpy 2), so it gets a venv of its own, made once and
kept in pytest's cache; the protocol's error paths are also driven with plain `websockets`.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from service.openpi_ws import pack, unpack
from tests.service_fixtures import SHIPPED_MODELS, UvicornProcess, shipped_models_available

pytestmark = pytest.mark.skipif(not shipped_models_available(), reason="needs the shipped models/flow and models/mse")

KEY = "openpi-test-key"
STATES = [[222.0, 97.0, 300.0, 300.0, 0.8], [100.0, 400.0, 250.0, 260.0, 3.1], [480.0, 30.0, 200.0, 350.0, 5.5]]

CLIENT = r"""
import json, sys
import numpy as np
from openpi_client import websocket_client_policy
url, key, states = sys.argv[1], sys.argv[2] or None, json.loads(sys.argv[3])
client = websocket_client_policy.WebsocketClientPolicy(host=url, api_key=key)
out = {"metadata": client.get_server_metadata(), "answers": []}
for i, state in enumerate(states):
    reply = client.infer({"state": np.asarray(state, dtype=np.float32), "seed": 1000 + i})
    out["answers"].append({"actions": reply["actions"].tolist(), "dtype": str(reply["actions"].dtype),
                           "shape": list(reply["actions"].shape), "timing": sorted(reply["server_timing"])})
try:
    client.infer({"state": np.zeros(4, dtype=np.float32)})
    out["bad"] = "no error"
except RuntimeError as exc:
    out["bad"] = str(exc)
again = client.infer({"state": np.asarray(states[0], dtype=np.float32), "seed": 1000})
out["again"] = again["actions"].tolist()
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def openpi_python(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> str:
    """A venv with the official openpi-client (and typing_extensions, which it imports without declaring)."""
    cache = getattr(request.config, "cache", None)  # absent under -p no:cacheprovider
    venv = Path(cache.mkdir("openpi-client-venv")) if cache is not None else tmp_path_factory.mktemp("openpi-client-venv")
    python = venv / "bin" / "python"
    if not (venv / ".complete").is_file():
        start = time.monotonic()
        subprocess.run([sys.executable, "-m", "venv", "--clear", str(venv)], check=True)
        pip = subprocess.run(
            [
                str(python),
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                "openpi-client==0.1.2",
                "typing_extensions",
            ],
            capture_output=True,
            text=True,
        )
        if pip.returncode != 0:
            pytest.skip(f"cannot install openpi-client into a venv: {pip.stderr.strip()[-500:]}")
        (venv / ".complete").write_text(f"installed in {time.monotonic() - start:.1f} s\n")
    return str(python)


@pytest.fixture(scope="module")
def server():
    with UvicornProcess({"PUSHT_MODELS_DIR": str(SHIPPED_MODELS), "PUSHT_API_KEY": KEY}, entry="service") as srv:
        yield srv


@pytest.fixture(scope="module")
def chooser_server(chooser_models):
    """The outcome chooser record as `flow`: its actions depend on the seed (the shipped student's do not)."""
    with UvicornProcess({"PUSHT_MODELS_DIR": str(chooser_models), "PUSHT_API_KEY": KEY}, entry="service") as srv:
        yield srv


def _act(url: str, state: list[float], seed: int) -> list[list[float]]:
    response = httpx.post(f"{url}/act", json={"policy": "flow", "state": state, "seed": seed}, headers={"X-API-Key": KEY})
    assert response.status_code == 200, response.text
    return response.json()["actions"]


@pytest.mark.parametrize("which", ["server", "chooser_server"], ids=["shipped", "chooser"])
def test_official_client_gets_the_actions_of_act(openpi_python: str, which: str, request: pytest.FixtureRequest) -> None:
    """openpi-client: metadata on connect, the same float32 actions as /act for the same seed, a bad message survived."""
    server = request.getfixturevalue(which)
    url = f"{server.url.removeprefix('http://')}/openpi/flow"
    run = subprocess.run([openpi_python, "-c", CLIENT, url, KEY, json.dumps(STATES)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    meta = out["metadata"]
    assert (meta["policy"], meta["kind"], meta["horizon"], meta["action_dim"], meta["state_dim"]) == ("flow", "flow", 12, 2, 5)
    for i, (state, answer) in enumerate(zip(STATES, out["answers"], strict=True)):
        assert (answer["dtype"], answer["shape"], answer["timing"][0]) == ("float32", [12, 2], "infer_ms")
        assert np.array_equal(np.float32(answer["actions"]), np.float32(_act(server.url, state, 1000 + i)))
    assert out["answers"][1]["timing"] == ["infer_ms", "prev_total_ms"]
    assert "Error in inference server" in out["bad"] and "'state' must be 5 numbers" in out["bad"]
    assert out["again"] == out["answers"][0]["actions"]
    # another seed moves the flow's actions: the equality with /act checks the seed's way through
    assert not np.array_equal(np.float32(_act(server.url, STATES[0], 1001)), np.float32(out["again"]))


def test_bad_messages_get_errors_and_the_connection_stays(server: UvicornProcess) -> None:
    """Text frames, garbage, wrong shapes, NaN, prev_state, unknown keys, bad seeds: each a text error, then a good answer."""
    url = f"ws://{server.url.removeprefix('http://')}/openpi/mse"
    bad: list[tuple[bytes | str, int, str]] = [
        ("{}", 400, "binary msgpack-numpy"),
        (b"\xc1\xc1", 400, "not valid msgpack-numpy"),
        (pack([1, 2]), 422, "must be a map"),
        (pack({"seed": 1}), 422, "no 'state'"),
        (pack({"state": np.zeros((1, 5), np.float32)}), 422, "5 numbers"),
        (pack({"state": np.array([1, 2, 3, 4, np.nan], np.float32)}), 422, "finite"),
        (pack({"state": ["a", "b", "c", "d", "e"]}), 422, "5 numbers"),
        (pack({"state": np.zeros(5, np.float32), "prev_state": np.zeros(5, np.float32)}), 422, "takes no prev_state"),
        (pack({"state": np.zeros(5, np.float32), "image": 1}), 422, "unknown keys"),
        (pack({"state": np.zeros(5, np.float32), "seed": -1}), 422, "'seed' must be an integer"),
        (pack({"state": np.zeros(5, np.float32), "seed": True}), 422, "'seed' must be an integer"),
        (pack({"state": np.zeros(5, np.float32), "num_steps": 10}), 422, "no sampler steps"),
        (pack({"state": {b"__ndarray__": True, b"data": b"x", b"dtype": "|O", b"shape": [1]}}), 422, "must be numeric"),
        (pack({"state": {b"__ndarray__": True, b"data": b"xx", b"dtype": "<f4", b"shape": [5]}}), 400, "not valid"),
    ]
    with connect(url, additional_headers={"Authorization": f"Api-Key {KEY}"}) as ws:
        meta = unpack(ws.recv())
        assert meta["kind"] == "mse" and meta["num_steps"] is None
        for message, status, text in bad:
            ws.send(message)
            reply = ws.recv()
            assert isinstance(reply, str), message
            error = json.loads(reply)
            assert error["status"] == status and text in error["error"], (message, error)
        ws.send(pack({"state": np.asarray(STATES[0], np.float32)}))
        actions = unpack(ws.recv())["actions"]
    expected = httpx.post(f"{server.url}/act", json={"policy": "mse", "state": STATES[0]}, headers={"X-API-Key": KEY}).json()[
        "actions"
    ]
    assert actions.dtype == np.float32 and np.array_equal(actions, np.float32(expected))


@pytest.mark.parametrize(
    ("path", "headers", "status", "text"),
    [
        ("/openpi/flow", {}, 401, "API key"),
        ("/openpi/flow", {"Authorization": "Api-Key wrong"}, 401, "Api-Key KEY"),
        ("/openpi/flow", {"Authorization": f"Api-Key {KEY}", "origin": "http://example.com"}, 403, "web pages"),
        ("/openpi/nope", {"Authorization": f"Api-Key {KEY}"}, 404, "unknown policy 'nope'"),
    ],
)
def test_refused_handshakes_get_json_errors(
    server: UvicornProcess, path: str, headers: dict[str, str], status: int, text: str
) -> None:
    """A missing or wrong key, a browser's Origin, an unknown policy: an HTTP JSON error instead of the upgrade."""
    origin = headers.pop("origin", None)
    with pytest.raises(InvalidStatus) as info:
        connect(f"ws://{server.url.removeprefix('http://')}{path}", additional_headers=headers, origin=origin).close()
    response = info.value.response
    assert response.status_code == status
    assert text in json.loads(response.body)["detail"]


def test_other_key_headers_work(server: UvicornProcess) -> None:
    """X-API-Key and a bearer token open the websocket too (as on /act)."""
    for headers in ({"X-API-Key": KEY}, {"Authorization": f"Bearer {KEY}"}):
        with connect(f"ws://{server.url.removeprefix('http://')}/openpi/flow", additional_headers=headers) as ws:
            assert unpack(ws.recv())["policy"] == "flow"


def test_a_client_that_hangs_up_mid_request_leaves_no_traceback(server: UvicornProcess) -> None:
    """The reply to a client gone while its chunk was computed is dropped quietly: no ASGI traceback in the log."""
    url = f"ws://{server.url.removeprefix('http://')}/openpi/flow-chooser"  # the slowest policy: the reply is still pending
    for i in range(5):
        ws = connect(url, additional_headers={"X-API-Key": KEY})
        ws.recv(timeout=10)  # metadata
        ws.send(pack({"state": np.asarray(STATES[i % 3], np.float32), "seed": i}))
        ws.close()
    time.sleep(2.0)
    assert "Traceback" not in server.output() and "Exception in ASGI application" not in server.output()
    with connect(url, additional_headers={"X-API-Key": KEY}) as ws:  # and the server answers the next client
        ws.recv(timeout=10)
        ws.send(pack({"state": np.asarray(STATES[0], np.float32), "seed": 0}))
        assert unpack(ws.recv(timeout=30))["actions"].shape == (12, 2)


def test_frames_are_bounded_like_bodies_and_not_compressed(server: UvicornProcess) -> None:
    """python -m service closes a frame over PUSHT_MAX_BODY_BYTES with 1009 and offers no per-message compression."""
    from websockets.exceptions import ConnectionClosed

    url = f"ws://{server.url.removeprefix('http://')}/openpi/mse"
    with connect(url, additional_headers={"X-API-Key": KEY}, compression="deflate") as ws:
        assert ws.response.headers.get("Sec-WebSocket-Extensions") is None  # compression refused
        ws.recv(timeout=10)
        with pytest.raises(ConnectionClosed) as closed:
            ws.send(b"\x00" * (2 << 20))  # the server may close (1009) while the frame is still being sent
            ws.recv(timeout=10)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1009

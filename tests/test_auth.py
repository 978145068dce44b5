"""One API-key rule on every route: the same headers accepted, the same precedence (a real server on loopback)."""

from __future__ import annotations

import json

import httpx
import pytest
from service_fixtures import SHIPPED_MODELS, UvicornProcess
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

KEY = "auth-matrix-key"
STATE = [222.0, 97.0, 300.0, 300.0, 0.8]
HEADERS = {  # what each header set should get: the key itself is all that matters, X-API-Key first when both come
    "x-api-key": ({"X-API-Key": KEY}, True),
    "bearer": ({"Authorization": f"Bearer {KEY}"}, True),
    "api-key": ({"Authorization": f"Api-Key {KEY}"}, True),
    "none": ({}, False),
    "wrong": ({"X-API-Key": "nope"}, False),
    "basic": ({"Authorization": f"Basic {KEY}"}, False),
    "wrong x-api-key beats a right bearer": ({"X-API-Key": "nope", "Authorization": f"Bearer {KEY}"}, False),
    "right x-api-key beats a wrong bearer": ({"X-API-Key": KEY, "Authorization": "Bearer nope"}, True),
}


@pytest.fixture(scope="module")
def server():
    with UvicornProcess({"PUSHT_MODELS_DIR": str(SHIPPED_MODELS), "PUSHT_API_KEY": KEY}, entry="service") as srv:
        yield srv


def _http(server, headers: dict) -> dict[str, int]:
    oip = {"inputs": [{"name": "state", "shape": [1, 5], "datatype": "FP32", "data": STATE}]}
    return {
        "/act": httpx.post(f"{server.url}/act", json={"policy": "mse", "state": STATE}, headers=headers).status_code,
        "/policies": httpx.get(f"{server.url}/policies", headers=headers).status_code,
        "/v2 infer": httpx.post(f"{server.url}/v2/models/mse/infer", json=oip, headers=headers).status_code,
    }


def _openpi(server, headers: dict) -> int:
    try:
        with connect(f"ws://{server.url.removeprefix('http://')}/openpi/mse", additional_headers=headers) as ws:
            ws.recv(timeout=10)
            return 200
    except InvalidStatus as exc:
        return exc.response.status_code


def _viewer(server, headers: dict) -> int:
    with connect(f"ws://{server.url.removeprefix('http://')}/viewer/ws", additional_headers=headers) as ws:
        ws.send(json.dumps({"type": "start", "policy": "mse", "seed": 1}))
        answer = json.loads(ws.recv(timeout=10))
        return 200 if answer["type"] == "state" else answer["status"]


@pytest.mark.parametrize("case", sorted(HEADERS))
def test_every_route_takes_the_key_the_same_way(server, case: str) -> None:
    headers, accepted = HEADERS[case]
    statuses = {**_http(server, headers), "/openpi": _openpi(server, headers), "/viewer/ws": _viewer(server, headers)}
    assert statuses == {route: (200 if accepted else 401) for route in statuses}, case

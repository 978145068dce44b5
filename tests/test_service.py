"""The policy service: backends, seeds, batching, auth, metrics; in-process and against a real uvicorn.

Random-weight `mse` and `flow` policies are built once per session into a temp dir (policies
+ checkpoint + export), so these tests need no trained models; the server tests repeat on the
shipped models/. The batcher alone, bad requests, hardening, startup refusals, per-row seeds and
fairness have their own tests/test_service_*.py.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import httpx
import numpy as np
import pytest

from pusht.rollout import chunk_noise
from tests.service_fixtures import SHIPPED_MODELS, UvicornProcess, iter_lines, raw_burst, shipped_models_available

STATE = [120.0, 300.0, 256.0, 250.0, 1.0]
STATES = [[120.0, 300.0, 256.0, 250.0, 1.0], [400.5, 80.25, 200.0, 310.0, 5.5], [256.0, 256.0, 256.0, 256.0, 0.0]]


SHIPPED_SKIP = "models/mse and models/flow (.json + .onnx) are not shipped yet: train and export them to run this on them"


def _models_dir(which: str, request: pytest.FixtureRequest) -> Path:
    if which == "shipped":
        if not shipped_models_available():
            pytest.skip(SHIPPED_SKIP)
        return SHIPPED_MODELS
    return request.getfixturevalue("test_models")


@pytest.fixture(scope="module", params=["test", "shipped"], ids=["test-models", "shipped-models"])
def server(request: pytest.FixtureRequest):
    """A real uvicorn on 127.0.0.1 serving the random test models, then the shipped models/ (if present)."""
    models_dir = _models_dir(request.param, request)
    with UvicornProcess({"PUSHT_MODELS_DIR": str(models_dir), "PUSHT_MAX_STATES": "64"}) as srv:
        yield srv


def act(url: str, timeout: float = 10.0, **body) -> httpx.Response:
    return httpx.post(f"{url}/act", json=body, timeout=timeout)


# ---- backends, in process ------------------------------------------------------------------------


def test_onnx_and_torch_backends_agree(test_models: Path) -> None:
    """The exported graph and the torch checkpoint give the same actions for the same states and noise."""
    from acting import load_policy

    rng = np.random.default_rng(0)
    states = np.column_stack([rng.uniform(0, 512, (37, 4)), rng.uniform(0, 2 * np.pi, 37)]).astype(np.float32)
    noise = chunk_noise(7, 37)
    for name in ("mse", "flow"):
        card_path = test_models / f"{name}.json"
        onnx_policy = load_policy(card_path, backend="onnx")
        torch_policy = load_policy(card_path, backend="torch")
        assert (onnx_policy.backend, torch_policy.backend) == ("onnx", "torch")
        assert onnx_policy.horizon == torch_policy.horizon == 12 and onnx_policy.action_dim == 2
        a = onnx_policy.act(states, noise=noise if name == "flow" else None)
        b = torch_policy.act(states, noise=noise if name == "flow" else None)
        assert a.shape == b.shape == (37, 12, 2)
        np.testing.assert_allclose(a, b, atol=1e-3, rtol=0)
        assert a.min() >= 0.0 and a.max() <= 512.0
    # torch honors other step counts; onnx refuses them with a reason
    flow_torch = load_policy(test_models / "flow.json", backend="torch")
    three = flow_torch.act(states, noise=noise, num_steps=3)
    assert not np.allclose(three, flow_torch.act(states, noise=noise, num_steps=10))
    assert flow_torch.check_num_steps(3) is None
    assert "onnx backend" in load_policy(test_models / "flow.json", backend="onnx").check_num_steps(3)


def test_every_shape_comes_from_the_card(horizon16_models: Path) -> None:
    """Cards of 16-action chunks: /act, /policies, OIP v2, openpi metadata, the batcher and the viewer all use 16."""
    from fastapi.testclient import TestClient

    from acting import load_policy
    from pusht.rollout import decision_seed, row_noise
    from service.app import create_app
    from service.openpi_ws import pack, unpack
    from service.settings import Settings
    from service.viewer_episode import Episode

    flow = load_policy(horizon16_models / "flow.json", backend="onnx")
    assert (flow.horizon, flow.action_dim) == (16, 2)
    with TestClient(create_app(Settings(models_dir=horizon16_models, max_states=64))) as client:
        listing = {p["name"]: p for p in client.get("/policies").json()["policies"]}
        assert {name: (p["horizon"], p["action_dim"]) for name, p in listing.items()} == {"flow": (16, 2), "mse": (16, 2)}
        assert (listing["flow"]["network_evaluations"], listing["mse"]["network_evaluations"]) == (10, 1)
        one = client.post("/act", json={"policy": "flow", "state": STATE, "seed": 3})
        assert one.status_code == 200, one.text
        assert np.asarray(one.json()["actions"]).shape == (16, 2)
        many = client.post("/act", json={"policy": "flow", "states": STATES, "seeds": [7, 8, 9]}).json()["actions"]
        expected = flow.act(np.asarray(STATES, np.float32), noise=row_noise([7, 8, 9], 16, 2))
        np.testing.assert_allclose(np.asarray(many, np.float32), expected, atol=1e-4, rtol=0)
        whole = client.post("/act", json={"policy": "flow", "states": STATES, "seed": 5}).json()["actions"]
        np.testing.assert_allclose(
            np.asarray(whole, np.float32),
            flow.act(np.asarray(STATES, np.float32), noise=chunk_noise(5, 3, 16, 2)),
            atol=1e-4,
            rtol=0,
        )
        assert np.asarray(client.post("/act", json={"policy": "mse", "states": STATES}).json()["actions"]).shape == (3, 16, 2)

        meta = client.get("/v2/models/flow").json()
        assert {t["name"]: t["shape"] for t in meta["inputs"]} == {"state": [-1, 5], "noise": [-1, 16, 2], "seeds": [-1]}
        assert meta["outputs"] == [{"name": "actions", "datatype": "FP32", "shape": [-1, 16, 2]}]
        noise = np.random.default_rng(0).standard_normal((2, 16, 2)).astype(np.float32)
        infer = client.post(
            "/v2/models/flow/infer",
            json={
                "inputs": [
                    {"name": "state", "datatype": "FP32", "shape": [2, 5], "data": STATES[:2]},
                    {"name": "noise", "datatype": "FP32", "shape": [2, 16, 2], "data": noise.ravel().tolist()},
                ]
            },
        ).json()
        assert infer["outputs"][0]["shape"] == [2, 16, 2]
        np.testing.assert_allclose(
            np.asarray(infer["outputs"][0]["data"], np.float32).reshape(2, 16, 2),
            flow.act(np.asarray(STATES[:2], np.float32), noise=noise),
            atol=1e-4,
            rtol=0,
        )
        twelve = client.post(
            "/v2/models/flow/infer",
            json={
                "inputs": [
                    {"name": "state", "datatype": "FP32", "shape": [1, 5], "data": STATE},
                    {"name": "noise", "datatype": "FP32", "shape": [1, 12, 2], "data": [0.0] * 24},
                ]
            },
        )
        assert twelve.status_code == 422 and "[B, 16, 2]" in twelve.json()["error"]

        with client.websocket_connect("/openpi/flow") as ws:
            hello = unpack(ws.receive_bytes())
            assert (hello["horizon"], hello["action_dim"], hello["state_dim"]) == (16, 2, 5)
            ws.send_bytes(pack({"state": np.asarray(STATE, np.float32), "seed": 3}))
            np.testing.assert_array_equal(unpack(ws.receive_bytes())["actions"], np.asarray(one.json()["actions"], np.float32))

    # the viewer runs each chunk whole: 16 env steps per policy decision
    episode = Episode(200000, "flow", max_steps=40)
    while not episode.done:
        if episode.needs_chunk():
            states, seed = episode.next_request()
            assert seed == decision_seed(200000, episode.decisions - 1)
            episode.set_chunk(flow.act(states, seeds=[seed])[0])
        episode.step()
    assert (episode.length, episode.decisions) == (40, 3)  # chunks of 16, 16, 8


# ---- a real server --------------------------------------------------------------------------------


@pytest.mark.slow
def test_act_shapes_ranges_and_policies(server: UvicornProcess) -> None:
    one = act(server.url, policy="flow", state=STATE, seed=1)
    assert one.status_code == 200, one.text
    body = one.json()
    assert (body["policy"], body["kind"], body["backend"]) == ("flow", "flow", "onnx")
    actions = np.asarray(body["actions"])
    assert actions.shape == (12, 2) and actions.min() >= 0 and actions.max() <= 512
    many = act(server.url, policy="mse", states=STATES)
    assert many.status_code == 200 and np.asarray(many.json()["actions"]).shape == (3, 12, 2)
    listing = httpx.get(f"{server.url}/policies").json()
    assert listing["backend"] == "onnx"
    kinds = {p["name"]: p["kind"] for p in listing["policies"]}
    assert kinds["flow"] == "flow" and kinds["mse"] == "mse"
    assert all(p["num_parameters"] > 0 for p in listing["policies"])
    assert all((p["horizon"], p["action_dim"]) == (12, 2) for p in listing["policies"])  # the cards' chunk shape
    assert httpx.get(f"{server.url}/healthz").json() == {"status": "alive"}
    assert httpx.get(f"{server.url}/readyz").status_code == 200
    assert httpx.get(f"{server.url}/docs").status_code == 200
    assert "/act" in httpx.get(f"{server.url}/openapi.json").json()["paths"]


@pytest.mark.slow
def test_seeds_are_deterministic_and_match_chunk_noise(server: UvicornProcess) -> None:
    """Same seed -> same actions, equal to the policy run in process on chunk_noise(seed, B)."""
    from acting import load_policy

    a = act(server.url, policy="flow", states=STATES, seed=42).json()["actions"]
    b = act(server.url, policy="flow", states=STATES, seed=42).json()["actions"]
    c = act(server.url, policy="flow", states=STATES, seed=43).json()["actions"]
    fresh = [act(server.url, policy="flow", state=STATE).json()["actions"] for _ in range(2)]
    policy = load_policy(server.models_dir / "flow.json", backend="onnx")
    assert a == b
    if policy.uses_noise:
        assert a != c and fresh[0] != fresh[1], "another seed, or none, must give other noise"
    else:  # the shipped student reads no noise: a seed changes nothing, and no seed is as good as any
        assert a == c and fresh[0] == fresh[1] == a[0]
    expected = policy.act(np.asarray(STATES, np.float32), noise=chunk_noise(42, len(STATES)))
    np.testing.assert_allclose(np.asarray(a, dtype=np.float32), expected, atol=1e-4, rtol=0)
    # mse accepts a seed and ignores it
    m1 = act(server.url, policy="mse", state=STATE, seed=5).json()["actions"]
    m2 = act(server.url, policy="mse", state=STATE).json()["actions"]
    assert m1 == m2


@pytest.mark.slow
def test_concurrent_requests_are_batched_and_independent(server: UvicornProcess) -> None:
    """64 concurrent seeded requests over 32 connections: fewer model calls than requests, same answers as alone."""

    def batch_counts() -> tuple[float, float]:
        text = httpx.get(f"{server.url}/metrics").text
        values = {}
        for line in iter_lines(text):
            for key in ("pusht_batch_requests_count", "pusht_batch_requests_sum"):
                if line.startswith(key + '{policy="flow"}'):
                    values[key] = float(line.split()[-1])
        return values.get("pusht_batch_requests_count", 0.0), values.get("pusht_batch_requests_sum", 0.0)

    n = 64
    alone = [act(server.url, policy="flow", state=STATES[i % 3], seed=500 + i).json()["actions"] for i in range(n)]
    calls0, reqs0 = batch_counts()

    bodies = [json.dumps({"policy": "flow", "state": STATES[i % 3], "seed": 500 + i}).encode() for i in range(n)]
    together = asyncio.run(raw_burst(server.port, bodies, connections=32))
    calls1, reqs1 = batch_counts()
    assert [status for status, _ in together] == [200] * n
    np.testing.assert_allclose([json.loads(body)["actions"] for _, body in together], alone, atol=1e-4, rtol=0)
    assert reqs1 - reqs0 == n
    assert calls1 - calls0 < n, f"{n} concurrent requests took {calls1 - calls0} model calls: no batching"


@pytest.mark.slow
@pytest.mark.parametrize("which", ["test", "shipped", "chooser"], ids=["test-models", "shipped-models", "chooser-models"])
def test_torch_backend_server_agrees_with_onnx(which: str, request: pytest.FixtureRequest) -> None:
    """PUSHT_BACKEND=torch answers like the onnx backend (same seeds), and runs any num_steps of a flow that has steps."""

    models_dir = request.getfixturevalue("chooser_models") if which == "chooser" else _models_dir(which, request)
    answers = {}
    for backend in ("onnx", "torch"):
        with UvicornProcess({"PUSHT_MODELS_DIR": str(models_dir), "PUSHT_BACKEND": backend}) as srv:
            answers[backend] = [act(srv.url, policy=name, states=STATES, seed=11).json() for name in ("mse", "flow")]
            if backend == "torch":
                five = act(srv.url, policy="flow", states=STATES, seed=11, num_steps=5)
                assert five.status_code == 200, five.text
                assert five.json()["actions"] != answers["torch"][1]["actions"]
    for onnx_answer, torch_answer in zip(answers["onnx"], answers["torch"], strict=True):
        assert (onnx_answer["backend"], torch_answer["backend"]) == ("onnx", "torch")
        np.testing.assert_allclose(onnx_answer["actions"], torch_answer["actions"], atol=1e-3, rtol=0)


@pytest.mark.slow
def test_32_connections_are_never_shed(test_models: Path) -> None:
    """Even with PUSHT_QUEUE_LIMIT=1, 32 concurrent full-size batch requests are all answered (the floor is 32 * max_states)."""
    env = {"PUSHT_MODELS_DIR": str(test_models), "PUSHT_MAX_STATES": "64", "PUSHT_QUEUE_LIMIT": "1"}
    with UvicornProcess(env) as srv:

        async def burst() -> list[int]:
            async with httpx.AsyncClient(base_url=srv.url, limits=httpx.Limits(max_connections=32), timeout=60) as client:
                body = {"policy": "flow", "states": [STATE] * 64, "seed": 3}
                responses = await asyncio.gather(*(client.post("/act", json=body) for _ in range(96)))
            return [r.status_code for r in responses]

        assert set(asyncio.run(burst())) == {200}


@pytest.mark.slow
def test_metrics_count_requests_by_route_and_status(server: UvicornProcess) -> None:
    act(server.url, policy="flow", state=STATE)
    act(server.url, policy="flow", state=[1, 2, 3])
    text = httpx.get(f"{server.url}/metrics").text
    lines = list(iter_lines(text))
    for status in ("200", "422"):
        assert any(
            line.startswith("pusht_http_requests_total{") and 'route="/act"' in line and f'status="{status}"' in line
            for line in lines
        ), status
    assert any(line.startswith('pusht_http_request_duration_seconds_bucket{le="0.005",route="/act"}') for line in lines)
    assert any(line.startswith('pusht_batch_rows_bucket{le="1.0",policy="flow"}') for line in lines)


def test_readyz_is_503_until_policies_load(test_models: Path) -> None:
    """Before the lifespan has loaded the policies, readiness and /act answer 503 (JSON)."""
    from service.app import create_app
    from service.settings import Settings

    app = create_app(Settings(models_dir=test_models))

    async def probe() -> tuple[httpx.Response, httpx.Response, httpx.Response]:
        # ASGITransport does not run the lifespan: exactly the state of a server still loading.
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://test") as client:
            return (
                await client.get("/readyz"),
                await client.post("/act", json={"policy": "flow", "state": STATE}),
                await client.get("/healthz"),
            )

    ready, acted, alive = asyncio.run(probe())
    assert ready.status_code == 503 and "loading" in ready.json()["detail"]
    assert acted.status_code == 503 and "loading" in acted.json()["detail"]
    assert alive.status_code == 200


@pytest.mark.slow
def test_api_key(test_models: Path) -> None:
    with UvicornProcess({"PUSHT_MODELS_DIR": str(test_models), "PUSHT_API_KEY": "s3cret"}) as srv:
        body = {"policy": "mse", "state": STATE}
        for headers in ({}, {"X-API-Key": "wrong"}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic s3cret"}):
            response = httpx.post(f"{srv.url}/act", json=body, headers=headers)
            assert response.status_code == 401 and "API key" in response.json()["detail"], headers
        assert httpx.get(f"{srv.url}/policies").status_code == 401
        assert httpx.post(f"{srv.url}/act", json=body, headers={"X-API-Key": "s3cret"}).status_code == 200
        assert httpx.post(f"{srv.url}/act", json=body, headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert httpx.get(f"{srv.url}/policies", headers={"X-API-Key": "s3cret"}).status_code == 200
        assert httpx.get(f"{srv.url}/healthz").status_code == 200 and httpx.get(f"{srv.url}/readyz").status_code == 200

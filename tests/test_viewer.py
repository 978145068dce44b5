"""The /viewer websocket against a real server with the shipped models: scores equal training.evaluate's, teleop, save, limits."""

from __future__ import annotations

import json
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import zarr
from service_fixtures import SHIPPED_MODELS, UvicornProcess, shipped_models_available
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from acting import load_policy
from pusht import PushTEnv
from training.data import load_replay
from training.evaluate import evaluate_policy

pytestmark = pytest.mark.skipif(not shipped_models_available(), reason="needs the shipped models/flow and models/mse")

KEY = "viewer-test-key"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("viewer-data")
    env = {"PUSHT_MODELS_DIR": str(SHIPPED_MODELS), "PUSHT_VIEWER_DATA_DIR": str(data)}
    with UvicornProcess(env, entry="service") as proc:
        proc.data_dir = data
        yield proc


@pytest.fixture(scope="module")
def chooser_server(chooser_models):
    """The outcome chooser record as `flow`: its episodes depend on each chunk's seed (the shipped student's do not)."""
    with UvicornProcess({"PUSHT_MODELS_DIR": str(chooser_models)}, entry="service") as proc:
        yield proc


def ws_url(server) -> str:
    return server.url.replace("http://", "ws://") + "/viewer/ws"


def session(server, key: str | None = None):
    """A connected websocket that said hello (with `key`), and the answer."""
    ws = connect(ws_url(server), open_timeout=10).__enter__()  # closed by the test's `with ws`
    ws.send(json.dumps({"type": "hello", "key": key}))
    return ws, json.loads(ws.recv(timeout=10))


def ask(ws, message: dict) -> dict:
    ws.send(json.dumps(message))
    return json.loads(ws.recv(timeout=10))


def play(ws, policy: str | None, seed: int, fps: float = 200) -> list[dict]:
    """Start an episode and read its states until it is done."""
    states = [ask(ws, {"type": "start", "policy": policy, "seed": seed, "fps": fps})]
    while not states[-1]["done"]:
        states.append(json.loads(ws.recv(timeout=10)))
        assert states[-1]["type"] == "state", states[-1]
    return states


@pytest.mark.parametrize(
    "which, policy, seeds",
    [("server", "flow", (200000, 200003)), ("server", "mse", (200001,)), ("chooser_server", "flow", (200000,))],
    ids=["flow", "mse", "chooser"],
)
def test_viewer_episode_scores_equal_training_evaluate(which, policy, seeds, request):
    server = request.getfixturevalue(which)
    in_process = load_policy(server.models_dir / f"{policy}.onnx")
    ws, hello = session(server)
    assert {"flow", "mse"} <= set(hello["policies"]) and len(hello["goal"]) == 2
    with ws:
        for seed in seeds:
            started = time.perf_counter()
            states = play(ws, policy, seed)
            elapsed = time.perf_counter() - started
            reference = evaluate_policy(in_process, episodes=1, seed=seed).episodes[0]
            last = states[-1]
            assert (last["maxReward"], last["success"], last["step"]) == (
                reference.max_reward,
                reference.success,
                reference.length,
            )
            assert last["coverage"] == reference.final_coverage
            assert [s["step"] for s in states] == list(range(len(states)))
            assert elapsed >= (last["step"] - 1) / 200  # paced at the asked rate, not faster


def test_viewer_teleop_records_human_steps_that_replay_exactly(server):
    ws, _ = session(server)
    with ws:
        first = ask(ws, {"type": "start", "policy": None, "seed": 7, "fps": 100})
        assert first["step"] == 0
        time.sleep(0.15)
        ws.send(json.dumps({"type": "save"}))
        assert json.loads(ws.recv(timeout=5))["status"] == 409  # teleop waits for the button: no steps yet
        target = (first["state"][0] + 60.0, first["state"][1] - 40.0)
        ws.send(json.dumps({"type": "pointer", "x": target[0], "y": target[1], "down": True}))
        states = [json.loads(ws.recv(timeout=5)) for _ in range(15)]
        ws.send(json.dumps({"type": "pointer", "x": target[0], "y": target[1], "down": False}))
        time.sleep(0.1)
        saved = ask(ws, {"type": "save"})
        while saved["type"] == "state":  # steps already under way when the button went up
            states.append(saved)
            saved = json.loads(ws.recv(timeout=5))
    assert saved["type"] == "saved" and saved["humanSteps"] == saved["steps"] == states[-1]["step"]
    assert all(s["actor"] == "human" and s["action"] == [pytest.approx(target[0]), pytest.approx(target[1])] for s in states)
    assert np.hypot(states[-1]["state"][0] - target[0], states[-1]["state"][1] - target[1]) < 5  # the agent followed the pointer

    path = Path(saved["path"])
    assert path.parent == server.data_dir
    replay = load_replay(path)  # the dataset's layout, read by training's own loader
    human = zarr.open_group(str(path), mode="r")["data/human"][...]
    assert replay.episode_ends.tolist() == [saved["steps"]] and human.tolist() == [1] * saved["steps"]
    env = PushTEnv()
    obs, _ = env.reset(seed=7)
    for state, action in zip(replay.states, replay.actions):
        assert np.array_equal(state, obs.astype(np.float32))
        obs, *_ = env.step(action)


def test_viewer_takeover_then_policy_resumes(server):
    ws, _ = session(server)
    with ws:
        states = [ask(ws, {"type": "start", "policy": "flow", "seed": 200002, "fps": 100})]
        states += [json.loads(ws.recv(timeout=5)) for _ in range(5)]
        ws.send(json.dumps({"type": "pointer", "x": 100.0, "y": 100.0, "down": True}))
        states += [json.loads(ws.recv(timeout=5)) for _ in range(10)]
        ws.send(json.dumps({"type": "pointer", "x": 100.0, "y": 100.0, "down": False}))
        states += [json.loads(ws.recv(timeout=5)) for _ in range(20)]
        saved = ask(ws, {"type": "save"})
        while saved["type"] == "state":
            saved = json.loads(ws.recv(timeout=5))
    actors = [s["actor"] for s in states[1:]]
    assert actors[:5] == ["policy"] * 5 and "human" in actors and actors[-1] == "policy"
    human = zarr.open_group(saved["path"], mode="r")["data/human"][...].astype(bool)
    assert 0 < human.sum() == saved["humanSteps"] < saved["steps"]


def test_viewer_bad_messages_get_4xx_errors_and_the_session_lives_on(server):
    ws, _ = session(server)
    with ws:
        assert ask(ws, {"type": "save"})["status"] == 409  # nothing played yet
        ws.send("not json")
        assert json.loads(ws.recv(timeout=5))["status"] == 400
        ws.send(b"\x00binary")
        assert json.loads(ws.recv(timeout=5))["status"] == 400
        assert ask(ws, {"type": "fly"})["status"] == 400
        assert ask(ws, {"type": "hello", "key": "k" * 10000})["status"] == 413
        assert ask(ws, [1, 2])["status"] == 400
        for kind in ({}, [1], None, 3):  # an unhashable or non-string type is an unknown type, not a crash
            assert ask(ws, {"type": kind})["status"] == 400, kind
        for bad in ({"seed": -1}, {"seed": 2**63}, {"seed": "3"}, {"fps": 0}, {"fps": 1e6}, {"extra": 1}, {"policy": 5}):
            error = ask(ws, {"type": "start", "policy": "flow", "seed": 1, **bad})
            assert error["type"] == "error" and error["status"] == 422, (bad, error)
        error = ask(ws, {"type": "start", "policy": "nope", "seed": 1})
        assert error["status"] == 404 and "flow" in error["detail"]
        for bad in ({"x": float("nan")}, {"x": "1"}, {"down": 1}):
            assert ask(ws, {"type": "pointer", "x": 1.0, "y": 2.0, "down": True, **bad})["status"] == 422
        assert ask(ws, {"type": "start", "policy": "mse", "seed": 3})["type"] == "state"


@pytest.mark.parametrize("query", ["seed=-1", "seed=x", "fps=0", "fps=500", "autoplay=2", "mode=fly", "policy=" + "p" * 300])
def test_viewer_page_rejects_bad_query_with_422(server, query):
    response = httpx.get(f"{server.url}/viewer?{query}")
    assert response.status_code == 422 and response.headers["content-type"] == "application/json"
    assert response.json()["detail"]


def test_viewer_page_and_script_are_served_locally(server):
    page = httpx.get(f"{server.url}/viewer?policy=flow&seed=3&autoplay=1")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert "http://" not in page.text and "https://" not in page.text  # no asset from another host
    script = httpx.get(f"{server.url}/viewer-assets/viewer.js")
    assert script.status_code == 200 and "window.pushtViewer" in script.text and "http" not in script.text.replace("https:", "")


def test_viewer_refuses_other_origins(server):
    with connect(ws_url(server), additional_headers={"Origin": "http://evil.example"}) as ws:
        error = json.loads(ws.recv(timeout=5))
        assert error["status"] == 403
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=5)
    assert closed.value.rcvd.code == 4403


def test_viewer_sessions_are_bounded_in_count_and_idle_time(tmp_path):
    env = {"PUSHT_MODELS_DIR": str(SHIPPED_MODELS), "PUSHT_VIEWER_MAX_SESSIONS": "1", "PUSHT_VIEWER_IDLE_S": "0.5"}
    with UvicornProcess(env) as server:
        ws, hello = session(server)
        assert hello["type"] == "hello" and hello["saving"] is False
        with ws:
            with connect(ws_url(server)) as second:
                error = json.loads(second.recv(timeout=5))
                assert error["status"] == 503 and "PUSHT_VIEWER_MAX_SESSIONS=1" in error["detail"]
            assert ask(ws, {"type": "start", "policy": "mse", "seed": 1, "fps": 100})["step"] == 0
            while not json.loads(ws.recv(timeout=5))["done"]:
                pass
            assert ask(ws, {"type": "save"})["status"] == 409  # saving is off without PUSHT_VIEWER_DATA_DIR
            started = time.monotonic()
            assert json.loads(ws.recv(timeout=5))["status"] == 408
            assert 0.3 < time.monotonic() - started < 3
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=5)
        time.sleep(0.2)
        ws, hello = session(server)  # its slot is free again
        ws.close()
        assert hello["type"] == "hello"


def test_viewer_honours_the_api_key():
    env = {"PUSHT_MODELS_DIR": str(SHIPPED_MODELS), "PUSHT_API_KEY": KEY}
    with UvicornProcess(env) as server:
        for key in (None, "wrong"):
            ws, error = session(server, key=key)
            assert error["status"] == 401
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=5)
        with connect(ws_url(server)) as ws:  # without hello, a start is refused too
            assert ask(ws, {"type": "start", "policy": "mse", "seed": 1})["status"] == 401
        ws, hello = session(server, key=KEY)
        with ws:
            assert hello["type"] == "hello" and ask(ws, {"type": "start", "policy": "mse", "seed": 1})["type"] == "state"
        for header in ({"X-API-Key": KEY}, {"Authorization": f"Bearer {KEY}"}):
            with connect(ws_url(server), additional_headers=header) as ws:  # the /act headers work as well
                assert ask(ws, {"type": "start", "policy": "mse", "seed": 1})["type"] == "state"


def test_keyless_sockets_hold_no_slot_and_are_closed_at_the_auth_deadline():
    """With an API key, sockets that never send it neither take the one session slot nor stay past AUTH_DEADLINE_S,
    however much junk they send; junk does not extend a keyed session's idle time either."""
    from service.viewer import AUTH_DEADLINE_S

    env = {
        "PUSHT_MODELS_DIR": str(SHIPPED_MODELS),
        "PUSHT_API_KEY": KEY,
        "PUSHT_VIEWER_MAX_SESSIONS": "1",
        "PUSHT_VIEWER_IDLE_S": "1.5",
    }
    with UvicornProcess(env) as server:
        junk = [connect(ws_url(server)) for _ in range(4)]
        opened = time.monotonic()
        for ws in junk:
            assert ask(ws, {})["status"] == 400
        keyed, hello = session(server, key=KEY)
        with keyed:
            assert hello["type"] == "hello"  # the keyless sockets hold no slot
            started = time.monotonic()
            while True:  # junk every 0.3 s: still closed as idle after PUSHT_VIEWER_IDLE_S
                try:
                    keyed.send("not json")
                except ConnectionClosed:
                    pass  # closed while we slept: its 408 is still to be read
                answer = json.loads(keyed.recv(timeout=5))
                if answer["status"] == 408:
                    break
                time.sleep(0.3)
            assert time.monotonic() - started < 4
        for ws in junk:
            closed = None
            while closed is None:
                try:
                    ws.send("{}")
                except ConnectionClosed:
                    pass  # closed already: its 401 is still to be read
                answer = json.loads(ws.recv(timeout=10))
                closed = answer if answer["status"] == 401 else None
            assert closed is not None and "within" in closed["detail"], closed
            assert time.monotonic() - opened < AUTH_DEADLINE_S + 3
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=5)

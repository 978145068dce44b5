"""`python -m service.ray_serve`: the service behind Ray Serve on a real local cluster (2 replicas, 2 CPUs, small object store)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from service.openpi_ws import pack, unpack
from tests.service_fixtures import REPO, SHIPPED_MODELS, UvicornProcess, free_port, shipped_models_available

pytest.importorskip("ray.serve", reason="Ray Serve is not installed (pip install -e '.[ray]'; the test extra includes it)")

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not shipped_models_available(), reason="needs the shipped models")]

RNG = np.random.default_rng(3)
STATES = np.column_stack([RNG.uniform(50, 460, (8, 4)), RNG.uniform(0, 6.28, 8)]).round(3).tolist()


@pytest.fixture(scope="module")
def ray_service():
    """The service under Ray Serve with 2 replicas, in its own session so its whole process group can be cleaned up."""
    port = free_port()
    env = {**os.environ, "PUSHT_MODELS_DIR": str(SHIPPED_MODELS), "RAY_ADDRESS": ""}
    cmd = [
        sys.executable,
        "-m",
        "service.ray_serve",
        "--replicas",
        "2",
        "--port",
        str(port),
        "--local-cpus",
        "2",
        "--object-store-mb",
        "100",
    ]
    log = tempfile.TemporaryFile(mode="w+")
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        _wait_for_line(proc, log, "ready: 2 replicas", timeout=240)
        yield proc, f"http://127.0.0.1:{port}", log
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                pass
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # whatever Ray left in the session we started
        except ProcessLookupError:
            pass
        log.close()


@pytest.fixture(scope="module")
def plain_service():
    with UvicornProcess({"PUSHT_MODELS_DIR": str(SHIPPED_MODELS)}, entry="service") as srv:
        yield srv


def _wait_for_line(proc: subprocess.Popen, log, text: str, timeout: float) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        log.seek(0)
        output = log.read()
        if text in output:
            return output
        if proc.poll() is not None:
            raise RuntimeError(f"service.ray_serve exited with {proc.returncode}:\n{output[-3000:]}")
        time.sleep(0.5)
    raise TimeoutError(f"service.ray_serve not ready after {timeout} s:\n{output[-3000:]}")


def test_same_answers_as_the_plain_service(ray_service, plain_service: UvicornProcess) -> None:
    """/act, OIP v2 and the openpi websocket through Ray's proxy answer exactly as `python -m service` does."""
    _, url, _ = ray_service
    bodies = [
        {"policy": "flow", "states": STATES, "seeds": list(range(100, 108))},
        {"policy": "flow", "state": STATES[0], "seed": 5},
        {"policy": "mse", "states": STATES},
    ]
    for body in bodies:
        ours, plain = httpx.post(f"{url}/act", json=body, timeout=30), httpx.post(f"{plain_service.url}/act", json=body)
        assert ours.status_code == plain.status_code == 200, ours.text
        assert ours.json() == plain.json()
    infer = {"inputs": [{"name": "state", "shape": [8, 5], "datatype": "FP32", "data": STATES}], "parameters": {"seed": 9}}
    ours = httpx.post(f"{url}/v2/models/flow/infer", json=infer, timeout=30)
    assert ours.status_code == 200, ours.text
    assert ours.json() == httpx.post(f"{plain_service.url}/v2/models/flow/infer", json=infer).json()
    bad = httpx.post(f"{url}/act", json={"policy": "flow", "state": [1, 2, 3]}, timeout=30)
    assert (
        bad.status_code == 422
        and bad.json() == httpx.post(f"{plain_service.url}/act", json={"policy": "flow", "state": [1, 2, 3]}).json()
    )
    with connect(f"ws://{url.removeprefix('http://')}/openpi/flow", open_timeout=30) as ws:
        assert unpack(ws.recv())["policy"] == "flow"
        ws.send(pack({"state": np.float32(STATES[1]), "seed": 7}))
        actions = unpack(ws.recv())["actions"]
    plain = httpx.post(f"{plain_service.url}/act", json={"policy": "flow", "state": STATES[1], "seed": 7}).json()["actions"]
    assert np.array_equal(actions, np.float32(plain))


def test_both_replicas_answer(ray_service) -> None:
    """Concurrent requests are spread over the two replicas (each response names its replica)."""
    _, url, _ = ray_service
    body = json.dumps({"policy": "flow", "state": STATES[2], "seed": 1})

    def ask(_: int) -> tuple[str, list]:
        response = httpx.post(f"{url}/act", content=body, headers={"content-type": "application/json"}, timeout=30)
        assert response.status_code == 200, response.text
        return response.headers["x-pusht-replica"], response.json()["actions"]

    with ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(ask, range(48)))
    assert len({replica for replica, _ in answers}) == 2
    assert all(actions == answers[0][1] for _, actions in answers)


def test_sigterm_stops_the_cluster(ray_service) -> None:
    """SIGTERM: the local cluster goes down with the command, which exits 0."""
    proc, _, log = ray_service
    proc.terminate()
    assert proc.wait(timeout=60) == 0
    log.seek(0)
    assert log.read().rstrip().endswith("stopped")

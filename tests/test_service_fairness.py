"""Scheduling: small requests are not starved by bulk ones, gone clients' work is dropped, queues count cost.

The batcher in process (which call answers whom), then a real uvicorn on loopback with the shipped
flow (bulk batches span many model calls), and the outcome chooser record where step counts matter. Orders
and counts are asserted, never speed: bench/service_fairness.py measures the latencies.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.service_fixtures import SHIPPED_MODELS, UvicornProcess, iter_lines, raw_burst, shipped_models_available

STATE = [120.0, 300.0, 256.0, 250.0, 1.0]


def _shipped() -> Path:
    if not shipped_models_available():
        pytest.skip("models/ has no shipped mse and flow")
    return SHIPPED_MODELS


def test_a_small_request_waits_one_call_behind_bulk_batches(test_models: Path) -> None:
    """Eight queued 256-row requests, then a 1-row one: it is answered by the next call; bulk rows still fill every call."""
    from acting import load_policy
    from service.batching import Batcher

    policy = load_policy(test_models / "flow.json", backend="onnx")
    calls: list[tuple[int, int]] = []
    finished_at: dict[str, int] = {}

    async def run() -> None:
        batcher = Batcher(policy, max_cost=640, queue_limit=1 << 20, observe=lambda name, rows, reqs: calls.append((rows, reqs)))
        try:
            bulk = np.full((256, 5), 200.0, dtype=np.float32)
            futures = {f"bulk{i}": batcher.enqueue(bulk, seed=i) for i in range(8)}
            await asyncio.sleep(0)  # the first call (bulk only) starts
            futures["small"] = batcher.enqueue(np.asarray([STATE], np.float32), seed=1)
            for name, future in futures.items():
                future.add_done_callback(lambda _, name=name: finished_at.setdefault(name, len(calls)))
            await asyncio.gather(*futures.values())
        finally:
            batcher.close()

    asyncio.run(run())
    assert finished_at["small"] <= 2, f"the 1-row request waited for {finished_at['small']} model calls"
    assert min(finished_at[f"bulk{i}"] for i in range(8)) > 2
    assert sum(rows for rows, _ in calls) == 8 * 256 + 1
    # the small request's call is short (8 rows), the 8 calls after it half (32 rows, in case more small
    # ones come), every other call but the last full (64 flow rows = 640 cost units); all merge requests
    sizes = [rows for rows, _ in calls[:-1]]
    short = sizes.index(8)
    assert sizes.count(8) == 1 and sizes[short + 1 : short + 9] == [32] * 8, sizes
    assert all(size == 64 for i, size in enumerate(sizes) if not short <= i <= short + 8), sizes
    assert all(reqs > 1 for _, reqs in calls[:-1]), calls


def test_queue_limits_count_rows_times_network_evaluations(test_models: Path) -> None:
    """A flow row costs its num_steps; an mse row 1: the same rows fit one queue and overflow the other."""
    from acting import load_policy
    from service.batching import Batcher, Overloaded

    flow = load_policy(test_models / "flow.json", backend="onnx")
    mse = load_policy(test_models / "mse.json", backend="onnx")
    assert (flow.network_evaluations(None), flow.network_evaluations(100), mse.network_evaluations(100)) == (10, 100, 1)
    five = np.full((5, 5), 256.0, dtype=np.float32)

    async def run(policy) -> list:
        batcher = Batcher(policy, queue_limit=120)
        try:
            return await asyncio.gather(*(batcher.submit(five) for _ in range(3)), return_exceptions=True)
        finally:
            batcher.close()

    assert [type(r).__name__ for r in asyncio.run(run(mse))] == ["ndarray"] * 3
    flow_results = asyncio.run(run(flow))
    assert [type(r).__name__ for r in flow_results] == ["ndarray", "ndarray", "Overloaded"]
    assert isinstance(flow_results[2], Overloaded) and "cost units" in str(flow_results[2])


async def _send(port: int, body: dict) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    data = json.dumps(body).encode()
    writer.write(
        b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: %d\r\n\r\n%s" % (len(data), data)
    )
    await writer.drain()
    return reader, writer


async def _answer(reader: asyncio.StreamReader) -> int:
    head = await reader.readuntil(b"\r\n\r\n")
    length = next(int(line.split(b":")[1]) for line in head.split(b"\r\n") if line.lower().startswith(b"content-length:"))
    await reader.readexactly(length)
    return int(head[9:12])


@pytest.mark.slow
def test_small_request_overtakes_queued_bulk_batches_on_a_real_server() -> None:
    """Eight 1,024-row flow requests queued first, then a 1-row one: its answer comes before every bulk answer."""
    with UvicornProcess({"PUSHT_MODELS_DIR": str(_shipped())}) as srv:

        async def scenario() -> list[str]:
            order: list[str] = []
            # At 2 network evaluations a row the shipped flow fits 320 rows in a call: a smaller bulk request could be
            # answered whole by the call already running when the small one arrives.
            bulk_body = {"policy": "flow", "states": [STATE] * 1024, "seed": 1}
            bulk = [await _send(srv.port, bulk_body) for _ in range(8)]
            await asyncio.sleep(0.05)  # the bulk bodies are parsed and queued
            small = await _send(srv.port, {"policy": "flow", "state": STATE, "seed": 2})

            async def wait(name: str, reader: asyncio.StreamReader) -> None:
                assert await _answer(reader) == 200
                order.append(name)

            await asyncio.gather(wait("small", small[0]), *(wait(f"bulk{i}", r) for i, (r, _) in enumerate(bulk)))
            for _, writer in [*bulk, small]:
                writer.close()
            return order

        order = asyncio.run(scenario())
        assert order[0] == "small", order


def _rows_computed(url: str) -> float:
    for line in iter_lines(httpx.get(f"{url}/metrics").text):
        if line.startswith('pusht_batch_rows_sum{policy="flow"}'):
            return float(line.split()[-1])
    return 0.0


@pytest.mark.slow
def test_work_of_clients_that_hung_up_is_dropped() -> None:
    """40 requests of 1,024 rows whose clients close right after sending: almost none of their rows are computed."""
    with UvicornProcess({"PUSHT_MODELS_DIR": str(_shipped())}) as srv:
        assert httpx.post(f"{srv.url}/act", json={"policy": "flow", "state": STATE}).status_code == 200
        before = _rows_computed(srv.url)

        async def abandon() -> None:
            body = {"policy": "flow", "states": [STATE] * 1024, "seed": 3}
            sent = [await _send(srv.port, body) for _ in range(40)]
            for _, writer in sent:
                writer.close()

        asyncio.run(abandon())
        probe = httpx.post(f"{srv.url}/act", json={"policy": "flow", "state": STATE, "seed": 4}, timeout=60)
        assert probe.status_code == 200
        computed = _rows_computed(srv.url) - before - 1
        assert computed < 40 * 1024 / 10, f"{computed:.0f} of {40 * 1024} abandoned rows were computed"


@pytest.mark.slow
def test_torch_queue_limit_counts_num_steps(chooser_models: Path) -> None:
    """torch backend, 4-row requests: at num_steps=100 a burst overflows the cost limit (503); at 10 it fits."""
    # the chooser: its candidates of 10 steps at 4 stretches, each scored by the outcome model and the value, so the cost of a step count is large
    env = {"PUSHT_MODELS_DIR": str(chooser_models), "PUSHT_BACKEND": "torch", "PUSHT_MAX_STATES": "4", "PUSHT_QUEUE_LIMIT": "1"}
    with UvicornProcess(env) as srv:  # limit: 32 requests x 4 rows x 10 steps = 1,280 cost units

        def burst(num_steps: int) -> list[tuple[int, bytes]]:
            body = json.dumps({"policy": "flow", "states": [STATE] * 4, "seed": 1, "num_steps": num_steps}).encode()
            return asyncio.run(raw_burst(srv.port, [body] * 32, connections=32))

        cheap = burst(10)
        assert {status for status, _ in cheap} == {200}
        costly = burst(100)
        statuses = [status for status, _ in costly]
        assert 503 in statuses and 200 in statuses, statuses
        refused = json.loads(next(body for status, body in costly if status == 503))["detail"]
        from acting import read_card

        card = read_card(chooser_models / "flow.json")
        k = card.architecture["outcome_candidates"]
        unit = card.network_evaluations(100)  # 100 steps, times the candidates of a chooser
        assert unit == k * 100 + k * 4 * 2 and "cost units" in refused and f"{unit} here" in refused

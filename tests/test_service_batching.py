"""The dynamic batcher in process: merging, waiting only under load, order, errors, load shedding.

Runs on the random-weight test policies; tests/test_service_fairness.py covers fairness between
small and bulk requests, tests/test_service_seeds.py requests split over calls.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np

from pusht.rollout import chunk_noise

STATES = [[120.0, 300.0, 256.0, 250.0, 1.0], [400.5, 80.25, 200.0, 310.0, 5.5], [256.0, 256.0, 256.0, 256.0, 0.0]]


def test_batcher_merges_and_keeps_each_request_seed(test_models: Path) -> None:
    """Concurrent submits share model calls, yet each answer equals the same request run alone."""
    from acting import load_policy
    from service.batching import Batcher

    policy = load_policy(test_models / "flow.json", backend="onnx")
    calls: list[tuple[int, int]] = []
    states = [np.asarray([STATES[i % 3]], dtype=np.float32) for i in range(40)]

    async def run() -> list[np.ndarray]:
        batcher = Batcher(policy, max_rows=16, max_wait_s=0.002, observe=lambda name, rows, reqs: calls.append((rows, reqs)))
        try:
            return await asyncio.gather(*(batcher.submit(s, seed=1000 + i) for i, s in enumerate(states)))
        finally:
            batcher.close()

    merged = asyncio.run(run())
    assert sum(reqs for _, reqs in calls) == 40
    assert len(calls) < 40 and max(rows for rows, _ in calls) <= 16
    for i, got in enumerate(merged):
        alone = policy.act(states[i], noise=chunk_noise(1000 + i, 1))
        # not bitwise: GEMM kernels may sum in another order for another batch size; a wrong noise
        # row would move actions by pixels
        np.testing.assert_allclose(got, alone, atol=1e-4, rtol=0)


def test_batcher_waits_only_under_load_and_never_past_a_full_batch(test_models: Path) -> None:
    """max_wait applies once calls merge several requests; a full batch goes at once; a lone client never waits."""
    import time

    from acting import load_policy
    from service.batching import Batcher

    policy = load_policy(test_models / "mse.json", backend="onnx")
    rows = np.full((8, 5), 256.0, dtype=np.float32)

    async def run() -> list[float]:
        batcher = Batcher(policy, max_rows=8, max_wait_s=1.0)
        times = []
        try:
            for batches in ([rows[:1]], [rows[:4], rows[4:]], [rows[:4], rows[4:]], [rows[:1]]):
                start = time.perf_counter()
                await asyncio.gather(*(batcher.submit(b) for b in batches))
                times.append(time.perf_counter() - start)
        finally:
            batcher.close()
        return times

    lone, first_pair, full_pair, lone_under_load = asyncio.run(run())
    assert lone < 0.5  # the previous call had no other request: no waiting
    assert first_pair < 0.5
    assert full_pair < 0.5  # waiting (the last call merged 2), but the second request fills the batch
    assert lone_under_load >= 0.9  # the last call merged 2 requests: wait for company


def test_batcher_answers_in_order_and_passes_model_errors_on() -> None:
    """Calls run one by one on the worker thread, also after it idled, and a failing call fails only its requests."""
    from service.batching import Batcher

    class Flaky:
        """Just the part of `acting.Policy` the batcher uses."""

        name, kind, horizon, action_dim, batch_multiple = "flaky", "mse", 12, 2, 4

        def network_evaluations(self, num_steps=None):
            return 1

        def act(self, states, prev_states=None, *, noise=None, num_steps=None):
            assert prev_states is None and noise is None and num_steps is None  # mse: states only
            if states[0, 0] < 0:
                raise RuntimeError("model call failed")
            return np.repeat(states[:, None, :2], 12, axis=1)

    async def run() -> list:
        batcher = Batcher(Flaky())
        try:
            answers = []
            for value in (1.0, -1.0, 2.0):
                await asyncio.sleep(0.005)
                answers += await asyncio.gather(batcher.submit(np.full((1, 5), value, np.float32)), return_exceptions=True)
            return answers
        finally:
            batcher.close()

    first, failed, third = asyncio.run(run())
    assert first[0, 0, 0] == 1.0 and third[0, 0, 0] == 2.0
    assert isinstance(failed, RuntimeError) and "model call failed" in str(failed)


def test_a_lone_small_request_runs_on_the_event_loop_and_the_rest_on_the_worker() -> None:
    """With inline_max_cost, a lone request that small skips the thread hop; bigger or concurrent ones do not; errors pass on alike."""
    import threading

    from service.batching import Batcher

    policy = _Recording()

    async def run() -> list:
        batcher = Batcher(policy, inline_max_cost=4)
        try:
            lone = await batcher.submit(np.full((4, 5), 1.0, np.float32))
            big = await batcher.submit(np.full((5, 5), 2.0, np.float32))
            pair = await asyncio.gather(*(batcher.submit(np.full((1, 5), 3.0 + i, np.float32)) for i in range(2)))
            failed = await asyncio.gather(batcher.submit(np.full((1, 5), -1.0, np.float32)), return_exceptions=True)
            return [lone, big, *pair, *failed]
        finally:
            batcher.close()

    lone, big, first, second, failed = asyncio.run(run())
    assert lone[0, 0, 0] == 1.0 and big[0, 0, 0] == 2.0 and first[0, 0, 0] == 3.0 and second[0, 0, 0] == 4.0
    assert isinstance(failed, RuntimeError) and "model call failed" in str(failed)
    # 4 rows alone: inline; 5 rows: over the cost; the pair queued together: one merged call on the worker
    on_worker = [name.startswith("policy-recording") for name in policy.threads]
    assert policy.threads[0] == threading.main_thread().name and on_worker == [False, True, True, False]


def test_a_small_request_beside_a_running_call_computes_at_once_on_the_event_loop() -> None:
    """While the worker runs a long call, a request within inline_max_cost is answered on the loop before that call ends."""
    import threading

    from service.batching import Batcher

    policy = _Recording(slow_over_rows=4)

    async def run() -> tuple:
        batcher = Batcher(policy, inline_max_cost=4)
        try:
            bulk = asyncio.ensure_future(batcher.submit(np.full((64, 5), 1.0, np.float32)))
            await asyncio.sleep(0.05)  # the bulk call is running on the worker
            small = await batcher.submit(np.full((1, 5), 2.0, np.float32))
            return small, bulk.done(), await bulk
        finally:
            batcher.close()

    small, bulk_done_first, bulk = asyncio.run(run())
    assert small[0, 0, 0] == 2.0 and bulk[0, 0, 0] == 1.0 and not bulk_done_first
    assert policy.threads[0].startswith("policy-recording") and policy.threads[1] == threading.main_thread().name


def test_batcher_sheds_load_beyond_its_queue_limit(test_models: Path) -> None:
    """Rows beyond queue_limit waiting at once are refused with Overloaded (-> 503); the rest are answered."""
    from acting import load_policy
    from service.batching import Batcher, Overloaded

    policy = load_policy(test_models / "mse.json", backend="onnx")
    five = np.full((5, 5), 256.0, dtype=np.float32)

    async def run() -> list:
        batcher = Batcher(policy, queue_limit=10)
        try:
            return await asyncio.gather(*(batcher.submit(five) for _ in range(3)), return_exceptions=True)
        finally:
            batcher.close()

    results = asyncio.run(run())
    assert [type(r).__name__ for r in results] == ["ndarray", "ndarray", "Overloaded"]
    assert isinstance(results[2], Overloaded) and "limit 10" in str(results[2])


class _Recording:
    """Just the part of `acting.Policy` the batcher uses: notes the thread of every call, fails on a negative first
    state, and with `slow_over_rows` takes 0.3 s over a call of more rows than that."""

    name, kind, horizon, action_dim, batch_multiple = "recording", "mse", 12, 2, 4

    def __init__(self, slow_over_rows: int | None = None) -> None:
        self.threads: list[str] = []
        self.slow_over_rows = slow_over_rows

    def network_evaluations(self, num_steps=None):
        return 1

    def act(self, states, prev_states=None, *, noise=None, num_steps=None):
        import threading
        import time

        self.threads.append(threading.current_thread().name)
        if states[0, 0] < 0:
            raise RuntimeError("model call failed")
        if self.slow_over_rows is not None and len(states) > self.slow_over_rows:
            time.sleep(0.3)
        return np.repeat(states[:, None, :2], 12, axis=1)

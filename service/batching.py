"""Dynamic batching: concurrent requests for one policy are merged into one model call.

Requests queue on the event loop. Whenever the policy's worker thread is free, everything queued
(up to `max_rows` state rows, and only requests with the same `num_steps`) goes to it as one call,
so under load batches grow by themselves while a lone request waits for nothing. `max_wait_s` > 0
additionally lets a batch wait until its oldest request is that old (or the batch is full) for
others to join. Each request's noise is drawn from its own seed and then concatenated, so an answer
never depends on what else was in the batch. Compute runs in the worker thread (ONNX Runtime and
torch release the GIL), off the event loop.
"""

from __future__ import annotations

import asyncio
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np

from pusht.rollout import chunk_noise
from service.backends import ACTION_DIM, HORIZON, LoadedPolicy

__all__ = ["Batcher", "Overloaded"]

BatchObserver = Callable[[str, int, int], None]
"""(policy name, state rows, requests) -> None, called once per model call."""


class Overloaded(RuntimeError):
    """The policy's queue is full; the request should be retried later."""


@dataclass(slots=True)
class _Item:
    states: np.ndarray
    seed: int | None
    num_steps: int | None
    future: asyncio.Future
    arrived: float


class Batcher:
    """Queues `act` requests for one policy and runs them in merged model calls on a worker thread."""

    def __init__(
        self,
        policy: LoadedPolicy,
        max_rows: int = 1024,
        max_wait_s: float = 0.0,
        queue_limit: int = 8192,
        observe: BatchObserver | None = None,
    ) -> None:
        self.policy = policy
        self.max_rows = max_rows
        self.max_wait_s = max_wait_s
        self.queue_limit = queue_limit
        self._observe = observe
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"policy-{policy.name}")
        # Only the worker thread draws from this generator, so it needs no lock.
        self._rng = np.random.default_rng()
        self._pending: deque[_Item] = deque()
        self._pending_rows = 0
        self._busy = False
        self._scheduled = False
        self._timer: asyncio.TimerHandle | None = None
        self._last_requests = 0
        self._closed = False

    async def submit(self, states: np.ndarray, seed: int | None = None, num_steps: int | None = None) -> np.ndarray:
        """Actions [B, 12, 2] for float32 states [B, 5]; raise Overloaded when the queue is full."""
        rows = len(states)
        if self._closed:
            raise Overloaded(f"policy {self.policy.name!r} is shutting down")
        if self._pending_rows + rows > self.queue_limit:
            raise Overloaded(
                f"policy {self.policy.name!r} has {self._pending_rows} state rows queued (limit {self.queue_limit}); retry later"
            )
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        self._pending.append(_Item(states, seed, num_steps, future, loop.time()))
        self._pending_rows += rows
        self._schedule(loop)
        return await future

    def close(self) -> None:
        """Fail queued requests, then wait for the running model call and stop the worker thread."""
        self._closed = True
        while self._pending:
            item = self._pending.popleft()
            if not item.future.done():
                item.future.set_exception(Overloaded(f"policy {self.policy.name!r} is shutting down"))
        self._pending_rows = 0
        self._executor.shutdown(wait=True)

    def _schedule(self, loop: asyncio.AbstractEventLoop) -> None:
        if self._busy or not self._pending:
            return
        if self._scheduled:
            if self._timer is not None and self._pending_rows >= self.max_rows:
                # A full batch need not wait for the rest of max_wait.
                self._timer.cancel()
                self._timer = None
                loop.call_soon(self._flush, loop)
            return
        self._scheduled = True
        # The wait counts from the oldest queued request, so requests that queued behind a running
        # model call go as soon as it ends.
        delay = self.max_wait_s - (loop.time() - self._pending[0].arrived)
        # Waiting only pays under load: with one request at a time (the last call had one) it is pure latency.
        if delay > 0 and self._pending_rows < self.max_rows and self._last_requests > 1:
            self._timer = loop.call_later(delay, self._flush, loop)
        else:
            # call_soon still lets every request whose bytes arrived in this loop iteration join.
            loop.call_soon(self._flush, loop)

    def _flush(self, loop: asyncio.AbstractEventLoop) -> None:
        self._scheduled = False
        self._timer = None
        if self._busy or self._closed:
            return
        batch = self._take_batch()
        if not batch:
            return
        self._busy = True
        self._last_requests = len(batch)
        done = loop.run_in_executor(self._executor, self._compute, batch)
        done.add_done_callback(lambda fut: self._finish(loop, batch, fut))

    def _take_batch(self) -> list[_Item]:
        batch: list[_Item] = []
        rows = 0
        pending = self._pending
        while pending:
            item = pending[0]
            if item.future.done():  # the client went away (cancelled) while queued
                pending.popleft()
                self._pending_rows -= len(item.states)
                continue
            if batch and (item.num_steps != batch[0].num_steps or rows + len(item.states) > self.max_rows):
                break
            pending.popleft()
            self._pending_rows -= len(item.states)
            rows += len(item.states)
            batch.append(item)
        return batch

    def _compute(self, batch: list[_Item]) -> np.ndarray:
        """Runs on the worker thread: per-request noise, one concatenated model call."""
        policy = self.policy
        if len(batch) == 1:
            states = batch[0].states
        else:
            states = np.concatenate([item.states for item in batch])
        noise = None
        if policy.kind == "flow":
            parts = [self._noise(item) for item in batch]
            noise = parts[0] if len(parts) == 1 else np.concatenate(parts)
        actions = policy.act(states, noise, batch[0].num_steps)
        if self._observe is not None:
            self._observe(policy.name, len(states), len(batch))
        return actions

    def _noise(self, item: _Item) -> np.ndarray:
        rows = len(item.states)
        if item.seed is not None:
            return chunk_noise(item.seed, rows, HORIZON, ACTION_DIM)
        return self._rng.standard_normal((rows, HORIZON, ACTION_DIM), dtype=np.float32)

    def _finish(self, loop: asyncio.AbstractEventLoop, batch: list[_Item], fut: asyncio.Future) -> None:
        self._busy = False
        if fut.cancelled():
            error: BaseException | None = asyncio.CancelledError()
        else:
            error = fut.exception()
        if error is not None:
            for item in batch:
                if not item.future.done():
                    item.future.set_exception(error)
        else:
            actions = fut.result()
            start = 0
            for item in batch:
                stop = start + len(item.states)
                if not item.future.done():
                    item.future.set_result(actions[start:stop])
                start = stop
        self._schedule(loop)

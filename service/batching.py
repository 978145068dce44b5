"""Dynamic batching: concurrent requests for one policy are merged into one model call.

Requests queue on the event loop. Whenever the policy's worker thread is free, everything queued
(up to `max_rows` state rows, and only requests with the same `num_steps`) goes to it as one call,
so under load batches grow by themselves while a lone request waits for nothing. `max_wait_s` > 0
additionally lets a batch wait until its oldest request is that old (or the batch is full) for
others to join. Each request's noise is drawn from its own seed and then concatenated, so an answer
never depends on what else was in the batch. Compute runs in the worker thread (ONNX Runtime and
torch release the GIL), off the event loop.

After each call the worker keeps polling for the next one for `spin_s` (yielding the core to any other
runnable thread) before it sleeps. On a VM, a sleeping thread's vCPU halts, and waking it and warming
it up again costs more than the model call itself (a flow call takes 0.33 ms right after another
and up to 0.77 ms after 2 ms idle), so back-to-back requests would otherwise pay that every time.
"""

from __future__ import annotations

import asyncio
import os
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

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
        spin_s: float = 0.002,
    ) -> None:
        self.policy = policy
        self.max_rows = max_rows
        self.max_wait_s = max_wait_s
        self.queue_limit = queue_limit
        self._observe = observe
        self._worker = _SpinningWorker(f"policy-{policy.name}", spin_s)
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
        self._worker.stop()

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
        done = loop.create_future()
        done.add_done_callback(lambda fut: self._finish(loop, batch, fut))
        self._worker.submit(loop, done, self._compute, batch)

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


class _SpinningWorker:
    """One thread running submitted calls in order; it polls for `spin_s` after each call before sleeping."""

    def __init__(self, name: str, spin_s: float) -> None:
        self.spin_s = spin_s
        self._jobs: deque[tuple[asyncio.AbstractEventLoop, asyncio.Future, Callable[..., Any], tuple]] = deque()
        self._wake = threading.Event()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, loop: asyncio.AbstractEventLoop, future: asyncio.Future, fn: Callable[..., Any], *args: Any) -> None:
        """Run fn(*args) on the worker; its result or exception goes to `future` on `loop`."""
        self._jobs.append((loop, future, fn, args))
        self._wake.set()

    def stop(self) -> None:
        """Finish the queued calls, then end the thread."""
        self._stopping = True
        self._wake.set()
        self._thread.join()

    def _run(self) -> None:
        jobs = self._jobs
        while True:
            if not jobs:
                deadline = time.perf_counter() + self.spin_s
                # os.sched_yield releases the GIL and lets any runnable thread have this core.
                while not jobs and not self._stopping and time.perf_counter() < deadline:
                    os.sched_yield()
            if not jobs:
                if self._stopping:
                    return
                # clear, then look again: a submit between the two is seen, one after sets the event
                self._wake.clear()
                if not jobs and not self._stopping:
                    self._wake.wait()
                continue
            loop, future, fn, args = jobs.popleft()
            try:
                outcome, ok = fn(*args), True
            except BaseException as exc:  # delivered to the awaiting request, never lost in the thread
                outcome, ok = exc, False
            try:
                loop.call_soon_threadsafe(_settle, future, outcome, ok)
            except RuntimeError:  # the loop closed while the call ran: nobody is waiting
                pass


def _settle(future: asyncio.Future, outcome: Any, ok: bool) -> None:
    if future.done():
        return
    if ok:
        future.set_result(outcome)
    else:
        future.set_exception(outcome)

"""Dynamic batching: concurrent requests for one policy are merged into model calls, fairly.

Requests queue on the event loop. Whenever the policy's worker thread is free, one model call is cut
from the queue: at most `max_cost` cost units (rows x network evaluations: a flow row costs its
num_steps, an mse row 1; but always up to one padded group of 4 rows) and `max_rows` rows, only rows with the oldest request's `num_steps`. The
call's rows are shared max-min fairly: requests with few rows left go whole, and bulk requests split
the rest evenly. When small requests wait beside bulk ones, the next call is short (an eighth of the
budget) and the next few half size, so a 1-row request waits about half a call however many
1,024-row batches are queued, while bulk rows still fill the calls (a model's cost per row is flat
beyond a few dozen rows). Noise is drawn per request (`seed`) or per row (`seeds`) and sliced, in
the policy's own chunk shape (its card's horizon and action width), and the call is one
`acting.Policy.act`, which pads it to a multiple of 4 rows (`pusht.seeding.pad_rows`; none for a graph
whose rows are the same alone as in any batch), so an answer never depends, to the last bit, on what
else was in the batch. Requests whose client left (their future is done) are dropped before their rows
reach the model. Compute runs in the worker thread (ONNX Runtime and torch release the GIL), off the
event loop, except a small request (`inline_max_cost`) with nothing else queued (handing it to a thread
and back costs more than its model call) or arriving while a call runs: it computes at once beside that
call instead of after it, so a cheap policy's lone rows never wait for bulk ones.
"""

from __future__ import annotations

import asyncio
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from acting import Policy
from pusht.seeding import chunk_noise, row_noise

__all__ = ["Batcher", "Overloaded"]

BatchObserver = Callable[[str, int, int], None]
"""(policy name, state rows, requests) -> None, called once per model call."""


class Overloaded(RuntimeError):
    """The policy's queue is full; the request should be retried later."""


@dataclass(slots=True, eq=False)
class _Item:
    states: np.ndarray
    seed: int | None
    seeds: Sequence[int] | None
    num_steps: int | None
    future: asyncio.Future
    arrived: float
    unit: int
    taken: int = 0
    """rows handed to model calls so far; set to all rows when the request is dropped (its future done early)"""
    done: int = 0
    noise: np.ndarray | None = None
    out: np.ndarray | None = None


_Slice = tuple[_Item, int, int]


class Batcher:
    """Queues `act` requests for one policy and runs them in fair, merged model calls on a worker thread."""

    def __init__(
        self,
        policy: Policy,
        max_rows: int = 1024,
        max_wait_s: float = 0.0,
        queue_limit: int = 8192,
        observe: BatchObserver | None = None,
        max_cost: int = 640,
        inline_max_cost: int = 0,
    ) -> None:
        self.policy = policy
        self.max_rows = max_rows
        self.max_cost = max_cost
        self.inline_max_cost = inline_max_cost
        self.max_wait_s = max_wait_s
        self.queue_limit = queue_limit
        self._observe = observe
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"policy-{policy.name}")
        # Only the worker thread draws from the first, only the event loop from the second: neither needs a lock.
        self._rng = np.random.default_rng()
        self._loop_rng = np.random.default_rng()
        self._pending: deque[_Item] = deque()
        self._pending_cost = 0
        self._pending_rows = 0
        self._busy = False
        self._scheduled = False
        self._timer: asyncio.TimerHandle | None = None
        self._last_requests = 0
        self._last_short = False
        self._calls_since_short = 1 << 30
        self._closed = False
        self._units: dict[int | None, int] = {}  # cost of a row by num_steps: the card's rule walks several properties

    async def submit(
        self, states: np.ndarray, seed: int | None = None, num_steps: int | None = None, seeds: Sequence[int] | None = None
    ) -> np.ndarray:
        """Actions [B, horizon, action_dim] for float32 states [B, state_dim]; raise Overloaded when the queue is full."""
        return await self.enqueue(states, seed, num_steps, seeds)

    def enqueue(
        self,
        states: np.ndarray,
        seed: int | None = None,
        num_steps: int | None = None,
        seeds: Sequence[int] | None = None,
        noise: np.ndarray | None = None,
    ) -> asyncio.Future:
        """Queue a request (`noise`: the caller's own flow noise [B, horizon, action_dim]); its future gets the actions; finished early, its rows drop."""
        rows = len(states)
        if self._closed:
            raise Overloaded(f"policy {self.policy.name!r} is shutting down")
        unit = self._units.get(num_steps)
        if unit is None:
            unit = self._units[num_steps] = self.policy.network_evaluations(num_steps)
        if self._pending_cost + rows * unit > self.queue_limit:
            raise Overloaded(
                f"policy {self.policy.name!r} has {self._pending_cost} cost units queued (limit {self.queue_limit}; "
                f"a row costs its network evaluations, {unit} here); retry later"
            )
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        item = _Item(states, seed, seeds, num_steps, future, loop.time(), unit, noise=noise)
        if self._busy and rows * unit <= self.inline_max_cost:
            # A small request beside a running call computes now, on the loop, beside the worker thread (both backends
            # take concurrent calls), rather than after that call: with a cheap policy a lone row then waits for no
            # bulk call at all.
            self._express(item)
            return future
        self._pending.append(item)
        self._pending_cost += rows * unit
        self._pending_rows += rows
        self._schedule(loop)
        return future

    def close(self) -> None:
        """Fail queued requests, then wait for the running model call and stop the worker thread."""
        self._closed = True
        while self._pending:
            item = self._pending.popleft()
            if not item.future.done():
                item.future.set_exception(Overloaded(f"policy {self.policy.name!r} is shutting down"))
        self._executor.shutdown(wait=True)

    def runs_alone(self) -> bool:
        """Whether the one queued request will run inline in the next loop iteration (a small one, nothing else queued or
        running), unless requests arriving in this iteration join it."""
        return not self._busy and len(self._pending) == 1 and self._pending_cost <= self.inline_max_cost

    def worth_watching(self) -> bool:
        """Whether more than two calls of work are queued: then a client that hangs up should have its rows dropped."""
        return self._pending_cost > 2 * self.max_cost

    def purge(self) -> None:
        """Drop the queued rows of requests whose future is done (their clients left), so they stop counting at once."""
        for item in self._pending:
            self._drop(item)

    def _drop(self, item: _Item) -> bool:
        """Drop the untaken rows of a request whose future is done (client gone); True if it was dropped."""
        if not item.future.done():
            return False
        left = len(item.states) - item.taken
        item.taken += left
        self._pending_cost -= left * item.unit
        self._pending_rows -= left
        return True

    def _schedule(self, loop: asyncio.AbstractEventLoop) -> None:
        if self._busy or not self._pending:
            return
        full = self._pending_rows >= self.max_rows or self._pending_cost >= self.max_cost
        if self._scheduled:
            if self._timer is not None and full:
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
        if delay > 0 and not full and self._last_requests > 1:
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
        if self._inline(batch):
            try:
                actions, error = self._compute(batch), None
            except Exception as exc:  # delivered to the request like a worker thread's failure
                actions, error = None, exc
            self._deliver(loop, batch, actions, error)
            return
        done = loop.run_in_executor(self._executor, self._compute, batch)
        done.add_done_callback(lambda fut: self._finish(loop, batch, fut))

    def _inline(self, batch: list[_Slice]) -> bool:
        """Whether to run this call on the event loop: one small request whole, nothing else waiting."""
        if len(batch) != 1 or self._pending_rows:
            return False
        item, start, stop = batch[0]
        return start == 0 and stop == len(item.states) and len(item.states) * item.unit <= self.inline_max_cost

    def _take_batch(self) -> list[_Slice]:
        """The next call's rows: the oldest request's num_steps, max-min fair shares of the call's budget."""
        pending = self._pending
        while pending and (pending[0].taken == len(pending[0].states) or self._drop(pending[0])):
            pending.popleft()
        if not pending:
            return []
        steps = pending[0].num_steps  # the oldest request picks, so no num_steps group waits forever
        if len(pending) == 1:
            group = [pending[0]]
        else:
            live = [item for item in pending if item.taken < len(item.states) and not self._drop(item)]
            pending.clear()
            pending.extend(live)
            group = sorted((item for item in live if item.num_steps == steps), key=lambda it: len(it.states) - it.taken)
        unit = group[0].unit
        # A call computes a whole padded group of rows however few it takes (`pad_rows`), so it may always take one,
        # even where a single row costs more than max_cost (a flow that chooses among many candidate chunks).
        group_rows = self.policy.batch_multiple
        left = max(group_rows, min(self.max_rows, self.max_cost // unit))
        short = max(group_rows, left // 8)
        remaining_first, remaining_last = (len(it.states) - it.taken for it in (group[0], group[-1]))
        if not self._last_short and remaining_first <= short < remaining_last:
            # Small requests beside bulk ones go in a short call, so they wait only for the call already
            # running; short calls alternate with full ones, so a stream of small requests cannot starve bulk.
            left = short
            self._last_short = True
            self._calls_since_short = 0
        else:
            self._last_short = False
            self._calls_since_short += 1
            if self._calls_since_short <= 8:
                left = max(short, left // 2)  # while small requests keep coming, halve what they may wait behind
        batch: list[_Slice] = []
        for k, item in enumerate(group):
            if left <= 0:
                break
            rows = min(len(item.states) - item.taken, max(1, left // (len(group) - k)))
            batch.append((item, item.taken, item.taken + rows))
            item.taken += rows
            left -= rows
            self._pending_cost -= rows * unit
            self._pending_rows -= rows
        return batch

    def _compute(self, batch: list[_Slice], rng: np.random.Generator | None = None) -> np.ndarray:
        """Runs on the worker thread (or inline): noise per request or row, one concatenated model call (`act` pads it);
        fresh noise from `rng` (default: the worker's generator)."""
        policy = self.policy
        if len(batch) == 1:
            item, start, stop = batch[0]
            states = item.states[start:stop]
        else:
            states = np.concatenate([item.states[start:stop] for item, start, stop in batch])
        noise = None  # a flow that uses no noise gets zeros from `act` itself
        if policy.kind == "flow" and policy.uses_noise:
            parts = [self._noise(*part, rng or self._rng) for part in batch]
            noise = parts[0] if len(parts) == 1 else np.concatenate(parts)
        actions = policy.act(states, noise=noise, num_steps=batch[0][0].num_steps)
        if self._observe is not None:
            self._observe(policy.name, len(states), len(batch))
        return actions

    def _express(self, item: _Item) -> None:
        """Compute a whole small request at once on the event loop (noise from the loop's own generator)."""
        try:
            actions = self._compute([(item, 0, len(item.states))], self._loop_rng)
        except Exception as exc:  # delivered to the request like a worker thread's failure
            item.future.set_exception(exc)
            return
        item.future.set_result(actions)

    def _noise(self, item: _Item, start: int, stop: int, rng: np.random.Generator) -> np.ndarray:
        horizon, action_dim = self.policy.horizon, self.policy.action_dim
        if item.noise is not None and item.seed is None:  # the caller's own noise (the OIP `noise` input)
            return item.noise[start:stop]
        if item.seeds is not None:
            return row_noise(item.seeds[start:stop], horizon, action_dim)
        if item.seed is not None:
            if start == 0 and stop == len(item.states):
                return chunk_noise(item.seed, stop, horizon, action_dim)
            if item.noise is None:  # a request split over calls: its one draw, sliced
                item.noise = chunk_noise(item.seed, len(item.states), horizon, action_dim)
            return item.noise[start:stop]
        return rng.standard_normal((stop - start, horizon, action_dim), dtype=np.float32)

    def _finish(self, loop: asyncio.AbstractEventLoop, batch: list[_Slice], fut: asyncio.Future) -> None:
        if fut.cancelled():
            self._deliver(loop, batch, None, asyncio.CancelledError())
        else:
            error = fut.exception()
            self._deliver(loop, batch, fut.result() if error is None else None, error)

    def _deliver(
        self, loop: asyncio.AbstractEventLoop, batch: list[_Slice], actions: np.ndarray | None, error: BaseException | None
    ) -> None:
        """Hand a call's actions (or its error) to its requests, then schedule the next call."""
        self._busy = False
        if error is not None:
            for item, _, _ in batch:
                if not item.future.done():
                    item.future.set_exception(error)
        else:
            offset = 0
            for item, start, stop in batch:
                part = actions[offset : offset + stop - start]
                offset += stop - start
                if item.future.done():
                    continue
                if start == 0 and stop == len(item.states):
                    item.future.set_result(part)
                    continue
                if item.out is None:
                    item.out = np.empty((len(item.states), *actions.shape[1:]), dtype=actions.dtype)
                item.out[start:stop] = part
                item.done += stop - start
                if item.done == len(item.states):
                    item.future.set_result(item.out)
        self._schedule(loop)

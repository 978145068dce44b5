"""`GET /viewer` (a page that draws a live episode) and `/viewer/ws` (the websocket that plays it server-side).

The env runs here, on a worker thread (never on the event loop, so `/act` is not held up), and the
policy's chunks come through the same batcher as `/act`'s requests. The page sends `hello` (with the
API key when the service has one), then `start`, `pointer` and `save`; the server answers `hello`,
one `state` per env step and `saved`, or `error` with an HTTP-like 4xx/503 `status` and a `detail`.
Sessions are bounded: at most PUSHT_VIEWER_MAX_SESSIONS at once, each closed after PUSHT_VIEWER_IDLE_S
without a message while no episode plays.
"""

from __future__ import annotations

import asyncio
import hmac
import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from service.batching import Overloaded
from service.request_input import key_matches, request_headers
from service.settings import Settings
from service.viewer_episode import Episode, goal_polygons, save_episode

__all__ = ["VIEWER_ASSETS", "make_viewer_router", "viewer_assets_dir"]

VIEWER_ASSETS = "/viewer-assets"
"""Where the app serves the page's script."""
MAX_FPS = 200.0
MAX_SEED = 2**63 - 1
MAX_MESSAGE_CHARS = 4096
"""Longest page message: the largest real one (hello with a key) is far smaller."""


class _Hello(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    type: Literal["hello"]
    key: str | None = Field(None, max_length=1000)


class _Start(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    type: Literal["start"]
    policy: str | None = Field(None, max_length=200, description="a loaded policy; null: teleop only")
    seed: int = Field(ge=0, le=MAX_SEED)
    fps: float = Field(10.0, ge=1.0, le=MAX_FPS)


class _Pointer(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    type: Literal["pointer"]
    x: float = Field(allow_inf_nan=False)
    y: float = Field(allow_inf_nan=False)
    down: bool


class _Save(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    type: Literal["save"]


_MESSAGES = {"hello": _Hello, "start": _Start, "pointer": _Pointer, "save": _Save}


class _Refused(Exception):
    """A message the session answers with an error; `close` ends the session too."""

    def __init__(self, status: int, detail: Any, close: bool = False) -> None:
        self.status, self.detail, self.close = status, detail, close


def viewer_assets_dir() -> Path:
    """The folder of the page and its script."""
    return Path(__file__).parent / "viewer_static"


AUTH_DEADLINE_S = 5.0
"""A socket of a service with an API key has this long to send its key, else it is closed (it holds no session slot)."""


def make_viewer_router(settings: Settings) -> APIRouter:
    """The viewer's page and websocket routes, with their session limit and worker thread."""
    router = APIRouter()
    expected_key = settings.api_key.get_secret_value().encode() if settings.api_key else None
    slots = _Slots(settings.viewer_max_sessions)
    # Env steps take ~0.05 ms: one thread for every session keeps them off the event loop.
    executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="viewer-env")

    @router.get("/viewer", include_in_schema=False)
    async def viewer_page(
        policy: str | None = Query(None, max_length=200),
        seed: int = Query(0, ge=0, le=MAX_SEED),
        autoplay: int = Query(0, ge=0, le=1),
        fps: float = Query(10.0, ge=1.0, le=MAX_FPS),
        mode: Literal["policy", "teleop"] = Query("policy"),
    ) -> FileResponse:
        """The page; its query (policy, seed, autoplay, fps, mode) is read by its script, checked here."""
        return FileResponse(viewer_assets_dir() / "viewer.html", media_type="text/html")

    @router.websocket("/viewer/ws")
    async def viewer_socket(ws: WebSocket) -> None:
        await ws.accept()
        session = _Session(ws, settings, expected_key, executor, slots)
        try:
            if not _same_origin(ws):
                raise _Refused(403, "the page's origin differs from this service's host", close=True)
            if settings.viewer_max_sessions == 0:
                raise _Refused(503, "the viewer is off on this service (PUSHT_VIEWER_MAX_SESSIONS=0)", close=True)
            if session.authorized:  # a socket that still owes its key takes a slot only once it gives it
                session.claim_slot()
        except _Refused as exc:
            await _send_error(ws, exc)
            await ws.close(code=4000 + exc.status)
            return
        try:
            await session.run()
        except WebSocketDisconnect:
            pass
        finally:
            session.release_slot()

    return router


class _Slots:
    """The open authorized viewer sessions, at most `limit`."""

    def __init__(self, limit: int) -> None:
        self.limit, self.live = limit, 0

    def claim(self) -> None:
        """Take a slot, or refuse the session with a 503 when all are taken."""
        if self.live >= self.limit:
            raise _Refused(
                503,
                f"{self.live} viewer sessions are open (PUSHT_VIEWER_MAX_SESSIONS={self.limit}); close one or retry later",
                close=True,
            )
        self.live += 1

    def release(self) -> None:
        self.live -= 1


class _Session:
    """One page's websocket: reads its messages on a task, steps its episode at the asked rate."""

    def __init__(
        self, ws: WebSocket, settings: Settings, expected_key: bytes | None, executor: ThreadPoolExecutor, slots: _Slots
    ) -> None:
        self.ws, self.settings, self.executor, self.slots, self.has_slot = ws, settings, executor, slots, False
        self.authorized = expected_key is None or _header_key_ok(ws, expected_key)
        self.expected_key = expected_key
        self.episode: Episode | None = None
        self.period = 0.1
        self.next_step = 0.0
        self.pointer: tuple[float, float] | None = None  # set while the button is held on the canvas
        self.inbox: asyncio.Queue[str | None] = asyncio.Queue(maxsize=256)

    def claim_slot(self) -> None:
        self.slots.claim()
        self.has_slot = True

    def release_slot(self) -> None:
        if self.has_slot:
            self.slots.release()
            self.has_slot = False

    async def run(self) -> None:
        reader = asyncio.ensure_future(self._read())
        loop = asyncio.get_running_loop()
        opened = last_heard = loop.time()
        try:
            while True:
                stepping = self._can_step()
                deadline = self.next_step if stepping else last_heard + self.settings.viewer_idle_s
                if not self.authorized:
                    deadline = min(deadline, opened + AUTH_DEADLINE_S)
                try:
                    text = await asyncio.wait_for(self.inbox.get(), timeout=max(0.0, deadline - loop.time()))
                except TimeoutError:
                    text = ""
                if text is None:
                    return  # the page went away
                if not text and not stepping:
                    await self._close_idle()
                    return
                try:
                    await (self._handle(text) if text else self._step())
                    last_heard = loop.time()  # an accepted message, or a playing episode: not idle; junk is
                except _Refused as exc:
                    await _send_error(self.ws, exc)
                    if exc.close:
                        await self.ws.close(code=4000 + exc.status)
                        return
        finally:
            reader.cancel()

    async def _close_idle(self) -> None:
        if not self.authorized:
            refused = _Refused(401, f'no {{"type": "hello", "key": KEY}} within {AUTH_DEADLINE_S:g} s: session closed')
        else:
            refused = _Refused(408, f"idle for {self.settings.viewer_idle_s:g} s: session closed")
        await _send_error(self.ws, refused)
        await self.ws.close(code=4000 + refused.status)

    async def _read(self) -> None:
        try:
            while True:
                message = await self.ws.receive()
                if message["type"] == "websocket.disconnect":
                    break
                text = message.get("text")
                if text is None:
                    text = "\0binary"  # answered with a 400 by _handle
                await self.inbox.put(text)
        finally:
            await self.inbox.put(None)

    def _can_step(self) -> bool:
        episode = self.episode
        return episode is not None and not episode.done and (self.pointer is not None or episode.policy is not None)

    async def _handle(self, text: str) -> None:
        if len(text) > MAX_MESSAGE_CHARS:
            raise _Refused(413, f"a message of {len(text)} characters exceeds the limit of {MAX_MESSAGE_CHARS}")
        try:
            raw = json.loads(text)
        except ValueError:
            raise _Refused(400, 'a message must be a JSON object, e.g. {"type": "hello"}') from None
        kind = raw.get("type") if isinstance(raw, dict) else None
        if not isinstance(kind, str) or kind not in _MESSAGES:  # {"type": {}} is unhashable: not a lookup key
            raise _Refused(400, f"unknown message type {kind!r}; expected one of {sorted(_MESSAGES)}")
        try:
            message = _MESSAGES[kind].model_validate(raw)
        except ValidationError as exc:
            errors = [{"loc": list(e["loc"]), "msg": e["msg"]} for e in exc.errors(include_url=False)[:20]]
            raise _Refused(422, errors) from None
        if isinstance(message, _Hello):
            return await self._hello(message)
        if not self.authorized:
            raise _Refused(401, 'send {"type": "hello", "key": KEY} with the service\'s API key first', close=True)
        if isinstance(message, _Start):
            await self._start(message)
        elif isinstance(message, _Pointer):
            waiting = not self._can_step()
            self.pointer = (message.x, message.y) if message.down else None
            if waiting and self._can_step():
                self.next_step = asyncio.get_running_loop().time()  # teleop starts at the press, not a period later
        else:
            await self._save()

    async def _hello(self, message: _Hello) -> None:
        if self.expected_key is not None and not self.authorized:
            given = (message.key or "").encode("latin-1", "replace")
            if not given or not hmac.compare_digest(given, self.expected_key):
                raise _Refused(401, 'missing or wrong API key: send it as {"type": "hello", "key": KEY}', close=True)
            self.authorized = True
            self.claim_slot()
        service = self.ws.app.state.service
        if not service.ready:
            raise _Refused(503, "policies are still loading; retry in a second", close=True)
        await self.ws.send_json(
            {
                "type": "hello",
                "policies": sorted(service.policies),
                "goal": goal_polygons(),
                "saving": self.settings.viewer_data_dir is not None,
                "maxFps": MAX_FPS,
            }
        )

    async def _start(self, message: _Start) -> None:
        policies = self.ws.app.state.service.batchers
        if message.policy is not None and message.policy not in policies:
            raise _Refused(404, f"unknown policy {message.policy!r}; loaded policies: {sorted(policies)}")
        loop = asyncio.get_running_loop()
        self.episode = await loop.run_in_executor(self.executor, Episode, message.seed, message.policy)
        self.period = 1.0 / message.fps
        self.next_step = loop.time() + self.period
        self.pointer = None
        await self.ws.send_json(self.episode.message())

    async def _step(self) -> None:
        episode, loop = self.episode, asyncio.get_running_loop()
        human = self.pointer
        if human is None and episode.needs_chunk():
            states, seed = episode.next_request()
            try:
                actions = await self.ws.app.state.service.batchers[episode.policy].enqueue(states, seeds=[seed])
            except Overloaded as exc:
                episode.decisions -= 1  # not asked: the retry asks with the same seed
                self.next_step = loop.time() + 1.0
                raise _Refused(503, str(exc)) from None
            episode.set_chunk(actions[0])
        state = await loop.run_in_executor(self.executor, episode.step, human)
        # paced from the planned time, so a late step does not push every later one back
        self.next_step = max(self.next_step + self.period, loop.time() - self.period)
        await self.ws.send_json(state)

    async def _save(self) -> None:
        folder = self.settings.viewer_data_dir
        if folder is None:
            raise _Refused(409, "saving is off: start the service with PUSHT_VIEWER_DATA_DIR=FOLDER")
        if self.episode is None or not self.episode.states:
            raise _Refused(409, "nothing to save: the episode has no steps yet")
        episode = self.episode
        path = await asyncio.get_running_loop().run_in_executor(self.executor, save_episode, Path(folder), episode)
        await self.ws.send_json(
            {
                "type": "saved",
                "path": str(path),
                "steps": episode.length,
                "humanSteps": int(sum(episode.human)),
                "name": path.name,
            }
        )


async def _send_error(ws: WebSocket, exc: _Refused) -> None:
    await ws.send_json({"type": "error", "status": exc.status, "detail": exc.detail})


def _headers(ws: WebSocket) -> dict[str, str]:
    return {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in ws.scope["headers"]}


def _header_key_ok(ws: WebSocket, expected: bytes) -> bool:
    """The key sent in the handshake's headers, by every route's rule (non-browser clients can send headers)."""
    return key_matches(request_headers(ws.scope, (b"x-api-key", b"authorization")), expected)


def _same_origin(ws: WebSocket) -> bool:
    """A browser's handshake carries Origin: only this service's own page may open a session (no cross-site use)."""
    headers = _headers(ws)
    origin = headers.get("origin")
    if origin is None:
        return True  # not a browser; the API key, when set, still applies
    return urlsplit(origin).netloc.lower() == headers.get("host", "").lower()

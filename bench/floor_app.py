"""The floor for bench/service_latency.py: the least an ASGI app can do per request under uvicorn.

It reads the request body and answers a fixed actions JSON ([12, 2] zeros), with no framework, no
parsing and no model: its latency is uvicorn's HTTP handling, the loopback and the load generator's
own share. Any app's p50 is at least this plus its model call.

    uvicorn bench.floor_app:app
"""

from __future__ import annotations

import json

_BODY = json.dumps({"policy": "flow", "actions": [[0.0, 0.0]] * 12}).encode()
_HEADERS = [(b"content-type", b"application/json"), (b"content-length", str(len(_BODY)).encode())]


async def app(scope, receive, send) -> None:
    """Answer every HTTP request with the fixed body (lifespan and other scopes are ignored)."""
    if scope["type"] != "http":
        return
    message = await receive()
    while message.get("more_body"):
        message = await receive()
    await send({"type": "http.response.start", "status": 200, "headers": _HEADERS})
    await send({"type": "http.response.body", "body": _BODY})

"""Hardening against hostile or unlucky clients, each against a real server on loopback (the body deadline also in-process).

Most cases run under both entry points: plain `uvicorn service.app:app` (the app's own ASGI checks)
and `python -m service` (the Makefile's and Dockerfile's command, which adds connection limits).
"""

from __future__ import annotations

import asyncio
import json
import re
import resource
import signal
import socket
import time
from pathlib import Path

import httpx
import pytest

from tests.service_fixtures import UvicornProcess

STATE = [120.0, 300.0, 256.0, 250.0, 1.0]
FAST_TIMEOUTS = {
    "PUSHT_HEADER_TIMEOUT_S": "1",
    "PUSHT_KEEP_ALIVE_S": "1",
    "PUSHT_BODY_TIMEOUT_S": "2",
    "PUSHT_SHUTDOWN_TIMEOUT_S": "2",
}


@pytest.fixture(scope="module", params=["uvicorn", "service"], ids=["plain-uvicorn", "python-m-service"])
def server(request: pytest.FixtureRequest, test_models: Path):
    """The service with short timeouts, started both ways users start it."""
    with UvicornProcess({"PUSHT_MODELS_DIR": str(test_models), **FAST_TIMEOUTS}, entry=request.param) as srv:
        srv.entry = request.param
        yield srv


def _raw(port: int, data: bytes, timeout: float = 10.0) -> bytes:
    """Send `data` on a fresh connection and read until the server closes it (or `timeout`); what came back."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        try:
            sock.sendall(data)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server may refuse and close before everything is written
        chunks = []
        try:
            while chunk := sock.recv(65536):
                chunks.append(chunk)
                if b"\r\n\r\n" in b"".join(chunks) and not _wants_more(b"".join(chunks)):
                    break
        except (ConnectionResetError, socket.timeout):
            pass
        return b"".join(chunks)


def _wants_more(data: bytes) -> bool:
    head, _, body = data.partition(b"\r\n\r\n")
    match = re.search(rb"content-length: *(\d+)", head, re.IGNORECASE)
    return match is not None and len(body) < int(match.group(1))


@pytest.mark.slow
def test_huge_headers_are_refused_with_bounded_memory(server: UvicornProcess) -> None:
    """A 4 MB header gets 431 or a closed connection; the server grows by under 32 MB and keeps answering."""
    assert httpx.get(f"{server.url}/healthz", headers={"cookie": "c" * 8000}).status_code == 200  # normal big headers pass
    before = server.rss_bytes()
    answer = _raw(server.port, b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * (4 << 20) + b"\r\n\r\n")
    grown = server.rss_bytes() - before
    assert answer == b"" or answer.startswith(b"HTTP/1.1 431"), answer[:200]
    assert grown < 32 << 20, f"server grew by {grown / 2**20:.1f} MB"
    with httpx.Client(base_url=server.url, timeout=10) as client:
        # the app's own check, whatever the server lets through: many headers, each small
        many = client.get("/healthz", headers={f"x-h{i}": "v" * 1000 for i in range(40)})
        assert many.status_code == 431 and "limit" in many.json()["detail"]
        assert client.get("/healthz").status_code == 200


@pytest.mark.slow
def test_idle_and_slow_connections_are_closed(test_models: Path) -> None:
    """python -m service closes connections that send nothing, trickle their headers, or idle after a response."""
    with UvicornProcess({"PUSHT_MODELS_DIR": str(test_models), **FAST_TIMEOUTS}, entry="service") as srv:

        async def scenario() -> list[str]:
            idle = [await asyncio.open_connection("127.0.0.1", srv.port) for _ in range(50)]
            slow_reader, slow_writer = await asyncio.open_connection("127.0.0.1", srv.port)
            kept_reader, kept_writer = await asyncio.open_connection("127.0.0.1", srv.port)
            kept_writer.write(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            await kept_reader.readuntil(b"\r\n\r\n")

            async def trickle() -> None:
                try:
                    for byte in b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"s" * 200:
                        slow_writer.write(bytes([byte]))
                        await asyncio.sleep(0.1)
                except ConnectionError:
                    pass

            async def closed(reader: asyncio.StreamReader) -> str:
                try:
                    while await asyncio.wait_for(reader.read(65536), timeout=8):
                        pass
                    return "closed"
                except asyncio.TimeoutError:
                    return "open"
                except ConnectionError:
                    return "closed"

            trickler = asyncio.ensure_future(trickle())
            states = await asyncio.gather(*(closed(r) for r, _ in idle), closed(slow_reader), closed(kept_reader))
            trickler.cancel()
            for _, writer in [*idle, (None, slow_writer), (None, kept_writer)]:
                writer.close()
            return states

        assert set(asyncio.run(scenario())) == {"closed"}
        assert httpx.get(f"{srv.url}/healthz").status_code == 200


@pytest.mark.slow
def test_connections_beyond_the_cap_get_a_fast_503(test_models: Path) -> None:
    env = {"PUSHT_MODELS_DIR": str(test_models), "PUSHT_MAX_CONNECTIONS": "10", "PUSHT_HEADER_TIMEOUT_S": "60"}
    with UvicornProcess(env, entry="service") as srv:
        held = [socket.create_connection(("127.0.0.1", srv.port)) for _ in range(10)]
        try:
            time.sleep(0.5)  # let the server accept them
            answer = _raw(srv.port, b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n", timeout=5)
            assert answer.startswith(b"HTTP/1.1 503"), answer[:200]
            assert "too many open connections" in json.loads(answer.partition(b"\r\n\r\n")[2])["detail"]
        finally:
            for sock in held:
                sock.close()
        time.sleep(0.5)
        assert httpx.get(f"{srv.url}/healthz").status_code == 200


@pytest.mark.slow
def test_connection_cap_fits_the_file_descriptor_limit(test_models: Path) -> None:
    """With `ulimit -n 256`, PUSHT_MAX_CONNECTIONS (1000) is lowered so sockets cannot exhaust the descriptors."""

    def low_fd_limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))

    with UvicornProcess({"PUSHT_MODELS_DIR": str(test_models)}, entry="service", preexec_fn=low_fd_limit) as srv:
        assert "PUSHT_MAX_CONNECTIONS lowered from 1000 to 192" in srv.output()
        assert httpx.post(f"{srv.url}/act", json={"policy": "mse", "state": STATE}).status_code == 200


@pytest.mark.slow
@pytest.mark.parametrize("entry", ["uvicorn", "service"])
def test_shutdown_is_bounded_with_a_stuck_request(entry: str, test_models: Path) -> None:
    """SIGTERM while a client is stuck halfway through its body: the server still exits within seconds."""
    with UvicornProcess({"PUSHT_MODELS_DIR": str(test_models), **FAST_TIMEOUTS}, entry=entry) as srv:
        with socket.create_connection(("127.0.0.1", srv.port)) as sock:
            sock.sendall(b'POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n{"po')
            time.sleep(0.5)
            srv.proc.send_signal(signal.SIGTERM)
            srv.proc.wait(timeout=20)  # raises TimeoutExpired if shutdown hangs
        # uvicorn re-raises the SIGTERM it handled once shut down, so -15 is the graceful exit status
        assert srv.proc.returncode in (0, -signal.SIGTERM)
        assert "Traceback" not in srv.output()


@pytest.mark.slow
def test_a_body_that_never_finishes_gets_408(server: UvicornProcess) -> None:
    head = b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n"
    answer = _raw(server.port, head + b'{"policy": "mse"', timeout=15)
    assert answer.startswith(b"HTTP/1.1 408"), answer[:200]
    assert "took longer than 2 s" in json.loads(answer.partition(b"\r\n\r\n")[2])["detail"]


def test_the_body_deadline_is_a_408_but_a_shutdown_still_cancels() -> None:
    """read_body keeps asyncio.timeout's rules: its own deadline is a 408, a cancellation from elsewhere propagates."""
    from service.request_input import ServiceError, read_body

    async def never() -> dict:
        await asyncio.sleep(3600)
        return {}

    async def run() -> tuple[int, bool]:
        try:
            await read_body(never, None, 100, timeout=0.05)
        except ServiceError as exc:
            status = exc.status
        reading = asyncio.create_task(read_body(never, None, 100, timeout=60))
        await asyncio.sleep(0.01)
        reading.cancel()
        try:
            await reading
        except asyncio.CancelledError:
            return status, True
        return status, False

    assert asyncio.run(run()) == (408, True)


@pytest.mark.slow
@pytest.mark.parametrize("chunked", [False, True], ids=["declared", "chunked"])
def test_a_413_closes_the_connection_without_reading_the_rest(server: UvicornProcess, chunked: bool) -> None:
    """A body over the limit gets its 413 and the connection closes at once, though the client has not sent the rest."""
    if chunked:
        head = b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n"
        first = b"%x\r\n%s\r\n" % (1_100_000, b" " * 1_100_000)  # more than PUSHT_MAX_BODY_BYTES, and no last chunk
    else:
        head = b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 5000000\r\n\r\n"
        first = b'{"policy": "mse", "states": ['
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as sock:
        sock.sendall(head + first)
        start, answer = time.monotonic(), b""
        try:
            while chunk := sock.recv(65536):
                answer += chunk
        except ConnectionResetError:
            pass  # closed with the client's unread bytes still queued: a reset, after the answer
        closed_after = time.monotonic() - start
    assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
    head_out, _, body = answer.partition(b"\r\n\r\n")
    assert b"connection: close" in head_out.lower() and "limit" in json.loads(body)["detail"]
    assert closed_after < 1.5, f"the connection stayed open {closed_after:.1f} s after the 413"  # the body deadline is 2 s


@pytest.mark.slow
def test_unparseable_requests_get_json_400(server: UvicornProcess) -> None:
    """Bytes that are not HTTP/1.1 get a 400 and a closed connection: JSON under `python -m service`, uvicorn's text under
    plain uvicorn (which the app cannot change; it warns at startup)."""
    for junk in (b"GARBAGE\r\n\r\n", b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Length: 5\r\nContent-Length: 7\r\n\r\n"):
        answer = _raw(server.port, junk)
        assert answer.startswith(b"HTTP/1.1 400"), answer[:200]
        head, _, body = answer.partition(b"\r\n\r\n")
        if server.entry == "service":
            assert b"content-type: application/json" in head.lower() and "HTTP/1.1" in json.loads(body)["detail"]
        else:
            assert b"text/plain" in head.lower()


@pytest.mark.slow
def test_bodies_that_are_not_json_get_415(server: UvicornProcess) -> None:
    """A cross-site form post (text/plain, form, multipart) or a body without a type never reaches a policy."""
    body = json.dumps({"policy": "mse", "state": STATE}).encode()
    with httpx.Client(base_url=server.url, timeout=10) as client:
        for content_type in ("text/plain", "application/x-www-form-urlencoded", "multipart/form-data; boundary=x", None):
            headers = {"content-type": content_type} if content_type else {}
            response = client.post("/act", content=body, headers=headers)
            assert response.status_code == 415, (content_type, response.text)
            assert "application/json" in response.json()["detail"]
        for ok in ("application/json", "application/json; charset=utf-8", "Application/JSON"):
            assert client.post("/act", content=body, headers={"content-type": ok}).status_code == 200, ok


@pytest.mark.slow
def test_422_bodies_are_capped(server: UvicornProcess) -> None:
    """A 25 KB body of wrong types gets the first 20 errors and a count of the rest, not a 470 KB answer."""
    body = json.dumps({"policy": "flow", "states": [["x"] * 5] * 1000}).encode()
    assert len(body) > 20_000
    response = httpx.post(f"{server.url}/act", content=body, headers={"content-type": "application/json"}, timeout=10)
    assert response.status_code == 422
    assert len(response.content) < 8000, len(response.content)
    detail = response.json()["detail"]
    assert len(detail) == 21 and detail[-1]["type"] == "too_many_errors" and "more errors" in detail[-1]["msg"]


@pytest.mark.slow
def test_docs_work_offline(server: UvicornProcess) -> None:
    """/docs loads Swagger UI's JavaScript and CSS from the app itself, never from a CDN."""
    with httpx.Client(base_url=server.url, timeout=10) as client:
        page = client.get("/docs")
        assert page.status_code == 200
        links = re.findall(r'(?:src|href)="([^"]+)"', page.text)
        assert links and all(link.startswith("/") for link in links), links
        assert "cdn" not in page.text.lower() and "https://" not in page.text
        for link, kind in (("swagger-ui-bundle.js", "javascript"), ("swagger-ui.css", "css")):
            url = next(u for u in links if u.endswith(link))
            asset = client.get(url)
            assert asset.status_code == 200 and kind in asset.headers["content-type"] and len(asset.content) > 10_000
        assert "/act" in client.get("/openapi.json").json()["paths"]


@pytest.mark.slow
def test_plain_uvicorn_says_which_limits_it_lacks(server: UvicornProcess) -> None:
    warned = "started without `python -m service`" in server.output()
    assert warned == (server.entry == "uvicorn")

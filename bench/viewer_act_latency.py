"""`POST /act` latency with and without a /viewer session playing: the viewer must not slow the API down.

    .venv/bin/python bench/viewer_act_latency.py                 # shipped models, 3 rounds
    .venv/bin/python bench/viewer_act_latency.py --rounds 5 --requests 3000

Starts `python -m service` on 127.0.0.1, then alternates, round by round: sequential single-state
flow requests with a seed over one keep-alive connection (p50/p95/p99), alone, beside a viewer
session playing flow episodes at the env's 10 Hz, and beside one playing at the viewer's top rate
(200 steps/s), with the server's CPU use. The viewer client runs in its own process.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    """Run the rounds and print one JSON line per condition (median of the rounds' percentiles, ms)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models-dir", default=str(REPO / "models"), help="PUSHT_MODELS_DIR of the server")
    parser.add_argument("--policy", default="flow", help="policy asked by /act and played by the viewer")
    parser.add_argument("--rounds", type=int, default=3, help="rounds, each measuring every condition once")
    parser.add_argument("--requests", type=int, default=2000, help="sequential /act requests per measurement")
    args = parser.parse_args(argv)

    port = _free_port()
    env = {**os.environ, "PUSHT_MODELS_DIR": args.models_dir}
    log = tempfile.TemporaryFile(mode="w+")
    server = subprocess.Popen(
        [sys.executable, "-m", "service", "--port", str(port), "--log-level", "warning"],
        cwd=REPO,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        _wait_ready(port, server)
        conditions = {"no viewer": None, "viewer at 10 steps/s": 10.0, "viewer at 200 steps/s": 200.0}
        results: dict[str, list[np.ndarray]] = {name: [] for name in conditions}
        cpu: dict[str, list[float]] = {name: [] for name in conditions}  # server CPU, % of one core
        asyncio.run(_latencies(port, args.policy, 200))  # warm-up
        for _ in range(args.rounds):
            for name, fps in conditions.items():
                viewer = None
                if fps is not None:
                    ready = multiprocessing.Event()
                    viewer = multiprocessing.Process(target=_play_forever, args=(port, args.policy, fps, ready), daemon=True)
                    viewer.start()
                    if not ready.wait(30):
                        raise RuntimeError("the viewer session did not start")
                try:
                    cpu_start, wall_start = _cpu_seconds(server.pid), time.perf_counter()
                    results[name].append(asyncio.run(_latencies(port, args.policy, args.requests)))
                    cpu[name].append(100 * (_cpu_seconds(server.pid) - cpu_start) / (time.perf_counter() - wall_start))
                finally:
                    if viewer is not None:
                        viewer.terminate()
                        viewer.join(5)
        for name, runs in results.items():
            figures = {f"p{q}_ms": round(float(np.median([np.percentile(r, q) for r in runs])) * 1000, 3) for q in (50, 95, 99)}
            print(
                json.dumps(
                    {
                        "condition": name,
                        "policy": args.policy,
                        "rounds": args.rounds,
                        "requests": args.requests,
                        **figures,
                        "server_cpu_pct": round(float(np.median(cpu[name])), 1),
                    }
                )
            )
    finally:
        server.terminate()
        server.wait(10)
    return 0


async def _latencies(port: int, policy: str, n: int) -> np.ndarray:
    """Seconds per request for `n` sequential /act requests on one keep-alive connection (a minimal HTTP/1.1 client)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    out = np.empty(n)
    try:
        for i in range(n):
            body = json.dumps({"policy": policy, "state": [222.0, 97.0, 300.0, 300.0, 0.8], "seed": i}).encode()
            request = b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: %d\r\n\r\n%s" % (
                len(body),
                body,
            )
            start = time.perf_counter()
            writer.write(request)
            head = await reader.readuntil(b"\r\n\r\n")
            length = next(int(line.split(b":")[1]) for line in head.split(b"\r\n") if line.lower().startswith(b"content-length:"))
            await reader.readexactly(length)
            out[i] = time.perf_counter() - start
            if head[9:12] != b"200":
                raise RuntimeError(f"/act answered {head[:12]!r}")
    finally:
        writer.close()
    return out


def _play_forever(port: int, policy: str, fps: float, ready) -> None:
    """A viewer page's traffic: hello, then episode after episode at `fps`, reading every state."""
    from websockets.sync.client import connect

    with connect(f"ws://127.0.0.1:{port}/viewer/ws") as ws:
        ws.send(json.dumps({"type": "hello"}))
        ws.recv()
        seed = 0
        ready.set()
        while True:
            ws.send(json.dumps({"type": "start", "policy": policy, "seed": seed, "fps": fps}))
            while not json.loads(ws.recv())["done"]:
                pass
            seed += 1


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _wait_ready(port: int, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode}")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=1) as response:
                if response.status == 200:
                    return
        except OSError:
            time.sleep(0.1)
    raise TimeoutError("server not ready")


if __name__ == "__main__":
    sys.exit(main())

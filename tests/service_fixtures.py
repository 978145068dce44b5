"""Helpers for the service tests: random-weight test policies, and a real uvicorn on a free loopback port."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO, Iterator

import httpx

REPO = Path(__file__).resolve().parents[1]
# PUSHT_SHIPPED_MODELS points the "shipped models" tests at another folder (e.g. a candidate export).
SHIPPED_MODELS = Path(os.environ.get("PUSHT_SHIPPED_MODELS", REPO / "models"))
# The shipped outcome chooser (its candidates x 10 flow steps at 4 stretches, start noise), served as `flow` beside mse by
# `cached_chooser_models`: the tests of step counts and noise costs need a flow whose chunk costs many evaluations.
CHOOSER = SHIPPED_MODELS / "flow-chooser"

# Realistic statistics (pixels), so random weights still give actions spread over the board.
NORMALIZATION = {
    "state_mean": [256.0, 256.0, 256.0, 256.0, 3.14],
    "state_std": [100.0, 100.0, 80.0, 80.0, 1.8],
    "action_mean": [256.0, 256.0],
    "action_std": [100.0, 100.0],
}


def build_test_models(models_dir: Path, hidden_dims: tuple[int, ...] = (64, 64), horizon: int = 12) -> Path:
    """Write random-weight `mse` and `flow` policies (safetensors, card, ONNX) of `horizon`-action chunks into `models_dir`."""
    import torch

    from policies.checkpoint import save_checkpoint
    from policies.factory import build_policy
    from training.export import export_onnx

    models_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    for kind in ("mse", "flow"):
        policy = build_policy(kind, hidden_dims=list(hidden_dims), dropout=0.0, horizon=horizon).eval()
        save_checkpoint(models_dir / kind, policy, NORMALIZATION, steps=0, git_commit="test", evaluation=None)
        export_onnx(models_dir / kind)
    return models_dir


def cached_test_models(base: Path, horizon: int = 12) -> Path:
    """`build_test_models` into BASE/service-models (-hH for another horizon) once per pytest session (shared by the service tests)."""
    models_dir = base / ("service-models" if horizon == 12 else f"service-models-h{horizon}")
    done = models_dir / ".complete"
    if not done.is_file():
        build_test_models(models_dir, (64, 64) if horizon == 12 else (32,), horizon=horizon)
        done.touch()
    return models_dir


def cached_chooser_models(base: Path) -> Path:
    """BASE/chooser-models once per pytest session: the shipped mse beside CHOOSER as `flow` (card, weights, ONNX), and
    without the default flag, so the service's default is by name."""
    import json
    import shutil

    models_dir = base / "chooser-models"
    done = models_dir / ".complete"
    if not done.is_file():
        models_dir.mkdir(parents=True, exist_ok=True)
        for suffix in (".json", ".onnx", ".safetensors"):
            shutil.copyfile(SHIPPED_MODELS / f"mse{suffix}", models_dir / f"mse{suffix}")
        for suffix in (".onnx", ".safetensors"):
            shutil.copyfile(CHOOSER.with_suffix(suffix), models_dir / f"flow{suffix}")
        card = json.loads(CHOOSER.with_suffix(".json").read_text())
        card["onnx"]["file"] = "flow.onnx"
        (models_dir / "flow.json").write_text(
            json.dumps({**card, "name": "flow", "default": False}, indent=2)
        )  # named by its stem
        done.touch()
    return models_dir


def shipped_models_available() -> bool:
    """True when the lead's trained `models/mse` and `models/flow` (cards and ONNX) are present."""
    return all((SHIPPED_MODELS / f"{name}{ext}").is_file() for name in ("mse", "flow") for ext in (".json", ".onnx"))


def free_port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def server_command(entry: str, port: int | str, python: str = sys.executable, app: str = "service.app:app") -> list[str]:
    """How users start the service: `entry` "uvicorn" (plain `uvicorn APP`) or "service" (`python -m service`, Makefile, Docker)."""
    if entry == "service":
        return [python, "-m", "service", "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"]
    return [python, "-m", "uvicorn", app, "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"]


class UvicornProcess:
    """The service (plain uvicorn, or `python -m service`) in a subprocess on 127.0.0.1, stopped on exit of the `with` block."""

    def __init__(
        self,
        env: dict[str, str],
        python: str = sys.executable,
        app: str = "service.app:app",
        cwd: Path = REPO,
        entry: str = "uvicorn",
        preexec_fn=None,
    ) -> None:
        self.models_dir = Path(env.get("PUSHT_MODELS_DIR", "models"))
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, **env}
        self.cmd = server_command(entry, self.port, python, app)
        self.cwd = cwd
        self.preexec_fn = preexec_fn
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> "UvicornProcess":
        # A file, not a pipe: nobody drains a pipe while the tests run, and a full one blocks the server.
        self.log = tempfile.TemporaryFile(mode="w+")
        self.proc = subprocess.Popen(
            self.cmd, cwd=self.cwd, env=self.env, stdout=self.log, stderr=subprocess.STDOUT, text=True, preexec_fn=self.preexec_fn
        )
        try:
            wait_ready(self.url, self.proc, log=self.log)
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        stop(self.proc)
        self.log.close()

    def output(self) -> str:
        """What the server printed so far."""
        self.log.seek(0)
        return self.log.read()

    def rss_bytes(self) -> int:
        """The server process's resident memory (Linux /proc)."""
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
        raise RuntimeError("no VmRSS")


def wait_ready(url: str, proc: subprocess.Popen | None = None, timeout: float = 60.0, log: IO[str] | None = None) -> None:
    """Poll GET /readyz until 200; fail with the server's output if it exits or times out."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            output = ""
            if log is not None:
                log.seek(0)
                output = log.read()
            raise RuntimeError(f"server exited with {proc.returncode}: {output}")
        try:
            if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    stop(proc)
    raise TimeoutError(f"{url} not ready after {timeout} s")


def stop(proc: subprocess.Popen | None) -> None:
    """Terminate a server subprocess we started (SIGTERM, then SIGKILL)."""
    if proc is None or proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)


def iter_lines(text: str) -> Iterator[str]:
    """Non-comment lines of a Prometheus exposition."""
    return (line for line in text.splitlines() if line and not line.startswith("#"))


async def raw_burst(port: int, bodies: list[bytes], connections: int = 32) -> list[tuple[int, bytes]]:
    """POST every body to /act over `connections` already-open keep-alive connections, all written at once.

    Pre-encoded requests written back to back (pipelined per connection) reach the server together,
    unlike a Python HTTP client whose own overhead spaces them out. Returns (status, body) in order.
    """
    import asyncio

    streams = await asyncio.gather(*(asyncio.open_connection("127.0.0.1", port) for _ in range(connections)))
    mine: list[list[int]] = [list(range(c, len(bodies), connections)) for c in range(connections)]
    for (_, writer), indices in zip(streams, mine, strict=True):
        writer.write(
            b"".join(
                b"POST /act HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\nContent-Length: %d\r\n\r\n%s"
                % (len(bodies[i]), bodies[i])
                for i in indices
            )
        )

    async def read(reader: asyncio.StreamReader, count: int) -> list[tuple[int, bytes]]:
        out = []
        for _ in range(count):
            head = await reader.readuntil(b"\r\n\r\n")
            length = next(int(line.split(b":")[1]) for line in head.split(b"\r\n") if line.lower().startswith(b"content-length:"))
            out.append((int(head[9:12]), await reader.readexactly(length)))
        return out

    try:
        answers = await asyncio.gather(*(read(reader, len(indices)) for (reader, _), indices in zip(streams, mine, strict=True)))
    finally:
        for _, writer in streams:
            writer.close()
    result: list[tuple[int, bytes]] = [(0, b"")] * len(bodies)
    for indices, got in zip(mine, answers, strict=True):
        for i, answer in zip(indices, got, strict=True):
            result[i] = answer
    return result

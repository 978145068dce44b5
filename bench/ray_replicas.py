"""Throughput of the service behind Ray Serve with 1 and 2 replicas, beside the plain service, in one run.

    .venv/bin/python bench/ray_replicas.py                  # shipped models/flow.onnx, 32 connections
    .venv/bin/python bench/ray_replicas.py --policy mse --rounds 2

Starts (a) `python -m service` (the baseline: one process, no Ray), (b) `python -m service.ray_serve
--replicas 1` and (c) `--replicas 2`, each on a fresh local Ray cluster, one at a time, and drives
each with bench/service_latency.py's keep-alive load generator: p50 latency at 1 connection and
requests/s at --connections connections, single-state requests with a seed. The load generator,
Ray's proxy and the replicas share this machine's cores, so on 2 cores a second replica has no core
of its own: the figures show what Ray's proxy costs and whether replicas pay off here.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from service_latency import Figures, _measure, _payloads, _wait_ready  # noqa: E402  (bench/ is not a package)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--models-dir", default=str(REPO / "models"), help="folder of the policies to serve")
    parser.add_argument("--policy", default="flow", help="policy to request")
    parser.add_argument("--sequential", type=int, default=1000, help="sequential requests at 1 connection (after warm-up)")
    parser.add_argument("--connections", type=int, default=32, help="concurrent connections for the throughput run")
    parser.add_argument("--duration", type=float, default=5.0, help="seconds of the throughput run")
    parser.add_argument("--warmup", type=int, default=300, help="warm-up requests before each measurement")
    parser.add_argument(
        "--rounds", type=int, default=1, help="alternate the three servers this many times; report each figure's median"
    )
    parser.add_argument("--local-cpus", type=int, default=os.cpu_count(), help="CPUs of each local Ray cluster")
    args = parser.parse_args(argv)
    payloads = _payloads(args.policy, 512)
    env = {**os.environ, "PUSHT_MODELS_DIR": str(Path(args.models_dir).resolve()), "RAY_ADDRESS": ""}
    servers = {
        "plain (python -m service)": ["-m", "service"],
        "ray serve, 1 replica": ["-m", "service.ray_serve", "--replicas", "1", "--local-cpus", str(args.local_cpus)],
        "ray serve, 2 replicas": ["-m", "service.ray_serve", "--replicas", "2", "--local-cpus", str(args.local_cpus)],
    }
    results: dict[str, list[Figures]] = {name: [] for name in servers}
    print(
        f"{args.policy}: {os.cpu_count()} cores, load average {', '.join(f'{x:.2f}' for x in os.getloadavg())} at start",
        flush=True,
    )
    for round_ in range(args.rounds):
        for name, cmd in servers.items():
            fig = _bench(name, cmd, env, payloads, args)
            results[name].append(fig)
            print(f"  round {round_ + 1}: {_line(fig)}", flush=True)
    print(f"\nmedians over {args.rounds} round(s); load average {', '.join(f'{x:.2f}' for x in os.getloadavg())} at the end:")
    base = np.median([f.throughput_rps for f in results["plain (python -m service)"]])
    for name, figs in results.items():
        rps = float(np.median([f.throughput_rps for f in figs]))
        p50 = float(np.median([f.p50_ms for f in figs]))
        conc = float(np.median([f.conc_p50_ms for f in figs]))
        errors = sum(f.errors for f in figs)
        print(
            f"  {name:28s} p50 @ 1 conn {p50:6.2f} ms   {rps:8,.0f} req/s @ {args.connections} conns "
            f"({rps / base:4.2f}x plain; p50 there {conc:6.1f} ms)   errors {errors}"
        )
    return 0


def _line(fig: Figures) -> str:
    return (
        f"{fig.name:28s} p50 {fig.p50_ms:6.2f} ms at 1 conn, {fig.throughput_rps:8,.0f} req/s "
        f"(p50 {fig.conc_p50_ms:.1f} ms, p99 {fig.conc_p99_ms:.1f} ms) at the connections, errors {fig.errors}"
    )


def _bench(name: str, args_: list[str], env: dict[str, str], payloads: list[bytes], args: argparse.Namespace) -> Figures:
    """Start one server in its own session, wait for /readyz, measure, and stop it with everything it started."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    log = tempfile.TemporaryFile(mode="w+")
    cmd = [sys.executable, *args_, "--port", str(port)] + (["--log-level", "warning"] if args_[-1] == "service" else [])
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        _wait_ready(port, proc, log, timeout=240.0)
        time.sleep(2.0)  # let Ray's start-up work settle before measuring
        return asyncio.run(_measure(name, port, payloads, args))
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            pass
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # anything the server's session left behind
        except ProcessLookupError:
            pass
        log.close()


if __name__ == "__main__":
    sys.exit(main())

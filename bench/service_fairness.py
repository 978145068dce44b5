"""Small requests beside bulk ones: 1-row latency while clients stream 512-row batches, and after hung-up clients.

    .venv/bin/python bench/service_fairness.py                            # the service, shipped models/
    .venv/bin/python bench/service_fairness.py --reference-rev 2bab7f9    # and the service as of that commit

Per server (`uvicorn service.app:app` on 127.0.0.1, one at a time, alternated over --rounds) and per policy
of --policies (default: mse, the cheapest, and the default policy): (1) --bulk-clients keep-alive
connections stream --bulk-rows-row requests for --duration s: bulk rows/s, the bulk requests' p50 and
server CPU per 1,000 rows; (2) the same plus one connection sending 1-row requests back to back: their
p50/p99, and p99 over the bulk p50 of (1) (the target: <= 0.3, a lone row waits about one model call);
(3) --abandoned requests of 1,024 rows whose clients close right after sending, then a 1-row probe: its
latency. The reference revision (service/ and pusht/ from `git archive`) is the baseline measured in the
same run.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.service_latency import _connection, _cpu_seconds, _payloads, _wait_ready, checkout_rev  # noqa: E402


def _request(body: dict) -> bytes:
    data = json.dumps(body).encode()
    return b"POST /act HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\nContent-Length: %d\r\n\r\n%s" % (
        len(data),
        data,
    )


def _bulk_payloads(policy: str, rows: int, n: int = 16) -> list[bytes]:
    rng = np.random.default_rng(1)
    out = []
    for i in range(n):
        states = np.column_stack([rng.uniform(50, 460, (rows, 4)), rng.uniform(0, 6.28, rows)]).round(3).tolist()
        out.append(_request({"policy": policy, "states": states, "seed": i}))
    return out


async def _stream(port: int, payloads: list[bytes], seconds: float, latencies: list[float], errors: list[int]) -> None:
    await _connection(port, payloads, 0, 10**9, latencies, errors, deadline=time.perf_counter() + seconds)


async def _bulk_and_probe(port: int, policy: str, args: argparse.Namespace, probe: bool) -> dict[str, float]:
    bulk = _bulk_payloads(policy, args.bulk_rows)
    small = _payloads(policy, 512)
    bulk_lat: list[float] = []
    probe_lat: list[float] = []
    errors = [0]
    start = time.perf_counter()
    tasks = [_stream(port, bulk[i:] + bulk[:i], args.duration, bulk_lat, errors) for i in range(args.bulk_clients)]
    if probe:

        async def delayed_probe() -> None:
            await asyncio.sleep(0.5)  # measure once the bulk stream is going
            await _stream(port, small, args.duration - 0.5, probe_lat, errors)

        tasks.append(delayed_probe())
    await asyncio.gather(*tasks)
    elapsed = time.perf_counter() - start
    out = {
        "bulk_rows_per_s": len(bulk_lat) * args.bulk_rows / elapsed,
        "bulk_p50_ms": float(np.percentile(np.asarray(bulk_lat) * 1e3, 50)),
        "errors": errors[0],
    }
    if probe:
        ms = np.asarray(probe_lat) * 1e3
        out.update(
            probe_p50_ms=float(np.percentile(ms, 50)),
            probe_p99_ms=float(np.percentile(ms, 99)),
            probe_max_ms=float(ms.max()),
            probes=len(ms),
        )
    return out


async def _abandoned(port: int, policy: str, count: int) -> float:
    """Send `count` 1,024-row requests and hang up at once; the latency (ms) of a 1-row probe right after."""
    payload = _bulk_payloads(policy, 1024, 1)[0]
    for _ in range(count):
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(payload)
        await writer.drain()
        writer.close()
    latencies: list[float] = []
    await _connection(port, _payloads(policy, 1), 0, 1, latencies, [0], None)
    return latencies[0] * 1e3


def _bench(cwd: Path, models_dir: Path, args: argparse.Namespace) -> dict[str, dict[str, float]]:
    """One server's figures by policy."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    cmd = [sys.executable, "-m", "uvicorn", "service.app:app", "--host", "127.0.0.1", "--port", str(port)]
    env = {**os.environ, "PUSHT_MODELS_DIR": str(models_dir), "PYTHONPATH": str(cwd)}
    log = tempfile.TemporaryFile(mode="w+")
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT, text=True)
    try:
        _wait_ready(port, proc, log)
        return {policy: _policy_figures(port, proc.pid, policy, args) for policy in args.policies}
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


def _policy_figures(port: int, pid: int, policy: str, args: argparse.Namespace) -> dict[str, float]:
    asyncio.run(_connection(port, _bulk_payloads(policy, args.bulk_rows, 2), 0, 5, None, [0], None))  # warm-up
    figures: dict[str, float] = {}
    cpu0 = _cpu_seconds(pid)
    figures.update({f"alone_{k}": v for k, v in asyncio.run(_bulk_and_probe(port, policy, args, probe=False)).items()})
    # server CPU per 1,000 bulk rows: the throughput figure least moved by what else runs
    figures["alone_cpu_s_per_krow"] = (_cpu_seconds(pid) - cpu0) / (figures["alone_bulk_rows_per_s"] * args.duration / 1000)
    figures.update(asyncio.run(_bulk_and_probe(port, policy, args, probe=True)))
    figures["p99_over_bulk_p50"] = figures["probe_p99_ms"] / figures["alone_bulk_p50_ms"]
    time.sleep(1.0)
    figures["abandoned_probe_ms"] = asyncio.run(_abandoned(port, policy, args.abandoned))
    return figures


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--models-dir", default=str(REPO / "models"), help="folder with the policies (cards + ONNX)")
    parser.add_argument("--policies", default=None, help="comma-separated policy names (default: mse and the default policy)")
    parser.add_argument("--reference-rev", default=None, help="also bench the service as of this git revision")
    parser.add_argument("--bulk-clients", type=int, default=8, help="connections streaming bulk requests")
    parser.add_argument("--bulk-rows", type=int, default=512, help="states per bulk request")
    parser.add_argument("--duration", type=float, default=8.0, help="seconds of each streaming phase")
    parser.add_argument("--abandoned", type=int, default=40, help="1,024-row requests abandoned before the last probe")
    parser.add_argument("--rounds", type=int, default=1, help="alternate the servers this many times (medians reported)")
    args = parser.parse_args(argv)
    args.policies = args.policies.split(",") if args.policies else ["mse", _default_policy(Path(args.models_dir))]

    with tempfile.TemporaryDirectory() as tmp:
        servers = {"service": REPO}
        if args.reference_rev:
            servers["reference"] = checkout_rev(args.reference_rev, Path(tmp))
        runs: dict[tuple[str, str], list[dict]] = {}
        for r in range(args.rounds):
            for name, cwd in servers.items():
                print(f"[{name}, round {r + 1}/{args.rounds}] ...", file=sys.stderr)
                for policy, figures in _bench(cwd, Path(args.models_dir), args).items():
                    runs.setdefault((name, policy), []).append(figures)
                    print(f"[{name}, {policy}, round {r + 1}/{args.rounds}] {figures}", file=sys.stderr)
    _print_table(runs, args)
    errors = sum(f["errors"] + f["alone_errors"] for figs in runs.values() for f in figs)
    print(f"errors: {errors}")
    return 0 if errors == 0 else 1


def _default_policy(models_dir: Path) -> str:
    """The name of the card in `models_dir` marked default."""
    for card in sorted(models_dir.glob("*.json")):
        data = json.loads(card.read_text())
        if data.get("default"):
            return data["name"]
    raise SystemExit(f"error: no card in {models_dir} is marked default; name the policies with --policies")


def _print_table(runs: dict[tuple[str, str], list[dict]], args: argparse.Namespace) -> None:
    print(f"\ncpu cores: {os.cpu_count()}; load generator, servers and anything else running share them")
    print(
        f"{args.bulk_clients} clients streaming {args.bulk_rows}-row requests for {args.duration:g} s, then one more sending "
        f"1-row requests; medians of {args.rounds} round(s)\n"
    )
    keys = [
        "alone_bulk_rows_per_s",
        "alone_cpu_s_per_krow",
        "alone_bulk_p50_ms",
        "bulk_rows_per_s",
        "probe_p50_ms",
        "probe_p99_ms",
        "p99_over_bulk_p50",
        "abandoned_probe_ms",
    ]
    print(f"{'server':<10}{'policy':<14}" + "".join(f"{k:>22}" for k in keys))
    medians = {}
    for (name, policy), figs in runs.items():
        medians[name, policy] = m = {k: float(np.median([f[k] for f in figs])) for k in keys}
        print(f"{name:<10}{policy:<14}" + "".join(f"{m[k]:22.3f}" for k in keys))
    print()
    for (name, policy), m in medians.items():
        verdict = "meets" if m["p99_over_bulk_p50"] <= 0.3 else "misses"
        print(f"{name} {policy}: 1-row p99 / bulk p50 = {m['p99_over_bulk_p50']:.2f} ({verdict} the target <= 0.3)")


if __name__ == "__main__":
    sys.exit(main())

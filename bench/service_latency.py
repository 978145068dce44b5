"""Latency and throughput of the policy service against a plain FastAPI + ONNX Runtime baseline.

    .venv/bin/python bench/service_latency.py                    # shipped models/flow.onnx
    .venv/bin/python bench/service_latency.py --random-models    # random-weight models (no trained ones needed)
    .venv/bin/python bench/service_latency.py --reference-rev 2bab7f9   # also the service as of that commit

Starts (a) bench/baseline_app.py (one ONNX Runtime call per request, default uvicorn settings) and
(b) `uvicorn service.app:app`, each as a subprocess on 127.0.0.1, one at a time, and drives both
with the same minimal keep-alive HTTP/1.1 client (asyncio + uvloop, pre-encoded requests, so the
client costs little CPU): p50/p99 latency at 1 connection (sequential requests) and throughput
at --connections concurrent connections, single-state flow requests with a seed. With
--reference-rev, the service as of that git revision (service/ and pusht/ extracted with
`git archive`) is measured too, alternated with the others, so a change is compared with what it
replaces in one run. With --floor, bench/floor_app.py (a fixed answer, no framework, no model)
shows what uvicorn and this client take by themselves: no app's p50 is below it plus its model
call. The load generator shares the machine's cores with the server: figures depend on what else
runs.
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
import urllib.request
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


@dataclass
class Figures:
    """What one server measured."""

    name: str
    p50_ms: float
    p99_ms: float
    seq_requests: int
    throughput_rps: float
    conc_p50_ms: float
    conc_p99_ms: float
    conc_requests: int
    errors: int
    seq_cpu_ms: float
    """server process CPU time (all threads, user + system) per request at 1 connection; nan off Linux"""
    conc_cpu_ms: float
    """the same at --connections connections: less sensitive than wall time to what else runs"""


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = _parser()
    args = parser.parse_args(argv)
    rounds = _run_rounds(args, parser)
    results = [_median(figs) for figs in rounds.values()]
    ratios = _report(args, results)
    if args.json:
        record = {
            "rounds": {name: [asdict(f) for f in figs] for name, figs in rounds.items()},
            "median": [asdict(f) for f in results],
        }
        Path(args.json).write_text(json.dumps({**record, **ratios, "cpu_count": os.cpu_count()}, indent=2) + "\n")
    return 0 if all(f.errors == 0 for f in results) else 1


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument(
        "--models-dir", default=str(REPO / "models"), help="folder with flow.json/flow.onnx (and the other policies)"
    )
    parser.add_argument(
        "--random-models",
        action="store_true",
        help="bench random-weight policies of the default architectures built into a temp dir",
    )
    parser.add_argument("--policy", default="flow", help="policy to request")
    parser.add_argument("--sequential", type=int, default=2000, help="sequential requests at 1 connection (after warm-up)")
    parser.add_argument("--connections", type=int, default=32, help="concurrent connections for the throughput run")
    parser.add_argument("--duration", type=float, default=5.0, help="seconds of the throughput run")
    parser.add_argument("--warmup", type=int, default=300, help="warm-up requests before each measurement")
    parser.add_argument(
        "--rounds", type=int, default=1, help="alternate the two servers this many times; report each figure's median"
    )
    parser.add_argument(
        "--only", choices=("baseline", "service", "reference", "floor"), default=None, help="run only one of the servers"
    )
    parser.add_argument(
        "--floor",
        action="store_true",
        help="also bench bench/floor_app.py: a fixed answer, no framework or model (uvicorn's own floor)",
    )
    parser.add_argument(
        "--reference-rev", default=None, help="also bench the service as of this git revision (e.g. the last release)"
    )
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    return parser


def _run_rounds(args: argparse.Namespace, parser: argparse.ArgumentParser) -> dict[str, list[Figures]]:
    """Each server's figures, one per round."""
    with tempfile.TemporaryDirectory() as tmp:
        models_dir = Path(args.models_dir)
        if args.random_models:
            models_dir = Path(tmp) / "models"
            _build_random_models(models_dir)
        onnx_path = models_dir / f"{args.policy}.onnx"
        if not onnx_path.is_file():
            parser.error(f"{onnx_path} not found: train and export the policies, or pass --random-models")
        payloads = _payloads(args.policy, 4096)
        servers = {
            "baseline": ("bench.baseline_app:app", {"BASELINE_ONNX": str(onnx_path)}, REPO),
            "service": ("service.app:app", {"PUSHT_MODELS_DIR": str(models_dir)}, REPO),
        }
        if args.floor or args.only == "floor":
            servers["floor"] = ("bench.floor_app:app", {}, REPO)
        if args.reference_rev:
            servers["reference"] = (
                "service.app:app",
                {"PUSHT_MODELS_DIR": str(models_dir)},
                checkout_rev(args.reference_rev, Path(tmp)),
            )
        rounds: dict[str, list[Figures]] = {}
        # Alternating rounds spread slow drifts of the background load over both servers.
        for r in range(args.rounds):
            for name, (app, env, cwd) in servers.items():
                if args.only and name != args.only:
                    continue
                print(f"[{name}, round {r + 1}/{args.rounds}] starting {app} ...", file=sys.stderr)
                rounds.setdefault(name, []).append(_bench_server(name, app, env, payloads, args, cwd))
                print(f"[{name}, round {r + 1}/{args.rounds}] {_line(rounds[name][-1])}", file=sys.stderr)
    return rounds


def _report(args: argparse.Namespace, results: list[Figures]) -> dict[str, float]:
    """Print the table and the ratios; returns the ratios."""
    print(f"\ncpu cores: {os.cpu_count()}; load generator, server and anything else running share them")
    print(
        f"policy {args.policy}, single-state requests with a seed, {args.connections} connections for {args.duration:.0f} s, "
        f"median of {args.rounds} round(s); both servers started as `uvicorn APP --host 127.0.0.1 --port P`\n"
    )
    c = args.connections
    print(
        f"{'server':<10} {'p50 ms':>8} {'p99 ms':>8} {'cpu ms/req':>11} {f'req/s @{c}':>11} {f'p50 ms @{c}':>11} "
        f"{f'p99 ms @{c}':>11} {f'cpu ms/req @{c}':>15} {'errors':>7}"
    )
    for fig in results:
        print(
            f"{fig.name:<10} {fig.p50_ms:8.3f} {fig.p99_ms:8.3f} {fig.seq_cpu_ms:11.3f} {fig.throughput_rps:11.0f} "
            f"{fig.conc_p50_ms:11.3f} {fig.conc_p99_ms:11.3f} {fig.conc_cpu_ms:15.3f} {fig.errors:7d}"
        )
    by_name = {fig.name: fig for fig in results}
    ratios = {}
    if "reference" in by_name and "service" in by_name:
        ref, ours = by_name["reference"], by_name["service"]
        ratios["throughput_vs_reference"] = ours.throughput_rps / ref.throughput_rps
        ratios["p50_vs_reference"] = ours.p50_ms / ref.p50_ms
        print(
            f"\nservice vs reference ({args.reference_rev}): throughput {ratios['throughput_vs_reference']:.3f}x, "
            f"p50 {ratios['p50_vs_reference']:.3f}x, cpu per request @{c} {ours.conc_cpu_ms / ref.conc_cpu_ms:.3f}x"
        )
    if "baseline" in by_name and "service" in by_name:
        base, ours = by_name["baseline"], by_name["service"]
        ratios = {
            "p50_ratio": ours.p50_ms / base.p50_ms,
            "p99_ratio": ours.p99_ms / base.p99_ms,
            "throughput_ratio": ours.throughput_rps / base.throughput_rps,
            "cpu_per_request_ratio_at_connections": ours.conc_cpu_ms / base.conc_cpu_ms,
        }
        print(
            f"\np50 ours/baseline: {ratios['p50_ratio']:.2f}x (target <= 0.6)   "
            f"p99 ours/baseline: {ratios['p99_ratio']:.2f}x   "
            f"throughput ours/baseline: {ratios['throughput_ratio']:.2f}x (target >= 5)   "
            f"server cpu per request @{c} ours/baseline: {ratios['cpu_per_request_ratio_at_connections']:.2f}x"
        )
    return ratios


def _median(figs: list[Figures]) -> Figures:
    """Each figure's median over rounds (errors summed)."""
    values = {}
    for f in fields(Figures):
        column = [getattr(fig, f.name) for fig in figs]
        if f.name == "name":
            values[f.name] = column[0]
        elif f.name == "errors":
            values[f.name] = sum(column)
        else:
            values[f.name] = type(column[0])(np.median(column))
    return Figures(**values)


def _line(fig: Figures) -> str:
    return f"p50 {fig.p50_ms:.3f} ms, p99 {fig.p99_ms:.3f} ms, {fig.throughput_rps:.0f} req/s, errors {fig.errors}"


def _build_random_models(models_dir: Path) -> None:
    import torch

    from policies.checkpoint import save_checkpoint
    from policies.factory import build_policy
    from training.export import export_onnx

    torch.manual_seed(0)
    stats = {
        "state_mean": [256.0, 256.0, 256.0, 256.0, 3.14],
        "state_std": [100.0, 100.0, 80.0, 80.0, 1.8],
        "action_mean": [256.0, 256.0],
        "action_std": [100.0, 100.0],
    }
    for kind in ("mse", "flow"):
        save_checkpoint(models_dir / kind, build_policy(kind).eval(), stats, git_commit="random")
        export_onnx(models_dir / kind)


def _payloads(policy: str, n: int) -> list[bytes]:
    """Pre-encoded HTTP/1.1 requests: random plausible states, one seed each."""
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        state = [*rng.uniform(50, 460, 4).round(3).tolist(), round(float(rng.uniform(0, 2 * np.pi)), 4)]
        body = json.dumps({"policy": policy, "state": state, "seed": i}).encode()
        head = (
            f"POST /act HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n"
        ).encode()
        out.append(head + body)
    return out


def checkout_rev(rev: str, tmp: Path) -> Path:
    """service/ and pusht/ as of git revision `rev`, extracted into a folder under `tmp` (returned)."""
    dest = tmp / f"rev-{rev.replace('/', '_')}"
    dest.mkdir()
    archive = subprocess.run(["git", "archive", rev, "service", "pusht"], cwd=REPO, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def _bench_server(
    name: str, app: str, env: dict[str, str], payloads: list[bytes], args: argparse.Namespace, cwd: Path = REPO
) -> Figures:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    # Default uvicorn settings for both, as the Dockerfile runs the service (the service turns its
    # own access log off unless PUSHT_ACCESS_LOG=1; the baseline keeps uvicorn's default).
    cmd = [sys.executable, "-m", "uvicorn", app, "--host", "127.0.0.1", "--port", str(port)]
    log = tempfile.TemporaryFile(mode="w+")
    # PYTHONPATH= so that a reference checkout imports its own service/ and pusht/, not the editable install's.
    proc = subprocess.Popen(
        cmd, cwd=cwd, env={**os.environ, **env, "PYTHONPATH": str(cwd)}, stdout=log, stderr=subprocess.STDOUT, text=True
    )
    try:
        _wait_ready(port, proc, log)
        return asyncio.run(_measure(name, port, payloads, args, lambda: _cpu_seconds(proc.pid)))
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        log.close()


def _wait_ready(port: int, proc: subprocess.Popen, log, timeout: float = 60.0) -> None:
    """Poll GET /readyz until 200; raise with the server's output if it exits or never gets ready."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            log.seek(0)
            raise RuntimeError(f"server exited with {proc.returncode}:\n{log.read()}")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=1) as response:
                if response.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.1)
    raise TimeoutError(f"server on port {port} not ready after {timeout} s")


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of process `pid` (all its threads), from /proc; nan where there is none."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def _measure(name: str, port: int, payloads: list[bytes], args: argparse.Namespace, cpu=lambda: float("nan")) -> Figures:
    errors = [0]
    await _connection(port, payloads, 0, args.warmup, None, errors, deadline=None)
    seq: list[float] = []
    cpu0 = cpu()
    await _connection(port, payloads, 0, args.sequential, seq, errors, deadline=None)
    seq_cpu = cpu() - cpu0
    await asyncio.gather(
        *(
            _connection(port, payloads, c * 97, args.warmup // args.connections + 1, None, errors, None)
            for c in range(args.connections)
        )
    )
    conc: list[float] = []
    cpu0 = cpu()
    start = time.perf_counter()
    deadline = start + args.duration
    await asyncio.gather(*(_connection(port, payloads, c * 97, 10**9, conc, errors, deadline) for c in range(args.connections)))
    elapsed = time.perf_counter() - start
    conc_cpu = cpu() - cpu0
    seq_ms = np.asarray(seq) * 1e3
    conc_ms = np.asarray(conc) * 1e3
    return Figures(
        name=name,
        p50_ms=float(np.percentile(seq_ms, 50)),
        p99_ms=float(np.percentile(seq_ms, 99)),
        seq_requests=len(seq),
        throughput_rps=len(conc) / elapsed,
        conc_p50_ms=float(np.percentile(conc_ms, 50)),
        conc_p99_ms=float(np.percentile(conc_ms, 99)),
        conc_requests=len(conc),
        errors=errors[0],
        seq_cpu_ms=1e3 * seq_cpu / max(len(seq), 1),
        conc_cpu_ms=1e3 * conc_cpu / max(len(conc), 1),
    )


async def _connection(
    port: int,
    payloads: list[bytes],
    offset: int,
    count: int,
    latencies: list[float] | None,
    errors: list[int],
    deadline: float | None,
) -> None:
    """Send `count` requests one after another on one keep-alive connection (or until `deadline`)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    clock = time.perf_counter
    try:
        for i in range(count):
            request = payloads[(offset + i) % len(payloads)]
            t0 = clock()
            if deadline is not None and t0 >= deadline:
                break
            writer.write(request)
            head = await reader.readuntil(b"\r\n\r\n")
            length = 0
            for line in head.split(b"\r\n"):
                if line[:15].lower() == b"content-length:":
                    length = int(line[15:])
            body = await reader.readexactly(length)
            if latencies is not None:
                latencies.append(clock() - t0)
            if head[9:12] != b"200" or b'"actions"' not in body:
                errors[0] += 1
    finally:
        writer.close()


if __name__ == "__main__":
    try:
        import uvloop

        uvloop.install()
    except ImportError:
        pass
    sys.exit(main())

"""The HTTP rollout client, run as a script against a real uvicorn server on 127.0.0.1."""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

REPO = Path(__file__).resolve().parents[1]
CLIENT = REPO / "clients" / "rollout.py"
API_KEY = "client-test-key"
SEED = 100000
# Short e2e runs: 4 episodes over 2 envs, 60 steps each.
SHORT = ["--episodes", "4", "--num-envs", "2", "--max-steps", "60", "--seed", str(SEED)]
FORBIDDEN_IMPORTS = ("torch", "training", "service", "onnxruntime", "fastapi")


def run_client(*args: str, importtime: bool = False, timeout: float = 180) -> subprocess.CompletedProcess:
    """Run clients/rollout.py as a script path, the way a user does."""
    cmd = [sys.executable] + (["-X", "importtime"] if importtime else []) + [str(CLIENT), *args]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=timeout)


def imported_modules(stderr: str) -> set[str]:
    """Module names from `python -X importtime` lines ('import time: self | cumulative | name')."""
    names = set()
    for line in stderr.splitlines():
        if line.startswith("import time:") and "|" in line:
            names.add(line.rsplit("|", 1)[1].strip())
    return names


def assert_one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> str:
    """A failed run: exit 2, nothing on stdout, exactly one 'error: ...' line on stderr that names the problem."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert proc.stdout == ""
    assert "Traceback" not in proc.stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def report_of(proc: subprocess.CompletedProcess) -> dict:
    """The one JSON line on stdout of a successful run."""
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) == 1, proc.stdout
    return json.loads(lines[0])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ---------------------------------------------------------------- fast: no server needed


def test_help_documents_flags_and_imports_no_torch():
    proc = run_client("--help", importtime=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    for flag in (
        "--url",
        "--policy",
        "--episodes",
        "--num-envs",
        "--seed",
        "--max-steps",
        "--action-horizon",
        "--gif",
        "--out",
        "--api-key",
        "--timeout",
    ):
        assert flag in proc.stdout
    text = " ".join(proc.stdout.split())
    assert "(default: None)" not in text and "(default: its default policy" in text and "(default: 200000)" in text
    assert all(option.count("(default") <= 1 for option in text.split(" --")[1:])
    modules = imported_modules(proc.stderr)
    assert "pusht.rollout" in modules and "httpx" in modules  # the parse works: it sees what is imported
    bad = sorted(m for m in modules if m.split(".")[0] in FORBIDDEN_IMPORTS + ("imageio",))
    assert bad == []


@pytest.mark.parametrize("url", ["ftp://127.0.0.1:8000", "127.0.0.1:8000", "http://"])
def test_invalid_url_is_one_line(url):
    assert_one_line_error(run_client("--url", url, "--episodes", "1", timeout=60), "--url", url)


def test_connection_refused_is_one_line():
    port = free_port()  # nothing listens there once the probe socket is closed
    line = assert_one_line_error(
        run_client("--url", f"http://127.0.0.1:{port}", "--episodes", "1", "--num-envs", "1", timeout=60)
    )
    assert "cannot connect" in line and str(port) in line


def test_bad_gif_path_fails_before_any_request(tmp_path):
    # The URL is unreachable too: the GIF error must come first, before minutes of rollout.
    proc = run_client("--url", f"http://127.0.0.1:{free_port()}", "--episodes", "1", "--gif", str(tmp_path), timeout=60)
    assert_one_line_error(proc, "--gif", "is a directory")


def test_silent_server_times_out_as_one_line():
    # A listening socket that never answers: the TCP connect succeeds (kernel backlog), the read times out.
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(8)
        port = server.getsockname()[1]
        start = time.perf_counter()
        proc = run_client(
            "--url", f"http://127.0.0.1:{port}", "--episodes", "1", "--num-envs", "1", "--timeout", "0.5", timeout=60
        )
        assert time.perf_counter() - start < 30
    assert_one_line_error(proc, "timed out")


# ---------------------------------------------------------------- e2e against a real server


def _tiny_flow_model(dest: Path) -> None:
    """A small random-weight flow policy exported to ONNX, for when no shipped model exists yet."""
    import torch

    from policies.checkpoint import save_checkpoint
    from policies.factory import build_policy
    from training.export import export_onnx

    torch.manual_seed(0)
    policy = build_policy("flow", hidden_dims=[32, 32], dropout=0.0)
    normalization = {
        "state_mean": [256.0, 256.0, 256.0, 256.0, math.pi],
        "state_std": [120.0, 120.0, 120.0, 120.0, 1.8],
        "action_mean": [256.0, 256.0],
        "action_std": [120.0, 120.0],
    }
    save_checkpoint(dest / "flow", policy, normalization, git_commit="test")
    export_onnx(dest / "flow")


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory) -> Path:
    """The shipped models/ when it has the flow policy, else a tiny exported one in a tmp dir."""
    shipped = REPO / "models"
    if (shipped / "flow.json").exists() and (shipped / "flow.onnx").exists():
        return shipped
    dest = tmp_path_factory.mktemp("models")
    _tiny_flow_model(dest)
    return dest


@pytest.fixture(scope="module")
def server(models_dir) -> str:
    """A real uvicorn serving `models_dir` on a free 127.0.0.1 port with an API key; shut down afterwards."""
    port = free_port()
    env = dict(os.environ, PUSHT_MODELS_DIR=str(models_dir), PUSHT_API_KEY=API_KEY)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "uvicorn",
            "service.app:app",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--log-level",
            "warning",
        ],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        import httpx

        deadline = time.monotonic() + 90
        while True:
            if proc.poll() is not None:
                pytest.fail(f"uvicorn exited with {proc.returncode}: {proc.stderr.read()[-2000:]}")
            try:
                if httpx.get(url + "/readyz", timeout=1.0).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                pytest.fail("the service was not ready within 90 s")
            time.sleep(0.3)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.slow
def test_e2e_report_gif_and_determinism(server, tmp_path):
    gif, out = tmp_path / "first.gif", tmp_path / "episodes.jsonl"
    first_proc = run_client("--url", server, "--api-key", API_KEY, *SHORT, "--gif", str(gif), "--out", str(out))
    first = report_of(first_proc)
    assert f"gif: wrote {gif}" in first_proc.stderr and f"to {out}" in first_proc.stderr
    # The second run also proves that a full real rollout loads neither torch nor the service.
    second_proc = run_client("--url", server, "--api-key", API_KEY, *SHORT, importtime=True)
    second = report_of(second_proc)

    listing = httpx.get(f"{server}/policies", headers={"X-API-Key": API_KEY}).json()["policies"]
    assert (
        first["policy"] == next(p["name"] for p in listing if p["default"]) and first["url"] == server
    )  # no --policy: the default
    assert first["episodes"] == 4 and first["seeds"] == [SEED, SEED + 3]
    assert first["action_horizon"] == 12  # the served policy's chunk length, from GET /policies
    assert 0.0 <= first["mean_max_reward"] <= 1.0 and 0.0 <= first["success_rate"] <= 1.0
    lo, hi = first["mean_max_reward_ci95"]
    assert lo <= first["mean_max_reward"] <= hi
    assert 0 < first["mean_length"] <= 60
    # one request per decision; a decision advances at most 2 envs by 12 steps
    assert first["requests"] == first["decisions"] >= math.ceil(4 * first["mean_length"] / (2 * 12))
    assert first["mean_request_latency_ms"] > 0 and first["wall_time_s"] > 0
    timing = {"wall_time_s", "mean_request_latency_ms", "p95_request_latency_ms"}
    assert {k: v for k, v in first.items() if k not in timing} == {k: v for k, v in second.items() if k not in timing}

    modules = imported_modules(second_proc.stderr)
    assert "pusht.rollout" in modules
    assert sorted(m for m in modules if m.split(".")[0] in FORBIDDEN_IMPORTS + ("imageio",)) == []

    from PIL import Image

    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["seed"] for r in records] == list(range(SEED, SEED + 4))
    assert {r["policy"] for r in records} == {first["policy"]} and len({r["card"] for r in records}) == 1
    assert records[0]["card"].startswith(f"{first['policy']}@")
    with Image.open(gif) as image:
        assert image.format == "GIF"
        assert image.n_frames == records[0]["length"] + 1  # every step, at the control rate: real speed
        assert image.info.get("duration") == 100  # 10 fps
        assert min(image.size) >= 64


@pytest.mark.slow
def test_e2e_server_errors_are_one_line(server):
    # the client asks GET /policies for the policy's chunk length first, so that is where an unknown policy shows
    line = assert_one_line_error(
        run_client("--url", server, "--api-key", API_KEY, "--policy", "nosuchpolicy", *SHORT),
        f"{server}/policies",
        "has no policy 'nosuchpolicy'",
    )
    assert "'flow'" in line  # what it has instead
    assert_one_line_error(run_client("--url", server, "--api-key", "wrong-key", *SHORT), "401")
    assert_one_line_error(run_client("--url", server, *SHORT), "401")
    assert_one_line_error(
        run_client("--url", server + "/no/such/path", "--api-key", API_KEY, *SHORT), "404", "/no/such/path/policies"
    )
    # an action horizon longer than the served chunks is refused before any episode
    assert_one_line_error(
        run_client("--url", server, "--api-key", API_KEY, "--action-horizon", "13", *SHORT),
        "--action-horizon 13",
        "chunks of 12 actions",
    )


@pytest.mark.slow
@pytest.mark.parametrize("policy", ["flow", "mse"])
def test_http_equals_in_process_evaluation_for_any_num_envs(server, models_dir, policy):
    """Same model and seeds: HTTP with 3 envs in lockstep plays exactly the episodes of in-process runs with 1 or 4."""
    import acting
    from clients.rollout import HttpPolicy
    from pusht.rollout import decision_seed, episode_seeds, run_episodes

    if not (models_dir / f"{policy}.onnx").exists():
        pytest.skip(f"no {policy} model served")
    in_process = acting.load_policy(models_dir / f"{policy}.onnx")
    seeds = episode_seeds(SEED, 4)
    sent: list[list[int]] = []

    http = HttpPolicy(server, policy, api_key=API_KEY)
    try:

        def recorded(states, row_seeds):
            sent.append(list(row_seeds))
            return http(states, row_seeds)

        over_http = run_episodes(recorded, seeds, num_envs=3, max_steps=60)
    finally:
        http.close()
    assert sent[0] == [decision_seed(s, 0) for s in seeds[:3]]  # the request names each row's seed
    for num_envs in (1, 4):
        local = run_episodes(acting.rollout_act(in_process), seeds, num_envs=num_envs, max_steps=60)
        assert over_http.episodes == local.episodes, num_envs


@pytest.mark.slow
def test_client_and_evaluate_write_the_same_episode_records(server, models_dir, tmp_path):
    """The two command lines, with different --num-envs, write identical per-episode files and scores."""
    flags = ["--episodes", "4", "--max-steps", "60", "--seed", str(SEED), "--no-progress"]
    cli = report_of(
        run_client(
            "--url",
            server,
            "--api-key",
            API_KEY,
            "--policy",
            "flow",
            "--num-envs",
            "3",
            "--out",
            str(tmp_path / "http.jsonl"),
            *flags,
        )
    )
    evaluated = subprocess.run(
        [
            sys.executable,
            "-m",
            "training.evaluate",
            "--model",
            str(models_dir / "flow.onnx"),
            "--num-envs",
            "2",
            "--out",
            str(tmp_path / "local.jsonl"),
            *flags,
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert evaluated.returncode == 0, evaluated.stderr
    reference = json.loads(evaluated.stdout.splitlines()[-1])
    for key in ("seeds", "mean_max_reward", "mean_max_reward_ci95", "success_rate", "success_rate_ci95", "mean_length"):
        assert cli[key] == reference[key], key
    assert (tmp_path / "http.jsonl").read_text() == (tmp_path / "local.jsonl").read_text()

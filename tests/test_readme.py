"""The README's first-hour commands, run as written in a fresh copy of the repo (shorter runs: SHORTER), and its results table."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SECTION = "## Your first hour"
# the only edits to the README's commands: a smaller scale and fewer episodes, and a free port
SHORTER = (
    ("--scale 0.05", "--scale 0.002"),
    ("--episodes 25 --num-envs 25", "--episodes 1 --num-envs 1"),
)


def readme_commands(text: str) -> list[str]:
    """The commands of the bash blocks in the README's first-hour section, continuation lines joined."""
    section = text.split(SECTION, 1)[1].split("\n## ", 1)[0]
    blocks = [block.split("\n", 1)[1] for block in section.split("```bash")[1:]]
    commands = []
    for block in blocks:
        body = block.split("```", 1)[0].replace("\\\n", " ")
        commands += [line.strip() for line in body.splitlines() if line.strip() and not line.startswith("#")]
    return commands


def _fresh_copy(dest: Path) -> Path:
    """The repo's files (tracked and untracked, not ignored) and a .venv that borrows the project's packages."""
    listed = (
        subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=REPO, capture_output=True, check=True)
        .stdout.decode()
        .split("\0")
    )
    for name in filter(None, listed):
        if (REPO / name).is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, dest / name)
    venv = dest / ".venv"
    (venv / "bin").mkdir(parents=True)
    shutil.copy2(REPO / ".venv" / "pyvenv.cfg", venv / "pyvenv.cfg")
    (venv / "bin" / "python").symlink_to(REPO / ".venv" / "bin" / "python")
    (venv / "lib").symlink_to(REPO / ".venv" / "lib")
    # fresh stamps: make then sees the extras installed and never runs pip into the borrowed packages
    (venv / ".serve-installed").touch()
    (venv / ".test-installed").touch()
    return dest


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _run(command: str, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-c", command], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_first_hour_commands_work_as_written(tmp_path):
    if not (REPO / ".venv" / "pyvenv.cfg").is_file():
        pytest.skip("needs the project's .venv (make test)")
    clone = _fresh_copy(tmp_path / "clone")
    port = _free_port()
    commands = []
    for command in readme_commands((REPO / "README.md").read_text()):
        for old, new in (*SHORTER, ("PORT=8001", f"PORT={port}"), ("127.0.0.1:8001", f"127.0.0.1:{port}")):
            command = command.replace(old, new)
        commands.append(command)
    recipe, serve, curl, rollout = commands
    env = {k: v for k, v in os.environ.items() if not k.startswith("PUSHT_")} | {"OMP_NUM_THREADS": "1"}

    done = _run(recipe, clone, env)
    assert done.returncode == 0 and "| imitation | train |" in done.stdout, done.stderr[-3000:]
    again = _run(recipe, clone, env)
    assert again.returncode == 0 and [line.split("|")[4].strip() for line in again.stdout.splitlines()[2:4]] == [
        "cached",
        "cached",
    ], again.stdout
    assert sorted(p.name for p in (clone / "runs" / "served").iterdir()) == [
        "flow.json",
        "flow.onnx",
        "flow.safetensors",
        "flow_rollout.gif",
    ]
    card = json.loads((clone / "runs" / "served" / "flow.json").read_text())

    dry_run = _run(serve.replace("make serve", "make -n serve"), clone, env).stdout
    assert "pip" not in dry_run and "-m service" in dry_run, dry_run
    server = subprocess.Popen(
        ["bash", "-c", serve],
        cwd=clone,
        env=env,
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while True:
            assert server.poll() is None, server.communicate()[0][-3000:]
            assert time.monotonic() < deadline, "the service never became ready"
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=2) as response:
                    if response.status == 200:
                        break
            except OSError:
                time.sleep(0.2)
        answer = _run(curl, clone, env)
        assert answer.returncode == 0, answer.stderr
        acted = json.loads(answer.stdout)
        assert acted["policy"] == "flow" and len(acted["actions"]) == 12
        scored = _run(rollout, clone, env)
        assert scored.returncode == 0, scored.stderr[-3000:]
        over_http = json.loads(scored.stdout.splitlines()[-1])
        in_process = card["heldout_evaluation"]["pusht"]
        assert over_http["seeds"] == in_process["seeds"] == [200000, 200000]
        assert over_http["mean_max_reward"] == in_process["mean_max_reward"]
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.communicate(timeout=30)


@pytest.mark.parametrize(
    "document, marker, args",
    [
        ("README.md", "results", []),
        ("models/README.md", "results", []),
        ("models/README.md", "stages", ["--stages"]),
    ],
)
def test_the_documents_tables_are_the_commands_output(document, marker, args):
    done = subprocess.run(
        [sys.executable, "scripts/results_table.py", *args], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    text = (REPO / document).read_text()
    start = next(line for line in text.splitlines() if line.startswith(f"<!-- {marker}: "))
    table = text.split(start + "\n", 1)[1].split(f"\n<!-- /{marker} -->", 1)[0]
    assert table == done.stdout.strip()


def test_the_documents_stay_short():
    assert (REPO / "README.md").stat().st_size <= 15_000
    assert (REPO / "models" / "README.md").stat().st_size <= 10_000

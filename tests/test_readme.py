"""The README's first-hour commands, run as written in a fresh copy of the repo (shorter runs: SHORTER)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SECTION = "## Your first hour"
# the only edits to the README's commands: fewer steps and episodes, and a free port
SHORTER = (
    ("--steps 5000", "--steps 40"),
    ("--eval-every 2500", "--eval-every 20"),
    ("--eval-episodes 50", "--eval-episodes 2"),
    ("--records-dir runs/records", "--records-dir runs/records --episodes 2"),
    ("--episodes 100 --num-envs 100", "--episodes 2 --num-envs 2"),
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
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=REPO, capture_output=True,
                            check=True).stdout.decode().split("\0")
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
    train, ship, serve, curl, rollout = commands
    env = {k: v for k, v in os.environ.items() if not k.startswith("PUSHT_")} | {"OMP_NUM_THREADS": "1"}

    done = _run(train, clone, env)
    assert done.returncode == 0 and "done: 40 steps" in done.stderr, done.stderr[-3000:]
    again = _run(train, clone, env)
    assert again.returncode == 2 and again.stderr.strip().endswith("or --overwrite to replace it"), again.stderr
    done = _run(ship, clone, env)
    assert done.returncode == 0, done.stderr[-3000:]
    shipped = [json.loads(line) for line in done.stdout.splitlines()]
    assert sorted(p.name for p in (clone / "runs" / "served").iterdir()) == [
        "first-flow.json", "first-flow.onnx", "first-flow.safetensors", "first-flow_rollout.gif"]

    dry_run = _run(serve.replace("make serve", "make -n serve"), clone, env).stdout
    assert "pip" not in dry_run and "-m service" in dry_run, dry_run
    server = subprocess.Popen(["bash", "-c", serve], cwd=clone, env=env, start_new_session=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
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
        assert acted["policy"] == "first-flow" and len(acted["actions"]) == 12
        scored = _run(rollout, clone, env)
        assert scored.returncode == 0, scored.stderr[-3000:]
        over_http = json.loads(scored.stdout.splitlines()[-1])
        in_process = next(line for line in shipped if line["checkpoint"] == "final" and line["env"] == "pusht")
        assert over_http["seeds"] == in_process["seeds"] == [200000, 200001]
        assert over_http["mean_max_reward"] == in_process["mean_max_reward"]
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.communicate(timeout=30)

"""training.train's run lifecycle for real: refused reuse, SIGTERM and SIGKILL mid-run, and --resume to the same weights."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from policies.checkpoint import load_card
from training.train import main

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "data" / "pusht_lowdim.zarr"
STEPS = 1500  # long enough that a signal sent after the first log record lands mid-run


def _args(out: Path, steps: int = STEPS, *extra: str) -> list[str]:
    # dropout and state noise stay on, so resuming must restore the RNG states too
    return [
        "--policy",
        "flow",
        "--name",
        "run",
        "--out-dir",
        str(out),
        "--data",
        str(DATA),
        "--steps",
        str(steps),
        "--batch-size",
        "32",
        "--log-every",
        "10",
        "--eval-every",
        "-1",
        "--threads",
        "1",
        "--no-progress",
        "--arch",
        '{"hidden_dims": [32, 32]}',
        *extra,
    ]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _weights(run_dir: Path) -> dict[str, torch.Tensor]:
    return load_file(str(run_dir / "last.safetensors"))


def _start(args: list[str]) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", "training.train", *args],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _wait_for(proc: subprocess.Popen, ready, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        assert time.monotonic() < deadline, "the run never got going"
        time.sleep(0.05)


def _records(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]


def _train_steps(run_dir: Path) -> list[int]:
    return [r["step"] for r in _records(run_dir) if r["type"] == "train"]


@pytest.fixture(scope="module")
def straight(tmp_path_factory) -> dict[str, torch.Tensor]:
    """The weights of the same run trained without interruption."""
    out = tmp_path_factory.mktemp("straight")
    assert main(_args(out)) == 0
    return _weights(out / "run")


def _assert_same(weights: dict[str, torch.Tensor], expected: dict[str, torch.Tensor]) -> None:
    assert weights.keys() == expected.keys()
    for key in expected:
        assert torch.equal(weights[key], expected[key]), f"{key} differs from the uninterrupted run"


@pytest.mark.slow
def test_sigterm_saves_within_seconds_and_resume_matches_an_uninterrupted_run(tmp_path, straight, capsys):
    run_dir = tmp_path / "run"
    proc = _start(_args(tmp_path))
    _wait_for(proc, lambda: (run_dir / "log.jsonl").is_file() and _train_steps(run_dir))
    sent = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    # generous: "within seconds" on a loaded 2-core machine; a run that waited would take far longer
    assert proc.returncode == 128 + signal.SIGTERM and time.monotonic() - sent < 20, err[-2000:]
    state = json.loads((run_dir / "state.json").read_text())
    stopped = load_card(run_dir / "last")
    assert 10 <= state["step"] < STEPS and not state["finished"]
    assert stopped["finished"] is False and stopped["steps"] == state["step"]
    assert f"at step {state['step']} of {STEPS}" in err and "--resume" in err

    assert main(_args(tmp_path, STEPS, "--resume")) == 0
    _assert_same(_weights(run_dir), straight)
    assert _train_steps(run_dir) == list(range(10, STEPS + 1, 10))  # no step logged twice
    assert load_card(run_dir / "last")["finished"] is True and not list(run_dir.glob("state-*"))
    assert main(_args(tmp_path, STEPS, "--resume")) == 2
    assert "already finished" in capsys.readouterr().err


@pytest.mark.slow
def test_sigkill_loses_at_most_the_steps_since_the_periodic_checkpoint(tmp_path, straight):
    run_dir = tmp_path / "run"
    proc = _start(_args(tmp_path, STEPS, "--checkpoint-every", "100"))
    _wait_for(proc, lambda: (run_dir / "state.json").is_file())
    proc.kill()
    proc.communicate(timeout=30)
    saved = json.loads((run_dir / "state.json").read_text())["step"]
    assert saved % 100 == 0 and load_card(run_dir / "last")["steps"] == saved
    assert main(_args(tmp_path, STEPS, "--checkpoint-every", "300", "--resume")) == 0  # the interval may change
    _assert_same(_weights(run_dir), straight)


@pytest.mark.slow
def test_sigterm_during_an_evaluation_does_not_wait_for_it(tmp_path):
    run_dir = tmp_path / "run"
    proc = _start(_args(tmp_path, STEPS, "--eval-every", "20", "--log-every", "20", "--eval-episodes", "200"))
    _wait_for(proc, lambda: (run_dir / "log.jsonl").is_file() and _train_steps(run_dir))
    proc.send_signal(signal.SIGTERM)  # the step-20 evaluation (200 episodes, several seconds) has begun
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    # the evaluation was cut short, not waited for: it never logged its result (no timing assumed)
    assert not [r for r in _records(run_dir) if r["type"] == "eval"]
    assert json.loads((run_dir / "state.json").read_text())["step"] == 20
    assert not (run_dir / "best.json").exists()


def test_reusing_a_name_is_refused_and_a_failed_start_changes_nothing(tmp_path, capsys):
    assert main(_args(tmp_path, 20)) == 0
    before = _snapshot(tmp_path)
    capsys.readouterr()
    refusals = [
        (_args(tmp_path, 20), "already exists: choose another --name, or pass --resume"),
        (_args(tmp_path, 20, "--resume"), "already finished at step 20"),
        (_args(tmp_path, 40, "--resume"), "changed: steps 20 -> 40"),
        (_args(tmp_path, 20, "--overwrite", "--data", str(tmp_path / "missing.zarr")), "missing.zarr"),
        (_args(tmp_path, 20, "--overwrite", "--arch", '{"width": 3}'), "width"),
    ]
    for args, message in refusals:
        assert main(args) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and message in err and "Traceback" not in err, err
        assert _snapshot(tmp_path) == before

    assert main(_args(tmp_path, 30, "--overwrite")) == 0
    assert load_card(tmp_path / "run" / "last")["steps"] == 30


def test_resume_refuses_a_changed_config(tmp_path, capsys):
    proc = _start(_args(tmp_path, STEPS, "--checkpoint-every", "10"))
    _wait_for(proc, lambda: (tmp_path / "run" / "state.json").is_file())
    proc.kill()
    proc.communicate(timeout=30)
    before = _snapshot(tmp_path)
    capsys.readouterr()
    assert main(_args(tmp_path, STEPS, "--resume", "--lr", "1e-3")) == 2
    err = capsys.readouterr().err
    assert "--resume needs the config it was started with; changed: lr 0.0003 -> 0.001" in err
    assert _snapshot(tmp_path) == before


@pytest.mark.slow
def test_a_weight_averaged_run_resumes_to_the_same_average(tmp_path):
    """--ema-decay: the average is resumable state too, so a stopped and resumed run ships the uninterrupted run's average."""
    average = ("--ema-decay", "0.99")
    assert main(_args(tmp_path / "straight", 600, *average)) == 0
    run_dir = tmp_path / "run"
    proc = _start(_args(tmp_path, 600, *average))
    _wait_for(proc, lambda: (run_dir / "log.jsonl").is_file() and _train_steps(run_dir))
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert json.loads((run_dir / "state.json").read_text())["step"] < 600
    assert main(_args(tmp_path, 600, "--resume", *average)) == 0
    _assert_same(_weights(run_dir), _weights(tmp_path / "straight" / "run"))

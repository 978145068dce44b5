"""The training entry point, run for real on the Push-T demonstrations with a tiny budget."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from policies.checkpoint import load_acting_policy, load_checkpoint
from training.config import TrainConfig, parse_config
from training.train import main, state_noise_std

REPO = Path(__file__).resolve().parent.parent
SHARED_DATA = REPO.parent / "shared" / "data" / "pusht" / "pusht_cchi_v7_replay.zarr"


def _dataset() -> Path:
    """The project's low-dimensional copy when it has been made, else the shared original."""
    own = REPO / "data" / "pusht_lowdim.zarr"
    return own if (own / "meta" / "episode_ends").exists() else SHARED_DATA


DATA = _dataset()


def _train_args(tmp_path: Path, name: str, *extra: str) -> list[str]:
    return [
        "--name",
        name,
        "--out-dir",
        str(tmp_path),
        "--data",
        str(DATA),
        "--threads",
        "1",
        "--no-progress",
        *extra,
    ]


def _records(run_dir: Path, kind: str) -> list[dict]:
    lines = (run_dir / "log.jsonl").read_text().splitlines()
    return [r for r in map(json.loads, lines) if r["type"] == kind]


@pytest.mark.slow
@pytest.mark.parametrize("policy", ["mse", "flow"])
def test_smoke_training_on_real_data(tmp_path, policy):
    args = _train_args(
        tmp_path,
        policy,
        "--policy",
        policy,
        "--steps",
        "300",
        "--batch-size",
        "64",
        "--log-every",
        "50",
        "--eval-every",
        "150",
        "--eval-episodes",
        "3",
        "--eval-max-steps",
        "24",
    )
    assert main(args) == 0
    run_dir = tmp_path / policy

    config = json.loads((run_dir / "config.json").read_text())
    assert config == parse_config(args).to_dict() | {"name": policy}
    assert (run_dir / "learning_curve.png").stat().st_size > 10_000

    train = _records(run_dir, "train")
    assert [r["step"] for r in train] == [50, 100, 150, 200, 250, 300]
    assert all(math.isfinite(r["loss"]) and r["ms_per_step"] > 0 for r in train)
    assert train[-1]["loss"] < 0.8 * train[0]["loss"], [r["loss"] for r in train]
    assert train[0]["lr"] > train[-1]["lr"] and train[0]["state_noise"] > train[-1]["state_noise"]

    evals = _records(run_dir, "eval")
    assert [r["step"] for r in evals] == [150, 300]
    for r in evals:
        assert r["seeds"] == [100000, 100001, 100002] and r["episodes"] == 3
        assert 0 <= r["mean_max_reward"] <= 1 and 0 <= r["success_rate"] <= 1

    last_policy, last = load_checkpoint(run_dir / "last")
    assert last["kind"] == policy and last["name"] == policy and last["steps"] == 300
    assert last["config"] == config and last["evaluation"]["step"] == 300
    assert last["num_parameters"] == sum(p.numel() for p in last_policy.parameters())
    assert last["wall_time_s"] > 0 and last["git_commit"] and last["finished"] is True
    _, best = load_checkpoint(run_dir / "best")
    assert best["evaluation"]["mean_max_reward"] == max(r["mean_max_reward"] for r in evals)
    assert best["steps"] == best["evaluation"]["step"]

    acting = load_acting_policy(run_dir / "last")
    with torch.no_grad():
        actions = acting(torch.tensor([[200.0, 300.0, 250.0, 250.0, 1.0]]), torch.zeros(1, 12, 2) if policy == "flow" else None)
    assert actions.shape == (1, 12, 2) and actions.min() >= 0 and actions.max() <= 512


@pytest.mark.slow
def test_two_process_ddp_matches_one_process(tmp_path):
    """Without dropout or noise, 2 ranks with half batches must follow the 1-process trajectory."""
    common = [
        "--policy",
        "mse",
        "--steps",
        "30",
        "--batch-size",
        "32",
        "--log-every",
        "10",
        "--eval-every",
        "-1",
        "--dropout",
        "0",
        "--state-noise-start",
        "0",
    ]
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m", "training.train"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        torchrun + _train_args(tmp_path, "ddp", *common), cwd=REPO, env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "world size: 2" in done.stderr
    assert main(_train_args(tmp_path, "single", *common)) == 0

    ddp_log = _records(tmp_path / "ddp", "train")
    assert [r["step"] for r in ddp_log] == [10, 20, 30]  # rank 0 alone writes
    ddp_policy, ddp_card = load_checkpoint(tmp_path / "ddp" / "last")
    single_policy, _ = load_checkpoint(tmp_path / "single" / "last")
    assert ddp_card["evaluation"] is None and not (tmp_path / "ddp" / "best.json").exists()
    for (name, a), (_, b) in zip(ddp_policy.state_dict().items(), single_policy.state_dict().items(), strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=0, msg=f"weight {name} differs between DDP and one process")
    single_log = _records(tmp_path / "single", "train")
    for d, s in zip(ddp_log, single_log, strict=True):
        assert d["loss"] == pytest.approx(s["loss"], rel=1e-4)


@pytest.mark.parametrize(
    "schedule, expected",
    [("linear", [0.05, 0.025, 0.0]), ("cosine", [0.05, 0.025, 0.0]), ("constant", [0.05, 0.05, 0.05])],
)
def test_state_noise_schedules(schedule, expected):
    cfg = TrainConfig(policy="mse", state_noise_schedule=schedule)
    got = [state_noise_std(cfg, p) for p in (0.0, 0.5, 1.0)]
    assert got == pytest.approx(expected, abs=1e-12)
    assert state_noise_std(cfg, 0.25) == pytest.approx(
        {"linear": 0.0375, "cosine": 0.025 * (1 + math.cos(math.pi / 4)), "constant": 0.05}[schedule]
    )


def test_command_line_reproduces_the_config():
    import shlex

    from training.config import command_line

    argv = [
        "--policy",
        "flow",
        "--name",
        "x",
        "--steps",
        "1234",
        "--pad-episode-end",
        "--no-progress",
        "--arch",
        '{"action_frame": "agent", "dropout": 0.0}',
        "--extra-data",
        "a.zarr,b.zarr",
        "--lr",
        "1e-4",
    ]
    config = parse_config(argv).to_dict()
    command = command_line(config)
    assert command.startswith("python -m training.train --policy flow --name x ")
    reparsed = parse_config(shlex.split(command)[3:]).to_dict()
    assert {k: v for k, v in reparsed.items() if k != "progress"} == {k: v for k, v in config.items() if k != "progress"}


def test_defaults_are_the_published_recipe():
    cfg = parse_config(["--policy", "flow"])
    assert (cfg.lr, cfg.weight_decay, cfg.batch_size, cfg.steps, cfg.dropout) == (3e-4, 1e-4, 128, 200_000, 0.1)
    assert (cfg.state_noise_start, cfg.state_noise_end, cfg.state_noise_schedule) == (0.05, 0.0, "linear")
    assert (cfg.eval_every, cfg.eval_episodes, cfg.eval_seed, cfg.eval_max_steps, cfg.action_horizon) == (
        10_000,
        100,
        100_000,
        300,
        12,
    )
    assert cfg.data == "data/pusht_lowdim.zarr"


def test_help_documents_every_field(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "--state-noise-schedule" in out and "std of Gaussian noise on normalized training states" in out


def test_help_shows_each_default_once(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "(default: None)" not in out and "(default: )" not in out and not re.search(r"\(default: [^)]*\) \(default:", out)
    assert "--steps STEPS optimizer steps (global batches) (default: 200000)" in out
    assert out.count("(default: POLICY-YYYYmmdd-HHMMSS)") == 1 and "--policy {mse,flow} policy kind: mse or flow --name" in out


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--policy", "diffusion"], "invalid choice"),
        (["--policy", "mse", "--batch-size", "0"], "batch_size must be >= 1"),
        (["--policy", "mse", "--arch", "[1, 2]"], "arch must be a JSON object"),
        (["--policy", "mse", "--action-horizon", "13"], "action_horizon"),
        (["--policy", "mse", "--steps", "ten"], "invalid int value"),
    ],
)
def test_bad_flags_are_named(capsys, flags, message):
    with pytest.raises(SystemExit) as exit_info:
        parse_config(flags)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_missing_data_and_bad_architecture_are_clear_errors(tmp_path, capsys):
    assert main(_train_args(tmp_path, "x", "--policy", "mse", "--eval-every", "-1", "--data", str(tmp_path / "nope.zarr"))) == 2
    assert "nope.zarr" in capsys.readouterr().err
    assert main(_train_args(tmp_path, "y", "--policy", "mse", "--eval-every", "-1", "--arch", '{"width": 3}')) == 2
    assert "width" in capsys.readouterr().err

"""training.run: refused name reuse, resume with the same config only, safe state files, stop signals."""

from __future__ import annotations

import json
import os
import random
import signal
from pathlib import Path

import numpy as np
import pytest
import torch

from training.run import Run, RunError, RunStopped, pack_optimizer, pack_rng, unpack_optimizer, unpack_rng

CONFIG = {"policy": "mse", "steps": 10, "progress": True}


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_fresh_run_saves_its_config_and_log(tmp_path, capsys):
    with Run.start(tmp_path, "a", CONFIG) as run:
        run.log({"type": "train", "step": 1, "loss": 0.5})
    assert json.loads((tmp_path / "a" / "config.json").read_text()) == CONFIG
    assert [json.loads(line) for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()] == run.records
    assert "config: " in capsys.readouterr().err


def test_an_existing_name_is_refused_and_left_untouched(tmp_path):
    Run.start(tmp_path, "a", CONFIG).close()
    before = _snapshot(tmp_path)
    with pytest.raises(RunError, match="already exists.*--resume.*--overwrite"):
        Run.start(tmp_path, "a", {**CONFIG, "steps": 99})
    for bad in ("", "..", "a/b"):
        with pytest.raises(RunError, match="plain folder name"):
            Run.start(tmp_path, bad, CONFIG)
    with pytest.raises(RunError, match="exclude"):
        Run.start(tmp_path, "a", CONFIG, resume=True, overwrite=True)
    assert _snapshot(tmp_path) == before


def test_overwrite_replaces_run_folders_only(tmp_path):
    Run.start(tmp_path, "a", CONFIG).save_state(3, {"w": torch.ones(2)})
    Run.start(tmp_path, "a", {**CONFIG, "steps": 5}, overwrite=True).close()
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["config.json", "log.jsonl"]
    (tmp_path / "precious").mkdir()
    (tmp_path / "precious" / "thesis.tex").write_text("years of work")
    with pytest.raises(RunError, match="not a run folder"):
        Run.start(tmp_path, "precious", CONFIG, overwrite=True)
    assert (tmp_path / "precious" / "thesis.tex").read_text() == "years of work"


def test_resume_returns_the_saved_state_and_cuts_the_log_back(tmp_path):
    run = Run.start(tmp_path, "a", CONFIG)
    for step in (1, 2, 3):
        run.log({"type": "train", "step": step})
    run.save_state(2, {"w": torch.arange(4.0), "step": torch.tensor([2])}, {"best": 0.25})
    run.save_state(3, {"w": torch.arange(4.0) + 1}, {"best": 0.5})
    run.log({"type": "train", "step": 4})  # after the last save: lost on resume
    run.close()
    assert sorted(p.name for p in (tmp_path / "a").glob("state*")) == ["state-000000003.safetensors", "state.json"]

    resumed = Run.start(tmp_path, "a", {**CONFIG, "progress": False}, resume=True)  # progress may change
    step, tensors, extra = resumed.load_state()
    assert step == 3 and extra == {"best": 0.5} and torch.equal(tensors["w"], torch.arange(4.0) + 1)
    assert [r["step"] for r in resumed.records] == [1, 2, 3]
    assert resumed.elapsed_s >= json.loads((tmp_path / "a" / "state.json").read_text())["elapsed_s"]
    resumed.log({"type": "train", "step": 10})
    resumed.finish()  # at the last logged step
    assert not list((tmp_path / "a").glob("state-*")) and json.loads((tmp_path / "a" / "state.json").read_text())["finished"]
    with pytest.raises(RunError, match="already finished at step 10"):
        Run.start(tmp_path, "a", CONFIG, resume=True)


def test_resume_refuses_another_config_and_a_missing_state(tmp_path):
    Run.start(tmp_path, "a", CONFIG).close()
    with pytest.raises(RunError, match="no resumable state"):
        Run.start(tmp_path, "a", CONFIG, resume=True)
    Run.start(tmp_path, "b", CONFIG).save_state(1, {"w": torch.zeros(1)})
    before = _snapshot(tmp_path)
    with pytest.raises(RunError, match="changed: steps 10 -> 20"):
        Run.start(tmp_path, "b", {**CONFIG, "steps": 20}, resume=True)
    with pytest.raises(RunError, match="nothing to resume"):
        Run.start(tmp_path, "c", CONFIG, resume=True)
    assert _snapshot(tmp_path) == before


def test_optimizer_and_rng_state_round_trip_exactly():
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 2)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    for _ in range(3):
        optimizer.zero_grad()
        model(torch.randn(4, 3)).square().sum().backward()
        optimizer.step()
    generator = torch.Generator().manual_seed(5)
    random.random(), np.random.rand(), torch.rand(1), torch.rand(1, generator=generator)
    opt_tensors, opt_extra = pack_optimizer(optimizer)
    rng = pack_rng({"perm": generator})
    json.dumps(opt_extra)  # the non-tensor part is JSON
    expected = (random.random(), np.random.rand(), np.random.randn(), torch.rand(3), torch.rand(2, generator=generator))

    twin = torch.optim.AdamW(torch.nn.Linear(3, 2).parameters(), lr=1e-3)
    unpack_optimizer(twin, opt_tensors, opt_extra)
    for a, b in zip(optimizer.state_dict()["state"].values(), twin.state_dict()["state"].values(), strict=True):
        assert all(torch.equal(a[k], b[k]) for k in a)
    other = torch.Generator().manual_seed(123)
    unpack_rng(rng, {"perm": other})
    got = (random.random(), np.random.rand(), np.random.randn(), torch.rand(3), torch.rand(2, generator=other))
    assert got[:3] == expected[:3] and torch.equal(got[3], expected[3]) and torch.equal(got[4], expected[4])


def test_sigterm_sets_stop_requested_and_interrupts_a_long_phase(tmp_path):
    previous = signal.getsignal(signal.SIGTERM)
    run = Run.start(tmp_path, "a", CONFIG)
    os.kill(os.getpid(), signal.SIGTERM)
    assert run.stop_requested and run.stop_signal == "SIGTERM" and run.exit_code() == 128 + signal.SIGTERM
    with pytest.raises(RunStopped):
        with run.interruptible():
            pass
    run.close()
    assert signal.getsignal(signal.SIGTERM) is previous

    run = Run.start(tmp_path, "b", CONFIG)
    with pytest.raises(RunStopped):
        with run.interruptible():
            os.kill(os.getpid(), signal.SIGINT)
            raise AssertionError("not interrupted")
    run.close()

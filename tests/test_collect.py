"""training.collect: a policy's successful episodes, in the demonstrations' zarr layout, on seeds clear of the held-out ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pusht.spec import HELD_OUT_SEED
from training.collect import CollectConfig, collect, main
from training.data import load_replay

REPO = Path(__file__).resolve().parent.parent
MSE = str(REPO / "models" / "mse.onnx")


def test_the_successful_episodes_are_written_and_the_failed_ones_left_out(tmp_path: Path) -> None:
    line = collect(CollectConfig(MSE, tmp_path / "mse.zarr", episodes=24, seed=10_000_000, num_envs=24))
    replay = load_replay(tmp_path / "mse.zarr")
    assert 0 < line["kept_episodes"] < 24 and line["success_rate"] == pytest.approx(line["kept_episodes"] / 24, abs=1e-4)
    assert replay.num_episodes == line["kept_episodes"] and replay.episode_ends[-1] == line["kept_frames"]

    assert replay.states.shape[1] == 5 and replay.actions.shape == (len(replay.states), 2)
    assert np.isfinite(replay.states).all()


def test_held_out_seeds_and_no_success_are_refused_with_one_line(tmp_path: Path, capsys) -> None:
    assert main(["--model", MSE, "--out", str(tmp_path / "x.zarr"), "--seed", str(HELD_OUT_SEED - 5), "--episodes", "10"]) == 2
    assert "overlap the held-out seeds" in capsys.readouterr().err
    with pytest.raises(ValueError, match="none of the 4 episodes succeeded"):
        collect(CollectConfig(MSE, tmp_path / "y.zarr", episodes=4, max_steps=2))
    assert not (tmp_path / "x.zarr").exists() and not (tmp_path / "y.zarr").exists()

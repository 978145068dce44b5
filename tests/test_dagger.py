"""Human-labelled steps in training (--human-weight, --policy-step-weight) and one tiny DAgger round on the real data and models."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from acting import load_policy, rollout_act
from service.viewer_episode import Episode, save_episode
from training.data import DEFAULT_DATASET, Replay, save_replay, training_set
from training.evaluate import evaluate_policy
from training import dagger, train

REPO = Path(__file__).resolve().parents[1]
# The outcome chooser shipped before the one-pass student: a fine-tuned flow whose base run's recipe DAgger reuses.
# (DAgger's flow-matching steps do not train the student's one-pass head, and its card's config is a distillation's.)
FLOW = REPO / "records" / "flow-outcome16-stretch" / "last"
pytestmark = pytest.mark.skipif(not (FLOW.with_suffix(".safetensors").is_file() and DEFAULT_DATASET.is_dir()),
                                reason="needs the chooser record and data/pusht_lowdim.zarr")


def corrected_episode(folder: Path, seed: int = 300000, policy_steps: int = 10, human_steps: int = 20, after: int = 10) -> Path:
    """A viewer recording made by the viewer's own code: the flow policy, a scripted 'human' takeover, the policy again."""
    act = rollout_act(load_policy(FLOW))
    episode = Episode(seed, "flow")
    for step in range(policy_steps + human_steps + after):
        if policy_steps <= step < policy_steps + human_steps:
            episode.step((float(episode.obs[2]), float(episode.obs[3])))  # towards the block
            continue
        if episode.needs_chunk():
            states, request_seed = episode.next_request()
            episode.set_chunk(act(states, [request_seed])[0])
        episode.step()
    return save_episode(folder, episode)


@pytest.fixture(scope="module")
def corrections(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("corrections")
    corrected_episode(folder)
    return folder


def test_windows_weigh_by_who_acted(corrections):
    store = next(corrections.glob("*.zarr"))
    plain = training_set(DEFAULT_DATASET, extra_data=(store,))
    assert plain.weights is None  # default weights: sampled exactly as before the option existed
    weighted = training_set(DEFAULT_DATASET, extra_data=(store,), human_weight=5.0, policy_step_weight=0.0)
    demo, extra = weighted.weights[: weighted.demo_windows], weighted.weights[weighted.demo_windows :]
    assert torch.all(demo == 1) and len(extra) == 40 - 12 + 1  # windows start at frames 0..28
    assert extra.tolist() == [0.0] * 10 + [5.0] * 19  # frames 10..29 were the human's
    padded = training_set(DEFAULT_DATASET, pad_end=True, extra_data=(store,), human_weight=2.0, policy_step_weight=0.5)
    assert padded.weights[padded.demo_windows :].tolist() == [0.5] * 10 + [2.0] * 20 + [0.5] * 10


def test_stores_without_labels_are_unweighted(tmp_path):
    replay = Replay(states=np.zeros((20, 5), np.float32), actions=np.zeros((20, 2), np.float32), episode_ends=np.array([20]))
    save_replay(tmp_path / "collected.zarr", replay)  # training.collect's stores have no data/human
    assert training_set(DEFAULT_DATASET, extra_data=(tmp_path / "collected.zarr",), human_weight=5.0, policy_step_weight=0.0).weights is None


def test_epoch_order_unweighted_is_the_old_permutation_and_weighted_follows_weights(corrections):
    data = training_set(DEFAULT_DATASET, extra_data=tuple(corrections.glob("*.zarr")))
    count = len(data) // 128 * 128
    old = torch.randperm(len(data), generator=torch.Generator().manual_seed(3))[:count]
    assert torch.equal(data.epoch_order(count, torch.Generator().manual_seed(3)), old)
    weighted = training_set(DEFAULT_DATASET, extra_data=tuple(corrections.glob("*.zarr")), human_weight=200.0, policy_step_weight=0.0)
    drawn = weighted.epoch_order(count, torch.Generator().manual_seed(3))
    extra = drawn[drawn >= weighted.demo_windows] - weighted.demo_windows
    assert len(extra) > 0 and bool(torch.all((extra >= 10) & (extra < 29)))  # only the human's windows, never weight 0
    # 19 windows at 200 beside ~23k at 1: about 14 % of the draws
    assert 0.10 < len(extra) / count < 0.18


def test_train_takes_the_weights_and_old_configs_stay_resumable(tmp_path, corrections):
    store = str(next(corrections.glob("*.zarr")))
    common = ["--policy", "mse", "--steps", "20", "--batch-size", "32", "--eval-every", "-1", "--no-progress",
              "--out-dir", str(tmp_path), "--extra-data", store, "--checkpoint-every", "0"]
    assert train.main([*common, "--name", "weighted", "--human-weight", "5", "--policy-step-weight", "0"]) == 0
    config = json.loads((tmp_path / "weighted" / "config.json").read_text())
    assert (config["human_weight"], config["policy_step_weight"]) == (5.0, 0.0)
    assert train.main([*common, "--name", "plain"]) == 0
    # at their defaults the weights are not written, so a run started before they existed resumes unchanged
    assert "human_weight" not in json.loads((tmp_path / "plain" / "config.json").read_text())
    with pytest.raises(SystemExit):
        train.main([*common, "--name", "bad", "--human-weight", "-1"])


def test_dagger_round_on_a_tiny_budget(tmp_path, corrections, capsys):
    argv = ["--model", str(FLOW), "--corrections", str(corrections), "--name", "round1", "--out-dir", str(tmp_path),
            "--steps", "5", "--batch-size", "16", "--episodes", "2", "--num-envs", "2", "--max-steps", "24", "--no-progress"]
    assert dagger.main(argv) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["corrections"] == {"folder": str(corrections), "stores": 1, "episodes": 1, "frames": 40, "human_frames": 20}
    base = evaluate_policy(load_policy(FLOW), episodes=2, seed=100000, max_steps=24).scores()
    assert line["before"]["mean_max_reward"] == base["mean_max_reward"]
    after_policy = load_policy(tmp_path / "round1" / "last")
    assert after_policy.kind == "flow"
    after = evaluate_policy(after_policy, episodes=2, seed=100000, max_steps=24).scores()
    assert line["after"]["mean_max_reward"] == after["mean_max_reward"]
    assert line["change"]["mean_max_reward"] == pytest.approx(after["mean_max_reward"] - base["mean_max_reward"])
    card = json.loads((tmp_path / "round1" / "last.json").read_text())
    assert card["finished"] and card["config"]["init"] == str(FLOW) and card["config"]["human_weight"] == 5.0
    assert card["config"]["pad_episode_end"] is True  # the base run's data recipe
    assert dagger.main(argv) == 2 and "already exists" in capsys.readouterr().err


def test_dagger_refuses_folders_without_corrections(tmp_path, capsys):
    argv = ["--model", str(FLOW), "--name", "r", "--out-dir", str(tmp_path / "runs"), "--no-progress", "--corrections"]
    assert dagger.main([*argv, str(tmp_path / "missing")]) == 2
    assert "no such folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert dagger.main([*argv, str(tmp_path / "empty")]) == 2
    assert "no .zarr stores" in capsys.readouterr().err
    corrected_episode(tmp_path / "policy-only", policy_steps=15, human_steps=0, after=0)
    assert dagger.main([*argv, str(tmp_path / "policy-only")]) == 2
    assert "no human-labelled steps" in capsys.readouterr().err


def test_dagger_refuses_a_one_pass_student(tmp_path, corrections, capsys):
    student = REPO / "records" / "distill-mc16-shared192" / "student"
    argv = ["--model", str(student), "--name", "r", "--out-dir", str(tmp_path / "runs"), "--no-progress", "--corrections", str(corrections)]
    assert dagger.main(argv) == 2
    assert "is a one-pass student" in capsys.readouterr().err and not (tmp_path / "runs").exists()

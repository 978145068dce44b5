"""Noise-space fine-tuning: the steering starts as the identity, PPO's pieces are right, a real short run exports and acts."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from pusht.env import PushTEnv
from training.checkpoint import load_acting_policy, load_card, load_checkpoint
from training.chunk_env import ChunkVectorEnv
from training.export import export_onnx
from training.finetune import finetune
from training.finetune_config import FinetuneConfig, parse_config
from training.policies import ActingPolicy, build_policy
from training.ppo import Rollout, gae

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "records" / "flow-agentframe-padend-150k-noise0.3" / "last"  # the plain flow that fine-tuning starts from


def _steered_from_shipped(steering_dims=(32, 32)):
    base, card = load_checkpoint(SHIPPED)
    arch = {**card["architecture"], "steering_dims": list(steering_dims)}
    policy = build_policy("flow", **arch)
    policy.load_state_dict(base.state_dict(), strict=False)
    policy.normalizer.set(base.normalizer)
    return base, policy, card


def test_fresh_steering_acts_exactly_as_its_base_flow() -> None:
    base, steered, card = _steered_from_shipped()
    torch.manual_seed(0)
    states = torch.rand(16, 5) * torch.tensor([400.0, 400.0, 300.0, 300.0, 6.0]) + torch.tensor([50.0, 50.0, 100.0, 100.0, 0.0])
    noise = torch.randn(16, 12, 2)
    with torch.no_grad():
        a = ActingPolicy(base.eval())(states, noise)
        b = ActingPolicy(steered.eval())(states, noise)
    assert torch.equal(a, b)
    # ...and a trained steering does move the actions
    with torch.no_grad():
        steered.steering.mean_head.bias.fill_(0.5)
        c = ActingPolicy(steered.eval())(states, noise)
    assert (c - a).abs().max() > 1.0


def test_steering_log_prob_is_the_gaussian_density_of_the_start() -> None:
    _, steered, _ = _steered_from_shipped()
    enc = torch.randn(4, 6)
    x0 = torch.randn(4, 12, 2)
    with torch.no_grad():
        steered.steering.log_std.fill_(-0.3)
        logp, entropy = steered.steering.log_prob(enc, x0, 0.6)
    std = 0.6 * np.exp(-0.3)
    expected = (-0.5 * (x0.numpy() / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi)).sum(axis=(1, 2))
    np.testing.assert_allclose(logp.numpy(), expected, rtol=1e-5)
    np.testing.assert_allclose(entropy.numpy(), 24 * (0.5 + 0.5 * np.log(2 * np.pi) + np.log(std)), rtol=1e-5)


def test_steering_dims_are_validated() -> None:
    with pytest.raises(ValueError, match="steering_dims"):
        build_policy("flow", steering_dims=[0])
    with pytest.raises(ValueError, match="steering_dims"):
        build_policy("flow", steering_dims="256")
    assert "steering_dims" not in build_policy("flow").architecture  # cards of unsteered flows are unchanged


def test_gae_matches_a_hand_computation() -> None:
    # one env, three decisions; the episode ends at the second one
    rollout = Rollout(
        encoded=torch.zeros(3, 1, 6), time_fraction=torch.zeros(3, 1), x0=torch.zeros(3, 1, 12, 2),
        log_prob=torch.zeros(3, 1), value=torch.tensor([[0.5], [0.2], [0.4]]), reward=torch.tensor([[1.0], [2.0], [0.5]]),
        done=torch.tensor([[0.0], [1.0], [0.0]]), last_value=torch.tensor([0.3]),
    )
    g, lam = 0.9, 0.8
    d2 = 0.5 + g * 0.3 - 0.4
    d1 = 2.0 - 0.2  # ended: no bootstrap
    d0 = 1.0 + g * 0.2 - 0.5
    expected = [d0 + g * lam * d1, d1, d2]
    adv, ret = gae(rollout, g, lam)
    np.testing.assert_allclose(adv[:, 0].numpy(), expected, rtol=1e-6)
    np.testing.assert_allclose(ret.numpy(), (adv + rollout.value).numpy())


def test_chunk_env_matches_the_plain_env_and_restarts_on_the_next_seed() -> None:
    envs = ChunkVectorEnv(2, seed_start=10_000_000, max_steps=24)
    reference = PushTEnv(render_mode=None)
    obs, _ = reference.reset(seed=10_000_000)
    np.testing.assert_array_equal(envs.obs[0], obs)
    chunk = np.tile(np.array([[256.0, 256.0]], dtype=np.float32), (2, 12, 1))
    first = envs.step(chunk)
    for action in chunk[0]:
        obs, reward, *_ = reference.step(action)
    np.testing.assert_array_equal(envs.obs[0], obs)
    assert first.reward_end[0] == reward and not first.done.any()
    second = envs.step(chunk)  # 24 steps: the step limit ends both episodes; they restart on seeds +2 and +3
    assert second.done.all() and envs.episodes_started == 4
    np.testing.assert_array_equal(envs.obs[1], PushTEnv(render_mode=None).reset(seed=10_000_003)[0])


def test_config_is_validated_and_reproducible() -> None:
    with pytest.raises(SystemExit):
        parse_config(["--num-envs", "0"])
    with pytest.raises(SystemExit):
        parse_config(["--algo", "dqn"])
    cfg = FinetuneConfig(iterations=7, name="x", algo="qselect")
    assert cfg.command() == "python -m training.finetune --algo qselect --init records/flow-agentframe-padend-150k-noise0.3/last --name x --iterations 7"
    assert parse_config(cfg.command().split()[3:]) == cfg


def test_help_runs() -> None:
    out = subprocess.run([sys.executable, "-m", "training.finetune", "--help"], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode == 0 and "--success-bonus" in out.stdout and "default: 1.0" in out.stdout


def _tiny(tmp_path: Path, **overrides) -> FinetuneConfig:
    settings = dict(name="ft", out_dir=str(tmp_path), iterations=3, num_envs=8, rollout_decisions=3, eval_every=3, eval_episodes=4,
                    log_every=1, minibatch=12, batch_size=12, learning_starts=12, steering_dims="32", critic_dims="32",
                    progress=False, lr=1e-2, label_envs=2, updates_per_decision=2, outcome_dims="32", candidates=4)
    return FinetuneConfig(**{**settings, **overrides})


@pytest.mark.parametrize("algo, learned", [("ppo", "steering"), ("qselect", "selector"), ("outcome", "outcome")])
def test_a_short_real_run_saves_a_flow_that_exports_and_acts(tmp_path: Path, algo: str, learned: str) -> None:
    run = finetune(_tiny(tmp_path, algo=algo, label_candidates=4 if algo == "qselect" else 0)).dir
    card = load_card(run / "last")
    key = {"ppo": "steering_dims", "qselect": "selector_dims", "outcome": "outcome_dims"}[algo]
    assert card["architecture"][key] == [32] and card["finished"] and card["steps"] == 3
    assert card["evaluation"]["seeds"] == [400000, 400003] and card["reproduce"]["finetune"].startswith("python -m training.finetune")
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if r["type"] == "train"] == [1, 2, 3]
    assert [r["step"] for r in records if r["type"] == "eval"] == [0, 3]
    assert (run / "learning_curve.png").stat().st_size > 0
    assert json.loads((run / "state.json").read_text())["finished"] and not list(run.glob("state-*"))
    # the frozen flow's weights are the shipped ones; the learned part moved
    tuned, _ = load_checkpoint(run / "last")
    base, _ = load_checkpoint(SHIPPED)
    for name, tensor in base.state_dict().items():
        assert torch.equal(tensor, tuned.state_dict()[name]), name
    fresh = build_policy("flow", **card["architecture"])
    moved = [k for k, v in tuned.state_dict().items() if k.startswith(learned + ".") and not torch.equal(v, fresh.state_dict()[k])]
    assert moved
    # export and act: ONNX equals torch, with the contract's inputs
    onnx_path = run / "last.onnx"
    export_onnx(run / "last", onnx_path)
    acting = load_acting_policy(run / "last")
    rng = np.random.default_rng(0)
    states = (rng.uniform(100, 400, (5, 5)) * [1, 1, 1, 1, 0.01]).astype(np.float32)
    noise = rng.standard_normal((5, 12, 2)).astype(np.float32)
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    assert sorted(i.name for i in session.get_inputs()) == ["noise", "state"]
    got = session.run(["actions"], {"state": states, "noise": noise})[0]
    with torch.no_grad():
        want = acting(torch.from_numpy(states), torch.from_numpy(noise)).numpy()
    np.testing.assert_allclose(got, want, atol=1e-3)


def test_the_selector_picks_the_candidate_its_critic_scores_highest() -> None:
    _, steered, card = _steered_from_shipped()
    arch = {**card["architecture"], "selector_dims": [16], "selector_candidates": 8}
    policy = build_policy("flow", **arch)
    selector = policy.selector
    enc, noise = torch.randn(6, 6), torch.randn(6, 12, 2)
    with torch.no_grad():
        chosen = selector(enc, noise, 0.6)
        cands = selector.candidates_of(noise, 0.6)
        scores = torch.stack([selector.value(enc, cands[:, k]) for k in range(8)], dim=1)
    for b in range(6):
        assert torch.equal(chosen[b], cands[b, scores[b].argmax()])
    assert torch.allclose(cands[:, 0], 0.6 * noise)  # candidate 0 is the plain flow's own start


def test_lookahead_predicts_a_real_step_and_leaves_the_env_alone() -> None:
    envs = ChunkVectorEnv(1, seed_start=10_000_000)
    rng = np.random.default_rng(1)
    block = envs.obs[0, 2:4]
    chunks = (block + rng.normal(0, 30, (3, 12, 2))).astype(np.float32)
    before = envs.obs.copy()
    ahead = envs.lookahead(0, chunks)
    np.testing.assert_array_equal(envs.obs, before)
    real = envs.step(chunks[1:2])
    np.testing.assert_allclose(ahead.next_obs[1], envs.obs[0], atol=1e-6)
    assert abs(ahead.reward_end[1] - real.reward_end[0]) < 1e-9


def test_a_reused_name_is_refused_and_a_stopped_run_resumes(tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "training.finetune", "--name", "r", "--out-dir", str(tmp_path), "--num-envs", "4",
           "--rollout-decisions", "1", "--iterations", "300", "--eval-every", "0", "--checkpoint-every", "50", "--log-every", "1",
           "--steering-dims", "16", "--critic-dims", "16", "--minibatch", "4", "--no-progress"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log = tmp_path / "r" / "log.jsonl"
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and not (log.is_file() and log.read_text().count('"train"') >= 2):
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    state = json.loads((tmp_path / "r" / "state.json").read_text())
    stopped_at = state["step"]
    assert not state["finished"] and 2 <= stopped_at < 300
    assert not load_card(tmp_path / "r" / "last")["finished"]

    again = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and "already exists" in again.stderr and "Traceback" not in again.stderr
    changed = subprocess.run([*cmd, "--resume", "--lr", "0.1"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert changed.returncode == 2 and "lr" in changed.stderr and json.loads((tmp_path / "r" / "state.json").read_text()) == state

    done = subprocess.run([*cmd, "--resume"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["step"] for r in records if r["type"] == "train"] == list(range(1, 301))  # no step lost or repeated
    assert [r["step"] for r in records if r["type"] == "resume"] == [stopped_at]
    assert load_card(tmp_path / "r" / "last")["finished"]


def test_lookahead_teacher_writes_episodes_in_the_dataset_layout(tmp_path: Path) -> None:
    from training.data import load_replay
    from training.lookahead_collect import main as collect_main

    out = tmp_path / "t.zarr"
    assert collect_main(["--episodes", "3", "--num-envs", "3", "--candidates", "4", "--seed", "3000000", "--out", str(out)]) == 0
    replay = load_replay(out)
    assert len(replay.episode_ends) == 3 and replay.states.shape[1] == 5 and replay.actions.shape[1] == 2
    # each episode starts at the reset state of one of the seeds (in the order they finished)
    firsts = replay.states[np.concatenate([[0], replay.episode_ends[:-1]])]
    resets = np.stack([PushTEnv(render_mode=None).reset(seed=s)[0] for s in range(3_000_000, 3_000_003)]).astype(np.float32)
    assert sorted(map(tuple, firsts.round(3))) == sorted(map(tuple, resets.round(3)))
    with pytest.raises(SystemExit):
        collect_main(["--episodes", "3", "--seed", "199999", "--out", str(out)])  # overlaps the held-out seeds

"""Fine-tuning beyond imitation: the chunk-level env matches the real one, a real short outcome fit exports and acts, a stopped run resumes."""

from __future__ import annotations

import dataclasses
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

from policies.checkpoint import load_acting_policy, load_card, load_checkpoint
from policies.factory import build_policy
from pusht.env import PushTEnv
from training.chunk_env import ChunkVectorEnv
from training.export import export_onnx
from training.finetune import finetune
from training.finetune_config import FinetuneConfig, parse_config

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "models" / "flow"  # the plain flow that fine-tuning starts from


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
    with pytest.raises(SystemExit):
        parse_config([])  # --init is required
    cfg = FinetuneConfig(iterations=7, name="x", init=str(SHIPPED))
    assert cfg.command() == f"python -m training.finetune --init {SHIPPED} --name x --iterations 7"
    assert parse_config(cfg.command().split()[3:]) == cfg


def test_help_runs() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "training.finetune", "--help"], capture_output=True, text=True, cwd=REPO, timeout=120
    )
    assert out.returncode == 0 and "--stretches" in out.stdout and "default: 0.2" in out.stdout


def _tiny(tmp_path: Path, **overrides) -> FinetuneConfig:
    settings = dict(
        name="ft",
        out_dir=str(tmp_path),
        iterations=3,
        num_envs=8,
        rollout_decisions=3,
        eval_every=3,
        eval_episodes=4,
        log_every=1,
        batch_size=12,
        learning_starts=12,
        init=str(SHIPPED),
        progress=False,
        label_envs=2,
        updates_per_decision=2,
        outcome_dims="32",
        candidates=4,
    )
    return FinetuneConfig(**{**settings, **overrides})


def test_a_short_real_run_saves_a_flow_that_exports_and_acts(tmp_path: Path) -> None:
    run = finetune(_tiny(tmp_path)).dir
    card = load_card(run / "last")
    assert card["architecture"]["outcome_dims"] == [32] and card["finished"] and card["steps"] == 3
    assert card["evaluation"]["seeds"] == [400000, 400003] and card["reproduce"]["finetune"].startswith(
        "python -m training.finetune"
    )
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
    moved = [k for k, v in tuned.state_dict().items() if k.startswith("outcome.") and not torch.equal(v, fresh.state_dict()[k])]
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
    cmd = [
        sys.executable,
        "-m",
        "training.finetune",
        "--init",
        str(SHIPPED),
        "--name",
        "r",
        "--out-dir",
        str(tmp_path),
        "--num-envs",
        "4",
        "--rollout-decisions",
        "1",
        "--iterations",
        "300",
        "--eval-every",
        "0",
        "--checkpoint-every",
        "50",
        "--log-every",
        "1",
        "--outcome-dims",
        "16",
        "--candidates",
        "2",
        "--label-envs",
        "1",
        "--batch-size",
        "4",
        "--updates-per-decision",
        "1",
        "--no-progress",
    ]
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
    changed = subprocess.run([*cmd, "--resume", "--critic-lr", "0.1"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert (
        changed.returncode == 2
        and "critic_lr" in changed.stderr
        and json.loads((tmp_path / "r" / "state.json").read_text()) == state
    )

    done = subprocess.run([*cmd, "--resume"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["step"] for r in records if r["type"] == "train"] == list(range(1, 301))  # no step lost or repeated
    assert [r["step"] for r in records if r["type"] == "resume"] == [stopped_at]
    assert load_card(tmp_path / "r" / "last")["finished"]


def test_a_value_fit_on_an_outcome_chooser_ranks_by_value_and_exports(tmp_path: Path) -> None:
    """--algo value starts from an outcome chooser (kept as it is), labels its own episodes and fits the value; the
    chooser then ranks by it, in torch and ONNX alike, and the chooser's other weights do not move."""
    from training.value_fit import value_labels

    chooser = finetune(_tiny(tmp_path, iterations=1, eval_every=0)).dir / "last"
    with pytest.raises(ValueError, match="starts from an outcome chooser"):
        finetune(_tiny(tmp_path, name="bad", algo="value"))
    cfg = _tiny(
        tmp_path,
        name="v",
        algo="value",
        init=str(chooser),
        iterations=2,
        eval_every=2,
        value_dims="16",
        value_episodes=3,
        value_max_steps=24,
        value_updates=5,
        value_tau=10.0,
        candidates=16,
    )
    run = finetune(cfg).dir
    card = load_card(run / "last")
    arch = card["architecture"]
    assert arch["value_dims"] == [16] and arch["outcome_dims"] == [32] and arch["outcome_candidates"] == 4  # as the init's
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    train = [r for r in records if r["type"] == "train"]
    assert [r["labels"] for r in train] == [72, 144]  # 3 episodes x 24 steps (none succeeds at random) per iteration
    tuned, _ = load_checkpoint(run / "last")
    base, _ = load_checkpoint(chooser)
    for name, tensor in base.state_dict().items():
        assert torch.equal(tensor, tuned.state_dict()[name]), name
    assert tuned.outcome.value is not None and tuned.outcome.rank_by_value
    # before its first fit the value is random: the first round's episodes are the outcome chooser's own
    from training.outcome_fit import FlowChooser
    from training.value_fit import ValueFit

    agent = FlowChooser(*load_checkpoint(chooser), cfg)
    ValueFit(agent, cfg, torch.Generator())
    assert agent.policy.outcome.value is not None and not agent.policy.outcome.rank_by_value
    export_onnx(run / "last", run / "last.onnx")
    acting = load_acting_policy(run / "last")
    rng = np.random.default_rng(0)
    states = (rng.uniform(100, 400, (5, 5)) * [1, 1, 1, 1, 0.01]).astype(np.float32)
    noise = rng.standard_normal((5, 12, 2)).astype(np.float32)
    session = ort.InferenceSession(str(run / "last.onnx"), providers=["CPUExecutionProvider"])
    got = session.run(["actions"], {"state": states, "noise": noise})[0]
    with torch.no_grad():
        want = acting(torch.from_numpy(states), torch.from_numpy(noise)).numpy()
    np.testing.assert_allclose(got, want, atol=1e-3)

    class Episodes:  # two episodes of 3 steps: one succeeds at its end, one fails
        episodes = [type("E", (), {"seed": 1, "success": True})(), type("E", (), {"seed": 2, "success": False})()]
        trajectories = [type("T", (), {"seed": s, "states": np.zeros((3, 5))})() for s in (1, 2)]

    _, values = value_labels(Episodes, tau=10.0)
    np.testing.assert_allclose(values, [np.exp(-0.3), np.exp(-0.2), np.exp(-0.1), 0, 0, 0], rtol=1e-6)


def test_a_dagger_fit_teaches_a_plain_flow_the_choosers_picks(tmp_path: Path) -> None:
    """--algo dagger starts a plain flow from an outcome chooser's flow weights, labels every decision of its episodes
    with the chooser's pick (the chooser playing all of the first round) and fits the student on them; the checkpoint
    is that plain flow, whose noise changes its actions, and the chooser is untouched."""
    from training.dagger_fit import DaggerFit
    from training.outcome_fit import FlowChooser

    with pytest.raises(ValueError, match="--algo dagger starts from an outcome chooser"):
        finetune(_tiny(tmp_path, name="bad", algo="dagger"))
    chooser = finetune(_tiny(tmp_path, iterations=1, eval_every=0)).dir / "last"
    settings = dict(name="d", algo="dagger", init=str(chooser), iterations=2, eval_every=2, num_envs=3)
    cfg = _tiny(tmp_path, **settings, dagger_episodes=3, dagger_updates=4, dagger_teacher_share=0.5)
    run = finetune(cfg).dir
    card = load_card(run / "last")
    assert card["kind"] == "flow" and card["finished"] and card["architecture"].get("outcome_dims") is None
    train = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    train = [r for r in train if r["type"] == "train"]
    assert [r["teacher_share"] for r in train] == [1.0, 0.5] and [r["episodes"] for r in train] == [3, 6]
    assert 0 < train[0]["labels"] < train[1]["labels"]
    student, _ = load_checkpoint(run / "last")
    teacher, _ = load_checkpoint(chooser)
    flow_weights = {k: v for k, v in teacher.state_dict().items() if not k.startswith("outcome.")}
    assert set(student.state_dict()) == set(flow_weights)
    assert any(not torch.equal(v, student.state_dict()[k]) for k, v in flow_weights.items() if "normalizer" not in k)
    # the labels are the chooser's picks, in the student's (= the chooser's) normalized units
    agent = FlowChooser(teacher, load_card(chooser), cfg)
    fit = DaggerFit(agent, cfg, torch.Generator().manual_seed(0))
    states = np.array([[200, 300, 250, 250, 0.5], [100, 100, 300, 300, 1.0]], dtype=np.float32)
    fit._labelling_act(share=1.0)(states, [5, 6])
    from pusht.seeding import row_noise

    with torch.no_grad():
        picked = teacher.sample_actions(teacher.policy_state(torch.from_numpy(states)), torch.from_numpy(row_noise([5, 6])))
    torch.testing.assert_close(fit.replay.data["x0"][:2], picked.flatten(1))
    # a resumed fit takes back the student, its optimizer, the labels, the episodes played and who plays next
    fit.episodes = 3
    fit._fit()
    tensors, extra = fit.state()
    resumed = DaggerFit(FlowChooser(teacher, load_card(chooser), cfg), cfg, torch.Generator())
    resumed.load_state(tensors, json.loads(json.dumps(extra)))
    assert resumed.episodes == 3 and resumed.replay.size == 2 and resumed.rng.random() == fit.rng.random()
    for name, tensor in fit.trained.policy.state_dict().items():
        assert torch.equal(tensor, resumed.trained.policy.state_dict()[name]), name
    assert resumed.opt.state_dict()["state"].keys() == fit.opt.state_dict()["state"].keys()
    acting = load_acting_policy(run / "last")
    with torch.no_grad():
        one, two = (acting(torch.from_numpy(states), torch.from_numpy(row_noise([s, s + 1]))) for s in (1, 7))
    assert not torch.allclose(one, two)
    # --dagger-teacher: the student is --init (here the student above), taught from its first round on at its own
    # states, each fit's rate annealed to 0
    more = _tiny(tmp_path, **settings | {"name": "d2", "init": str(run / "last"), "iterations": 1}, dagger_teacher=str(chooser))
    more = dataclasses.replace(more, dagger_episodes=3, dagger_updates=4, dagger_teacher_share=0.0, dagger_lr_schedule="cosine")
    again = DaggerFit(FlowChooser(teacher, load_card(chooser), more), more, torch.Generator().manual_seed(0))
    for name, tensor in student.state_dict().items():
        assert torch.equal(tensor, again.trained.policy.state_dict()[name]), name
    record = again.iterate([], [])
    assert (
        record["teacher_share"] == 0.0
        and record["episodes"] == 3
        and again.opt.param_groups[0]["lr"] == pytest.approx(more.dagger_lr * 0.5 * (1 + np.cos(np.pi * 3 / 4)))
    )  # the last of the 4 updates
    assert load_card(finetune(more).dir / "last")["teacher"] == str(chooser)
    with pytest.raises(ValueError, match="a plain flow of the chooser's flow architecture"):
        DaggerFit(agent, dataclasses.replace(more, init=str(chooser)), torch.Generator())


def test_a_dagger_student_grows_into_wider_layers_and_starts_as_the_same_function(tmp_path: Path) -> None:
    """`dagger_student_dims` grows the student's first weights into wider layers: before its first fit it computes
    what the flow it came from computes; fewer or narrower layers are refused with the setting's name."""
    from training.dagger_fit import DaggerFit
    from training.outcome_fit import FlowChooser

    chooser = finetune(_tiny(tmp_path, iterations=1, eval_every=0)).dir / "last"
    teacher, card = load_checkpoint(chooser)
    narrow = card["architecture"]["hidden_dims"]
    wide = [2 * w for w in narrow[:-1]] + [narrow[-1] + 3]
    cfg = _tiny(tmp_path, name="w", algo="dagger", init=str(chooser), dagger_student_dims=",".join(map(str, wide)))
    grown = DaggerFit(FlowChooser(teacher, card, cfg), cfg, torch.Generator()).trained.policy
    plain = DaggerFit(FlowChooser(teacher, card, cfg), dataclasses.replace(cfg, dagger_student_dims=""), torch.Generator())
    assert grown.architecture["hidden_dims"] == wide and plain.trained.policy.architecture["hidden_dims"] == narrow
    states = torch.tensor([[200, 300, 250, 250, 0.5], [100, 100, 300, 300, 1.0]])
    x_t, t = torch.randn(2, grown.horizon, grown.action_dim, generator=torch.Generator().manual_seed(1)), torch.rand(2)
    with torch.no_grad():
        torch.testing.assert_close(
            grown(grown.policy_state(states), x_t, t), plain.trained.policy(grown.policy_state(states), x_t, t)
        )
    for bad in (narrow[:-1], [*narrow[:-1], narrow[-1] - 1]):
        with pytest.raises(ValueError, match="dagger_student_dims"):
            DaggerFit(
                FlowChooser(teacher, card, cfg), dataclasses.replace(cfg, dagger_student_dims=",".join(map(str, bad))), None
            )
    with pytest.raises(ValueError, match="dagger_student_dims is a setting of --algo dagger"):
        _tiny(tmp_path, dagger_student_dims="64")
    with pytest.raises(ValueError, match="dagger_student_dims must be comma-separated"):
        _tiny(tmp_path, algo="dagger", dagger_student_dims="64,wide")


def test_a_dagger_run_keeps_its_labels_and_a_later_run_starts_its_pool_with_them(tmp_path: Path) -> None:
    """A finished dagger run writes labels.safetensors (every label of its pool); `dagger_labels` puts them in a later
    run's pool before its first round; a file that is not such labels, or was labelled under another normalization,
    is refused with its name."""
    from training.dagger_fit import DaggerFit
    from training.outcome_fit import FlowChooser

    chooser = finetune(_tiny(tmp_path, iterations=1, eval_every=0)).dir / "last"
    settings = dict(name="d", algo="dagger", init=str(chooser), iterations=1, eval_every=0, num_envs=3)
    cfg = _tiny(tmp_path, **settings, dagger_episodes=3, dagger_updates=2)
    run = finetune(cfg).dir
    labelled = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if '"train"' in line][-1]["labels"]
    teacher, card = load_checkpoint(chooser)
    later = dataclasses.replace(cfg, name="d2", dagger_labels=str(run / "labels.safetensors"))
    fit = DaggerFit(FlowChooser(teacher, card, later), later, torch.Generator().manual_seed(0))
    assert fit.replay.size == labelled > 0
    with pytest.raises(ValueError, match="is a setting of --algo dagger"):
        _tiny(tmp_path, dagger_labels=str(run / "labels.safetensors"))
    (tmp_path / "junk.safetensors").write_bytes(b"not labels")
    with pytest.raises(ValueError, match="junk.safetensors: not a readable labels file"):
        DaggerFit(
            FlowChooser(teacher, card, later),
            dataclasses.replace(later, dagger_labels=str(tmp_path / "junk.safetensors")),
            torch.Generator(),
        )
    fit.trained.normalization = {**fit.trained.normalization, "other": 1}
    fit.save_labels(tmp_path / "other.safetensors")
    with pytest.raises(ValueError, match="another normalization"):
        DaggerFit(
            FlowChooser(teacher, card, later),
            dataclasses.replace(later, dagger_labels=str(tmp_path / "other.safetensors")),
            torch.Generator(),
        )

"""Few-step distillation: a real short run (the shipped chooser's teacher, DAgger rounds included) saves a plain-flow
student whose card and export carry its step count."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from training.checkpoint import load_acting_policy, load_card, load_checkpoint
from training.distill import DistillConfig, distill, outcome_term, student_of
from training.distill_data import PAIRS_FILE, Pairs
from training.export import export_onnx

REPO = Path(__file__).resolve().parent.parent
TEACHER = REPO / "records" / "flow-outcome16-stretch" / "last"
"""the many-step teacher of the shipped flow: the imitation flow with its stretched outcome chooser"""


def test_a_short_distillation_with_dagger_rounds_moves_the_student_toward_the_teachers_map(tmp_path: Path) -> None:
    cfg = DistillConfig(teacher=str(TEACHER), name="d", out_dir=str(tmp_path), pairs=200, teacher_episodes=2, rounds=1,
                        round_episodes=2, steps=40, batch_size=64, lr=3e-4, eval_episodes=4, log_every=20, progress=False,
                        student_steps=2)
    run = distill(cfg).dir
    card = load_card(run / "last")
    assert card["sampler_steps"] == 2 and card["finished"] and card["evaluation"]["seeds"] == [400000, 400003]
    assert card["reproduce"]["distill"] == f"python -m training.distill --teacher {TEACHER} --student-steps 2 --name d " \
        f"--out-dir {tmp_path} --pairs 200 --steps 40 --batch-size 64 --lr 0.0003 --eval-episodes 4 --log-every 20 " \
        "--teacher-episodes 2 --rounds 1 --round-episodes 2"
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in records if r["type"] == "train"]
    assert len(losses) == 4 and min(losses[1], losses[3]) < losses[0]  # the 2-step student gets closer to the teacher
    pairs, round_ = [r for r in records if r["type"] == "pairs"], [r for r in records if r["type"] == "round"]
    # the round labels the decision states of the student's own 2 episodes, played on training seeds after the teacher's
    assert len(round_) == 1 and round_[0]["played_seeds"] == [23000002, 23000003] and round_[0]["pairs"] > pairs[0]["pairs"] > 200
    assert [r["round"] for r in records if r["type"] == "eval"] == [0, 1]
    assert (run / "learning_curve.png").stat().st_size > 0 and load_card(run / "round0")["finished"] is False

    # a plain flow with the teacher's flow weights to start from: the chooser's own parts stay behind
    teacher, _ = load_checkpoint(TEACHER)
    student, _ = load_checkpoint(run / "last")
    assert "outcome_dims" not in card["architecture"] and student.outcome is None and teacher.outcome is not None
    flow_weights = {k: v for k, v in teacher.state_dict().items() if not k.startswith("outcome.")}
    assert flow_weights.keys() == student.state_dict().keys()
    assert any(not torch.equal(v, student.state_dict()[k]) for k, v in flow_weights.items())
    export_onnx(run / "last", run / "last.onnx", num_steps=card["sampler_steps"])
    assert load_card(run / "last")["onnx"]["num_steps"] == 2
    rng = np.random.default_rng(0)
    states = np.array([[222.0, 97.0, 222.0, 222.0, 0.8], [300.0, 400.0, 250.0, 260.0, 3.1]], dtype=np.float32)
    noise = rng.standard_normal((2, 12, 2)).astype(np.float32)
    got = ort.InferenceSession(str(run / "last.onnx"), providers=["CPUExecutionProvider"]).run(["actions"], {"state": states, "noise": noise})[0]
    with torch.no_grad():
        want = load_acting_policy(run / "last", num_steps=2)(torch.from_numpy(states), torch.from_numpy(noise)).numpy()
    np.testing.assert_allclose(got, want, atol=1e-3)


def test_a_run_can_start_from_another_runs_pairs_with_a_smaller_student_and_weigh_the_teachers_outcome_model(tmp_path: Path) -> None:
    first = distill(DistillConfig(teacher=str(TEACHER), name="a", out_dir=str(tmp_path), pairs=64, steps=4, batch_size=16,
                                  eval_episodes=1, log_every=2, progress=False, student_steps=2)).dir
    assert not (first / "round0.json").exists() and (first / PAIRS_FILE).is_file()  # no DAgger round: `last` only
    second = distill(DistillConfig(teacher=str(TEACHER), name="b", out_dir=str(tmp_path), pairs_from=str(first), steps=4,
                                   batch_size=16, eval_episodes=1, log_every=2, progress=False, student_steps=1,
                                   outcome_weight=1.0, outcome_root=True, student_hidden_dims="64,64")).dir
    assert load_card(second / "last")["architecture"]["hidden_dims"] == [64, 64]  # a fresh, smaller student
    assert not (second / PAIRS_FILE).exists()  # it labelled nothing new
    # a student goes on from its own checkpoint (more rounds), not from one of another architecture
    more = DistillConfig(teacher=str(TEACHER), name="c", out_dir=str(tmp_path), pairs_from=str(first), init=str(second / "last"),
                         student_hidden_dims="64,64", student_steps=1, steps=2, batch_size=16, eval_episodes=1, progress=False)
    assert load_card(distill(more).dir / "last")["steps"] == 2
    with pytest.raises(ValueError, match="is not a student of .* with this run's architecture"):
        distill(DistillConfig(**{**more.to_dict(), "name": "d", "student_hidden_dims": ""}))
    assert not (tmp_path / "d").exists()
    records = [json.loads(line) for line in (second / "log.jsonl").read_text().splitlines()]
    assert [r["pairs"] for r in records if r["type"] == "pairs"] == [64]
    assert all(r["outcome_distance"] > 0 for r in records if r["type"] == "train")

    # pairs labelled by another teacher, or in another step count, are refused with the file named
    teacher, _ = load_checkpoint(TEACHER)
    with pytest.raises(ValueError, match=f"{PAIRS_FILE}: chunks labelled by {TEACHER} in 10 steps with fixed noise -1, not chunks by models/flow in 10 with -1"):
        Pairs(teacher, "models/flow", 10).load(first / PAIRS_FILE)
    with pytest.raises(FileNotFoundError, match="no saved pairs"):
        Pairs(teacher, str(TEACHER), 10).load(tmp_path / PAIRS_FILE)


def test_the_outcome_term_looks_ahead_through_the_students_own_next_chunks() -> None:
    from pusht.spec import ACTION_HIGH, ACTION_LOW

    teacher, _ = load_checkpoint(TEACHER)
    teacher.requires_grad_(False)  # frozen, as distillation keeps it
    student = student_of(teacher, noise_scale=0.0)
    states = torch.tensor([[222.0, 97.0, 222.0, 222.0, 0.8], [300.0, 400.0, 250.0, 260.0, 3.1]])
    state_n = teacher.policy_state(states)
    with torch.no_grad():  # the first chunk as a constant: any gradient below comes from the chunks played after it
        chunk_n = student.sample_actions(state_n, torch.zeros(2, 12, 2), 2)
    one = outcome_term(student, teacher, state_n, chunk_n, DistillConfig(outcome_weight=1.0, outcome_root=True))
    clipped = torch.clamp(teacher.normalizer.actions(states, chunk_n), ACTION_LOW, ACTION_HIGH)
    torch.testing.assert_close(one, teacher.outcome.goal_distance(states, clipped).sqrt().mean())
    assert not one.requires_grad
    three = outcome_term(student, teacher, state_n, chunk_n, DistillConfig(outcome_weight=1.0, outcome_root=True, outcome_chunks=3))
    three.backward()
    assert three > one and any(p.grad is not None and p.grad.abs().sum() > 0 for p in student.parameters())


def test_distillation_settings_are_checked_before_any_work(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="outcome_weight must be >= 0"):
        DistillConfig(outcome_weight=-1)
    with pytest.raises(ValueError, match="outcome_chunks looks ahead in the outcome term: give --outcome-weight"):
        DistillConfig(outcome_chunks=3)
    with pytest.raises(ValueError, match="outcome_chunks must be >= 1"):
        DistillConfig(outcome_chunks=0, outcome_weight=1.0)
    with pytest.raises(ValueError, match="student_hidden_dims must be comma-separated positive widths"):
        DistillConfig(student_hidden_dims="256,,256")
    with pytest.raises(ValueError, match="round_seed 300000 lies among the evaluation seeds"):
        DistillConfig(round_seed=300_000)
    plain = REPO / "records" / "flow-agentframe-padend-150k-noise0.3" / "last"
    with pytest.raises(ValueError, match="needs a teacher with an outcome chooser"):
        distill(DistillConfig(teacher=str(plain), name="c", out_dir=str(tmp_path), outcome_weight=1.0, progress=False))
    assert not (tmp_path / "c").exists()

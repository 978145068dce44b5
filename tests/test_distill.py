"""Few-step distillation: a real short run saves a student whose card and export carry its step count."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from training.checkpoint import load_acting_policy, load_card, load_checkpoint
from training.distill import DistillConfig, distill
from training.export import export_onnx

REPO = Path(__file__).resolve().parent.parent


def test_a_short_distillation_moves_the_student_toward_the_teachers_map(tmp_path: Path) -> None:
    cfg = DistillConfig(name="d", out_dir=str(tmp_path), pairs=3000, steps=60, batch_size=64, lr=3e-4, eval_episodes=4,
                        log_every=20, progress=False, student_steps=2)
    run = distill(cfg).dir
    card = load_card(run / "last")
    assert card["sampler_steps"] == 2 and card["finished"] and card["evaluation"]["seeds"] == [400000, 400003]
    assert card["reproduce"]["distill"] == "python -m training.distill --teacher models/flow --student-steps 2 --name d " \
        f"--out-dir {tmp_path} --pairs 3000 --steps 60 --batch-size 64 --lr 0.0003 --eval-episodes 4 --log-every 20"
    losses = [r["loss"] for r in map(json.loads, (run / "log.jsonl").read_text().splitlines()) if r["type"] == "train"]
    assert len(losses) == 3 and losses[-1] < losses[0]  # the 2-step student gets closer to the 10-step teacher
    assert (run / "learning_curve.png").stat().st_size > 0

    # the student acts in its own step count, and its ONNX graph unrolls exactly that many
    teacher, _ = load_checkpoint(REPO / "models" / "flow")
    student, _ = load_checkpoint(run / "last")
    assert any(not torch.equal(a, b) for a, b in zip(teacher.state_dict().values(), student.state_dict().values()))
    export_onnx(run / "last", run / "last.onnx", num_steps=card["sampler_steps"])
    assert load_card(run / "last")["onnx"]["num_steps"] == 2
    rng = np.random.default_rng(0)
    states = np.array([[222.0, 97.0, 222.0, 222.0, 0.8], [300.0, 400.0, 250.0, 260.0, 3.1]], dtype=np.float32)
    noise = rng.standard_normal((2, 12, 2)).astype(np.float32)
    got = ort.InferenceSession(str(run / "last.onnx"), providers=["CPUExecutionProvider"]).run(["actions"], {"state": states, "noise": noise})[0]
    with torch.no_grad():
        want = load_acting_policy(run / "last", num_steps=2)(torch.from_numpy(states), torch.from_numpy(noise)).numpy()
    np.testing.assert_allclose(got, want, atol=1e-3)

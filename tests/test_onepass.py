"""The one-pass chooser: given the chooser's own candidates and scores it picks the chooser's chunk, and a short
`training.distill --student one-pass` run gives a flow with no steps that exports, loads and refuses num_steps."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from acting import load_policy
from pusht.seeding import chunk_noise
from training.checkpoint import load_acting_policy, load_card, load_checkpoint
from training.distill import DistillConfig, distill
from training.distill_data import PAIRS_FILE, teacher_choices
from training.export import export_onnx
from training.onepass import OnePassChooser, first_nearest, score_target
from training.outcome import goal_corner_distance, nearest, pose_after

REPO = Path(__file__).resolve().parent.parent
TEACHER = REPO / "records" / "flow-outcome16-stretch" / "last"
STATES = np.array([[222.0, 97.0, 222.0, 222.0, 0.8], [300.0, 400.0, 250.0, 260.0, 3.1], [180.0, 260.0, 240.0, 250.0, 2.0],
                   [260.0, 300.0, 250.0, 280.0, 5.5], [120.0, 150.0, 300.0, 200.0, 1.2], [400.0, 380.0, 330.0, 300.0, 4.0]],
                  dtype=np.float32)


def test_given_the_choosers_candidates_and_scores_the_one_pass_head_picks_the_choosers_chunk() -> None:
    teacher, _ = load_checkpoint(TEACHER)
    teacher.eval()
    state_n = teacher.policy_state(torch.from_numpy(STATES))
    noise = torch.as_tensor(chunk_noise(12345, 1, 12, 2)).expand(len(STATES), -1, -1)
    candidates, distances = teacher_choices(teacher, state_n, noise, 10)
    assert candidates.shape == (6, 64, 12, 2) and distances.shape == (6, 256)
    head = OnePassChooser(6, (12, 2), [8], 64, teacher.outcome.stretches)
    head.forward = lambda flow, s: (candidates, score_target(distances))  # a perfect student
    with torch.no_grad():
        want = teacher.sample_actions(state_n, noise, 10)
        got = head.best_chunk(teacher, state_n, torch.randn(6, 12, 2))
    # the chooser keeps its own sample on a near tie (TIE_MARGIN); the student has no such rule
    agree = (nearest(distances) == distances.argmin(dim=1)).numpy()
    assert agree.any()
    np.testing.assert_allclose(got.numpy()[agree], want.numpy()[agree], atol=1e-4)


def test_a_short_one_pass_distillation_gives_a_flow_without_steps(tmp_path: Path) -> None:
    cfg = DistillConfig(teacher=str(TEACHER), name="o", out_dir=str(tmp_path), student="one-pass", fixed_noise=12345, pairs=64,
                        rounds=1, round_episodes=1, steps=6, batch_size=16, eval_episodes=1, log_every=3, progress=False,
                        student_hidden_dims="32,32")
    run = distill(cfg).dir
    card = load_card(run / "last")
    arch = card["architecture"]
    assert arch["onepass_dims"] == [32, 32] and arch["outcome_candidates"] == 64 and "outcome_dims" not in arch
    assert card["sampler_steps"] is None and "--student one-pass" in card["reproduce"]["distill"]
    export_onnx(run / "last", run / "last.onnx")
    session = ort.InferenceSession(str(run / "last.onnx"), providers=["CPUExecutionProvider"])
    assert {i.name for i in session.get_inputs()} == {"state", "noise"}  # the ONNX contract keeps the noise input
    noise = np.random.default_rng(0).standard_normal((6, 12, 2)).astype(np.float32)
    got = session.run(["actions"], {"state": STATES, "noise": noise})[0]
    with torch.no_grad():
        want = load_acting_policy(run / "last")(torch.from_numpy(STATES), torch.from_numpy(noise)).numpy()
    np.testing.assert_allclose(got, want, atol=1e-3)
    np.testing.assert_array_equal(got, session.run(["actions"], {"state": STATES, "noise": 0 * noise})[0])  # deterministic

    # its states, labelled anew as chunks for a flow student; its choice labels cannot serve one as they are
    flow = DistillConfig(teacher=str(TEACHER), name="f", out_dir=str(tmp_path), fixed_noise=12345, states_from=str(run), steps=2,
                         batch_size=16, eval_episodes=1, progress=False, student_steps=2)
    records = (distill(flow).dir / "log.jsonl").read_text()
    assert f'"type": "pairs", "step": 0, "round": 0, "pairs": {_saved_states(run)},' in records
    with pytest.raises(ValueError, match="choices labelled by .* not chunks by"):
        distill(DistillConfig(**{**flow.to_dict(), "name": "g", "states_from": "", "pairs_from": str(run)}))
    with pytest.raises(ValueError, match="carry no start noises"):
        distill(DistillConfig(**{**flow.to_dict(), "name": "h", "fixed_noise": -1}))

    policy = load_policy(run / "last.onnx")
    assert policy.network_evaluations() == 1 and policy.default_num_steps is None and not policy.uses_noise
    assert "one network pass" in policy.check_num_steps(1)
    with pytest.raises(ValueError, match="one network pass"):
        load_policy(run / "last.onnx", num_steps=2)


def test_a_one_pass_student_needs_a_fixed_noise_and_a_chooser(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="give --fixed-noise SEED"):
        DistillConfig(student="one-pass")
    plain = REPO / "records" / "flow-agentframe-padend-150k-noise0.3" / "last"
    with pytest.raises(ValueError, match="a one-pass student needs a teacher with an outcome chooser"):
        distill(DistillConfig(teacher=str(plain), name="c", out_dir=str(tmp_path), student="one-pass", fixed_noise=1, progress=False))
    assert not (tmp_path / "c").exists()


def _saved_states(run: Path) -> int:
    from safetensors import safe_open

    with safe_open(str(run / PAIRS_FILE), framework="pt") as f:
        return f.get_slice("state_n").get_shape()[0]


def test_a_multichoice_head_learns_which_hypothesis_is_nearest_and_plays_it() -> None:
    torch.manual_seed(0)
    teacher, _ = load_checkpoint(TEACHER)
    head = OnePassChooser(teacher.encode_state(torch.zeros(1, teacher.state_dim)).shape[1], (12, 2), [32], 3, [1.0])
    state_n = teacher.policy_state(torch.from_numpy(STATES))
    target = torch.randn(len(STATES), 12, 2)
    optimizer = torch.optim.Adam(head.parameters(), lr=1e-2)
    first = None
    for _ in range(300):
        loss, played = head.multichoice_loss(teacher, state_n, target, relax=0.05)
        first = float(loss.detach()) if first is None else first
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert float(loss.detach()) < 0.1 * first
    with torch.no_grad():
        chunks, scores = head(teacher, state_n)
        nearest_ = (chunks - target[:, None]).pow(2).mean(dim=(2, 3)).argmin(dim=1)
        np.testing.assert_array_equal(scores.argmin(dim=1).numpy(), nearest_.numpy())  # the nearest one is the one played
        want = chunks[torch.arange(len(chunks)), nearest_]
        np.testing.assert_allclose(head.best_chunk(teacher, state_n, torch.randn(6, 12, 2)).numpy(), want.numpy(), atol=1e-5)


def test_a_short_multichoice_distillation_gives_a_one_pass_flow_with_its_hypotheses(tmp_path: Path) -> None:
    cfg = DistillConfig(teacher=str(TEACHER), name="m", out_dir=str(tmp_path), student="multichoice", hypotheses=4, fixed_noise=12345,
                        pairs=64, rounds=1, round_episodes=1, steps=6, batch_size=16, eval_episodes=1, log_every=3, progress=False,
                        student_hidden_dims="32,32", outcome_weight=3.0, outcome_root=True)
    run = distill(cfg).dir
    card = load_card(run / "last")
    arch = card["architecture"]
    assert arch["onepass_dims"] == [32, 32] and arch["outcome_candidates"] == 4
    assert load_checkpoint(run / "last")[0].onepass.stretches == (1.0,)  # the default, unstretched
    assert card["sampler_steps"] is None and "--student multichoice" in card["reproduce"]["distill"] and "--hypotheses 4" in card["reproduce"]["distill"]
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert any(r.get("type") == "train" and "outcome_distance" in r for r in records)
    export_onnx(run / "last", run / "last.onnx")
    policy = load_policy(run / "last.onnx")
    assert policy.network_evaluations() == 1 and not policy.uses_noise
    with pytest.raises(ValueError, match="relax must be in"):
        DistillConfig(student="multichoice", relax=1.0)


def test_a_scoring_pass_learns_where_each_hypothesis_leaves_the_block_and_plays_the_nearest(tmp_path: Path) -> None:
    torch.manual_seed(0)
    teacher, _ = load_checkpoint(TEACHER)
    encoded = teacher.encode_state(torch.zeros(1, teacher.state_dim)).shape[1]
    head = OnePassChooser(encoded, (12, 2), [32], 3, [1.0], scorer_dims=[64])
    state_n = teacher.policy_state(torch.from_numpy(STATES))
    with torch.no_grad():
        chunks_n = head(teacher, state_n)[0]  # its own hypotheses, which it plays
    changes = torch.randn(len(STATES), 3, 3)
    rows = torch.from_numpy(STATES).repeat_interleave(3, dim=0)
    nearest_ = goal_corner_distance(pose_after(rows, changes.reshape(-1, 3))).reshape(-1, 3).argmin(dim=1)
    _fit_scorer(head, teacher, state_n, chunks_n, changes)
    with torch.no_grad():
        torch.testing.assert_close(head.changes(teacher, state_n, chunks_n), changes, atol=0.25, rtol=0)  # the regret term pulls too
        np.testing.assert_array_equal(head.scores(teacher, state_n, chunks_n).argmin(dim=1).numpy(), nearest_.numpy())
        want = chunks_n[torch.arange(len(STATES)), nearest_]
        np.testing.assert_allclose(head.best_chunk(teacher, state_n, torch.randn(6, 12, 2)).numpy(), want.numpy(), atol=1e-6)
    with pytest.raises(ValueError, match="not stretches"):
        OnePassChooser(encoded, (12, 2), [32], 3, [1.0, 1.5], scorer_dims=[64])


def _fit_scorer(head: OnePassChooser, flow, state_n: torch.Tensor, chunks_n: torch.Tensor, changes: torch.Tensor) -> None:
    """300 Adam steps of the second pass's loss on fixed hypotheses and labels."""
    optimizer = torch.optim.Adam(head.scorer.parameters(), lr=1e-2)
    for _ in range(300):
        loss = head.scorer_loss(flow, state_n, chunks_n, changes)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


def test_a_second_pass_with_stretches_learns_the_outcome_of_each_hypothesis_stretched_and_plays_the_nearest() -> None:
    from training.distill_scorer import hypothesis_changes
    from training.distill import student_of
    from training.outcome import stretch

    torch.manual_seed(0)
    teacher, _ = load_checkpoint(TEACHER)
    student = student_of(teacher, 0.0, onepass_dims="32", hypotheses=3, scorer_dims="64", scorer_stretches=[1.0, 1.5]).eval()
    head, state = student.onepass, torch.from_numpy(STATES)
    state_n = student.policy_state(state)
    with torch.no_grad():
        for p in head.net.parameters():  # hypotheses tens of pixels apart
            p.mul_(3.0)
        chunks_n = head(student, state_n)[0]
        _, plain = head.hypothesis_actions(student, state_n, chunks_n)  # [6 * 3, 12, 2]
        labels = hypothesis_changes(student, teacher, state_n)  # [6, 3 * 2, 3]: the 3 plain, then the 3 stretched
        stretched = torch.clamp(stretch(state.repeat_interleave(3, dim=0), plain, 1.5), 0, 512)
        torch.testing.assert_close(labels[:, 3:].reshape(-1, 3), teacher.outcome.model.net(teacher.outcome.model.features(
            state.repeat_interleave(3, dim=0), stretched)))
    nearest_ = head.goal_distances(student, state_n, labels).argmin(dim=1)
    _fit_scorer(head, student, state_n, chunks_n, labels)
    with torch.no_grad():
        np.testing.assert_array_equal(head.scores(student, state_n, chunks_n).argmin(dim=1).numpy(), nearest_.numpy())
        options = torch.cat([plain.reshape(6, 3, 12, 2), stretched.reshape(6, 3, 12, 2)], dim=1)
        # the first within the tie margin of its own nearest (choices that miss the block tie)
        pick = first_nearest(head.goal_distances(student, state_n, head.changes(student, state_n, chunks_n)))
        want = options[torch.arange(6), pick]
        played = student.normalizer.actions(state, head.best_chunk(student, state_n, torch.zeros(6, 12, 2)))
        torch.testing.assert_close(played, want, atol=1e-3, rtol=0)
    assert set(nearest_.tolist()) & {3, 4, 5}  # some play stretched
    with pytest.raises(ValueError, match="scorer_stretches must be"):
        DistillConfig(student="multichoice", scorer_dims="16", steps=0, init="x", scorer_stretches="1.3,1")
    with pytest.raises(ValueError, match="give --scorer-dims too"):
        DistillConfig(student="multichoice", scorer_stretches="1,1.5")
    from training.policies import build_policy

    with pytest.raises(ValueError, match="onepass_scorer_stretches are what a second pass scores"):
        build_policy("flow", **{**student.architecture, "onepass_scorer_dims": None})


def test_a_second_pass_run_scores_a_multichoice_students_hypotheses_in_two_evaluations(tmp_path: Path) -> None:
    cfg = DistillConfig(teacher=str(TEACHER), name="m", out_dir=str(tmp_path), student="multichoice", hypotheses=4, fixed_noise=-1, top=3,
                        pairs=32, steps=4, batch_size=8, eval_episodes=1, log_every=2, progress=False, student_hidden_dims="32,32")
    first = distill(cfg).dir
    assert load_checkpoint(first / "last")[0].onepass.scorer is None
    with pytest.raises(ValueError, match="--init CARD and --steps 0"):
        DistillConfig(student="multichoice", scorer_dims="16")
    cfg = DistillConfig(teacher=str(TEACHER), name="s", out_dir=str(tmp_path), student="multichoice", hypotheses=4, steps=0,
                        init=str(first / "last"), scorer_dims="16,16", scorer_steps=4, scorer_rounds=1, round_episodes=1, pairs=32,
                        batch_size=8, eval_episodes=1, log_every=2, progress=False, student_hidden_dims="32,32", states_from=str(first))
    run = distill(cfg).dir
    student, card = load_checkpoint(run / "last")
    generator = load_checkpoint(first / "last")[0]
    for name, tensor in generator.state_dict().items():  # the hypotheses stay as trained
        torch.testing.assert_close(student.state_dict()[name], tensor)
    assert card["architecture"]["onepass_scorer_dims"] == [16, 16] and "--scorer-dims 16,16" in card["reproduce"]["distill"]
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert {"scorer", "scorer_round", "scorer_eval"} <= {r.get("type") for r in records}
    # it keeps the states it learned from, for the next run's --states-from
    round_ = next(r for r in records if r.get("type") == "scorer_round")
    assert _saved_states(run) == round_["states"] > 32
    # --scorer-jitter: moved copies of each visited state join them
    jittered = distill(dataclasses.replace(cfg, name="sj", scorer_jitter=2)).dir
    moved = next(r for r in map(json.loads, (jittered / "log.jsonl").read_text().splitlines()) if r.get("type") == "scorer_round")
    assert moved["states"] - round_["states"] == 2 * (round_["states"] - _saved_states(first) - 32)
    export_onnx(run / "last", run / "last.onnx")
    policy = load_policy(run / "last.onnx")
    assert policy.network_evaluations() == 2 and not policy.uses_noise
    state_n = student.policy_state(torch.from_numpy(STATES))
    with torch.no_grad():
        chunks_n, _ = student.onepass(student, state_n)
        pick = student.onepass.scores(student, state_n, chunks_n).argmin(dim=1)
        want = student.normalizer.actions(torch.from_numpy(STATES), chunks_n[torch.arange(len(STATES)), pick]).clamp(0, 512).numpy()
    np.testing.assert_allclose(policy.act(STATES, np.zeros((6, 12, 2), np.float32)), want, atol=1e-3)  # ONNX plays the best-scored
    # --init with a second pass of the same widths goes on training it (a tiny rate leaves it where it was); of other widths,
    # its hypotheses get a fresh one
    more = distill(dataclasses.replace(cfg, name="s2", init=str(run / "last"), scorer_lr=1e-12, scorer_rounds=0, states_from=str(run))).dir
    trained, again = student.onepass.scorer.state_dict(), load_checkpoint(more / "last")[0].onepass.scorer.state_dict()
    for name, tensor in trained.items():
        torch.testing.assert_close(again[name], tensor)
    other, other_card = load_checkpoint(distill(dataclasses.replace(cfg, name="s3", init=str(run / "last"), scorer_dims="8",
                                                                    scorer_rounds=0, states_from="")).dir / "last")
    assert other_card["architecture"]["onepass_scorer_dims"] == [8]
    for name, tensor in generator.state_dict().items():
        torch.testing.assert_close(other.state_dict()[name], tensor)
    # of the same widths scoring other stretches: its layers but the last stay
    stretched, _ = load_checkpoint(distill(dataclasses.replace(cfg, name="s4", init=str(run / "last"), scorer_stretches="1,1.5",
                                                               scorer_lr=1e-12, scorer_rounds=0, states_from="")).dir / "last")
    assert stretched.onepass.scored == 8
    for name, tensor in trained.items():
        if name.startswith("4."):  # the last layer: 8 x 3 outputs now
            assert stretched.onepass.scorer.state_dict()[name].shape[0] == 24
        else:
            torch.testing.assert_close(stretched.onepass.scorer.state_dict()[name], tensor)


def test_the_teachers_outcome_model_as_the_second_pass_predicts_and_chooses_as_the_model_does(tmp_path: Path) -> None:
    from training.distill_scorer import hypothesis_changes
    from training.policies import build_policy

    cfg = DistillConfig(teacher=str(TEACHER), name="m", out_dir=str(tmp_path), student="multichoice", hypotheses=4, fixed_noise=-1,
                        pairs=32, steps=2, batch_size=8, eval_episodes=1, log_every=1, progress=False, student_hidden_dims="32,32")
    first = distill(cfg).dir
    run = distill(dataclasses.replace(cfg, name="o", steps=0, init=str(first / "last"), scorer_outcome=True)).dir
    student, card = load_checkpoint(run / "last")
    teacher, teacher_card = load_checkpoint(TEACHER)
    arch = card["architecture"]
    assert arch["onepass_scorer_dims"] == teacher_card["architecture"]["outcome_dims"]
    assert arch["onepass_scorer_shared"] and arch["onepass_scorer_context"] is False and "--scorer-outcome" in card["reproduce"]["distill"]
    assert {"scorer_eval"} <= {json.loads(line).get("type") for line in (run / "log.jsonl").read_text().splitlines()}
    state = torch.from_numpy(STATES)
    state_n = student.policy_state(state)
    with torch.no_grad():
        chunks_n = student.onepass(student, state_n)[0]
        changes = student.onepass.changes(student, state_n, chunks_n)
        torch.testing.assert_close(changes, hypothesis_changes(student, teacher, state_n), atol=1e-4, rtol=1e-4)
        # the pass's pick is the outcome model's own among the hypotheses
        rows, actions = student.onepass.hypothesis_actions(student, state_n, chunks_n)
        model_pick = goal_corner_distance(teacher.outcome.model(rows, actions)).reshape(len(STATES), 4).argmin(dim=1)
        torch.testing.assert_close(student.onepass.scores(student, state_n, chunks_n).argmin(dim=1), model_pick)
    export_onnx(run / "last", run / "last.onnx")  # the lean graph of a pass without context
    policy = load_policy(run / "last.onnx")
    assert policy.network_evaluations() == 2
    np.testing.assert_allclose(policy.act(STATES, np.zeros((6, 12, 2), np.float32)),
                               load_policy(run / "last").act(STATES, np.zeros((6, 12, 2), np.float32)), atol=1e-3)
    # with --scorer-top and a ranker, the model itself scores the ranker's best two; only the ranker learns
    ranked = distill(dataclasses.replace(cfg, name="r", steps=0, init=str(first / "last"), scorer_outcome=True, scorer_top=2,
                                         ranker_dims="16", scorer_steps=2, scorer_rounds=1, round_episodes=1, states_from=str(first))).dir
    ranker, ranker_card = load_checkpoint(ranked / "last")
    assert ranker_card["architecture"]["onepass_scorer_top"] == 2 and ranker_card["architecture"]["onepass_ranker_dims"] == [16]
    with torch.no_grad():
        ranked_n = ranker.policy_state(state)
        torch.testing.assert_close(ranker.onepass.changes(ranker, ranked_n, ranker.onepass(ranker, ranked_n)[0]),
                                   hypothesis_changes(ranker, teacher, ranked_n), atol=1e-4, rtol=1e-4)
    export_onnx(ranked / "last", ranked / "last.onnx")
    np.testing.assert_allclose(load_policy(ranked / "last.onnx").act(STATES, np.zeros((6, 12, 2), np.float32)),
                               load_policy(ranked / "last").act(STATES, np.zeros((6, 12, 2), np.float32)), atol=1e-3)
    with pytest.raises(ValueError, match="give --scorer-top too"):
        DistillConfig(student="multichoice", steps=0, init="x", scorer_outcome=True, ranker_dims="16")
    with pytest.raises(ValueError, match="each hypothesis alone"):
        DistillConfig(student="multichoice", steps=0, init="x", scorer_dims="16", scorer_top=2)
    # narrower, it starts from the model's most active units and learns on
    pruned = distill(dataclasses.replace(cfg, name="p", steps=0, init=str(first / "last"), scorer_outcome=True,
                                         scorer_dims="64,64,64,64", scorer_steps=2, scorer_rounds=0, states_from=str(first))).dir
    assert load_card(pruned / "last")["architecture"]["onepass_scorer_dims"] == [64, 64, 64, 64]
    assert "scorer" in {json.loads(line).get("type") for line in (pruned / "log.jsonl").read_text().splitlines()}
    with pytest.raises(ValueError, match="of as many layers, none wider"):
        distill(dataclasses.replace(cfg, name="w", steps=0, init=str(first / "last"), scorer_outcome=True, scorer_dims="64,64"))
    with pytest.raises(ValueError, match="give no --scorer-shared"):
        DistillConfig(student="multichoice", steps=0, init="x", scorer_outcome=True, scorer_shared=True, scorer_dims="16")
    with pytest.raises(ValueError, match="--init CARD and --steps 0"):
        DistillConfig(student="multichoice", scorer_outcome=True)
    with pytest.raises(ValueError, match="give --scorer-shared too"):
        DistillConfig(student="multichoice", steps=0, init="x", scorer_dims="16", scorer_context=False)
    with pytest.raises(ValueError, match="it needs onepass_scorer_shared"):
        build_policy("flow", **{**student.architecture, "onepass_scorer_shared": False})
    with pytest.raises(ValueError, match="a second pass needs a teacher with an outcome chooser"):
        distill(dataclasses.replace(cfg, name="x", teacher=str(REPO / "records" / "flow-agentframe-padend-150k-noise0.3" / "last"),
                                    steps=0, init=str(first / "last"), scorer_outcome=True))


def test_a_shared_second_pass_treats_every_hypothesis_alike_and_exports(tmp_path: Path) -> None:
    from training.checkpoint import save_checkpoint
    from training.distill import student_of
    from training.onepass_graph import lean_graph
    from training.policies import build_policy

    torch.manual_seed(0)
    teacher, card = load_checkpoint(TEACHER)
    student = student_of(teacher, 0.0, onepass_dims="32,32", hypotheses=4, scorer_dims="16,16", scorer_shared=True).eval()
    assert student.architecture["onepass_scorer_shared"] and lean_graph(student) is not None  # exported as a lean graph
    with pytest.raises(ValueError, match="it needs onepass_scorer_dims"):
        build_policy("flow", **{**student.architecture, "onepass_scorer_dims": None})
    with pytest.raises(ValueError, match="give --scorer-dims too"):
        DistillConfig(student="multichoice", scorer_shared=True)
    state_n = student.policy_state(torch.from_numpy(STATES))
    with torch.no_grad():
        chunks_n = student.onepass(student, state_n)[0]
        changes = student.onepass.changes(student, state_n, chunks_n)
        order = torch.tensor([2, 0, 3, 1])
        # one set network: the hypotheses in another order get the same changes in that order
        torch.testing.assert_close(student.onepass.changes(student, state_n, chunks_n[:, order]), changes[:, order])
    save_checkpoint(tmp_path / "flow", student, card["normalization"], steps=0, git_commit="test", evaluation=None)
    export_onnx(tmp_path / "flow")
    policy = load_policy(tmp_path / "flow.onnx")
    assert policy.network_evaluations() == 2
    torch_policy = load_policy(tmp_path / "flow")  # the torch backend: the module itself
    want = torch_policy.act(STATES, np.zeros((6, 12, 2), np.float32))
    np.testing.assert_allclose(policy.act(STATES, np.zeros((6, 12, 2), np.float32)), want, atol=1e-3)


def test_a_near_tie_goes_to_the_earlier_choice() -> None:
    distance = torch.tensor([[1.0, 1.0005, 0.9999], [2.0, 1.0, 1.0], [0.5, 0.4, 0.3]])
    assert first_nearest(distance).tolist() == [0, 1, 2]

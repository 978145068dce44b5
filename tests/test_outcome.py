"""The outcome chooser: its model learns real one-chunk lookaheads, it picks the chunk it predicts closest to the goal,
and a flow choosing among one candidate is the plain flow."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from policies.checkpoint import load_checkpoint
from policies.chooser import FLOAT_TIE, TIE_MARGIN, OutcomeModel, OutcomeSelector, goal_corner_distance, nearest
from policies.factory import build_policy
from policies.selection import orthogonal_maps
from pusht.geometry import GOAL_POSE, coverage
from training.chunk_env import ChunkVectorEnv

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "models" / "flow"  # the plain flow inside the chooser
CHOOSER = REPO / "models" / "flow-chooser"


def _chooser_from_shipped(candidates: int, dims=(32,), stretches=(1.0,)):
    base, card = load_checkpoint(SHIPPED)
    policy = build_policy(
        "flow",
        **{
            **card["architecture"],
            "outcome_dims": list(dims),
            "outcome_candidates": candidates,
            "outcome_stretches": list(stretches),
        },
    )
    policy.load_state_dict(base.state_dict(), strict=False)
    policy.normalizer.set(base.normalizer)
    return base.eval(), policy.eval()


def test_goal_corner_distance_is_zero_at_the_goal_and_grows_with_the_error() -> None:
    gx, gy, ga = GOAL_POSE
    poses = torch.tensor(
        [[gx, gy, ga], [gx + 2, gy, ga], [gx + 8, gy, ga], [gx, gy, ga + 0.05], [gx, gy, ga + 0.2]], dtype=torch.float64
    )
    d = goal_corner_distance(poses)
    assert d[0] < 1e-12 and d[1] < d[2] and d[3] < d[4]
    covered = [coverage(*p) for p in poses.tolist()]
    assert covered[0] > covered[1] > covered[2] and covered[3] > covered[4]  # the same orders as coverage


def test_an_untrained_model_with_a_zero_head_predicts_no_motion() -> None:
    model = OutcomeModel(12, (16,))
    torch.nn.init.zeros_(model.net[-1].weight)
    torch.nn.init.zeros_(model.net[-1].bias)
    state = torch.tensor([[100.0, 120.0, 300.0, 280.0, 1.3]])
    end = model(state, torch.full((1, 12, 2), 200.0))
    torch.testing.assert_close(end, state[:, 2:5])


def test_the_model_learns_real_lookaheads_better_than_no_motion() -> None:
    torch.manual_seed(0)
    envs = ChunkVectorEnv(24, seed_start=10_000_000)
    rng = np.random.default_rng(0)
    states, chunks, ends = [], [], []
    for i in range(24):  # targets around the block, so most chunks push it
        cands = (envs.obs[i, 2:4] + rng.normal(0, 40, (8, 1, 2)) + rng.normal(0, 5, (8, 12, 2))).astype(np.float32)
        ends.append(envs.lookahead(i, cands).next_obs)
        states.append(np.repeat(envs.obs[i : i + 1], 8, axis=0))
        chunks.append(cands)
    state, chunk, end = (torch.as_tensor(np.concatenate(x), dtype=torch.float32) for x in (states, chunks, ends))
    model = OutcomeModel(12, (128, 128))
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(300):
        loss = model.loss(state, chunk, end)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        err = (model(state, chunk)[:, :2] - end[:, 2:4]).norm(dim=1).mean()
    still = (state[:, 2:4] - end[:, 2:4]).norm(dim=1).mean()
    assert still > 5 and err < 0.3 * still, (float(err), float(still))


def test_the_chooser_picks_the_candidate_predicted_closest_to_the_goal() -> None:
    selector = OutcomeSelector((12, 2), (16,), candidates=6)
    state = torch.tensor([[200.0, 220.0, 260.0, 250.0, 0.9], [300.0, 300.0, 240.0, 270.0, 0.6]])
    chunks = 256 + 60 * torch.randn(2, 6, 12, 2)
    with torch.no_grad():
        chosen = selector.choose(state, chunks)
        poses = selector.model(state.repeat_interleave(6, 0), chunks.reshape(-1, 12, 2))
    distance = goal_corner_distance(poses).reshape(2, 6)
    want = torch.where(distance.min(dim=1).values < distance[:, 0] * (1 - 1e-3), distance.argmin(dim=1), 0)
    assert torch.equal(chosen, want)
    # chunks that leave the block where it is tie, and the flow's own sample (candidate 0) plays
    still = torch.zeros(1, 6, 12, 2)
    torch.nn.init.zeros_(selector.model.net[-1].weight)
    torch.nn.init.zeros_(selector.model.net[-1].bias)
    assert selector.choose(state[:1], still + torch.randn(1, 6, 12, 2)).item() == 0


def test_a_flow_choosing_among_one_candidate_is_the_plain_flow() -> None:
    base, one = _chooser_from_shipped(candidates=1)
    states = torch.tensor([[150.0, 350.0, 240.0, 260.0, 0.5], [300.0, 100.0, 200.0, 300.0, 2.0]])
    noise = torch.randn(2, 12, 2)
    with torch.no_grad():
        torch.testing.assert_close(one.act(states, noise), base.act(states, noise), atol=1e-4, rtol=0)


@pytest.mark.parametrize("stretches", [(1.0,), (1.0, 1.5, 0.7)])
def test_a_flow_with_candidates_plays_one_of_its_candidate_chunks(stretches) -> None:
    _, policy = _chooser_from_shipped(candidates=5, stretches=stretches)
    states = torch.tensor(
        [[150.0, 350.0, 240.0, 260.0, 0.5], [300.0, 100.0, 200.0, 300.0, 2.0], [260.0, 250.0, 255.0, 258.0, math.pi / 4]]
    )
    noise = torch.randn(3, 12, 2)
    with torch.no_grad():
        acted = policy.act(states, noise)
        _, actions = policy.outcome.candidate_chunks(policy, policy.policy_state(states), noise, 10)
        index = policy.outcome.choose(states, actions)
    assert actions.shape == (3, 5 * len(stretches), 12, 2) and policy.outcome.choices == 5 * len(stretches)
    torch.testing.assert_close(acted, actions[torch.arange(3), index], atol=1e-3, rtol=0)
    assert not torch.allclose(actions[:, 0], actions[:, 1])  # the candidates differ


def test_a_stretched_candidate_moves_every_target_that_much_farther_from_the_agent() -> None:
    _, policy = _chooser_from_shipped(candidates=4, stretches=(1.0, 1.5, 0.5))
    states = torch.tensor([[250.0, 240.0, 300.0, 280.0, 0.5], [220.0, 300.0, 260.0, 250.0, 2.0]])  # mid-arena: nothing clipped
    with torch.no_grad():
        _, actions = policy.outcome.candidate_chunks(policy, policy.policy_state(states), torch.randn(2, 12, 2), 10)
    plain, agent = actions[:, :4], states[:, None, None, :2]
    assert plain.min() > 0 and plain.max() < 512
    for i, stretch in enumerate((1.5, 0.5), start=1):
        want = torch.clamp(agent + stretch * (plain - agent), 0, 512)
        torch.testing.assert_close(actions[:, 4 * i : 4 * (i + 1)], want, atol=1e-3, rtol=0)


def test_outcome_keys_are_validated() -> None:
    with pytest.raises(ValueError, match="outcome_dims"):
        build_policy("flow", outcome_dims=[0])
    with pytest.raises(ValueError, match="outcome_candidates"):
        build_policy("flow", outcome_dims=[8], outcome_candidates=0)
    for bad in ([1.5, 1.0], [], [1.0, 0.0], [1.0, 5.0], "1"):
        with pytest.raises(ValueError, match="outcome_stretches"):
            build_policy("flow", outcome_dims=[8], outcome_stretches=bad)
    assert "outcome_dims" not in build_policy("flow").architecture  # cards of plain flows are unchanged
    assert "outcome_stretches" not in build_policy("flow", outcome_dims=[8]).architecture  # nor those of unstretched choosers


def test_a_chooser_counts_every_candidate_pass(tmp_path: Path) -> None:
    from policies.card import Card
    from training.ship import reproduce_commands

    arch = {"hidden_dims": [8], "horizon": 12, "outcome_dims": [8], "outcome_candidates": 16}
    card = Card(tmp_path / "c.json", {"name": "c", "kind": "flow", "architecture": arch, "onnx": None})
    assert card.network_evaluations() == 16 * 11 and card.network_evaluations(2) == 16 * 3
    plain = Card(tmp_path / "p.json", {"name": "p", "kind": "flow", "architecture": {"hidden_dims": [8]}, "onnx": None})
    assert plain.network_evaluations() == 10
    stretched = Card(
        tmp_path / "s.json",
        {"name": "s", "kind": "flow", "architecture": {**arch, "outcome_stretches": [1.0, 1.5, 2.0]}, "onnx": None},
    )
    assert stretched.network_evaluations() == 16 * 10 + 16 * 3  # the flow integrates 16 chunks; the model scores 48
    # a fine-tuned run ships with its own command, not a training.train one
    tuned = {
        "architecture": arch,
        "config": {"algo": "outcome"},
        "reproduce": {"finetune": "python -m training.finetune --algo outcome"},
    }
    assert reproduce_commands(tuned, Path("runs/x"), "flow")[0] == "python -m training.finetune --algo outcome"


def test_an_outcome_fit_continues_a_chooser_of_the_same_widths(tmp_path: Path) -> None:
    from training.finetune import finetune
    from training.finetune_config import FinetuneConfig

    with pytest.raises(ValueError, match="must match to start from it"):
        finetune(FinetuneConfig(init=str(CHOOSER), outcome_dims="8", name="again", out_dir=str(tmp_path), progress=False))
    run = finetune(
        FinetuneConfig(
            init=str(CHOOSER),
            stretches="1,1.5",
            iterations=1,
            num_envs=2,
            rollout_decisions=1,
            label_envs=1,
            eval_every=0,
            batch_size=8,
            learning_starts=8,
            name="warm",
            out_dir=str(tmp_path),
            progress=False,
        )
    )
    policy, card = load_checkpoint(str(run.dir / "last"))
    chooser, _ = load_checkpoint(CHOOSER)
    assert card["architecture"]["outcome_stretches"] == [1.0, 1.5] and policy.outcome.choices == 32
    # the fit starts from the chooser's model (one iteration moves it only a little) and leaves the flow as it was
    before, after = chooser.state_dict(), policy.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before if not k.startswith("outcome."))
    k = policy.outcome.candidates  # the candidate maps are the configured count's, the first ones the same for every count
    assert k == 16 and torch.equal(after["outcome.rotations"], orthogonal_maps(64, 24)[:k])
    # the chooser's saved maps came from another machine's QR: the same maps, to its float rounding
    torch.testing.assert_close(after["outcome.rotations"], before["outcome.rotations"][:k], rtol=0, atol=1e-5)
    start = chooser.outcome.model.net[0].weight
    assert (policy.outcome.model.net[0].weight - start).abs().max() < 0.05 * start.abs().max()


def test_a_resumed_outcome_fit_goes_on_with_its_random_stream(tmp_path: Path) -> None:
    from training.finetune_config import FinetuneConfig
    from training.outcome_fit import FlowChooser, OutcomeFit

    cfg = FinetuneConfig(init=str(SHIPPED), outcome_dims="8", candidates=2, name="x", out_dir=str(tmp_path), progress=False)
    base, card = load_checkpoint(SHIPPED)
    fit = OutcomeFit(FlowChooser(base, card, cfg), cfg, torch.Generator().manual_seed(0))
    fit.rng.random(5)
    tensors, extra = fit.state()
    again = OutcomeFit(FlowChooser(base, card, cfg), cfg, torch.Generator().manual_seed(0))
    again.load_state(tensors, json.loads(json.dumps(extra)))  # the state goes through JSON on disk
    assert again.rng.random() == fit.rng.random()


def test_bad_stretches_on_the_command_line_get_one_line_naming_them() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "training.finetune", "--init", str(SHIPPED), "--stretches", "1.5,1"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2 and "stretches must be comma-separated numbers in (0, 4] starting with 1" in done.stderr


def test_a_stretched_chooser_exports_and_the_graph_acts_as_torch(tmp_path: Path) -> None:
    import acting
    from policies.checkpoint import save_checkpoint
    from training.export import export_onnx

    _, policy = _chooser_from_shipped(candidates=4, stretches=(1.0, 1.4))
    save_checkpoint(tmp_path / "c", policy, policy.normalizer.to_dict())
    info = export_onnx(tmp_path / "c")
    assert info["max_abs_diff"] < 1e-3
    states = np.array(
        [[222.0, 97.0, 222.0, 222.0, 0.8], [300.0, 400.0, 250.0, 260.0, 3.1], [250.0, 240.0, 300.0, 280.0, 0.5]], np.float32
    )
    onnx_policy, torch_policy = acting.load_policy(tmp_path / "c.onnx"), acting.load_policy(tmp_path / "c")
    np.testing.assert_allclose(onnx_policy.act(states, seeds=[1, 2, 3]), torch_policy.act(states, seeds=[1, 2, 3]), atol=1e-3)
    assert torch_policy.card.network_evaluations() == 4 * 10 + 4 * 2


def test_setting_the_candidate_count_keeps_every_learned_weight_and_the_first_maps(tmp_path: Path) -> None:
    from policies.checkpoint import save_checkpoint, set_outcome_candidates
    from training.ship import reproduce_commands

    _, policy = _chooser_from_shipped(candidates=4, stretches=(1.0, 1.5))
    save_checkpoint(
        tmp_path / "c",
        policy,
        policy.normalizer.to_dict(),
        config={"algo": "outcome", "candidates": 4},
        reproduce={"finetune": "python -m training.finetune --algo outcome --candidates 4"},
    )
    card = set_outcome_candidates(tmp_path / "c", 8)
    resized, loaded = load_checkpoint(tmp_path / "c")
    assert (
        card["architecture"]["outcome_candidates"] == loaded["architecture"]["outcome_candidates"] == 8
        and resized.outcome.choices == 16
    )
    before, after = policy.state_dict(), resized.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before if k != "outcome.rotations")
    assert torch.equal(after["outcome.rotations"][:4], before["outcome.rotations"])
    assert loaded["config"] == {"algo": "outcome", "candidates": 4}  # the fit's own config stays
    assert reproduce_commands(loaded, Path("runs/c"), "flow")[1].endswith("--outcome-candidates 8")
    save_checkpoint(tmp_path / "plain", *load_checkpoint(SHIPPED)[:1])
    with pytest.raises(ValueError, match="outcome chooser"):
        set_outcome_candidates(tmp_path / "plain", 8)


def test_nearest_picks_the_first_of_tied_costs_and_the_own_sample_unless_clearly_better() -> None:
    """Costs within float rounding are one cost (the first plays, in ONNX Runtime as in torch); a candidate must beat
    the flow's own sample (index 0) by TIE_MARGIN to replace it."""
    ties = torch.tensor([[1.0, 0.5, 0.5 * (1 - FLOAT_TIE / 10), 0.5, 0.7]])
    clear = torch.tensor([[1.0, 0.9, 0.4, 0.4 * (1 + FLOAT_TIE * 10)]])
    own = torch.tensor([[1.0, 1.0 - TIE_MARGIN / 2, 2.0]])
    assert nearest(torch.cat([ties, torch.ones(1, 1)], dim=1)).tolist() == [1]
    assert nearest(clear).tolist() == [2] and nearest(own).tolist() == [0]

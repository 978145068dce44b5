"""`training.finetune --algo ppo`: the flow's own weights move, the card records its Euler steps, the advantages are GAE."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from policies.checkpoint import load_card, load_checkpoint
from training.export import default_num_steps, export_onnx
from training.finetune import finetune
from training.finetune_config import FinetuneConfig
from training.outcome_fit import FlowChooser
from training.ppo_fit import PPOFit

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "models" / "flow"


def _tiny(tmp_path: Path, **overrides) -> FinetuneConfig:
    settings = dict(
        name="ppo",
        algo="ppo",
        init=str(SHIPPED),
        out_dir=str(tmp_path),
        iterations=3,
        num_envs=6,
        rollout_decisions=2,
        batch_size=4,
        ppo_warmup=1,
        ppo_lr=1e-4,
        eval_every=3,
        eval_episodes=3,
        log_every=1,
        flow_num_steps=2,
        progress=False,
    )
    return FinetuneConfig(**{**settings, **overrides})


def test_a_short_ppo_run_moves_the_flows_weights_and_records_its_euler_steps(tmp_path: Path) -> None:
    run = finetune(_tiny(tmp_path)).dir
    card = load_card(run / "last")
    assert card["finished"] and card["sampler_steps"] == 2 and "outcome_dims" not in card["architecture"]
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    train = [r for r in records if r["type"] == "train"]
    assert "kl" not in train[0] and all(r["updates"] >= 1 and r["kl"] >= 0 for r in train[1:])
    tuned, _ = load_checkpoint(run / "last")
    base, _ = load_checkpoint(SHIPPED)
    moved = [k for k, v in base.state_dict().items() if not torch.equal(v, tuned.state_dict()[k])]
    assert moved and tuned.normalizer.to_dict() == base.normalizer.to_dict()
    export_onnx(run / "last", run / "last.onnx")
    assert default_num_steps(run / "last") == 2


def test_ppo_refuses_an_outcome_chooser(tmp_path: Path) -> None:
    chooser = finetune(_tiny(tmp_path, name="c", algo="outcome", iterations=1, eval_every=0, outcome_dims="8", candidates=2))
    with pytest.raises(ValueError, match="ppo fine-tunes a plain flow"):
        finetune(_tiny(tmp_path, init=str(chooser.dir / "last")))


def test_advantages_are_discounted_returns_with_lambda_one_and_a_zero_critic(tmp_path: Path) -> None:
    """With lambda 1 and a critic of 0 the advantage is the discounted return of the decisions that follow, cut at an
    episode's end."""
    cfg = dataclasses.replace(_tiny(tmp_path), ppo_lambda=1.0, ppo_gamma=0.9)
    base, card = load_checkpoint(SHIPPED)
    fit = PPOFit(FlowChooser(base, card, cfg), cfg, torch.Generator().manual_seed(0))
    torch.nn.init.zeros_(fit.critic.net[-1].weight)
    torch.nn.init.zeros_(fit.critic.net[-1].bias)
    fit.envs = type("Envs", (), {"obs": np.zeros((2, 5)), "time_fraction": lambda self: np.zeros(2)})()
    rewards = [np.array([1.0, 0.5]), np.array([2.0, 0.0]), np.array([4.0, 1.0])]
    done = [np.array([False, True]), np.array([False, False]), np.array([False, False])]
    zero = torch.zeros(2)
    steps = [(torch.zeros(2, 5), zero, torch.zeros(2, 12, 2), torch.zeros(2, 24), zero, r, d) for r, d in zip(rewards, done)]
    batch = fit._advantages(steps)
    g = 0.9**12
    want = [[1 + g * 2 + g * g * 4, 0.5], [2 + g * 4, 0 + g * 1], [4, 1]]
    np.testing.assert_allclose(batch["advantage"].reshape(3, 2).numpy(), want, rtol=1e-5)
    np.testing.assert_allclose(batch["return"].numpy(), batch["advantage"].numpy())


def test_a_resumed_ppo_fit_has_the_flow_the_critic_and_the_episodes_it_saved(tmp_path: Path) -> None:
    cfg = _tiny(tmp_path, ppo_warmup=0)
    base, card = load_checkpoint(SHIPPED)
    fit = PPOFit(FlowChooser(base, card, cfg), cfg, torch.Generator().manual_seed(0))
    fit.iterate([], [])
    tensors, extra = fit.state()
    again = PPOFit(FlowChooser(*load_checkpoint(SHIPPED), cfg), cfg, torch.Generator().manual_seed(0))
    again.load_state(tensors, json.loads(json.dumps(extra)))
    assert again.iterations == 1 and again.episodes == fit.episodes >= cfg.num_envs
    for mine, theirs in ((fit.trained.policy, again.trained.policy), (fit.critic.net, again.critic.net)):
        for name, tensor in mine.state_dict().items():
            assert torch.equal(tensor, theirs.state_dict()[name]), name
    assert again.opt.state_dict()["state"].keys() == fit.opt.state_dict()["state"].keys()

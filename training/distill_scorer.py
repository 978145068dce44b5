"""The scoring pass of a multichoice student: which of its K hypotheses to play, learned from the teacher's outcome model.

A multichoice student's hypotheses hold a better policy than its own scores play: the teacher's outcome
model, choosing among them, plays within a few points of the chooser. That choice is a jump, but what the
model predicts for each hypothesis (where it leaves the block) is smooth in the state, so a second network
pass (`OnePassChooser.changes`, `--scorer-dims`) regresses it, all K at once; the goal distances follow
exactly, and the nearest plays. The
hypotheses stay frozen; the labels cost K outcome-model passes a state and no flow integration, so
the scorer learns from every state the run holds and then, DAgger-style, from the states of episodes it
plays itself (`--scorer-rounds`); after each round the run keeps them all (its pairs file, states only), so that
the next run can start where this one went (`--states-from`).
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

from training.outcome import FEATURE_STATE, FEATURE_TARGETS

__all__ = ["hypothesis_changes", "outcome_scorer", "save_states", "train_scorer"]

LABEL_BATCH = 4096
JITTER = torch.tensor([3.0, 3.0, 3.0, 3.0, 0.03])
"""how far `--scorer-jitter`'s copies of a visited state lie from it, one standard deviation (px, px, px, px, rad)"""


def train_scorer(student, teacher, state_n: torch.Tensor, run, cfg, generator: torch.Generator) -> dict:
    """Train `student.onepass.scorer` on where the teacher's outcome model says the student's hypotheses leave the block at the
    network inputs `state_n` [N, S'] (then `cfg.scorer_rounds` rounds of its own episodes' states); returns the last evaluation."""
    from training.distill_data import PAIRS_FILE, decision_pairs
    from training.evaluate import evaluate_policy
    from training.policies import ActingPolicy

    head = student.onepass
    changes = hypothesis_changes(student, teacher, state_n)
    # what learns: the second pass (unless it is the outcome model itself), the ranker picking what it sees (if any)
    learned = [m for m in (head.scorer if cfg.scorer_dims else None, head.ranker) if m is not None]
    optimizer = torch.optim.AdamW([p for m in learned for p in m.parameters()], lr=cfg.scorer_lr, weight_decay=0.0)
    seed = cfg.round_seed + cfg.teacher_episodes + cfg.rounds * cfg.round_episodes  # after the generator's episodes
    evaluation: dict = {}
    for round_ in range(cfg.scorer_rounds + 1):
        if round_:
            visited, _, scores = decision_pairs(ActingPolicy(student.eval(), 1), cfg.round_episodes, seed)
            seed += cfg.round_episodes
            visited = torch.as_tensor(visited)
            # moved copies cost labels, not episodes: the pass learns around the states it goes to, not at points
            moved = [visited + torch.randn(visited.shape, generator=generator) * JITTER for _ in range(cfg.scorer_jitter)]
            new = teacher.policy_state(torch.cat([visited, *moved]))
            state_n, changes = torch.cat([state_n, new]), torch.cat([changes, hypothesis_changes(student, teacher, new)])
            run.log({"type": "scorer_round", "step": round_, "round": round_, "states": len(state_n), "elapsed_s": run.elapsed_s,
                     **{f"played_{k}": v for k, v in scores.items()}})
            save_states(run.dir / PAIRS_FILE, state_n, cfg.teacher)
        steps = cfg.scorer_steps if round_ == 0 else cfg.scorer_steps // 2
        lr = cfg.scorer_lr if round_ == 0 else cfg.scorer_lr / 3
        _fit(student, learned, state_n, changes, optimizer, steps, lr, run, cfg, generator, round_)
        student.eval()
        summary = evaluate_policy(ActingPolicy(student, 1), episodes=cfg.eval_episodes, seed=cfg.eval_seed)
        evaluation = {"scorer_round": round_, **{k: v for k, v in summary.scores().items() if k != "wall_time_s"}}
        run.log({"type": "scorer_eval", "step": round_, **evaluation})
    return evaluation


@torch.no_grad()
def outcome_scorer(student, teacher, state_n: torch.Tensor) -> None:
    """Make the student's second pass (shared, without context) the teacher's outcome model: at the model's widths the
    model itself, what the pass would learn, exactly; narrower (as many layers), each layer's units that matter most on the
    student's hypotheses at the inputs `state_n` [N, S'] (mean activity times outgoing weight), a start to learn from."""
    from torch import nn

    from training.onepass import SharedScorer

    scorer, model = student.onepass.scorer, teacher.outcome.model
    layers = [m for m in model.net if isinstance(m, nn.Linear)]
    full = [m.out_features for m in layers[:-1]]
    widths = [scorer.state.out_features, *(m.out_features for m in scorer.hidden)] if isinstance(scorer, SharedScorer) else []
    if not widths or scorer.context is not None or len(widths) != len(full) or any(w > f for w, f in zip(widths, full)):
        raise ValueError(f"the teacher's outcome model (widths {full}) starts a shared second pass without context of as many "
                         f"layers, none wider; got {widths or 'another pass'}")
    on_state, bias = _first_layer_on_features(student, model, layers[0])
    keep = [torch.arange(f) for f in full] if widths == full else _most_active(student, model, layers, widths, state_n)
    scorer.state.weight.copy_(on_state[keep[0]])
    scorer.state.bias.copy_(bias[keep[0]])
    scorer.chunk.weight.copy_(layers[0].weight[keep[0]][:, FEATURE_TARGETS])
    for mine, theirs, rows, columns in zip(scorer.hidden, layers[1:-1], keep[1:], keep[:-1]):
        mine.weight.copy_(theirs.weight[rows][:, columns])
        mine.bias.copy_(theirs.bias[rows])
    scorer.out.weight.copy_(layers[-1].weight[:, keep[-1]])
    scorer.out.bias.copy_(layers[-1].bias)


def _first_layer_on_features(student, model, first) -> tuple[torch.Tensor, torch.Tensor]:
    """The outcome model's first layer's part on the state ([W, 6] and its bias) as weights [W, F] on the second pass's own
    features: both are functions of the same five numbers, the model's affine in the pass's (solved on random states,
    checked to rounding)."""
    from training.onepass import head_features

    normalizer = student.normalizer
    noise = torch.randn(1024, len(normalizer.state_mean), generator=torch.Generator().manual_seed(0))
    state = normalizer.state_mean + normalizer.state_std * noise
    ours = torch.cat([head_features(student, student.policy_state(state)), torch.ones(len(state), 1)], dim=1).double()
    theirs = model.features(state, torch.zeros(len(state), *student.onepass.chunk_shape))[:, FEATURE_STATE].double()
    solution = torch.linalg.pinv(ours) @ theirs  # [F + 1, 6]; least squares, rank-deficient (the corners follow from the pose)
    if (ours @ solution - theirs).abs().max() > 1e-6:
        raise ValueError("the second pass's features do not carry the outcome model's view of the state")
    weight = first.weight[:, FEATURE_STATE].double()
    return (weight @ solution[:-1].T).float(), (first.bias.double() + weight @ solution[-1]).float()


def _most_active(student, model, layers, widths: list[int], state_n: torch.Tensor) -> list[torch.Tensor]:
    """For each hidden layer of the outcome model, the indices (in order) of its `widths` units of most mean activity times
    outgoing weight on the student's hypotheses at the inputs `state_n`."""
    from torch.nn import functional as F

    rows, actions = student.onepass.hypothesis_actions(student, state_n, student.onepass(student, state_n)[0])
    h, keep = model.features(rows, actions), []
    for layer, after, width in zip(layers, layers[1:], widths):
        h = F.silu(layer(h))
        keep.append((h.abs().mean(dim=0) * after.weight.norm(dim=0)).topk(width).indices.sort().values)
    return keep


def save_states(path, state_n: torch.Tensor, teacher: str) -> None:
    """Keep the network inputs [N, S'] the second pass learned from (a run's pairs file with states only), so that another
    run can start from them (`--states-from`)."""
    from safetensors.torch import save_file

    save_file({"state_n": state_n.contiguous()}, str(path), metadata={"teacher": str(teacher), "labels": "states"})


@torch.no_grad()
def hypothesis_changes(student, teacher, state_n: torch.Tensor) -> torch.Tensor:
    """[N, K * S, 3]: where the teacher's outcome model says each of the student's K hypotheses at the inputs `state_n` [N, S']
    leaves the block at each stretch the second pass scores (its network's output: a move in the block's frame and a turn, scaled)."""
    head, model, out = student.onepass, teacher.outcome.model, []
    for i in range(0, len(state_n), LABEL_BATCH // len(head.scorer_stretches)):
        rows_n = state_n[i : i + LABEL_BATCH // len(head.scorer_stretches)]
        state, actions = head.scored_actions(student, rows_n, head(student, rows_n)[0])
        out.append(model.net(model.features(state, actions)).reshape(len(rows_n), -1, 3))  # all K, even where acting scores the top
    return torch.cat(out)


def _fit(student, learned: list, state_n, changes, optimizer, steps: int, lr: float, run, cfg, generator: torch.Generator,
         round_: int) -> None:
    """`steps` optimizer steps of the `learned` parts' losses (`OnePassChooser.scorer_loss`, `ranker_loss`) on random batches
    (cosine from `lr`), logged as "scorer" records."""
    from tqdm import tqdm

    head = student.onepass
    for module in learned:
        module.train()
    running, start = 0.0, time.perf_counter()
    for step in tqdm(range(1, steps + 1), desc=f"scorer {round_}", disable=not cfg.progress, file=sys.stderr):
        for group in optimizer.param_groups:
            group["lr"] = lr * 0.5 * (1 + np.cos(np.pi * (step - 1) / steps))
        rows = torch.randint(0, len(state_n), (cfg.batch_size,), generator=generator)
        loss = head.ranker_loss(student, state_n[rows], changes[rows]) if head.ranker in learned else 0.0
        if head.scorer in learned:
            with torch.no_grad():
                chunks_n, _ = head(student, state_n[rows])
            loss = loss + head.scorer_loss(student, state_n[rows], chunks_n, changes[rows])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        running += float(loss.detach())
        if step % cfg.log_every == 0:
            run.log({"type": "scorer", "step": step, "round": round_, "loss": running / cfg.log_every,
                     "ms_per_step": 1e3 * (time.perf_counter() - start) / step})
            running = 0.0
        if run.stop_requested:
            raise ValueError(f"stopped by {run.stop_signal} at scorer step {step}; start it again with another --name")

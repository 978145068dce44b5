"""The outcome chooser's whole decision in one network pass: K candidate chunks and their K x S scores at once.

The shipped chooser integrates 64 flow candidates in 10 Euler steps each and scores 256 stretched
versions with its outcome model: 896 network evaluations. From one fixed start noise those candidates
are smooth functions of the state, and so are their predicted distances to the goal; only the choice
among them jumps. A flow student that regresses the chosen chunk must average across those jumps
(hesitant pushes, models/README.md); `OnePassChooser` instead regresses what is smooth (every
candidate and every score, as multi-hypothesis heads) and keeps the jump exact: an argmin over the
predicted scores, then the chosen candidate stretched as the chooser stretches it. One MLP pass per
chunk. `training.distill --student one-pass` trains it on the chooser's labels. Imports only torch (and pusht's action bounds).

The same head serves a multiple-choice student (`training.distill --student multichoice`; Guzman-Rivera et
al. 2012): K hypotheses of the chooser's one chosen chunk, trained winner-takes-all, and K scores that
learn which hypothesis is nearest (`multichoice_loss`); it plays the best-scored one, unstretched. Its own scores
only guess which hypothesis the chooser would pick; with `scorer_dims` a second pass (2 network evaluations) sees
all K hypotheses, their targets in the block's frame as the outcome model sees them, and predicts where each
leaves the block as the teacher's outcome model would (`scorer_loss`): the one predicted nearest the goal plays.
With `scorer_stretches` the second pass also predicts each hypothesis stretched (as the chooser stretches its
candidates) from the same inputs, and the nearest of all K x S plays at its stretch: the hypotheses, chosen
so by the teacher's outcome model, play 1.6 points better than unstretched (models/README.md).
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn
from torch.nn import functional as F

from pusht.spec import ACTION_HIGH, ACTION_LOW
from training.features import KEYPOINT_FEATURES, tee_keypoints
from training.networks import silu_mlp
from training.outcome import TIE_MARGIN, agent_in_block_frame, goal_corner_distance, pose_after, stretch, targets_in_block_frame

__all__ = ["CHOICE_WEIGHT", "EXTRA_FEATURES", "OnePassChooser", "first_nearest", "gather_hypotheses", "head_features", "score_target",
           "winner_takes_all"]

EXTRA_FEATURES = KEYPOINT_FEATURES + 2
"""what `head_features` adds to the flow's encoded state: the tee's corners and the agent in the block's frame"""

# Scores are learned as standardized log distances (the order is all that acting uses): near the goal, where the
# student used to fail, distances of 1e-4 and 1e-3 differ as much as 0.1 and 1. Constants from the chooser's labels.
_LOG_FLOOR, _LOG_MEAN, _LOG_STD = 1e-5, -2.7, 2.0
CHOICE_WEIGHT = 0.1
"""a multiple-choice student's scores are logits (negated); their cross-entropy counts a tenth of the chunks' error"""
REGRET_TEMPERATURE = 0.1
"""of the second pass's softmax pick, in `score_target` units (a tenth of a standardized log distance)"""


class OnePassChooser(nn.Module):
    """MLP(encoded state, tee corners, agent in the block's frame) -> K normalized candidate chunks and K x S scores (lower: predicted closer to the goal)."""

    def __init__(self, encoded_dim: int, chunk_shape: tuple[int, int], hidden_dims: Sequence[int], candidates: int,
                 stretches: Sequence[float], scorer_dims: Sequence[int] | None = None, scorer_shared: bool = False,
                 scorer_stretches: Sequence[float] = (1.0,), scorer_context: bool = True, scorer_top: int | None = None,
                 ranker_dims: Sequence[int] | None = None) -> None:
        super().__init__()
        self.chunk_shape = tuple(chunk_shape)
        self.candidates = int(candidates)
        self.stretches = tuple(float(s) for s in stretches)
        self.choices = self.candidates * len(self.stretches)
        self.chunk_dim = self.chunk_shape[0] * self.chunk_shape[1]
        self.scorer_stretches = tuple(float(s) for s in scorer_stretches)
        self.scorer_top = scorer_top
        """the second pass scores only the first pass's this many best-scored hypotheses (None: all K)"""
        self.scored = (scorer_top or self.candidates) * len(self.scorer_stretches)
        """how many (hypothesis, stretch) choices the second pass scores: the K (or top) hypotheses at each stretch in turn"""
        self.net = silu_mlp(encoded_dim + EXTRA_FEATURES, hidden_dims, self.candidates * self.chunk_dim + self.choices)
        # One network pass over the K hypotheses: a plain MLP over them side by side, or with `scorer_shared` a set network
        # whose layers they share (`SharedScorer`).
        # It predicts where each hypothesis leaves the block (as the outcome model's network: a move and a turn); the
        # goal distances, where the choice's jumps lie, then follow exactly. Plain hypotheses only (no first-pass stretch);
        # the second pass may score each at `scorer_stretches`.
        self.scorer = None
        if scorer_dims:
            if self.stretches != (1.0,):
                raise ValueError(f"a scoring pass scores plain hypotheses, not stretches {list(self.stretches)}")
            features = encoded_dim + EXTRA_FEATURES
            self.scorer = (SharedScorer(features, self.chunk_dim, scorer_dims, 3 * len(self.scorer_stretches), scorer_context) if scorer_shared
                           else silu_mlp(features + self.candidates * self.chunk_dim, scorer_dims, self.scored * 3))
        # With `scorer_top` the first pass's K scores pick which hypotheses the second pass sees: its own score rows, or a
        # small MLP on its last hidden layer (`ranker_dims`) that learns where the outcome model's pick lies (`ranker_loss`).
        self.ranker = silu_mlp(hidden_dims[-1], ranker_dims, self.candidates) if ranker_dims else None

    # Shapes below use -1 and flatten, never a traced batch size, so the exported graph keeps a dynamic batch.
    def forward(self, flow: nn.Module, state_n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalized candidate chunks [B, K, H, A] and scores [B, K * S] (the K candidates at each stretch in turn) for the flow's inputs."""
        return self._split(self.net(head_features(flow, state_n)))

    def _split(self, out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The first pass's output [B, K * H * A + K * S] as chunks [B, K, H, A] and scores [B, K * S]."""
        split = self.candidates * self.chunk_dim
        return out[:, :split].reshape(-1, self.candidates, *self.chunk_shape), out[:, split:]

    def scores(self, flow: nn.Module, state_n: torch.Tensor, chunks_n: torch.Tensor | None = None) -> torch.Tensor:
        """The scores [B, K * S] that choose (lower: predicted closer to the goal): the second pass's, `score_target` of the
        goal distances after the hypotheses `chunks_n` [B, K, H, A] (normalized; this head's own when None), else the head's own."""
        if self.scorer is None:
            return self(flow, state_n)[1]
        if chunks_n is None:
            chunks_n = self(flow, state_n)[0]
        return score_target(self._distances(flow, state_n, chunks_n, head_features(flow, state_n)))

    def changes(self, flow: nn.Module, state_n: torch.Tensor, chunks_n: torch.Tensor, features: torch.Tensor | None = None) -> torch.Tensor:
        """The second pass: [B, K * S, 3] where each hypothesis [B, K, H, A] (normalized) at each scored stretch leaves the
        block, in the outcome model's units (`features`: `head_features` of `state_n`, if at hand)."""
        features = head_features(flow, state_n) if features is None else features
        rows, actions = self.hypothesis_actions(flow, state_n, chunks_n)
        frame = targets_in_block_frame(rows, actions)
        k, stretches = chunks_n.shape[1], len(self.scorer_stretches)
        if isinstance(self.scorer, SharedScorer):  # [B, K, S * 3] -> the K at each stretch in turn
            out = self.scorer(features, frame.reshape(-1, k, self.chunk_dim))
            return out.reshape(-1, k, stretches, 3).transpose(1, 2).reshape(-1, k * stretches, 3)
        return self.scorer(torch.cat([features, frame.reshape(-1, k * self.chunk_dim)], dim=1)).reshape(-1, k * stretches, 3)

    def hypothesis_actions(self, flow: nn.Module, state_n: torch.Tensor, chunks_n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each hypothesis [B, K, H, A] (normalized) as env-unit rows: its state [B * K, S] and clipped actions [B * K, H, A]."""
        rows = flow.normalizer.env_state(state_n[:, : flow.state_dim]).repeat_interleave(chunks_n.shape[1], dim=0)
        return rows, torch.clamp(flow.normalizer.actions(rows, chunks_n.reshape(-1, *self.chunk_shape)), ACTION_LOW, ACTION_HIGH)

    def scored_actions(self, flow: nn.Module, state_n: torch.Tensor, chunks_n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """What the second pass scores, as env-unit rows: each row's state [B * K * S, S'] and the clipped actions
        [B * K * S, H, A] of each hypothesis [B, K, H, A] (normalized) at each scored stretch (the K at each stretch in turn)."""
        rows, actions = self.hypothesis_actions(flow, state_n, chunks_n)
        if self.scorer_stretches == (1.0,):
            return rows, actions
        states = rows[:: self.candidates]
        actions = actions.reshape(-1, self.candidates, *self.chunk_shape)
        every = torch.stack([_stretched(states, actions, factor) for factor in self.scorer_stretches], dim=1)
        return states.repeat_interleave(self.scored, dim=0), every.reshape(-1, *self.chunk_shape)

    def goal_distances(self, flow: nn.Module, state_n: torch.Tensor, changes: torch.Tensor) -> torch.Tensor:
        """[B, K * S]: the goal distances (`goal_corner_distance`) after the K hypotheses at each scored stretch move the block by
        `changes` [B, K * S, 3] (the outcome model's units) from the flow's inputs `state_n`."""
        rows = flow.normalizer.env_state(state_n[:, : flow.state_dim]).repeat_interleave(changes.shape[1], dim=0)
        return goal_corner_distance(pose_after(rows, changes.reshape(-1, 3))).reshape(-1, changes.shape[1])

    def _distances(self, flow: nn.Module, state_n: torch.Tensor, chunks_n: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """[B, K * S]: the goal distances after the hypotheses at each scored stretch, by the second pass."""
        return self.goal_distances(flow, state_n, self.changes(flow, state_n, chunks_n, features))

    def scorer_loss(self, flow: nn.Module, state_n: torch.Tensor, chunks_n: torch.Tensor, changes: torch.Tensor) -> torch.Tensor:
        """The second pass's loss on hypotheses [B, K, H, A] that the teacher's outcome model says move the block by `changes`
        [B, K * S, 3] at the scored stretches (its network's output): their squared error, plus the expected regret of a softmax pick by the scores
        (in `score_target` units: what a wrong pick costs)."""
        predicted = self.changes(flow, state_n, chunks_n)
        scores, target = (score_target(self.goal_distances(flow, state_n, c)) for c in (predicted, changes))
        regret = target - target.min(dim=1, keepdim=True).values
        return F.mse_loss(predicted, changes) + (torch.softmax(-scores / REGRET_TEMPERATURE, dim=1) * regret).sum(dim=1).mean()

    def ranker_loss(self, flow: nn.Module, state_n: torch.Tensor, changes: torch.Tensor) -> torch.Tensor:
        """The ranker's listwise cross-entropy: its softmax over the K hypotheses against the outcome model's, whose `changes`
        [B, K, 3] (its network's output) rank them by goal distance (at `REGRET_TEMPERATURE`: near ties share the mass)."""
        target = score_target(self.goal_distances(flow, state_n, changes))
        want = torch.softmax(-(target - target.min(dim=1, keepdim=True).values) / REGRET_TEMPERATURE, dim=1)
        scores = self.ranker(self.net[:-1](head_features(flow, state_n)))
        return -(want * torch.log_softmax(-scores, dim=1)).sum(dim=1).mean()

    def loss(self, flow: nn.Module, state_n: torch.Tensor, candidates: torch.Tensor, distances: torch.Tensor) -> torch.Tensor:
        """Mean squared error of the candidates [B, K, H, A] (normalized) plus that of the scores against `score_target` of the
        chooser's predicted goal distances [B, K * S]."""
        chunks_n, scores = self(flow, state_n)
        return F.mse_loss(chunks_n, candidates) + F.mse_loss(scores, score_target(distances))

    def multichoice_loss(self, flow: nn.Module, state_n: torch.Tensor, target: torch.Tensor, relax: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Multiple-choice learning of one chunk [B, H, A] or M [B, M, H, A] (normalized): the candidate nearest to each regresses
        it (the others get `relax` of that loss, so none dies), the scores learn which one is nearest (the first); returns the loss
        and the best-scored chunks."""
        chunks_n, scores = self(flow, state_n)
        loss, nearest = winner_takes_all(chunks_n, target, relax)
        loss = loss + CHOICE_WEIGHT * F.cross_entropy(-scores, nearest)
        return loss, chunks_n[torch.arange(len(chunks_n)), scores.argmin(dim=1)]

    def best_chunk(self, flow: nn.Module, state_n: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """The normalized chunk [B, H, A]: the best-scored candidate at its stretch (a stretch s moves every target s times
        as far from the agent, as `training.outcome.OutcomeSelector` offers it). Deterministic: `noise` [B, H, A] is unused."""
        # A zero term keeps `noise` an input of the exported graph, as the ONNX contract has every flow take it.
        if self.scorer is None:
            chunks_n, scores = self(flow, state_n)
            stretches = self.stretches
            best = (scores + 0.0 * noise.flatten(1)[:, :1]).argmin(dim=1)
        else:  # the features once for both passes, and the distances themselves: their argmin is the scores'
            features = head_features(flow, state_n)
            hidden = self.net[:-1](features)
            chunks_n, first = self._split(self.net[-1](hidden))
            if self.scorer_top:  # the second pass sees only the first pass's best-scored (in order)
                first = first if self.ranker is None else self.ranker(hidden)
                chunks_n = gather_hypotheses(chunks_n, torch.topk(first, self.scorer_top, dim=1, largest=False).indices)
            stretches = self.scorer_stretches
            best = first_nearest(self._distances(flow, state_n, chunks_n, features) + 0.0 * noise.flatten(1)[:, :1])
        index = torch.remainder(best, self.candidates).reshape(-1, 1, 1, 1).expand(-1, 1, *self.chunk_shape)
        chunk_n = torch.gather(chunks_n, 1, index).squeeze(1)
        if stretches == (1.0,):
            return chunk_n
        factor = torch.tensor(stretches, dtype=state_n.dtype, device=state_n.device)[torch.div(best, self.candidates, rounding_mode="floor")]
        state = flow.normalizer.env_state(state_n[:, : flow.state_dim])
        actions = flow.normalizer.actions(state, chunk_n)
        if self.scorer is None:  # as the chooser stretches its candidates
            return flow.normalizer.chunk(state, stretch(state, actions, factor.reshape(-1, 1, 1)))
        # as the second pass's labels stretch the hypotheses (`scored_actions`): clipped before and after
        return flow.normalizer.chunk(state, _stretched(state, torch.clamp(actions, ACTION_LOW, ACTION_HIGH), factor.reshape(-1, 1, 1)))


class SharedScorer(nn.Module):
    """A second pass whose layers the K hypotheses share (a set network, one pass over all K): each layer maps every
    hypothesis alike and adds a map of their mean, so each learns from all K slots; the state's features enter once.
    Without `context` each hypothesis is scored alone: the teacher's outcome model fits it (`training.distill_scorer.outcome_scorer`)."""

    def __init__(self, feature_dim: int, chunk_dim: int, dims: Sequence[int], outputs: int = 3, context: bool = True) -> None:
        super().__init__()
        self.state = nn.Linear(feature_dim, dims[0])
        self.chunk = nn.Linear(chunk_dim, dims[0], bias=False)
        self.hidden = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.context = nn.ModuleList(nn.Linear(a, b, bias=False) for a, b in zip(dims[:-1], dims[1:])) if context else None
        self.out = nn.Linear(dims[-1], outputs)

    def forward(self, features: torch.Tensor, chunks: torch.Tensor) -> torch.Tensor:
        """[B, K, outputs] from the state's features [B, F] and the K hypotheses' targets in the block's frame [B, K, H * A]."""
        h = F.silu(self.chunk(chunks) + self.state(features)[:, None])
        for i, layer in enumerate(self.hidden):
            h = layer(h) if self.context is None else layer(h) + self.context[i](h.mean(dim=1, keepdim=True))
            h = F.silu(h)
        return self.out(h)


def gather_hypotheses(chunks: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """The hypotheses [B, M, H, A] at `index` [B, M] of chunks [B, K, H, A]."""
    return torch.gather(chunks, 1, index[:, :, None, None].expand(-1, -1, *chunks.shape[2:]))


def _stretched(state: torch.Tensor, actions: torch.Tensor, factor: float | torch.Tensor) -> torch.Tensor:
    """Clipped env-unit actions [B, ..., H, A] stretched by `factor` from the agent of states [B, S] (`stretch`), clipped again."""
    agent = state[:, : actions.shape[-1]].reshape(len(state), *([1] * (actions.dim() - 2)), actions.shape[-1])
    return torch.clamp(agent + factor * (actions - agent), ACTION_LOW, ACTION_HIGH)


def head_features(flow: nn.Module, state_n: torch.Tensor) -> torch.Tensor:
    """[B, encoded + EXTRA_FEATURES]: the flow's encoded state, the tee's corners and the agent in the block's frame, from its inputs."""
    state = flow.normalizer.env_state(state_n[:, : flow.state_dim])
    return torch.cat([flow.encode_state(state_n), tee_keypoints(state[:, 2:5]), agent_in_block_frame(state)], dim=1)


def winner_takes_all(chunks_n: torch.Tensor, target: torch.Tensor, relax: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The relaxed winner-takes-all regression of hypotheses [B, K, H, A] on one chunk [B, H, A] or M chunks [B, M, H, A], each
    pulling its nearest hypothesis (which gets 1 - `relax` of its error, the mean over all `relax`), and the index [B] of the
    hypothesis nearest the (first) chunk."""
    targets = target[:, None] if target.dim() == 3 else target
    error = (chunks_n[:, None] - targets[:, :, None]).pow(2).mean(dim=(3, 4))  # [B, M, K]
    nearest = error.argmin(dim=2)
    return (1 - relax) * error.gather(2, nearest[..., None]).mean() + relax * error.mean(), nearest[:, 0]


def first_nearest(distance: torch.Tensor) -> torch.Tensor:
    """Index [B] of the first of the choices' goal distances [B, C] within `TIE_MARGIN` (relative) of the least. Hypotheses
    that miss the block tie to the last bit, and torch and ONNX Runtime round differently: the earlier one plays in both."""
    least = distance.min(dim=1, keepdim=True).values
    return (distance <= least * (1 + TIE_MARGIN)).float().argmax(dim=1)


def score_target(distance: torch.Tensor) -> torch.Tensor:
    """What a score regresses: the standardized log of a predicted goal distance (`training.outcome.goal_corner_distance`)."""
    return (torch.log(distance + _LOG_FLOOR) - _LOG_MEAN) / _LOG_STD

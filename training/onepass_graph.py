"""A scoring student's act (`OnePassChooser` with a second pass) as a lean graph: the same function in two fifths of the ops.

At batch 1 ONNX Runtime spends about a microsecond per node, and the module as written for training (z-scored
inputs turned back into env units, sines taken four times, indexing by slices) exports to 170 nodes, a quarter
of the chunk's cost. Here every linear step is folded into the networks' weights: the features that the first
layers see are linear in ten numbers of the state (its four coordinates, the angle's sine and cosine, and the
agent's offset from the block times them), the action statistics go into the generator's last layer, the
block frame's scale into the scorer's first, the outcome units into its last; the goal distance of the tee's
corners after each hypothesis is one small product with a constant matrix. The scorer's first layer is kept as
two (on z, and on the hypotheses' targets: `frame`) so that `training.quantize` can take the second to int8
and leave the first, which sees pixels beside sines, in float32. A shared (set-network) pass runs each hypothesis
as a row of its own, so its layers are plain products that quantize alike; the maps of their mean stay float32. Float rounding differs from the module's, so a
choice between two hypotheses tied to about 1e-6 may differ; nothing else does.
"""

from __future__ import annotations

import copy
import math

import torch
from torch import nn

from pusht.geometry import GOAL_POSE
from pusht.spec import ACTION_HIGH, ACTION_LOW
from training.features import _CORNERS, _CENTER, _SCALE
from training.onepass import SharedScorer, _stretched, first_nearest, gather_hypotheses
from training.outcome import _FRAME_SCALE, _POSE_SCALE

__all__ = ["LeanScoredChoice", "lean_graph"]


def lean_graph(flow: nn.Module) -> "LeanScoredChoice | None":
    """The lean graph of a scoring student (a one-pass head with its second pass, the shipped flows' inputs), None for any other policy."""
    return LeanScoredChoice(flow) if _fits(flow) else None


def _fits(flow: nn.Module) -> bool:
    """Whether the folding below holds: a scoring head, a 5-d state seen as z-scores and the angle's sine and cosine (no
    history or pace input), 2-d actions relative to the agent."""
    head = getattr(flow, "onepass", None)
    return (head is not None and isinstance(head.scorer, (nn.Sequential, SharedScorer)) and head.stretches == (1.0,) and flow.state_dim == 5
            and head.chunk_shape[1] == 2 and flow.angle_encoding == "sincos" and not flow.prev_state and not flow.pace_input
            and flow.normalizer.action_frame == "agent")


class LeanScoredChoice(nn.Module):
    """Env-unit states [B, 5] and noise [B, H, A] (unused, kept as the ONNX contract's input) -> clipped actions [B, H, A]."""

    def __init__(self, flow: nn.Module) -> None:
        super().__init__()
        if not _fits(flow):
            raise ValueError("a lean graph needs a scoring student of the shipped flows' inputs (see lean_graph)")
        head = flow.onepass
        self.k, self.chunk_shape, self.scored, self.top = head.candidates, head.chunk_shape, head.scored, head.scorer_top
        self.stretched = head.scorer_stretches != (1.0,)
        self.register_buffer("stretches", torch.tensor(head.scorer_stretches, dtype=torch.float32))
        with torch.no_grad():
            linear = _feature_map(flow)  # features [20] = z [10] @ linear[:10] + linear[10]
            gen = [m for m in head.net if isinstance(m, nn.Linear)]
            self.gen = nn.ModuleList([_fold_first(gen[0], linear), *(copy.deepcopy(m) for m in gen[1:-1]), _fold_actions(gen[-1], flow, head)])
            if self.top:  # what picks the hypotheses the second pass sees: the ranker, or the generator's score rows
                rows = head.candidates * head.chunk_dim
                self.first_scores = (nn.Sequential(_linear(gen[-1].weight[rows:], gen[-1].bias[rows:])) if head.ranker is None
                                     else copy.deepcopy(head.ranker))
            # A shared pass's layers map each hypothesis as a row of its own [B * K, ...], plus a map of their mean (`context`).
            self.shared = isinstance(head.scorer, SharedScorer)
            if self.shared:
                scorer = head.scorer
                first, self.frame = _fold_scorer_first(scorer.state.weight, scorer.state.bias, scorer.chunk.weight, linear)
                sco = [first, *(copy.deepcopy(m) for m in scorer.hidden), _fold_changes(scorer.out, len(head.scorer_stretches))]
                self.context = copy.deepcopy(scorer.context)
            else:
                layers = [m for m in head.scorer if isinstance(m, nn.Linear)]
                w = layers[0].weight
                first, self.frame = _fold_scorer_first(w[:, :20], layers[0].bias, w[:, 20:], linear)
                sco = [first, *(copy.deepcopy(m) for m in layers[1:-1]), _fold_changes(layers[-1], head.scored)]
            self.sco = nn.ModuleList(sco)
            self.stretch_count = len(head.scorer_stretches)
            self.register_buffer("corners", _corner_map())  # [5, 12]: [d_x, d_y, cos, sin, 1] -> corner differences
            self.register_buffer("goal", torch.tensor(GOAL_POSE[:2], dtype=torch.float32))

    def forward(self, state: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Clipped actions [B, H, A]: the hypothesis (at the stretch) whose predicted outcome leaves the tee's corners nearest the goal's."""
        agent, block, angle = state[:, 0:2], state[:, 2:4], state[:, 4:5]
        cos, sin = torch.cos(angle), torch.sin(angle)
        offset = agent - block
        z = torch.cat([state[:, :4], sin, cos, cos * offset, sin * offset], dim=1)
        h = z
        for layer in self.gen[:-1]:
            h = nn.functional.silu(layer(h))
        actions = torch.clamp(self.gen[-1](h).reshape(-1, self.k * self.chunk_shape[0], 2) + agent[:, None], ACTION_LOW, ACTION_HIGH)
        k = self.k
        if self.top:  # the first pass's best-scored, in order
            k, best_first = self.top, torch.topk(self.first_scores(h), self.top, dim=1, largest=False).indices
            actions = gather_hypotheses(actions.reshape(-1, self.k, *self.chunk_shape), best_first).reshape(-1, k * self.chunk_shape[0], 2)
        # [[cos, -sin], [sin, cos]]: rows @ it rotates world vectors into the block's frame, its transpose back out.
        to_block = torch.cat([cos, -sin, sin, cos], dim=1).reshape(-1, 2, 2)
        frame = torch.matmul(actions - block[:, None], to_block)
        change = self._shared_changes(z, frame, k) if self.shared else self._changes(z, frame)  # the K at each scored stretch in turn
        moved = torch.matmul(change[:, :, :2], to_block.transpose(1, 2)) + (block - self.goal)[:, None]
        turned = angle[:, None] + change[:, :, 2:]
        pose = torch.cat([moved, torch.cos(turned), torch.sin(turned)], dim=2)
        distance = torch.matmul(pose, self.corners[:4]).add(self.corners[4]).pow(2).sum(dim=2)
        # A zero term keeps `noise` an input of the exported graph, as the ONNX contract has every flow take it.
        best = first_nearest(distance + 0.0 * noise[:, 0, :1])
        index = torch.remainder(best, k).reshape(-1, 1, 1, 1).expand(-1, 1, *self.chunk_shape)
        chosen = torch.gather(actions.reshape(-1, k, *self.chunk_shape), 1, index).squeeze(1)
        if not self.stretched:
            return chosen
        factor = self.stretches[torch.div(best, self.k, rounding_mode="floor")].reshape(-1, 1, 1)
        return _stretched(state, chosen, factor)


    def _changes(self, z: torch.Tensor, frame: torch.Tensor) -> torch.Tensor:
        """[B, K * S, 3]: the side-by-side pass on z [B, 10] and all K hypotheses' targets in the block's frame [B, K * H, 2]."""
        h = nn.functional.silu(self.sco[0](z) + self.frame(frame.flatten(1)))  # one layer on [z, frame], split so the frame's part can go int8
        for layer in self.sco[1:-1]:
            h = nn.functional.silu(layer(h))
        return self.sco[-1](h).reshape(-1, self.scored, 3)

    def _shared_changes(self, z: torch.Tensor, frame: torch.Tensor, k: int) -> torch.Tensor:
        """[B, K * S, 3]: the shared pass over k hypotheses, each a row [B * k, ...] so that every layer is one plain product."""
        first = self.frame(frame.reshape(-1, self.chunk_shape[0] * 2))
        h = nn.functional.silu((first.reshape(-1, k, first.shape[1]) + self.sco[0](z)[:, None]).reshape(-1, first.shape[1]))
        for i, layer in enumerate(self.sco[1:-1]):
            if self.context is None:  # each hypothesis alone
                h = nn.functional.silu(layer(h))
                continue
            mean = h.reshape(-1, k, h.shape[1]).mean(dim=1)
            out = layer(h)
            h = nn.functional.silu((out.reshape(-1, k, out.shape[1]) + self.context[i](mean)[:, None]).reshape(-1, out.shape[1]))
        return self.sco[-1](h).reshape(-1, k, self.stretch_count, 3).transpose(1, 2).reshape(-1, k * self.stretch_count, 3)


def _feature_map(flow: nn.Module) -> torch.Tensor:
    """[11, 20]: `head_features` as z @ map[:10] + map[10], z = [agent, block, sin, cos, cos * offset, sin * offset]
    (offset: agent - block), column for column."""
    mean, std = flow.normalizer.state_mean.float(), flow.normalizer.state_std.float()
    m = torch.zeros(11, 20)
    for i in range(4):  # the encoded state: z-scored coordinates, then sin and cos
        m[i, i], m[10, i] = 1.0 / std[i], -mean[i] / std[i]
    m[4, 4], m[5, 5] = 1.0, 1.0
    for k, (cx, cy) in enumerate(_CORNERS):  # tee_keypoints: x = bx + cos cx - sin cy, y = by + sin cx + cos cy
        col = 6 + 2 * k
        m[2, col], m[5, col], m[4, col], m[10, col] = 1 / _SCALE, cx / _SCALE, -cy / _SCALE, -_CENTER / _SCALE
        m[3, col + 1], m[4, col + 1], m[5, col + 1], m[10, col + 1] = 1 / _SCALE, cx / _SCALE, cy / _SCALE, -_CENTER / _SCALE
    # agent_in_block_frame: (cos dx + sin dy, -sin dx + cos dy) / scale; z[6:8] = cos * (dx, dy), z[8:10] = sin * (dx, dy)
    m[6, 18], m[9, 18] = 1 / _FRAME_SCALE, 1 / _FRAME_SCALE
    m[8, 19], m[7, 19] = -1 / _FRAME_SCALE, 1 / _FRAME_SCALE
    return m


def _linear(weight: torch.Tensor, bias: torch.Tensor) -> nn.Linear:
    out = nn.Linear(weight.shape[1], weight.shape[0])
    out.weight.copy_(weight)
    out.bias.copy_(bias)
    return out


def _fold_first(layer: nn.Linear, linear: torch.Tensor) -> nn.Linear:
    """The generator's first layer on z instead of the 20 features."""
    w = layer.weight.double()
    return _linear((w @ linear[:10].double().T).float(), (layer.bias.double() + w @ linear[10].double()).float())


def _fold_scorer_first(on_features: torch.Tensor, bias: torch.Tensor, on_targets: torch.Tensor, linear: torch.Tensor) -> tuple[nn.Linear, nn.Linear]:
    """The scorer's first layer on z (with its bias) and on the targets in the block's frame, unscaled (a zero bias), instead
    of its weights on the 20 features and on the scaled targets."""
    features, targets = on_features.double(), on_targets.double() / _FRAME_SCALE
    on_z = _linear((features @ linear[:10].double().T).float(), (bias.double() + features @ linear[10].double()).float())
    return on_z, _linear(targets.float(), torch.zeros(targets.shape[0]))


def _fold_actions(layer: nn.Linear, flow: nn.Module, head: nn.Module) -> nn.Linear:
    """The generator's last layer giving the K hypotheses' env-unit actions less the agent (agent frame), score rows dropped."""
    rows = head.candidates * head.chunk_dim
    std = flow.normalizer.action_std.double().expand(*head.chunk_shape).reshape(-1).repeat(head.candidates)
    mean = flow.normalizer.action_mean.double().expand(*head.chunk_shape).reshape(-1).repeat(head.candidates)
    w, b = layer.weight[:rows].double(), layer.bias[:rows].double()
    return _linear((w * std[:, None]).float(), (b * std + mean).float())


def _fold_changes(layer: nn.Linear, scored: int) -> nn.Linear:
    """The scorer's last layer in env units (px, px, rad) instead of the outcome model's."""
    scale = torch.tensor(_POSE_SCALE, dtype=torch.float64).repeat(scored)
    return _linear((layer.weight.double() * scale[:, None]).float(), (layer.bias.double() * scale).float())


def _corner_map() -> torch.Tensor:
    """[5, 12]: [d_x, d_y, cos a, sin a, 1] @ map = the tee's corners at (goal + d, a) less the goal's corners (x, y per corner)."""
    gc, gs = math.cos(GOAL_POSE[2]), math.sin(GOAL_POSE[2])
    m = torch.zeros(5, 12, dtype=torch.float64)
    for k, (cx, cy) in enumerate(_CORNERS):
        m[0, 2 * k], m[1, 2 * k + 1] = 1.0, 1.0
        m[2, 2 * k], m[3, 2 * k] = cx, -cy
        m[2, 2 * k + 1], m[3, 2 * k + 1] = cy, cx
        m[4, 2 * k], m[4, 2 * k + 1] = -(gc * cx - gs * cy), -(gs * cx + gc * cy)
    return m.float()

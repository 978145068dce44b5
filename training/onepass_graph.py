"""A scoring student's act (`OnePassChooser` with a second pass) as a lean graph: the same function in a third of the ops.

At batch 1 ONNX Runtime spends about a microsecond per node, and the module as written for training (z-scored
inputs turned back into env units, sines taken four times, indexing by slices) exports to 170 nodes, a quarter
of the chunk's cost. Here every linear step is folded into a weight:
- One product of the state gives everything the graph needs of it: the angle at four phases (one Sin: cos, -sin,
  sin, cos, which is also the rotation into the block's frame), the agent's offset from the block and the block
  (whose products with them are the rest of the features), and the agent and block tiled over the chunks.
- The features the first layers see are linear in those numbers (`_feature_map`); so is, per tee corner, where the
  goal's corner lies from the block, in the block's frame (`_goal_map`), which the scoring pass's first layer gives
  beside its units.
- The action statistics go into the generator's last layer, the block frame's scale into the scorer's first, the
  outcome units and the tee's corners into its last: it gives each hypothesis's corners, moved (`sco.-1`), and the
  turn's cosine and sine (`turns`, one Sin), so the goal distance is one product and a sum of squares.
The scorer's first layer is kept as two (on the features, and on the hypotheses' targets: `frame`) so that
`training.quantize` can take the second to int8 and leave the first, which sees pixels beside sines, in float32.
A shared (set-network) pass runs each hypothesis as a row of its own, so its layers are plain products that
quantize alike; the maps of their mean stay float32. Float rounding differs from the module's, so a choice between
two hypotheses tied to about 1e-6 may differ; nothing else does.
"""

from __future__ import annotations

import copy
import math

import torch
from torch import nn

from pusht.geometry import GOAL_POSE
from pusht.spec import ACTION_HIGH, ACTION_LOW
from training.features import _CORNERS, _CENTER, _SCALE
from training.onepass import SharedScorer, _stretched, first_nearest
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
    """Env-unit states [B, 5] and noise [B, H, A] (unused, the ONNX contract's input) -> clipped actions [B, H, A]."""

    def __init__(self, flow: nn.Module) -> None:
        super().__init__()
        if not _fits(flow):
            raise ValueError("a lean graph needs a scoring student of the shipped flows' inputs (see lean_graph)")
        head = flow.onepass
        self.k, self.chunk_shape, self.top = head.candidates, head.chunk_shape, head.scorer_top
        self.stretch_count = len(head.scorer_stretches)
        self.register_buffer("stretches", torch.tensor(head.scorer_stretches, dtype=torch.float32))
        self.targets = targets = 2 * self.chunk_shape[0]  # a chunk's targets' coordinates
        self.shared = isinstance(head.scorer, SharedScorer)
        with torch.no_grad():
            self.state_map, self.parts = _state_map(self.k * targets, targets)
            linear = _feature_map(flow)  # features [20] = z [21] @ linear[:21] + linear[21]
            gen = [m for m in head.net if isinstance(m, nn.Linear)]
            last = _fold_actions(gen[-1], flow, head)
            self.ranked = 0
            if self.top:  # what picks the hypotheses the second pass sees: the ranker, or the generator's score rows
                # Both read the generator's last hidden layer: their first layer is more outputs of its last, one product.
                rows = head.candidates * head.chunk_dim
                ranker = [] if head.ranker is None else list(copy.deepcopy(head.ranker))
                first = _linear(gen[-1].weight[rows:], gen[-1].bias[rows:]) if head.ranker is None else ranker[0]
                last = _linear(torch.cat([last.weight, first.weight]), torch.cat([last.bias, first.bias]))
                self.ranked, self.first_scores = first.out_features, nn.Sequential(*ranker[1:])
            self.gen = nn.ModuleList([_fold_first(gen[0], linear), *(copy.deepcopy(m) for m in gen[1:-1]), last])
            # A shared pass's layers map each hypothesis as a row of its own [B * K, ...], plus a map of their mean (`context`).
            if self.shared:
                scorer = head.scorer
                first, self.frame = _fold_scorer_first(scorer.state.weight, scorer.state.bias, scorer.chunk.weight, linear)
                hidden, out, per_row = list(scorer.hidden), scorer.out, self.stretch_count
                self.context = copy.deepcopy(scorer.context)
            else:
                layers = [m for m in head.scorer if isinstance(m, nn.Linear)]
                w = layers[0].weight
                first, self.frame = _fold_scorer_first(w[:, :20], layers[0].bias, w[:, 20:], linear)
                hidden, out, per_row = layers[1:-1], layers[-1], head.scored
            self.width = first.out_features
            moves, self.turns = _fold_outcome(out, per_row)
            self.sco = nn.ModuleList([_with_goal(first), *(copy.deepcopy(m) for m in hidden), moves])
            self.register_buffer("turn_corners", torch.block_diag(*[_corner_maps()[1]] * per_row).float())  # [2 n, 12 n]

    def forward(self, state: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Clipped actions [B, H, A]: the hypothesis (at the stretch) whose predicted outcome leaves the tee's corners nearest the goal's."""
        phases, sources, agent, block = torch.split(self.state_map(state), self.parts, dim=1)
        trig = torch.sin(phases)  # [cos, -sin, sin, cos] twice
        z = torch.cat([state, trig, trig * sources], dim=1)
        h = z
        for layer in self.gen[:-1]:
            h = nn.functional.silu(layer(h))
        targets = self.targets
        out = self.gen[-1](h)
        if self.top:
            out, ranking = torch.split(out, [self.k * targets, self.ranked], dim=1)
        actions = torch.clamp(out + agent, ACTION_LOW, ACTION_HIGH).reshape(-1, self.k, targets)
        k = self.k
        if self.top:  # the first pass's best-scored, in order
            k, best_first = self.top, torch.topk(self.first_scores(ranking), self.top, dim=1, largest=False).indices
            actions = torch.gather(actions, 1, best_first[:, :, None].expand(-1, -1, targets))
        # rows @ [[cos, -sin], [sin, cos]] rotate world vectors into the block's frame
        frame = torch.matmul((actions - block[:, None]).reshape(-1, k * self.chunk_shape[0], 2), trig[:, :4].reshape(-1, 2, 2))
        on_z, goal = torch.split(self.sco[0](z), [self.width, _CORNER_XY], dim=1)
        h = self._shared_pass(on_z, frame, k) if self.shared else self._side_by_side(on_z, frame)
        corners = torch.addmm(self.sco[-1](h), torch.sin(self.turns(h)), self.turn_corners)  # each choice's moved corners
        if self.shared and self.stretch_count > 1:  # [B, K, S, 12] -> the K at each stretch in turn
            corners = corners.reshape(-1, k, self.stretch_count, _CORNER_XY).transpose(1, 2)
        distance = (corners.reshape(-1, k * self.stretch_count, _CORNER_XY) + goal[:, None]).pow(2).sum(dim=2)
        best = first_nearest(distance)
        index = best if self.stretch_count == 1 else torch.remainder(best, k)
        chosen = torch.gather(actions, 1, index[:, None, None].expand(-1, 1, targets)).reshape(-1, *self.chunk_shape)
        if self.stretch_count == 1:
            return chosen
        factor = self.stretches[torch.div(best, k, rounding_mode="floor")].reshape(-1, 1, 1)
        return _stretched(state, chosen, factor)

    def _side_by_side(self, on_z: torch.Tensor, frame: torch.Tensor) -> torch.Tensor:
        """The side-by-side pass's last hidden layer [B, W] on all K hypotheses' targets in the block's frame [B, K * H, 2]."""
        h = nn.functional.silu(on_z + self.frame(frame.flatten(1)))  # one layer on [z, frame], split so the frame's part can go int8
        for layer in self.sco[1:-1]:
            h = nn.functional.silu(layer(h))
        return h

    def _shared_pass(self, on_z: torch.Tensor, frame: torch.Tensor, k: int) -> torch.Tensor:
        """The shared pass's last hidden layer [B * k, W] over k hypotheses, each a row so that every layer is one plain product."""
        first = self.frame(frame.reshape(-1, self.targets))
        h = nn.functional.silu((first.reshape(-1, k, self.width) + on_z[:, None]).reshape(-1, self.width))
        for i, layer in enumerate(self.sco[1:-1]):
            if self.context is None:  # each hypothesis alone
                h = nn.functional.silu(layer(h))
                continue
            mean = h.reshape(-1, k, h.shape[1]).mean(dim=1)
            out = layer(h)
            h = nn.functional.silu((out.reshape(-1, k, out.shape[1]) + self.context[i](mean)[:, None]).reshape(-1, out.shape[1]))
        return h


# z = [state (5), trig (8), trig * sources (8)]: trig = sin(angle + PHASES) = [c, -s, s, c] twice (c, s: the block angle's
# cosine and sine), sources = [dx, dy, dx, dy, bx, by, bx, by] (d: the agent less the block; b: the block).
_PHASES = (math.pi / 2, math.pi, 0.0, math.pi / 2) * 2
_C, _S, _C_DX, _NEG_S_DY, _S_DX, _C_DY, _C_BX, _NEG_S_BY, _S_BX, _C_BY = 5, 7, 13, 14, 15, 16, 17, 18, 19, 20
_Z = 21
_CORNER_XY = 2 * len(_CORNERS)


def _state_map(agents: int, blocks: int) -> tuple[nn.Linear, list[int]]:
    """State [B, 5] -> [phases (8), sources (8), the agent tiled `agents` / 2 times, the block tiled `blocks` / 2 times],
    and those parts' widths."""
    parts = [8, 8, agents, blocks]
    m, b = torch.zeros(sum(parts), 5), torch.zeros(sum(parts))
    m[:8, 4], b[:8] = 1.0, torch.tensor(_PHASES)
    for j, (x, y) in enumerate([(0, 2), (1, 3), (0, 2), (1, 3)]):
        m[8 + j, x], m[8 + j, y] = 1.0, -1.0
    for j, x in enumerate([2, 3, 2, 3]):
        m[12 + j, x] = 1.0
    for j in range(agents):
        m[16 + j, j % 2] = 1.0
    for j in range(blocks):
        m[16 + agents + j, 2 + j % 2] = 1.0
    return _linear(m, b), parts


def _feature_map(flow: nn.Module) -> torch.Tensor:
    """[22, 20]: `head_features` as z @ map[:21] + map[21], column for column."""
    mean, std = flow.normalizer.state_mean.double(), flow.normalizer.state_std.double()
    m = torch.zeros(_Z + 1, 20, dtype=torch.float64)
    one = _Z
    for i in range(4):  # the encoded state: z-scored coordinates, then sin and cos
        m[i, i], m[one, i] = 1.0 / std[i], -mean[i] / std[i]
    m[_S, 4], m[_C, 5] = 1.0, 1.0
    for k, (cx, cy) in enumerate(_CORNERS):  # tee_keypoints: x = bx + cos cx - sin cy, y = by + sin cx + cos cy
        col = 6 + 2 * k
        m[2, col], m[_C, col], m[_S, col], m[one, col] = 1 / _SCALE, cx / _SCALE, -cy / _SCALE, -_CENTER / _SCALE
        m[3, col + 1], m[_S, col + 1], m[_C, col + 1], m[one, col + 1] = 1 / _SCALE, cx / _SCALE, cy / _SCALE, -_CENTER / _SCALE
    # agent_in_block_frame: (cos dx + sin dy, -sin dx + cos dy) / scale
    m[_C_DX, 18], m[_NEG_S_DY, 18] = 1 / _FRAME_SCALE, -1 / _FRAME_SCALE
    m[_S_DX, 19], m[_C_DY, 19] = -1 / _FRAME_SCALE, 1 / _FRAME_SCALE
    return m


def _goal_map() -> torch.Tensor:
    """[22, 12]: z @ map[:21] + map[21] = per tee corner (x, y), the block's position less the goal's and the goal pose's
    corner less the block angle's, in the block's frame: a hypothesis's goal distance is |its moved corners + this|^2."""
    gx, gy, ga = GOAL_POSE
    cg, sg = math.cos(ga), math.sin(ga)
    m = torch.zeros(_Z + 1, _CORNER_XY, dtype=torch.float64)
    for k, (kx, ky) in enumerate(_CORNERS):
        x, y = 2 * k, 2 * k + 1
        # rotated into the block's frame, the block less the goal: (c (bx - gx) + s (by - gy), -s (bx - gx) + c (by - gy))
        m[_C_BX, x], m[_NEG_S_BY, x], m[_C, x], m[_S, x] = 1.0, -1.0, -gx, -gy
        m[_S_BX, y], m[_C_BY, y], m[_S, y], m[_C, y] = -1.0, 1.0, gx, -gy
        # less the goal angle's corner seen from the block's: R(ga - a) k, with cos(ga - a) = cg c + sg s, sin = sg c - cg s
        m[_C, x] -= cg * kx - sg * ky
        m[_S, x] -= sg * kx + cg * ky
        m[_C, y] -= sg * kx + cg * ky
        m[_S, y] -= sg * ky - cg * kx
    return m


def _corner_maps() -> tuple[torch.Tensor, torch.Tensor]:
    """[2, 12] each: a move (x, y) and a turn's [cos, sin] to where they put each tee corner, in the block's frame."""
    moves, turns = torch.zeros(2, _CORNER_XY, dtype=torch.float64), torch.zeros(2, _CORNER_XY, dtype=torch.float64)
    for k, (kx, ky) in enumerate(_CORNERS):
        moves[0, 2 * k], moves[1, 2 * k + 1] = 1.0, 1.0
        turns[0, 2 * k], turns[0, 2 * k + 1], turns[1, 2 * k], turns[1, 2 * k + 1] = kx, ky, -ky, kx
    return moves, turns


def _linear(weight: torch.Tensor, bias: torch.Tensor) -> nn.Linear:
    out = nn.Linear(weight.shape[1], weight.shape[0])
    out.weight.copy_(weight)
    out.bias.copy_(bias)
    return out


def _fold_first(layer: nn.Linear, linear: torch.Tensor) -> nn.Linear:
    """The generator's first layer on z instead of the 20 features."""
    w = layer.weight.double()
    return _linear((w @ linear[:_Z].T).float(), (layer.bias.double() + w @ linear[_Z]).float())


def _fold_scorer_first(on_features: torch.Tensor, bias: torch.Tensor, on_targets: torch.Tensor, linear: torch.Tensor) -> tuple[nn.Linear, nn.Linear]:
    """The scorer's first layer on z (with its bias) and on the targets in the block's frame, unscaled (a zero bias), instead
    of its weights on the 20 features and on the scaled targets."""
    features, targets = on_features.double(), on_targets.double() / _FRAME_SCALE
    on_z = _linear((features @ linear[:_Z].T).float(), (bias.double() + features @ linear[_Z]).float())
    return on_z, _linear(targets.float(), torch.zeros(targets.shape[0]))


def _with_goal(on_z: nn.Linear) -> nn.Linear:
    """The scorer's first layer on z with `_goal_map`'s 12 outputs after its units."""
    goal = _goal_map()
    return _linear(torch.cat([on_z.weight, goal[:_Z].T.float()]), torch.cat([on_z.bias, goal[_Z].float()]))


def _fold_actions(layer: nn.Linear, flow: nn.Module, head: nn.Module) -> nn.Linear:
    """The generator's last layer giving the K hypotheses' env-unit actions less the agent (agent frame), score rows dropped."""
    rows = head.candidates * head.chunk_dim
    std = flow.normalizer.action_std.double().expand(*head.chunk_shape).reshape(-1).repeat(head.candidates)
    mean = flow.normalizer.action_mean.double().expand(*head.chunk_shape).reshape(-1).repeat(head.candidates)
    w, b = layer.weight[:rows].double(), layer.bias[:rows].double()
    return _linear((w * std[:, None]).float(), (b * std + mean).float())


def _fold_outcome(layer: nn.Linear, choices: int) -> tuple[nn.Linear, nn.Linear]:
    """The scorer's last layer (a move and a turn per choice, in the outcome model's units) as two: the tee's corners after
    each choice's move [12 per choice], and its turn at two phases [cos-phase, sine-phase per choice] for one Sin."""
    scale = torch.tensor(_POSE_SCALE, dtype=torch.float64)
    w = (layer.weight.double().reshape(choices, 3, -1) * scale[:, None]).reshape(-1, layer.in_features)
    b = layer.bias.double() * scale.repeat(choices)
    moves = _corner_maps()[0]
    on_move = torch.cat([moves.T @ w[3 * c : 3 * c + 2] for c in range(choices)])
    move_bias = torch.cat([b[3 * c : 3 * c + 2] @ moves for c in range(choices)])
    on_turn = w[2::3].repeat_interleave(2, dim=0)
    turn_bias = b[2::3].repeat_interleave(2) + torch.tensor([math.pi / 2, 0.0], dtype=torch.float64).repeat(choices)
    return _linear(on_move.float(), move_bias.float()), _linear(on_turn.float(), turn_bias.float())

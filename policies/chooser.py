"""A learned model of what one chunk does to the block, and the choice among a flow's candidate chunks it makes.

The flow's samples already contain success: keeping, at each decision, the best of 16 start noises by
simulating each chunk lifts success from 66 % to 82-84 % (an oracle measured in docs/findings.md). A
critic regressing the reward could not rank those chunks (models/README.md), but a chunk's outcome is a
smooth function of the chunk (shifted by 2 px, the coverage change correlates at 0.97), and contact
physics looks the same in the block's frame wherever the block lies. So `OutcomeModel` learns there:
the agent and the chunk's 12 targets relative to the block -> the block's displacement and rotation.
Acting, `OutcomeSelector` has the flow integrate K candidates (K fixed orthogonal maps of the one
`noise` input, as `policies.selection`), offers each also stretched (faster), predicts where each
leaves the block, and keeps the one that leaves the tee's corners closest to the goal's. Nothing simulates the env at acting time; the exported
graph keeps its `state` and `noise` inputs. Imports only torch (and pusht's geometry constants).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import nn
from torch.nn import functional as F

from policies.features import tee_keypoints
from policies.networks import silu_mlp
from policies.selection import candidate_starts, orthogonal_maps
from pusht.geometry import GOAL_POSE
from pusht.spec import ACTION_HIGH, ACTION_LOW

__all__ = [
    "FEATURE_STATE",
    "FEATURE_TARGETS",
    "OutcomeModel",
    "OutcomeSelector",
    "ValueModel",
    "agent_in_block_frame",
    "goal_corner_distance",
    "nearest",
    "pose_after",
    "stretch",
    "targets_in_block_frame",
    "value_cost",
]

DEFAULT_OUTCOME_DIMS = (512, 512, 512, 512)
DEFAULT_OUTCOME_CANDIDATES = 16
_FRAME_SCALE = 100.0  # px: agent and targets relative to the block, to order 1
_ARENA_CENTER = 256.0  # px: the block's own position (walls), to about [-1, 1]
# The targets' units (px, px, rad): a push moves the block by some px and some hundredths of a radian.
_POSE_SCALE = (10.0, 10.0, 0.1)
DEFAULT_VALUE_DIMS = (256, 256, 256)
TIE_MARGIN = 1e-3  # relative: a candidate replaces the flow's own sample only if predicted this much closer to the goal
FLOAT_TIE = 1e-5  # relative: costs this close are one cost (float rounding differs between runtimes by ~1e-7)


FEATURE_TARGETS = slice(2, -4)
"""the columns of `OutcomeModel.features` that hold the chunk's targets (after the agent's 2, before the block's 4)"""
FEATURE_STATE = [0, 1, -4, -3, -2, -1]
"""the other columns: the agent in the block's frame, the block's place and heading"""


class OutcomeModel(nn.Module):
    """Block pose after a chunk [B, 3] from env-unit states [B, 5] and the chunk's env-unit targets [B, H, 2]."""

    def __init__(self, horizon: int, hidden_dims: Sequence[int] = DEFAULT_OUTCOME_DIMS) -> None:
        super().__init__()
        self.net = silu_mlp(2 + 2 * horizon + 4, hidden_dims, 3)
        self.register_buffer("pose_scale", torch.tensor(_POSE_SCALE), persistent=False)

    def forward(self, state: torch.Tensor, chunk: torch.Tensor) -> torch.Tensor:
        """The predicted block pose (x, y, angle) after the chunk, in env units."""
        return pose_after(state, self.net(self.features(state, chunk)))

    def features(self, state: torch.Tensor, chunk: torch.Tensor) -> torch.Tensor:
        """The model's input [B, F]: agent and targets in the block's frame, the block's place and heading."""
        block, angle = state[:, 2:4], state[:, 4]
        cos, sin = torch.cos(angle), torch.sin(angle)
        agent = _to_block_frame(state[:, None, 0:2] - block[:, None], cos, sin).flatten(1)
        return torch.cat(
            [
                agent / _FRAME_SCALE,
                targets_in_block_frame(state, chunk),
                block / _ARENA_CENTER - 1.0,
                torch.stack([sin, cos], dim=1),
            ],
            dim=1,
        )

    def loss(self, state: torch.Tensor, chunk: torch.Tensor, end_state: torch.Tensor) -> torch.Tensor:
        """Smooth L1 between predicted and true pose change, in the block's frame and the targets' units."""
        angle = state[:, 4]
        cos, sin = torch.cos(angle), torch.sin(angle)
        moved = _to_block_frame((end_state[:, 2:4] - state[:, 2:4])[:, None], cos, sin)[:, 0]
        turned = torch.remainder(end_state[:, 4] - angle + math.pi, 2 * math.pi) - math.pi
        target = torch.cat([moved, turned[:, None]], dim=1) / self.pose_scale
        return F.smooth_l1_loss(self.net(self.features(state, chunk)), target, beta=0.1)


class ValueModel(nn.Module):
    """How soon the chooser succeeds from env-unit states [B, 5]: a regression of exp(-steps to success / tau) (0 for a
    failure), fitted on its own episodes (training.value_fit)."""

    def __init__(self, hidden_dims: Sequence[int] = DEFAULT_VALUE_DIMS) -> None:
        super().__init__()
        self.net = silu_mlp(16, hidden_dims, 1)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        """The value [B] of each state."""
        return self.net(self.features(state)).squeeze(1)

    @staticmethod
    def features(state: torch.Tensor) -> torch.Tensor:
        """[B, 16]: the tee's corners relative to the goal's, the agent in the arena and in the block's frame."""
        goal = torch.tensor([GOAL_POSE], dtype=state.dtype, device=state.device)
        corners = tee_keypoints(state[:, 2:5]) - tee_keypoints(goal)
        return torch.cat([corners, state[:, 0:2] / _ARENA_CENTER - 1.0, agent_in_block_frame(state)], dim=1)


def value_cost(value: torch.Tensor) -> torch.Tensor:
    """exp(-value) of values [N]: > 0 as `nearest` needs, and ordered as the values however small (a regression may
    predict a hopeless state's value below 0; a floor would make its candidates tie)."""
    return torch.exp(-value)


class OutcomeSelector(nn.Module):
    """The outcome model, K orthogonal candidate maps of the start noise and S stretches of each chunk; `choose` picks among K x S.

    A stretch s moves every target of a chunk s times as far from the agent: the same motion, faster. The flow copies
    demonstrators who are slow (given 450 steps instead of 300 the chooser succeeds in 91 % of episodes, not 78 %), and
    the outcome model predicts where a stretched chunk leaves the block as well as a plain one."""

    def __init__(
        self,
        chunk_shape: tuple[int, int],
        hidden_dims: Sequence[int] = DEFAULT_OUTCOME_DIMS,
        candidates: int = DEFAULT_OUTCOME_CANDIDATES,
        stretches: Sequence[float] = (1.0,),
        value_dims: Sequence[int] | None = None,
    ) -> None:
        super().__init__()
        self.chunk_shape = tuple(chunk_shape)
        self.candidates = int(candidates)
        # Python floats, not a buffer: they follow from the architecture, and checkpoints without them still load.
        self.stretches = tuple(float(s) for s in stretches)
        self.choices = self.candidates * len(self.stretches)
        self.model = OutcomeModel(self.chunk_shape[0], hidden_dims)
        self.value = ValueModel(value_dims) if value_dims is not None else None
        # Not saved: a value still unfitted (its first round of training.value_fit) leaves the ranking to the distance.
        self.rank_by_value = self.value is not None
        self.register_buffer("rotations", orthogonal_maps(self.candidates, self.chunk_shape[0] * self.chunk_shape[1]))

    # Shapes below use -1 and flatten, never a traced batch size, so the exported graph keeps a dynamic batch.
    def candidates_of(self, noise: torch.Tensor, noise_scale: float) -> torch.Tensor:
        """The K candidate starts [B, K, H, A] of standard-normal `noise` [B, H, A] (candidate 0 is noise_scale * noise)."""
        return candidate_starts(noise, self.rotations, noise_scale)

    def candidate_chunks(
        self, flow: nn.Module, state_n: torch.Tensor, noise: torch.Tensor, num_steps: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The K x S normalized candidate chunks [B, K * S, H, A] of `noise` from the flow's inputs `state_n` (the K flow
        chunks at each stretch in turn, the first K unstretched), and their clipped env-unit actions."""
        k, shape = self.candidates, self.chunk_shape
        starts = self.candidates_of(noise, flow.noise_scale).reshape(-1, *shape)
        rows = state_n.unsqueeze(1).expand(-1, k, -1).reshape(-1, state_n.shape[1])
        chunks_n = flow.integrate(rows, starts, num_steps)
        env_rows = _env_state(flow, rows)
        raw = flow.normalizer.actions(env_rows, chunks_n)
        every_n, every = [], []
        for factor in self.stretches:
            stretched = raw if factor == 1.0 else stretch(env_rows, raw, factor)
            every_n.append((chunks_n if factor == 1.0 else flow.normalizer.chunk(env_rows, stretched)).reshape(-1, k, *shape))
            every.append(torch.clamp(stretched, ACTION_LOW, ACTION_HIGH).reshape(-1, k, *shape))
        return torch.cat(every_n, dim=1), torch.cat(every, dim=1)

    def best_chunk(self, flow: nn.Module, state_n: torch.Tensor, noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        """The normalized candidate chunk [B, H, A] of least predicted cost (`cost`)."""
        chunks_n, cost = self.scored_candidates(flow, state_n, noise, num_steps)
        index = nearest(cost).reshape(-1, 1, 1, 1).expand(-1, 1, *self.chunk_shape)
        return torch.gather(chunks_n, 1, index).squeeze(1)

    def scored_candidates(
        self, flow: nn.Module, state_n: torch.Tensor, noise: torch.Tensor, num_steps: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The normalized candidate chunks [B, K * S, H, A] of `noise` (as `candidate_chunks`) and their predicted costs [B, K * S]."""
        chunks_n, actions = self.candidate_chunks(flow, state_n, noise, num_steps)
        return chunks_n, self.costs(_env_state(flow, state_n), actions)

    def cost(self, state: torch.Tensor, chunk: torch.Tensor) -> torch.Tensor:
        """[B]: the cost of env-unit chunks [B, H, A] from states [B, S]: how far (`goal_corner_distance`) the model predicts
        they leave the block, or with a value, the `value_cost` of the end state it predicts."""
        pose = self.model(state, chunk)
        if self.value is None or not self.rank_by_value:
            return goal_corner_distance(pose)
        return value_cost(self.value(torch.cat([chunk[:, -1], pose], dim=1)))

    def costs(self, state: torch.Tensor, chunks: torch.Tensor) -> torch.Tensor:
        """`cost` [B, K * S] of each of the chunks [B, K * S, H, A] (env units) from states [B, S]."""
        k = self.choices
        states = state.unsqueeze(1).expand(-1, k, -1).reshape(-1, state.shape[1])
        return self.cost(states, chunks.reshape(-1, *self.chunk_shape)).reshape(-1, k)

    def choose(self, state: torch.Tensor, chunks: torch.Tensor) -> torch.Tensor:
        """Index [B] of the chunk among [B, K * S, H, A] (env units) of least predicted cost (0 on a near tie)."""
        return nearest(self.costs(state, chunks))


def nearest(distance: torch.Tensor) -> torch.Tensor:
    """Index [B] of the least of the candidates' predicted costs [B, C] (>= 0), 0 (the flow's own sample) on a near tie."""
    # Candidates whose clipped chunks are the same (stretched past the arena's edge) tie exactly, up to float noise:
    # the first within FLOAT_TIE of the least plays, so ONNX Runtime and torch pick the same one.
    least = distance.min(dim=1, keepdim=True).values
    best = (distance <= least * (1 + FLOAT_TIE)).to(torch.int32).argmax(dim=1)
    # Chunks that do not reach the block tie up to float noise, and float noise must not choose (ONNX Runtime and
    # torch round differently): unless a candidate is clearly better, the flow's own sample (candidate 0) plays.
    clearly = distance.gather(1, best[:, None]).squeeze(1) < distance[:, 0] * (1 - TIE_MARGIN)
    return torch.where(clearly, best, torch.zeros_like(best))


def goal_corner_distance(pose: torch.Tensor) -> torch.Tensor:
    """Mean squared distance [B] (in policies.features' units) of the tee's corners at poses [B, 3] to the goal's."""
    goal = torch.tensor([GOAL_POSE], dtype=pose.dtype, device=pose.device)
    return (tee_keypoints(pose) - tee_keypoints(goal)).pow(2).mean(dim=1)


def stretch(state: torch.Tensor, actions: torch.Tensor, factor: float | torch.Tensor) -> torch.Tensor:
    """Env-unit chunks [B, H, A] with every target `factor` times as far from the agent of states [B, S]: the same motion, faster."""
    agent = state[:, None, : actions.shape[-1]]
    return agent + factor * (actions - agent)


def pose_after(state: torch.Tensor, change: torch.Tensor) -> torch.Tensor:
    """The block's pose [B, 3] (env units) after a change [B, 3] in `OutcomeModel`'s units (its network's output: a move in
    the block's frame, a turn) from states [B, S]."""
    change = change * torch.tensor(_POSE_SCALE, dtype=change.dtype, device=change.device)
    cos, sin = torch.cos(state[:, 4]), torch.sin(state[:, 4])
    dx = cos * change[:, 0] - sin * change[:, 1]
    dy = sin * change[:, 0] + cos * change[:, 1]
    return torch.stack([state[:, 2] + dx, state[:, 3] + dy, state[:, 4] + change[:, 2]], dim=1)


def targets_in_block_frame(state: torch.Tensor, chunk: torch.Tensor) -> torch.Tensor:
    """[B, H * 2]: env-unit chunks' targets [B, H, 2] relative to the block of states [B, S], in its frame and `OutcomeModel`'s units."""
    angle = state[:, 4]
    return _to_block_frame(chunk - state[:, None, 2:4], torch.cos(angle), torch.sin(angle)).flatten(1) / _FRAME_SCALE


def agent_in_block_frame(state: torch.Tensor) -> torch.Tensor:
    """[B, 2]: the agent relative to the block, in the block's frame and `OutcomeModel`'s units, from env-unit states [B, S]."""
    angle = state[:, 4]
    return _to_block_frame(state[:, None, 0:2] - state[:, None, 2:4], torch.cos(angle), torch.sin(angle))[:, 0] / _FRAME_SCALE


def _env_state(flow: nn.Module, state_n: torch.Tensor) -> torch.Tensor:
    """Env-unit states [B, S] back from the flow's inputs (the normalized state comes first)."""
    return flow.normalizer.env_state(state_n[:, : flow.state_dim])


def _to_block_frame(vectors: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """World-frame vectors [B, N, 2] rotated into frames of heading (cos, sin) [B]."""
    x, y = vectors[..., 0], vectors[..., 1]
    cos, sin = cos[:, None], sin[:, None]
    return torch.stack([cos * x + sin * y, -sin * x + cos * y], dim=-1)

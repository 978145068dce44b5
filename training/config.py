"""The training configuration: one typed dataclass whose field docs are the CLI's `--help`.

Defaults are the published recipe (AdamW 3e-4, weight decay 1e-4, cosine decay to 0 without warmup,
batch 128, 200k steps, dropout 0.1, z-scored states and actions, Gaussian noise on the normalized
training states).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass, field
from typing import Any

from policies.pace import Pace
from pusht.spec import DEFAULT_HORIZON, DEFAULT_NUM_STEPS, POLICY_KINDS, TRAIN_EVAL_SEED
from training.cli import HelpFormatter
from training.cli import build_parser as _build_parser
from training.cli import command_line as _command_line
from training.cli import option as _f

__all__ = ["HelpFormatter", "TrainConfig", "build_parser", "command_line", "parse_config"]

PROG = "python -m training.train"
NOISE_SCHEDULES = ("linear", "cosine", "constant")
EVAL_ENVS = ("pusht", "gym-pusht")


@dataclass
class TrainConfig:
    """Everything that defines a training run."""

    policy: str = field(default="", metadata={"help": "policy kind: mse or flow", "choices": POLICY_KINDS, "required": True})
    name: str = _f("", "run name; outputs go to OUT_DIR/NAME, which must not exist yet (default: POLICY-YYYYmmdd-HHMMSS)")
    resume: bool = _f(
        False, "continue the existing run NAME to its configured steps from its latest resumable state (same config)"
    )
    overwrite: bool = _f(False, "delete the existing run NAME and start it again")
    out_dir: str = _f("runs", "parent folder of run folders")
    data: str = _f("data/pusht_lowdim.zarr", "replay zarr with data/state, data/action, meta/episode_ends")
    extra_data: str = _f(
        "",
        "comma-separated zarr stores (same layout, e.g. episodes saved by /viewer) whose windows join the demonstrations'; normalization stays the demonstrations'",
    )
    human_weight: float = _f(
        1.0,
        "sampling weight of extra-data windows whose first action a human gave (data/human, as /viewer saves); demonstrations weigh 1",
    )
    extra_stride: int = _f(
        1,
        "extra-data windows start only every N-th frame of an episode (12: a collecting policy's decision points, where its chunk was chosen)",
    )
    policy_step_weight: float = _f(
        1.0, "sampling weight of the other windows of stores with data/human, the policy's own steps (0: learn only the human's)"
    )
    init: str = _f(
        "",
        "checkpoint stem to start from (fine-tuning): its weights, architecture and normalization are used, --arch and --dropout are ignored",
    )
    steps: int = _f(200_000, "optimizer steps (global batches)")
    batch_size: int = _f(128, "global batch size (split across DDP ranks)")
    lr: float = _f(3e-4, "AdamW peak learning rate (cosine decay to 0, no warmup)")
    weight_decay: float = _f(1e-4, "AdamW weight decay")
    ema_decay: float = _f(
        0.0,
        "evaluate and save an exponential moving average of the weights with this largest decay (e.g. 0.9999, warmed up as Diffusion Policy's EMA); 0: the raw weights",
    )
    dropout: float = _f(0.1, "dropout of the policy MLP")
    arch: str = _f(
        "{}",
        'extra policy constructor kwargs as JSON, e.g. \'{"hidden_dims": [256, 256], "action_frame": "agent"}\' (keys: policies.configuration)',
    )
    horizon: int = _f(DEFAULT_HORIZON, "actions per chunk")
    pad_episode_end: bool = _f(
        False, "also train on windows starting in an episode's last horizon-1 frames, their chunks padded with its last action"
    )
    action_speed: float = _f(
        1.0,
        "chunks play the demonstrations this many times as fast (action k = the demonstrated action at frame t + speed k, interpolated): the demonstrators are slow, and a policy that only copies their pace often runs out of the 300 steps (policies.pace)",
    )
    action_speed_near: float = _f(
        0.0, "the pace of windows whose block is within --speed-radius of the goal (0: --action-speed everywhere)"
    )
    speed_radius: float = _f(
        0.0, "goal distance (40 px + 0.6 rad per unit, policies.pace) inside which --action-speed-near applies"
    )
    speed_ramp: float = _f(
        0.0, "goal distances beyond --speed-radius over which the pace rises linearly to --action-speed (0: a step)"
    )
    pace_copies: int = _f(
        0,
        'for a policy with the pace as an input (--arch \'{"pace_input": true, "acting_pace": [far, near, radius, ramp]}\'): each demonstration window this many times, at paces drawn uniformly in [1, --action-speed] (0: no pace input)',
    )
    # 0.05 is the recipe; policy-quality.md measured 0.15 and 0.3 hurting, 0.02 and 0.05 within noise.
    state_noise_start: float = _f(0.05, "std of Gaussian noise on normalized training states at step 0")
    state_noise_end: float = _f(0.0, "std of that noise at the last step")
    state_noise_schedule: str = _f("linear", "how the noise std moves from start to end", choices=NOISE_SCHEDULES)
    eval_every: int = _f(10_000, "evaluate every N steps (0: only at the end; -1: never)")
    eval_episodes: int = _f(100, "episodes per evaluation")
    eval_seed: int = _f(TRAIN_EVAL_SEED, "first episode seed of evaluation (seeds eval_seed..eval_seed+eval_episodes-1)")
    eval_num_envs: int = _f(0, "envs in lockstep during evaluation (0: all episodes at once)")
    eval_env: str = _f("pusht", "evaluation env: ours (pusht) or the reference gym-pusht", choices=EVAL_ENVS)
    eval_max_steps: int = _f(300, "episode step limit in evaluation")
    action_horizon: int = _f(DEFAULT_HORIZON, "actions of each chunk executed open loop in evaluation")
    flow_num_steps: int = _f(DEFAULT_NUM_STEPS, "flow: Euler steps when sampling in evaluation")
    log_every: int = _f(100, "write a log.jsonl record every N steps")
    # about 10-30 s of flow training on 2 cores: what a SIGKILL can lose
    checkpoint_every: int = _f(
        1000, "save a resumable state and the `last` checkpoint every N steps (0: only at evaluations and stops)"
    )
    seed: int = _f(0, "seed of torch and numpy (DDP rank r uses seed + r for its noise)")
    # 1 thread: on an idle 2-core machine 2 threads gained only 5-25 %, on a loaded one they were 8x slower
    threads: int = _f(1, "torch intra-op threads per process (0: all cores / world size)")
    progress: bool = _f(True, "show a tqdm progress bar on stderr")

    def __post_init__(self) -> None:
        checks = [
            (self.policy in POLICY_KINDS, f"policy must be one of {POLICY_KINDS}, got {self.policy!r}"),
            (
                self.state_noise_schedule in NOISE_SCHEDULES,
                f"state_noise_schedule must be one of {NOISE_SCHEDULES}, got {self.state_noise_schedule!r}",
            ),
            (self.eval_env in EVAL_ENVS, f"eval_env must be one of {EVAL_ENVS}, got {self.eval_env!r}"),
            (self.steps >= 1, f"steps must be >= 1, got {self.steps}"),
            (self.batch_size >= 1, f"batch_size must be >= 1, got {self.batch_size}"),
            (self.lr > 0, f"lr must be > 0, got {self.lr}"),
            (0 <= self.human_weight <= 1000, f"human_weight must be in [0, 1000], got {self.human_weight}"),
            (0 <= self.policy_step_weight <= 1000, f"policy_step_weight must be in [0, 1000], got {self.policy_step_weight}"),
            (self.weight_decay >= 0, f"weight_decay must be >= 0, got {self.weight_decay}"),
            (0 <= self.dropout < 1, f"dropout must be in [0, 1), got {self.dropout}"),
            (self.horizon >= 1, f"horizon must be >= 1, got {self.horizon}"),
            (0.25 <= self.action_speed <= 4, f"action_speed must be in [0.25, 4], got {self.action_speed}"),
            (
                self.action_speed_near == 0 or 0.25 <= self.action_speed_near <= 4,
                f"action_speed_near must be 0 or in [0.25, 4], got {self.action_speed_near}",
            ),
            (self.speed_radius >= 0, f"speed_radius must be >= 0, got {self.speed_radius}"),
            (self.speed_ramp >= 0, f"speed_ramp must be >= 0, got {self.speed_ramp}"),
            (0 <= self.pace_copies <= 16, f"pace_copies must be in [0, 16], got {self.pace_copies}"),
            (
                not self.pace_copies or self.action_speed_near == 0,
                "pace_copies draws paces in [1, --action-speed]; --action-speed-near does not apply",
            ),
            (self.state_noise_start >= 0 and self.state_noise_end >= 0, "state noise stds must be >= 0"),
            (self.eval_every >= -1, f"eval_every must be >= -1, got {self.eval_every}"),
            (self.eval_episodes >= 1, f"eval_episodes must be >= 1, got {self.eval_episodes}"),
            (self.eval_seed >= 0, f"eval_seed must be >= 0, got {self.eval_seed}"),
            (self.eval_num_envs >= 0, f"eval_num_envs must be >= 0, got {self.eval_num_envs}"),
            (self.eval_max_steps >= 1, f"eval_max_steps must be >= 1, got {self.eval_max_steps}"),
            (
                1 <= self.action_horizon <= self.horizon,
                f"action_horizon must be in [1, horizon={self.horizon}], got {self.action_horizon}",
            ),
            (self.flow_num_steps >= 1, f"flow_num_steps must be >= 1, got {self.flow_num_steps}"),
            (self.log_every >= 1, f"log_every must be >= 1, got {self.log_every}"),
            (self.checkpoint_every >= 0, f"checkpoint_every must be >= 0, got {self.checkpoint_every}"),
            (not (self.resume and self.overwrite), "--resume and --overwrite exclude each other"),
            (self.seed >= 0, f"seed must be >= 0, got {self.seed}"),
            (self.threads >= 0, f"threads must be >= 0, got {self.threads}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(message)
        self.architecture_overrides()  # validates the JSON early

    def architecture_overrides(self) -> dict[str, Any]:
        """The `arch` JSON as a dict of policy constructor kwargs."""
        try:
            value = json.loads(self.arch)
        except json.JSONDecodeError as exc:
            raise ValueError(f"arch must be a JSON object, got {self.arch!r}: {exc}") from None
        if not isinstance(value, dict):
            raise ValueError(f"arch must be a JSON object, got {self.arch!r}")
        return value

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict of every field; the weights and the pace only when set, so configs saved before they existed match (--resume)."""
        unset = {
            "human_weight": 1.0,
            "policy_step_weight": 1.0,
            "action_speed": 1.0,
            "action_speed_near": 0.0,
            "speed_radius": 0.0,
            "speed_ramp": 0.0,
            "pace_copies": 0,
        }
        return {k: v for k, v in asdict(self).items() if not (k in unset and v == unset[k])}

    def pace(self) -> Pace:
        """The pace of the training chunks (policies.pace)."""
        return Pace(self.action_speed, self.action_speed_near or None, self.speed_radius, self.speed_ramp)


def build_parser() -> argparse.ArgumentParser:
    """An argparse parser with one `--flag` per TrainConfig field, its help from the field doc."""
    return _build_parser(
        TrainConfig, PROG, "Train an MSE or flow-matching behavioral-cloning policy on Push-T (single process or torchrun DDP)."
    )


def command_line(config: dict[str, Any]) -> str:
    """The `python -m training.train` command that reproduces a run's saved config (flags that differ from the defaults)."""
    return _command_line(TrainConfig, PROG, config, always=("policy", "name"))


def parse_config(argv: list[str] | None = None) -> TrainConfig:
    """Parse command-line flags into a validated TrainConfig (argparse reports bad values)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return TrainConfig(**vars(args))
    except ValueError as exc:
        parser.error(str(exc))
        raise  # unreachable: parser.error exits

"""The fine-tuning configuration: one typed dataclass whose field docs are `python -m training.finetune --help`.

Seed ranges: training episodes start at `train_seed_start` (10,000,000: far from every evaluation
range), periodic evaluation uses 400000.. (disjoint from the held-out 200000.. and 600000.. and from
the tuning range 300000..).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from training.cli import build_parser, command_line, option

PROG = "python -m training.finetune"
# fields that do not change what a run computes, so --resume accepts new values
RESUMABLE_CHANGES = ("progress", "threads", "resume", "overwrite", "checkpoint_every")
# Noise-space PPO (DSRL, the flow frozen) and a Q-critic picking start noises were tried and dropped (docs/findings.md);
# --algo ppo is PPO on the flow's own weights.
ALGOS = ("outcome", "value", "dagger", "ppo")


@dataclass
class FinetuneConfig:
    """Everything that defines a fine-tuning run."""

    init: str = option(
        "",
        "flow checkpoint stem to fine-tune (its weights stay frozen but in dagger and ppo), or a flow with an outcome "
        "chooser, whose model the fit goes on fitting",
        required=True,
    )
    algo: str = option(
        "outcome",
        "what is fitted: outcome (a one-chunk model of the block that picks the best of --candidates chunks); value (the "
        "chooser's value of time, by policy iteration on its own episodes; --init must be an outcome chooser); dagger (a plain "
        "flow, from the chooser's flow weights, taught the picks of the chooser --init at its own states); ppo (a plain flow "
        "--init fine-tuned in the env by PPO on a discounted return)",
        choices=ALGOS,
    )
    name: str = option("flow-outcome", "run name; outputs go to OUT_DIR/NAME")
    out_dir: str = option("runs", "parent folder of run folders")
    iterations: int = option(100, "iterations (each: rollout_decisions chunks in every env, each followed by the updates)")
    num_envs: int = option(128, "envs stepped in lockstep")
    rollout_decisions: int = option(8, "chunks per env between updates")
    critic_lr: float = option(1e-3, "Adam learning rate of the outcome model")
    outcome_dims: str = option("512,512,512,512", "hidden widths of the one-chunk outcome model (comma-separated)")
    stretches: str = option(
        "1", "stretches of each candidate chunk (comma-separated, the first 1): a chunk's targets s times as far from the agent"
    )
    explore: float = option(0.2, "probability that an env plays a random candidate instead of the model's choice")
    batch_size: int = option(256, "minibatch size")
    buffer_size: int = option(1_000_000, "replay capacity (labels)")
    learning_starts: int = option(20_000, "labels before the model chooses (random candidates until then)")
    updates_per_decision: int = option(16, "gradient updates after each decision step of all envs")
    candidates: int = option(16, "candidates chosen from at each decision")
    label_envs: int = option(32, "envs whose state is labelled at each decision step")
    value_dims: str = option("256,256,256", "value and ppo: hidden widths of the value model or critic (comma-separated)")
    value_tau: float = option(100.0, "value: a state's label is exp(-steps to success / tau), 0 in a failed episode")
    value_episodes: int = option(1024, "value: episodes played by the current chooser per iteration")
    value_max_steps: int = option(600, "value: step limit of those episodes (past 300, so slow successes are labelled too)")
    value_updates: int = option(12_000, "value: minibatches of regression per iteration (learning rate annealed to 0)")
    dagger_episodes: int = option(512, "dagger: episodes per iteration, each chunk played by the student or the chooser")
    dagger_teacher: str = option(
        "",
        "dagger: the chooser checkpoint stem that labels; --init is then the student, a plain flow of the chooser's flow "
        "architecture (default: --init is the chooser and the student starts from its flow weights)",
    )
    dagger_teacher_share: float = option(
        0.25,
        "dagger: share of chunks the chooser plays (all of them in the first iteration of a student that starts from "
        "the chooser's flow)",
    )
    dagger_labels: str = option(
        "",
        "dagger: labels.safetensors of an earlier dagger run of the same chooser, its labels put in the pool before the "
        "first iteration (every dagger run writes its own beside its checkpoint)",
    )
    dagger_updates: int = option(4000, "dagger: minibatches of flow matching on all labels per iteration")
    dagger_lr: float = option(1e-4, "dagger: AdamW learning rate of the student flow")
    dagger_lr_schedule: str = option(
        "constant",
        "dagger: constant, or cosine (each iteration's fit anneals the rate from dagger_lr to 0)",
        choices=("constant", "cosine"),
    )
    ppo_lr: float = option(1e-5, "ppo: Adam learning rate of the flow")
    ppo_sigma: float = option(0.08, "ppo: std of the Gaussian around the flow's chunk in training (normalized chunk units)")
    ppo_gamma: float = option(0.99, "ppo: discount per env step of the return (1 at success)")
    ppo_lambda: float = option(0.95, "ppo: lambda of the generalized advantage estimates (per chunk)")
    ppo_shaping: float = option(1.0, "ppo: weight of the env's reward as a potential in the return (0: success only)")
    ppo_clip: float = option(0.1, "ppo: clip range of the probability ratio")
    ppo_epochs: int = option(4, "ppo: passes over each iteration's chunks (minibatches of batch_size)")
    ppo_target_kl: float = option(0.05, "ppo: stop an iteration's flow updates after an epoch whose mean KL exceeds this")
    ppo_warmup: int = option(10, "ppo: first iterations that fit only the critic")
    flow_num_steps: int = option(10, "Euler steps of the frozen flow (and of the dagger student)")
    train_seed_start: int = option(10_000_000, "first training episode seed (episodes use consecutive seeds)")
    eval_every: int = option(50, "evaluate (and checkpoint) every N iterations (0: only at the end)")
    eval_episodes: int = option(200, "episodes per evaluation")
    eval_seed: int = option(400_000, "first evaluation episode seed (never a held-out one)")
    checkpoint_every: int = option(
        25, "save a resumable state and the `last` checkpoint every N iterations (and on SIGTERM/SIGINT)"
    )
    resume: bool = option(
        False, "continue the existing run NAME to its configured iterations from its latest resumable state (same config)"
    )
    overwrite: bool = option(False, "delete the existing run NAME and start it again")
    log_every: int = option(5, "write a log.jsonl record every N iterations")
    seed: int = option(0, "seed of torch (start noise, minibatch order, initialization)")
    threads: int = option(1, "torch intra-op threads")
    progress: bool = option(True, "show a tqdm progress bar on stderr")

    def __post_init__(self) -> None:
        if not self.init:
            raise ValueError("init must name the flow checkpoint to fine-tune")
        if self.algo not in ALGOS:
            raise ValueError(f"algo must be one of {ALGOS}, got {self.algo!r}")
        positive = (
            "iterations",
            "num_envs",
            "rollout_decisions",
            "flow_num_steps",
            "eval_episodes",
            "log_every",
            "threads",
            "batch_size",
            "buffer_size",
            "updates_per_decision",
            "label_envs",
            "checkpoint_every",
            "candidates",
            "value_episodes",
            "value_max_steps",
            "value_updates",
            "dagger_episodes",
            "dagger_updates",
            "ppo_epochs",
        )
        for name in positive:
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("critic_lr", "dagger_lr", "ppo_lr", "ppo_sigma", "ppo_clip", "ppo_target_kl"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.resume and self.overwrite:
            raise ValueError("--resume and --overwrite exclude each other")
        if self.eval_every < 0 or self.train_seed_start < 0 or self.eval_seed < 0 or self.seed < 0:
            raise ValueError("eval_every, train_seed_start, eval_seed and seed must be >= 0")
        for name in ("explore", "dagger_teacher_share", "ppo_gamma", "ppo_lambda"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.dagger_lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"dagger_lr_schedule must be constant or cosine, got {self.dagger_lr_schedule!r}")
        for name in ("dagger_teacher", "dagger_labels"):
            if getattr(self, name) and self.algo != "dagger":
                raise ValueError(f"{name} is a setting of --algo dagger")
        if self.ppo_warmup < 0 or self.ppo_shaping < 0:
            raise ValueError("ppo_warmup and ppo_shaping must be >= 0")
        if not self.value_tau > 0:
            raise ValueError(f"value_tau must be > 0, got {self.value_tau}")
        self.outcome_dims_list()
        self.value_dims_list()
        self.stretches_list()

    def chooser_stem(self) -> str:
        """The checkpoint the chooser comes from: `dagger_teacher` when set, else `init`."""
        return self.dagger_teacher or self.init

    def outcome_dims_list(self) -> list[int]:
        """`outcome_dims` as a list of widths."""
        return _widths("outcome_dims", self.outcome_dims)

    def value_dims_list(self) -> list[int]:
        """`value_dims` as a list of widths."""
        return _widths("value_dims", self.value_dims)

    def stretches_list(self) -> list[float]:
        """`stretches` as a list of floats."""
        from policies.configuration import check_stretches

        try:
            return check_stretches([float(s) for s in self.stretches.split(",")])
        except ValueError:
            raise ValueError(
                f"stretches must be comma-separated numbers in (0, 4] starting with 1, got {self.stretches!r}"
            ) from None

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict of every field."""
        return asdict(self)

    def command(self) -> str:
        """The command that reproduces this config."""
        return command_line(FinetuneConfig, PROG, self.to_dict(), always=("init", "name"))


def parse_config(argv: list[str] | None = None) -> FinetuneConfig:
    """Parse command-line flags into a validated FinetuneConfig (argparse reports bad values)."""
    parser = build_parser(
        FinetuneConfig,
        PROG,
        "Fine-tune a flow beyond imitation: fit a one-chunk outcome model that chooses among its frozen chunks, or that "
        "chooser's value of time; teach a plain flow the chooser's picks (dagger); or fine-tune a plain flow in the env by "
        "PPO (ppo).",
    )
    args = parser.parse_args(argv)
    try:
        return FinetuneConfig(**vars(args))
    except ValueError as exc:
        parser.error(str(exc))
        raise


def _widths(name: str, text: str) -> list[int]:
    try:
        widths = [int(w) for w in text.split(",")]
    except ValueError:
        raise ValueError(f"{name} must be comma-separated positive ints, got {text!r}") from None
    if not widths or any(w < 1 for w in widths):
        raise ValueError(f"{name} must be comma-separated positive ints, got {text!r}")
    return widths

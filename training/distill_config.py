"""The settings of a distillation run (`training.distill`): one typed dataclass, each field a command-line option."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from pusht.spec import RESERVED_SEEDS
from training.cli import option
from training.finetune_config import CHOOSER

__all__ = ["DEFAULT_MULTICHOICE_DIMS", "DEFAULT_ONEPASS_DIMS", "STUDENTS", "DistillConfig"]

STUDENTS = ("flow", "one-pass", "multichoice")
DEFAULT_ONEPASS_DIMS = "512,512,512,512"
DEFAULT_MULTICHOICE_DIMS = "512,512,512"


@dataclass
class DistillConfig:
    """Everything that defines a distillation run."""

    teacher: str = option(CHOOSER, "flow checkpoint stem to distil (its noise_scale and steps define the map): the outcome chooser")
    teacher_steps: int = option(10, "Euler steps of the teacher's sampler")
    student: str = option("flow", "flow: a plain flow sampling in --student-steps Euler steps; one-pass: an outcome chooser's "
                                  "candidates and scores in one network pass (needs --fixed-noise); multichoice: --hypotheses chunks "
                                  "and which to play in one network pass", choices=STUDENTS)
    student_steps: int = option(1, "Euler steps (network evaluations) of a flow student")
    hypotheses: int = option(8, "hypothesis chunks of a multichoice student")
    relax: float = option(0.05, "share of a multichoice student's regression loss on the hypotheses not nearest the label")
    top: int = option(1, "a multichoice student's labels per state: the chooser's that many best (candidate, stretch) chunks, "
                         "each pulling its nearest hypothesis")
    scorer_dims: str = option("", "comma-separated hidden widths of a multichoice student's second pass, which learns the "
                                  "teacher's outcome model's goal distance of each hypothesis and chooses (2 network evaluations)")
    scorer_shared: bool = option(False, "the second pass's layers are shared by the hypotheses (a set network: each layer maps "
                                        "every hypothesis alike plus their mean) instead of one MLP over all of them side by side")
    scorer_stretches: str = option("1", "comma-separated stretches (the first 1) at which the second pass scores each hypothesis: "
                                        "the nearest of all plays at its stretch (training.outcome.stretch)")
    scorer_context: bool = option(True, "each layer of a shared second pass adds a map of the hypotheses' mean; without it "
                                        "each hypothesis is scored alone, as the outcome model scores a chunk")
    scorer_outcome: bool = option(False, "the second pass starts as the teacher's outcome model, each hypothesis scored alone: "
                                         "the model itself (nothing to train: it is what the pass learns), or with --scorer-dims "
                                         "(as many layers, narrower) its most active units, trained on")
    scorer_top: int = option(0, "the second pass scores only the first pass's this many best-scored hypotheses, each alone "
                                "(with --scorer-outcome or --no-scorer-context; 0: all); it learns on all of them")
    ranker_dims: str = option("", "comma-separated widths of a ranker: an MLP on the first pass's last hidden layer whose K scores "
                                  "pick the --scorer-top hypotheses the second pass sees; it learns where the outcome model's pick lies")
    scorer_jitter: int = option(0, "copies of each state the student visits in a second-pass round, moved by about 3 px and 0.03 rad, "
                                   "that join its states (labels cost no episodes)")
    scorer_steps: int = option(12_000, "optimizer steps of the second pass (half as many after each of its rounds)")
    scorer_rounds: int = option(2, "rounds of the second pass: the student plays --round-episodes, the outcome model labels its hypotheses there")
    scorer_lr: float = option(1e-3, "AdamW peak learning rate of the second pass (a third of it in its rounds)")
    name: str = option("flow-distill", "run name; outputs go to OUT_DIR/NAME")
    out_dir: str = option("runs", "parent folder of run folders")
    data: str = option("data/pusht_lowdim.zarr", "demonstrations whose states are distilled")
    extra_states: str = option("", "comma-separated zarr stores whose states join (e.g. policy rollouts)")
    pairs: int = option(400_000, "(state, start noise, teacher chunk) triples drawn before training")
    steps: int = option(40_000, "optimizer steps (0 with --scorer-dims: only the second pass of the --init student learns)")
    batch_size: int = option(256, "batch size")
    lr: float = option(1e-4, "AdamW peak learning rate (cosine decay to 0)")
    eval_episodes: int = option(200, "episodes of the final evaluation")
    eval_seed: int = option(400_000, "first evaluation episode seed (never a held-out one)")
    log_every: int = option(200, "write a log record every N steps")
    teacher_episodes: int = option(0, "episodes the teacher plays first (from --round-seed); their decision states join the pairs")
    rounds: int = option(0, "DAgger rounds after the first training: the student plays, the teacher labels, training goes on")
    round_episodes: int = option(1000, "episodes the student plays in each round")
    round_seed: int = option(23_000_000, "first episode seed of the teacher's and the rounds' episodes (training seeds)")
    init: str = option("", "start the student from this checkpoint stem (a student of the same teacher, e.g. a run's last, "
                           "to go on with more rounds; with --scorer-dims its hypotheses get a second pass: its own if of those "
                           "widths, which goes on training, else a fresh one) instead of the teacher's flow")
    student_hidden_dims: str = option("", "comma-separated hidden widths of a fresh student network (default: the teacher's "
                                         f"flow, weights included; a one-pass student's: {DEFAULT_ONEPASS_DIMS}; "
                                         f"a multichoice student's: {DEFAULT_MULTICHOICE_DIMS})")
    fixed_noise: int = option(-1, "if >= 0: the teacher labels every state from the one start noise of this seed (a deterministic "
                                  "policy), and the student, its start noise scaled to 0, copies that policy")
    pairs_from: str = option("", "a distillation run folder whose saved pairs (pairs.safetensors, same teacher) replace the "
                                 "demonstration and teacher pairs")
    states_from: str = option("", "a distillation run folder whose saved pairs' states (pairs.safetensors, any labels) this run's "
                                  "teacher labels anew (at most --pairs of them, drawn at random); they replace the demonstration and teacher pairs")
    outcome_weight: float = option(0.0, "weight of the teacher's outcome-model distance to the goal after the student's chunk, "
                                        "beside the regression (a chooser teacher only)")
    outcome_root: bool = option(False, "weigh the root of that (mean squared corner) distance: steeper near the goal")
    outcome_chunks: int = option(1, "chunks that outcome term looks ahead: after each the agent stands at the chunk's last target "
                                    "and the block where the outcome model predicts, the student acts again there, and the "
                                    "distances after each chunk add up (a model-based rollout; the student learns to set up pushes)")
    seed: int = option(0, "seed of the pairs and of the batch order")
    threads: int = option(1, "torch intra-op threads")
    progress: bool = option(True, "show a tqdm progress bar on stderr")

    def __post_init__(self) -> None:
        for name in ("teacher_steps", "student_steps", "pairs", "batch_size", "eval_episodes", "log_every", "threads", "round_episodes",
                     "outcome_chunks", "hypotheses", "top", "scorer_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("teacher_episodes", "rounds", "scorer_rounds", "scorer_jitter", "scorer_top"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.round_seed in RESERVED_SEEDS:
            raise ValueError(f"round_seed {self.round_seed} lies among the evaluation seeds {RESERVED_SEEDS.start}..{RESERVED_SEEDS.stop - 1}")
        for name in ("student_hidden_dims", "scorer_dims", "ranker_dims"):
            widths = getattr(self, name)
            if widths and not all(w.strip().isdigit() and int(w) > 0 for w in widths.split(",")):
                raise ValueError(f"{name} must be comma-separated positive widths, got {widths!r}")
        if not self.outcome_weight >= 0:
            raise ValueError(f"outcome_weight must be >= 0, got {self.outcome_weight}")
        if self.outcome_chunks > 1 and not self.outcome_weight:
            raise ValueError("outcome_chunks looks ahead in the outcome term: give --outcome-weight too")
        if self.student not in STUDENTS:
            raise ValueError(f"student must be one of {STUDENTS}, got {self.student!r}")
        if self.pairs_from and self.states_from:
            raise ValueError("give --pairs-from (labelled pairs) or --states-from (states to label), not both")
        if self.student == "one-pass" and (self.fixed_noise < 0 or self.outcome_weight):
            raise ValueError("a one-pass student learns a chooser from one fixed start noise: give --fixed-noise SEED "
                             "(and no --outcome-weight: it learns the chooser's own scores)")
        if self.scored_stretches() != [1.0] and not self.scorer_dims:
            raise ValueError("--scorer-stretches are what a second pass scores: give --scorer-dims too")
        if not self.scorer_context and not self.scorer_shared:
            raise ValueError("--no-scorer-context shapes a shared second pass: give --scorer-shared too")
        if self.scorer_top and not (self.scorer_outcome or (self.scorer_shared and not self.scorer_context)):
            raise ValueError("--scorer-top has the second pass score each hypothesis alone: give --scorer-outcome, "
                             "or --scorer-shared --no-scorer-context")
        if self.ranker_dims and not self.scorer_top:
            raise ValueError("--ranker-dims picks the hypotheses the second pass scores: give --scorer-top too")
        if self.scorer_shared and not self.scorer_dims:
            raise ValueError("--scorer-shared shapes the second pass: give --scorer-dims too")
        if (self.top > 1 or self.scorer_dims) and self.student != "multichoice":
            raise ValueError("--top and --scorer-dims belong to a multichoice student: give --student multichoice")
        if self.scorer_outcome and (self.scorer_shared or not self.scorer_context or self.scored_stretches() != [1.0]):
            raise ValueError("--scorer-outcome shapes the second pass as the outcome model (shared, no context) and scores plain "
                             "hypotheses: give no --scorer-shared, --no-scorer-context or --scorer-stretches")
        if self.steps < 1 and not self.second_pass:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if self.second_pass and (self.steps or not self.init or self.student != "multichoice"):
            raise ValueError("--scorer-dims and --scorer-outcome give a trained multichoice student its second pass: "
                             "give --student multichoice, --init CARD and --steps 0")
        if not self.scorer_lr > 0:
            raise ValueError(f"scorer_lr must be > 0, got {self.scorer_lr}")
        if not 0 <= self.relax < 1:
            raise ValueError(f"relax must be in [0, 1), got {self.relax}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")

    @property
    def second_pass(self) -> bool:
        """Whether the run gives a trained multichoice student a second pass (learned, or the outcome model's)."""
        return bool(self.scorer_dims) or self.scorer_outcome

    def scored_stretches(self) -> list[float]:
        """`scorer_stretches` as numbers (ValueError unless in (0, 4] and the first 1)."""
        from training.architecture import check_stretches

        try:
            factors = [float(s) for s in self.scorer_stretches.split(",")]
        except ValueError:
            raise ValueError(f"scorer_stretches must be comma-separated numbers, got {self.scorer_stretches!r}") from None
        return check_stretches(factors, "scorer_stretches")

    def to_dict(self) -> dict:
        """A JSON-ready dict of every field."""
        return asdict(self)

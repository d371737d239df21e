"""`illm distil`'s settings (`DistilConfig`, validated once) and what a distillation measured
(`DistilResult`, distil/report.json); `run.py` does the work."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from illm_tools.distil.loss import RANKING_TARGETS
from illm_tools.errors import UsageError
from illm_tools.tasks.registry import DEFAULT_TASKS

SETTINGS_VERSION = 1
DTYPES = ("float32", "bfloat16")


@dataclass
class DistilConfig:
    """Everything that determines a distillation."""

    cache: Path
    """Annotation cache holding the teacher's answers (`illm annotate`; `illm cache info` lists its models)."""
    out: Path
    """Folder of the student, e.g. models/NAME: a Hugging Face model folder (`--model OUT` loads it) with its work
    files in OUT/distil."""
    student: str = "smollm2-135m"
    """The base model fine-tuned into the student: an alias (`illm models`), hub id or model folder (transformers)."""
    teacher: str | None = None
    """The cache's model whose answers are taught, as its rows name it (oracle, smollm2-135m, a hub id);
    default: the cache's only one."""
    tasks: tuple[str, ...] = DEFAULT_TASKS
    """Tasks taught: a ranking task (action: the teacher's distribution over the valid actions) and text
    tasks (summary, goal, plan: the teacher's texts)."""
    states: int | None = None
    """Lessons taught per epoch (states in the split's hash order; with --balance, a rare action's states
    repeated); default: every state not held out."""
    balance: float = 0.0
    """How the lessons share the teacher's top actions: each action's share in proportion to its states in the
    cache to the power 1 - balance (0: as the cache holds them; 1: equal shares). An action with fewer distinct
    states than its share has them repeated: in BabyAI the states that call for pick up or toggle are few as
    texts but frequent in play (of the 4,060 distinct states of 12,000 UnlockLocal steps of the bot, 120 call
    for pick up, though the bot picks up in 9% of its steps). With --visits, the shares are of the visits
    instead, each action's states drawn in proportion to their visits. Held-out states keep the cache's shares."""
    min_share: float = 0.0
    """Each top action's share of the lessons at least this (after --balance; with --visits, of the draws), the
    other actions keeping their proportions to one another, a rare action's states repeated to fill its share.
    --balance's power also moves the common actions' shares toward each other (go forward's toward turn left's,
    the teacher's runner-up in most go-forward states); a floor (e.g. 0.08) raises only the rare ones. 0: none."""
    visits: list[Path] = field(default_factory=list)
    """Trajectory datasets (`illm collect`) that weight the lessons: --states lessons drawn (with replacement,
    seeded by --seed) in proportion to how often each state is visited there, so the student learns the states
    an agent meets as often as it meets them; states they never visit are not taught. Default: each distinct
    state once."""
    held_out: int = 200
    """States held out of training (the first by a salted hash of the state), on which the base and the
    student are measured."""
    max_tokens: int = 256
    """States whose longest sequence (a prompt and its longest target) is longer are left out (counted)."""
    epochs: float = 1.0
    """Passes over the training states."""
    batch_size: int = 8
    """States per optimiser step."""
    learning_rate: float = 1e-3
    """AdamW's peak learning rate (linear warm-up over 5% of the steps, then linear decay)."""
    rank: int = 16
    """LoRA rank of the adapters on every linear layer (alpha = 2 x rank); 0: fine-tune every weight."""
    blocks: int | None = None
    """Keep N of the student's transformer blocks before fine-tuning, evenly spaced from its first block to its last
    (the others removed; the saved student has N blocks): a step and every later annotation cost about N / all of
    the forward pass. The student of a teacher's narrow task needs less depth than its base was given for all of
    language, and a CPU's half hour affords more lessons through fewer blocks. Default: every block."""
    layers: int | None = None
    """Adapters (or, at rank 0, trained weights) in the top N transformer blocks only: the backward pass stops
    below them (on 2 CPU cores the top half of SmolLM2's 30 blocks makes a step 1.6x faster); default every block."""
    ranking_target: str = "distribution"
    """What the ranking is taught from: distribution (KL from the teacher's distribution over the valid actions)
    or argmax (cross-entropy of the teacher's top action, the one-hot target of the paper's Algorithm 1 for f^a:
    the teacher's runner-up earns nothing, so a student that tells two actions apart weakly is not pulled to
    the runner-up). Held-out figures are the same either way (agreement, KL)."""
    text_weight: float = 1.0
    """Weight of the text tasks' loss (per-token NLL of the teacher's texts) beside the ranking loss (KL from
    the teacher's distribution over the valid actions)."""
    save_every: int = 25
    """Steps between checkpoints (the two newest are kept); an interrupt also writes one."""
    max_minutes: float | None = None
    """Stop training after this many minutes, with a checkpoint; the same command again goes on."""
    seed: int = 0
    """Seed of the adapters' initialisation and of the order of the training states."""
    dtype: str = "float32"
    """float32 | bfloat16: the matmuls of training (bfloat16: autocast, the weights stay float32; pays on a
    CPU with bf16 instructions or a GPU). The student is saved in float32."""
    device: str = "auto"
    """Where the fine-tuning runs: auto (a GPU where torch sees one, else the CPU) | cpu | cuda | cuda:N."""

    def __post_init__(self) -> None:
        from illm_tools.devices import check_device
        from illm_tools.folders import refuse_foreign
        from illm_tools.settings import check_folder, check_numbers
        from illm_tools.tasks.registry import get_task, parse_tasks

        self.cache, self.out = Path(self.cache), Path(self.out)
        check_numbers(self, positive=("states", "max_tokens", "epochs", "batch_size", "learning_rate", "save_every",
                                      "max_minutes", "layers", "blocks"),
                      non_negative=("held_out", "rank", "text_weight", "seed"), unit=("balance", "min_share"))
        self.tasks = parse_tasks(self.tasks)
        if not any(get_task(t).kind == "ranking" for t in self.tasks):
            raise UsageError(f"--tasks {','.join(self.tasks)} has no ranking task: add action (the student learns "
                             "to rank the valid actions)")
        if self.ranking_target not in RANKING_TARGETS:
            raise UsageError(f"--ranking-target must be distribution or argmax, got {self.ranking_target!r}")
        if self.dtype not in DTYPES:
            raise UsageError(f"--dtype must be float32 or bfloat16, got {self.dtype!r}")
        self.visits = [Path(v) for v in self.visits]
        check_device(self.device)
        check_folder(self.out, "--out")
        if self.out.resolve() == self.cache.resolve():
            raise UsageError("--out is the cache's folder: pass another folder for the student")
        refuse_foreign(self.out, "student model", "--out")

    def settings(self) -> dict:
        """What decides the student beside the lessons (checked when a run resumes)."""
        keep = ("student", "states", "held_out", "max_tokens", "epochs", "batch_size", "learning_rate", "rank",
                "text_weight", "seed", "dtype")
        unsets = (("layers", None), ("blocks", None), ("balance", 0.0), ("min_share", 0.0),
                  ("ranking_target", "distribution"))
        later = {k: getattr(self, k) for k, unset in unsets if getattr(self, k) != unset}
        if self.visits:
            later["visits"] = [str(v) for v in self.visits]
        return {"version": SETTINGS_VERSION, **{k: getattr(self, k) for k in keep}, **later}  # unset: as before them


@dataclass
class DistilResult:
    """What a distillation did and measured (distil/report.json)."""

    out: str
    teacher: str
    teacher_fingerprint: str
    base: str
    base_fingerprint: str
    student_fingerprint: str = ""
    train_states: int = 0
    held_out_states: int = 0
    left_out_long: int = 0
    """States left out for being longer than max_tokens."""
    steps: int = 0
    steps_done: int = 0
    resumed_from: int = 0
    """The checkpoint's step this session went on from (0: from the start)."""
    loss_first: float = 0.0
    """Mean training loss over the first tenth of the logged steps."""
    loss_last: float = 0.0
    """... and over the last tenth."""
    base_measure: dict = field(default_factory=dict)
    student_measure: dict = field(default_factory=dict)
    train_seconds: float = 0.0
    """Training time of this session."""
    train_tokens_per_s: float = 0.0
    wall_seconds: float = 0.0
    """This session's wall time, loading and measuring included."""
    machine: dict = field(default_factory=dict)
    stopped: bool = False
    """Stopped before the end (a signal, max_minutes): run the command again to go on."""
    already: bool = False
    """The student was already there: nothing was trained."""
    log_history: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


# --- the output folder -------------------------------------------------------------------------------

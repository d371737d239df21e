"""`illm distil`: fine-tune a small causal LM on a teacher's annotations, into a student annotator.

The teacher is any model of an annotation cache (the oracle; a large model annotated through vLLM
elsewhere). The student reads the cache's prompts and learns, through the annotator's own
candidate scoring (`illm_tools.distil.loss`), to rank the valid actions as the teacher did and to
write the teacher's texts. The fine-tuning is transformers' `Trainer` with peft's LoRA adapters
(`rank` 0: every weight); the adapters are merged into the weights at the end and the student is
saved as a Hugging Face model folder, which `--model PATH` loads offline like any other. Its
fingerprint is that of a local folder, a digest of its weight, config and tokenizer files
(`illm_tools.llm.loading.folder_sha256`), so its cache rows never mix with its base model's.

The output folder (`out`):

    config.json, model.safetensors, tokenizer files, illm_student.json   the student (written last:
                                       staged in a temporary folder, config.json moved in last)
    distil/settings.json             what decides the student (a resumed run must match it)
    distil/lessons.json              the rows taught and held out, by key (`LessonPlan`)
    distil/checkpoints/checkpoint-N  the Trainer's checkpoints (adapters, optimizer, scheduler, RNG,
                                     trainer_state.json) and illm_checkpoint.json, the sha256 of each
                                     file written after the checkpoint is whole
    distil/base.json                 the base model's figures on the held-out states
    distil/training.json             the training's figures (written before the student is saved)
    distil/report.json               the run's figures (written last)

Interrupted (a signal, `max_minutes`) the Trainer writes a checkpoint and stops; the same command
again resumes from the newest checkpoint whose files match their hashes (a damaged one is moved to
distil/damaged/, never deleted), and a finished student is not trained again.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from illm_tools import durable
from illm_tools.distil.loss import RANKING_TARGETS
from illm_tools.errors import UsageError
from illm_tools.tasks.registry import DEFAULT_TASKS

log = logging.getLogger(__name__)

WORK = "distil"
STUDENT_INFO = "illm_student.json"
SETTINGS_VERSION = 1
DTYPES = ("float32", "bfloat16")
TRAINING_FIELDS = ("steps", "steps_done", "resumed_from", "train_seconds", "train_tokens_per_s", "log_history")
"""The training's figures, kept in distil/training.json for a session that finds the student saved."""
Progress = Callable[..., None]
"""`on_progress(phase, n, total=None, **figures)`: phase base | train | student; n done since the last call."""


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
def _check_out(config: DistilConfig) -> None:
    """Refuse an --out holding something other than this command's work."""
    out, work = config.out, config.out / WORK
    ours = (work / "settings.json").is_file() or (work / "lessons.json").is_file()
    if out.is_dir() and any(out.iterdir()) and not ours:
        raise UsageError(f"--out {out} already holds files that are not a distillation's: pass a new folder")


def _check_settings(work: Path, settings: dict) -> None:
    """A resumed run must be the same distillation (one line naming what differs)."""
    path = work / "settings.json"
    if not path.is_file():
        return
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        raise UsageError(f"{path} is unreadable: restore it, or distil into a new --out") from None
    differ = sorted(k for k in set(saved) | set(settings) if saved.get(k) != settings.get(k))
    if differ:
        was = ", ".join(f"{k}={saved.get(k)!r}" for k in differ)
        raise UsageError(f"{work.parent} holds a distillation with other settings ({was}): run it with those, "
                         "or pass a new --out")


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


# --- the run -----------------------------------------------------------------------------------------
def distil(config: DistilConfig, *, on_progress: Progress | None = None,
           should_stop: Callable[[], bool] | None = None) -> DistilResult:
    """Teach the student the teacher's answers (module docstring); resumable."""
    from illm_tools.keys import fingerprint_hash
    from illm_tools.llm.loading import load_model

    started = time.perf_counter()
    say = on_progress or (lambda *a, **k: None)
    _check_out(config)
    work = config.out / WORK
    cache = _open_cache(config.cache)
    plan = _saved_plan(work) or _new_plan(cache, config)
    if tuple(plan.tasks) != tuple(config.tasks) or (config.teacher not in (None, plan.teacher)):
        raise UsageError(f"{config.out} holds a distillation of {plan.teacher}'s {','.join(plan.tasks)}: run it with "
                         "those, or pass a new --out")
    from illm_tools.devices import resolve_device

    device = resolve_device(config.device)
    lm = load_model(config.student, dtype="float32", device=device)
    from illm_tools.distil.training import keep_blocks, top_blocks

    settings = {**config.settings(), "student_fingerprint": fingerprint_hash(lm.fingerprint)}
    keep_blocks(lm.model, config.blocks)  # before anything is measured or trained: the base is the kept blocks
    top_blocks(lm.model, config.layers)  # more --layers than the student has: refused before anything is written
    _check_settings(work, settings)
    result = DistilResult(str(config.out), plan.teacher, plan.teacher_fingerprint, config.student,
                          fingerprint_hash(lm.fingerprint), machine=_machine(config, device))
    finished = _read_json(work / "report.json")
    if finished is not None and (config.out / "config.json").is_file():
        return DistilResult(**{**finished, "already": True, "stopped": False})
    train, held, long = _examples(lm, cache, plan, config.max_tokens)
    if not train:
        raise UsageError(f"no training state is at most --max-tokens {config.max_tokens} tokens long "
                         f"({long:,} left out): raise --max-tokens")
    result.train_states, result.held_out_states, result.left_out_long = len(train), len(held), long
    work.mkdir(parents=True, exist_ok=True)
    if not (work / "lessons.json").is_file():
        durable.write_text(work / "lessons.json", plan.to_json())
    if not (work / "settings.json").is_file():
        durable.write_text(work / "settings.json", json.dumps(settings, indent=2, sort_keys=True))

    from illm_tools.distil.loss import Measure, measure

    base = _read_json(work / "base.json")
    if base is None and held:
        say("base", 0, total=len(held))
        base = measure(lm, held, batch_size=config.batch_size, text_weight=config.text_weight,
                       on_progress=lambda n: say("base", n)).as_dict()
        durable.write_text(work / "base.json", json.dumps(base, indent=2))
    result.base_measure = base or Measure().as_dict()

    if not (config.out / "config.json").is_file():
        from illm_tools.distil.training import train_student

        trained = train_student(lm, train, config, work / "checkpoints", say=say, should_stop=should_stop)
        result.steps, result.steps_done, result.resumed_from = trained.steps, trained.step, trained.resumed_from
        result.train_seconds, result.log_history = trained.seconds, trained.log_history
        result.train_tokens_per_s = trained.tokens / trained.seconds if trained.seconds else 0.0
        _losses(result)
        if trained.stopped:
            result.stopped = True
            result.wall_seconds = time.perf_counter() - started
            return result
        durable.write_text(work / "training.json", json.dumps(
            {k: getattr(result, k) for k in TRAINING_FIELDS}, indent=2))
        _save_student(trained.model, lm.tokenizer, config, plan, settings)
        del trained
    else:  # a student saved by a session that ended before its report: its training's figures
        for k, v in (_read_json(work / "training.json") or {}).items():
            setattr(result, k, v)
        _losses(result)

    student = load_model(str(config.out), dtype="float32", device=device)  # as `--model OUT` loads it
    result.student_fingerprint = fingerprint_hash(student.fingerprint)
    if held:
        say("student", 0, total=len(held))
        result.student_measure = measure(student, held, batch_size=config.batch_size, text_weight=config.text_weight,
                                         on_progress=lambda n: say("student", n)).as_dict()
    result.wall_seconds = time.perf_counter() - started
    durable.write_text(work / "report.json", json.dumps(result.to_dict(), indent=2))
    return result


def _open_cache(path: Path):
    """The cache to read (a folder that is no cache is refused by the cache itself, in one line)."""
    from illm_tools.cache.store import AnnotationCache

    if not path.is_dir():
        raise UsageError(f"no annotation cache at {path}: annotate into it first (e.g. `illm annotate DATA --cache "
                         f"{path} --backend oracle --history 0`)")
    return AnnotationCache(path)


def _saved_plan(work: Path):
    from illm_tools.distil.lessons import LessonPlan

    path = work / "lessons.json"
    if not path.is_file():
        return None
    try:
        return LessonPlan.from_json(path.read_text())
    except (OSError, ValueError, KeyError, TypeError):
        raise UsageError(f"{path} is unreadable: restore it, or distil into a new --out") from None


def _new_plan(cache, config: DistilConfig):
    """The lessons of a new distillation: the teacher's rows of the tasks, split by state."""
    import pyarrow as pa
    import pyarrow.compute as pc

    from illm_tools.distil.lessons import COLUMNS, LessonPlan, lessons_of, pick_teacher, teachers, visits_of
    from illm_tools.tasks.registry import get_task

    if not len(cache):
        raise UsageError(f"the cache {cache.root} is empty: annotate into it first (e.g. `illm annotate DATA --cache "
                         f"{cache.root} --backend oracle --history 0`)")
    table = cache.table(COLUMNS)
    table = table.filter(pc.is_in(table.column("task"), value_set=pa.array(list(config.tasks))))
    ranking = [t for t in config.tasks if get_task(t).kind == "ranking"]
    ranked = table.filter(pc.is_in(table.column("task"), value_set=pa.array(ranking)))
    if not ranked.num_rows:
        held = ", ".join(f"{k} {v:,}" for k, v in sorted(cache.tasks().items()))
        raise UsageError(f"the cache {cache.root} holds no {'/'.join(ranking)} rows to learn a ranking from (it holds "
                         f"{held}): annotate with --tasks action,summary")
    teacher = pick_teacher(teachers(ranked), config.teacher, str(cache.root))
    mine = table.filter(pc.and_(pc.equal(table.column("model"), teacher.model),
                                pc.equal(table.column("model_fingerprint"), teacher.fingerprint)))
    rows = mine.to_pylist()
    lessons = lessons_of(rows, config.tasks)
    visits = visits_of(config.visits, sorted({r["history_len"] for r in rows})) if config.visits else None
    if len(lessons) <= config.held_out:
        raise UsageError(f"the cache {cache.root} holds {len(lessons):,} states of {teacher.model}, not more than "
                         f"--held-out {config.held_out}: annotate more states, or hold out fewer")
    return LessonPlan.split(teacher, config.tasks, lessons, held_out=config.held_out, states=config.states,
                            balance=config.balance, visits=visits, seed=config.seed, min_share=config.min_share)


def _examples(lm, cache, plan, max_tokens: int):
    """The plan's lessons tokenised for the student; those longer than max_tokens left out."""
    from illm_tools.distil.lessons import lessons_from_plan, tokenise
    from illm_tools.llm.joint import can_share_prefix

    share = can_share_prefix(lm)
    out, long = [], 0
    for keys in (plan.train, plan.held_out):
        examples = [tokenise(lm, lesson, share=share) for lesson in lessons_from_plan(cache, keys)]
        kept = [e for e in examples if e.longest <= max_tokens]
        long += len(examples) - len(kept)
        out.append(kept)
    return out[0], out[1], long


def _losses(result: DistilResult) -> None:
    losses = [h["loss"] for h in result.log_history if "loss" in h]
    if losses:
        k = max(1, len(losses) // 10)
        result.loss_first = sum(losses[:k]) / k
        result.loss_last = sum(losses[-k:]) / k


def _machine(config: DistilConfig, device: str) -> dict:
    import torch

    from illm_tools.llm.dtype import cpu_signature

    return {"cpu": cpu_signature(), "threads": torch.get_num_threads(), "device": device, "dtype": config.dtype,
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}


def _save_student(model, tokenizer, config: DistilConfig, plan, settings: dict) -> None:
    """The merged student into `out`: staged in a temporary folder inside it, then each file moved
    in, config.json last (a folder without it is no model folder: `--model` refuses it, and the
    next run saves again)."""
    out = config.out
    tmp = out / f".tmp-student-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    from illm_tools.distil.training import quiet_libraries

    try:
        with quiet_libraries():
            model.save_pretrained(tmp)
            tokenizer.save_pretrained(tmp)
        info = {"base": config.student, "base_fingerprint": settings["student_fingerprint"], "teacher": plan.teacher,
                "teacher_fingerprint": plan.teacher_fingerprint, "tasks": list(plan.tasks),
                "train_states": len(plan.train), "held_out_states": len(plan.held_out), "settings": settings}
        durable.write_text(tmp / STUDENT_INFO, json.dumps(info, indent=2, sort_keys=True))
        names = sorted(p.name for p in tmp.iterdir() if p.is_file())
        for name in names:
            with open(tmp / name, "rb") as fh:
                os.fsync(fh.fileno())
        for name in sorted(names, key=lambda n: n == "config.json"):  # config.json last
            os.replace(tmp / name, out / name)
        durable.fsync_dir(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

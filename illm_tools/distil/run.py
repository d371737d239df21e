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
from pathlib import Path

from illm_tools import durable
from illm_tools.distil.config import DistilConfig, DistilResult
from illm_tools.errors import UsageError

log = logging.getLogger(__name__)

WORK = "distil"
STUDENT_INFO = "illm_student.json"
TRAINING_FIELDS = ("steps", "steps_done", "resumed_from", "train_seconds", "train_tokens_per_s", "log_history")
"""The training's figures, kept in distil/training.json for a session that finds the student saved."""
Progress = Callable[..., None]
"""`on_progress(phase, n, total=None, **figures)`: phase base | train | student; n done since the last call."""


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

    share = not lm.sliding_window
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

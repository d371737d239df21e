"""The fine-tuning loop of `illm distil`: transformers' `Trainer` over the lessons, with peft's LoRA
adapters, checkpoints that are verified before a resume, and illm's own progress.

The Trainer is given a dataset of lesson indices (with their lengths, so batches group states of
similar length) and computes each batch's loss with `illm_tools.distil.loss.lesson_loss`, the
annotator's scoring path with autograd on. Its own progress bar and printed logs are replaced by a
callback that reports each step to illm's progress (`say("train", 1, loss=...)`) and stops the run,
with a checkpoint, when asked (a signal) or when `max_minutes` have passed.

Checkpoints: the Trainer writes `checkpoint-N` (adapters or weights, optimizer, scheduler, RNG
states, trainer_state.json last), keeping the two newest; after each, `illm_checkpoint.json` records
the sha256 of its files and the training's seconds and tokens so far (a resumed run reports the
whole training's time). A resume takes the newest checkpoint whose files match; newer ones that do
not (a kill while writing) are moved to `damaged/` beside the checkpoints folder.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from illm_tools import durable
from illm_tools.distil.lessons import Example
from illm_tools.errors import UsageError

log = logging.getLogger(__name__)

CHECKPOINT_INFO = "illm_checkpoint.json"
LORA_DROPOUT = 0.0
"""No dropout on the adapters' inputs: one epoch over fresh states needs no such regularisation, and peft's
dropout draws a mask over every adapted layer's input (10% of a step on 2 CPU cores, measured with cProfile)."""
WARMUP = 0.05
"""Share of the steps with a linear warm-up of the learning rate."""


@dataclass
class Trained:
    """What `train_student` returns."""

    model: object
    """The student's model, adapters merged (None when stopped)."""
    step: int
    steps: int
    resumed_from: int
    seconds: float
    """Training time of the steps done, the sessions before a resume included (up to their last checkpoint)."""
    tokens: int
    """Tokens of those steps, likewise."""
    stopped: bool
    log_history: list = field(default_factory=list)


def train_student(lm, examples: Sequence[Example], config, checkpoints: Path, *, say: Callable,
                  should_stop: Callable[[], bool] | None = None) -> Trained:
    """Fine-tune `lm` (a `LoadedModel`, float32) on `examples` under `config` (a `DistilConfig`),
    resuming from the newest verified checkpoint in `checkpoints`."""
    with quiet_libraries():
        return _train(lm, examples, config, checkpoints, say, should_stop)


def _train(lm, examples, config, checkpoints: Path, say, should_stop) -> Trained:
    import datasets
    import torch
    from transformers import Trainer, TrainerCallback, TrainingArguments
    from transformers.trainer_callback import PrinterCallback

    from illm_tools.distil.loss import lesson_loss

    torch.manual_seed(config.seed)
    model = lm.model
    model.train()
    top = top_blocks(model, config.layers)
    if config.rank:
        from peft import LoraConfig, get_peft_model

        targets = "all-linear" if top is None else linear_modules(top)
        model = get_peft_model(model, LoraConfig(r=config.rank, lora_alpha=2 * config.rank, lora_dropout=LORA_DROPOUT,
                                                 target_modules=targets, task_type="CAUSAL_LM"))
    else:
        model.requires_grad_(top is None)
        for _, block in top or ():
            block.requires_grad_(True)
    student = replace(lm, model=model)
    resume = latest_checkpoint(checkpoints)
    data = datasets.Dataset.from_dict({"index": list(range(len(examples))),
                                       "length": [e.longest for e in examples]})
    args = TrainingArguments(
        output_dir=str(checkpoints), per_device_train_batch_size=config.batch_size, num_train_epochs=config.epochs,
        learning_rate=config.learning_rate, lr_scheduler_type="linear", warmup_steps=WARMUP, weight_decay=0.0,
        logging_steps=1, save_strategy="steps", save_steps=config.save_every, save_total_limit=2,
        report_to="none", disable_tqdm=True, seed=config.seed, data_seed=config.seed, use_cpu=config.device == "cpu",
        bf16=config.dtype == "bfloat16", dataloader_num_workers=0, remove_unused_columns=False,
        train_sampling_strategy="group_by_length", length_column_name="length", save_only_model=False)
    figures = {"tokens": 0, "kl": 0.0, "nll": 0.0, "agree": 0, "ranked": 0, "batches": 0}

    class LessonTrainer(Trainer):
        def compute_loss(self, model, inputs, return_outputs=False, num_items_in_batch=None):
            batch = [examples[i] for i in inputs["index"].tolist()]
            r = lesson_loss(replace(student, model=model), batch, text_weight=config.text_weight, grad=True,
                            ranking_target=config.ranking_target)
            figures["tokens"] += r.tokens
            figures["kl"] += r.ranking_kl
            figures["nll"] += r.text_nll
            figures["agree"] += r.agree
            figures["ranked"] += r.ranked
            figures["batches"] += 1
            return (r.loss, {}) if return_outputs else r.loss

        def log(self, logs, start_time=None):
            if "loss" in logs and figures["batches"]:
                n = figures["batches"]
                logs = {**logs, "ranking_kl": figures["kl"] / n, "text_nll": figures["nll"] / n,
                        "agreement": figures["agree"] / max(figures["ranked"], 1)}
                figures.update(kl=0.0, nll=0.0, agree=0, ranked=0, batches=0)
            super().log(logs, start_time)

    started = time.perf_counter()
    before_seconds, before_tokens = _spent(resume)  # the sessions before this one, up to the resumed checkpoint

    def spent() -> dict:
        """The whole training's seconds and tokens so far, every session's."""
        return {"seconds": before_seconds + time.perf_counter() - started, "tokens": before_tokens + figures["tokens"]}

    class Report(TrainerCallback):
        """illm's progress and stop; checkpoint hashes after each save."""

        def on_train_begin(self, args, state, control, **kwargs):
            say("train", state.global_step, total=state.max_steps)

        def on_log(self, args, state, control, logs=None, **kwargs):
            if logs and "loss" in logs:
                say("train", 0, loss=f"{logs['loss']:.3f}", agree=f"{logs.get('agreement', 0):.2f}")

        def on_step_end(self, args, state, control, **kwargs):
            say("train", 1)
            over = config.max_minutes is not None and time.perf_counter() - started >= 60 * config.max_minutes
            if over or (should_stop is not None and should_stop()):
                control.should_save = True
                control.should_training_stop = True

        def on_save(self, args, state, control, **kwargs):
            seal(checkpoints / f"checkpoint-{state.global_step}", spent=spent())

    trainer = LessonTrainer(model=model, args=args, train_dataset=data,
                            data_collator=lambda rows: {"index": torch.tensor([r["index"] for r in rows])},
                            callbacks=[Report()])
    trainer.remove_callback(PrinterCallback)
    trainer.train(resume_from_checkpoint=str(resume) if resume else None)
    state = trainer.state
    stopped = state.global_step < state.max_steps
    total = spent()
    history = [h for h in state.log_history if "loss" in h]
    merged = None
    if not stopped:
        model.eval()
        merged = model.merge_and_unload() if config.rank else model
        merged.requires_grad_(False)
    return Trained(merged, state.global_step, state.max_steps, _step_of(resume), total["seconds"], total["tokens"],
                   stopped, history)


def top_blocks(model, layers: int | None) -> list[tuple[str, object]] | None:
    """The top `layers` transformer blocks of `model` as (qualified name, module), or None for every block.

    The blocks are the model's longest `ModuleList` (`model.layers` in Llama-like models,
    `transformer.h` in GPT-2), found by shape rather than by name so that any causal LM of
    transformers works; more layers than it has is refused in one line."""
    if layers is None:
        return None
    name, blocks = transformer_blocks(model, "--layers")
    if layers > len(blocks):
        raise UsageError(f"--layers {layers} is more than the student's {len(blocks)} transformer blocks: pass at most "
                         f"{len(blocks)}, or leave --layers out (every block)")
    return [(f"{name}.{i}", blocks[i]) for i in range(len(blocks) - layers, len(blocks))]


def transformer_blocks(model, option: str):
    """(qualified name, ModuleList) of `model`'s transformer blocks: its longest `ModuleList`."""
    import torch

    lists = [(name, m) for name, m in model.named_modules() if isinstance(m, torch.nn.ModuleList)]
    if not lists:
        raise UsageError(f"{option} needs a model whose transformer blocks are a ModuleList; leave {option} out")
    return max(lists, key=lambda item: len(item[1]))


def kept_indices(total: int, n: int) -> list[int]:
    """`n` of `total` block indices, evenly spaced from the first to the last (n = 1: the first).

    The last block is kept because its output is what the final norm and the language-model head were
    trained to read; the first because it reads the embeddings. DistilBERT initialised its student the
    same way, from every other block of its teacher."""
    if n == 1:
        return [0]
    return [round(i * (total - 1) / (n - 1)) for i in range(n)]  # distinct: the step is at least 1


def keep_blocks(model, n: int | None) -> list[int] | None:
    """Remove all but `n` of `model`'s transformer blocks (`kept_indices`), in place; None keeps every block.

    What indexes the blocks is renumbered so that the model is an ordinary n-block model of its class:
    the config's `num_hidden_layers` (and `layer_types`, Gemma 3's per-block attention kinds) and each
    block's `layer_idx`, by which the KV cache files its keys and values. Saved, it loads with
    `from_pretrained` like any model folder. Returns the indices kept."""
    import torch

    if n is None:
        return None
    name, blocks = transformer_blocks(model, "--blocks")
    total = len(blocks)
    if n > total:
        raise UsageError(f"--blocks {n} is more than the student's {total} transformer blocks: pass at most {total}, "
                         "or leave --blocks out (every block)")
    keep = kept_indices(total, n)
    parent, _, attribute = name.rpartition(".")
    kept = torch.nn.ModuleList([blocks[i] for i in keep])
    setattr(model.get_submodule(parent), attribute, kept)
    for new, block in enumerate(kept):
        for module in block.modules():
            if isinstance(getattr(module, "layer_idx", None), int):
                module.layer_idx = new
    for config in {id(c): c for c in (model.config, model.config.get_text_config())}.values():
        if getattr(config, "num_hidden_layers", None) == total:
            config.num_hidden_layers = n
        types = getattr(config, "layer_types", None)
        if types is not None and len(types) == total:
            config.layer_types = [types[i] for i in keep]
    return keep


def linear_modules(blocks) -> list[str]:
    """The qualified names of the linear layers inside `blocks` (peft's target_modules for them)."""
    import torch

    out = []
    for prefix, block in blocks:
        out += [f"{prefix}.{name}" for name, m in block.named_modules() if isinstance(m, torch.nn.Linear)]
    if not out:
        raise UsageError("the student's top blocks hold no linear layer for adapters: leave --layers out")
    return out


def _step_of(checkpoint: Path | None) -> int:
    return int(checkpoint.name.rsplit("-", 1)[1]) if checkpoint is not None else 0


def seal(folder: Path, spent: dict | None = None) -> None:
    """Record the sha256 of a finished checkpoint's files (fsynced first), and `spent`: the training's
    seconds and tokens up to it, over every session (what a resumed run adds its own to)."""
    import os

    files = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file() and p.name != CHECKPOINT_INFO):
        with open(path, "rb") as fh:
            os.fsync(fh.fileno())
        files[str(path.relative_to(folder))] = durable.sha256_file(path)
    durable.write_text(folder / CHECKPOINT_INFO, json.dumps({"files": files, **({"spent": spent} if spent else {})},
                                                           indent=1, sort_keys=True))


def _spent(checkpoint: Path | None) -> tuple[float, int]:
    """(seconds, tokens) of training up to `checkpoint`, as `seal` recorded them; (0, 0) without one."""
    if checkpoint is None:
        return 0.0, 0
    spent = json.loads((checkpoint / CHECKPOINT_INFO).read_text()).get("spent") or {}
    return float(spent.get("seconds", 0.0)), int(spent.get("tokens", 0))


def intact(folder: Path) -> bool:
    """Whether a checkpoint's files are those `seal` recorded."""
    try:
        files = json.loads((folder / CHECKPOINT_INFO).read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return all((folder / name).is_file() and durable.sha256_file(folder / name) == digest
               for name, digest in files.items())


def latest_checkpoint(checkpoints: Path) -> Path | None:
    """The newest intact checkpoint; newer damaged or unfinished ones are moved to damaged/."""
    if not checkpoints.is_dir():
        return None
    found = sorted((p for p in checkpoints.iterdir() if p.is_dir() and p.name.startswith("checkpoint-")
                    and p.name.rsplit("-", 1)[1].isdigit()), key=_step_of, reverse=True)
    for folder in found:
        if intact(folder):
            return folder
        damaged = checkpoints.parent / "damaged"
        damaged.mkdir(exist_ok=True)
        target = damaged / f"{folder.name}-{int(time.time())}"
        folder.rename(target)
        log.warning("checkpoint %s is damaged or unfinished: moved to %s, going on from an "
                                            "older one", folder.name, target)
    return None


@contextlib.contextmanager
def quiet_libraries():
    """What a user reads is illm's: transformers', peft's, accelerate's and bitsandbytes' progress bars,
    warnings and log lines are held back while the fine-tuning libraries load and run."""
    import warnings

    from illm_tools.llm.quiet import quiet_transformers

    names = ("bitsandbytes", "peft", "accelerate", "torch")
    levels = {n: logging.getLogger(n).level for n in names}
    for n in names:
        logging.getLogger(n).setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), quiet_transformers():
            warnings.simplefilter("ignore")
            yield
    finally:
        for n, level in levels.items():
            logging.getLogger(n).setLevel(level)

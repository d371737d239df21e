"""`illm annotate`: a trajectory dataset in, its distinct states' LLM answers into the cache."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from illm_tools.annotate.engine import Annotator, Stats
from illm_tools.errors import UsageError
from illm_tools.tasks.prompts import LAYOUTS, TASKS


@dataclass
class AnnotateConfig:
    """Everything that determines a bulk annotation run."""

    data: Path
    """Trajectory dataset written by `illm collect`."""
    cache: Path = Path("data/ann")
    """Annotation cache folder (created if absent; shared by every run that reads it)."""
    model: str = "smollm2-135m"
    """Model alias (see `illm models`), hub id or local folder."""
    tasks: tuple[str, ...] = TASKS
    """Language tasks: action (next-action ranking), summary (64-token history compression)."""
    history: int = 3
    """Observation/action pairs of history in the prompts (paper B.1 uses 3)."""
    layout: str = "shared"
    """Template layout: shared (history first, prefix computed once) or paper (as printed)."""
    batch_size: int = 8
    """States per LLM batch."""
    limit: int | None = None
    """Annotate at most this many missing states (None: all)."""
    dtype: str = "bfloat16"
    """Compute dtype (bfloat16 is the fast path on CPU)."""
    quant: str = "none"
    """bitsandbytes quantisation: none, 4bit or 8bit."""
    chunk: int = 64
    """States per written shard: a killed run loses at most one chunk."""

    def __post_init__(self) -> None:
        self.data, self.cache = Path(self.data), Path(self.cache)
        self.tasks = tuple(self.tasks)
        unknown = sorted(set(self.tasks) - set(TASKS))
        if unknown or not self.tasks:
            raise UsageError(f"unknown --tasks {','.join(unknown) or '(none)'}: choose from {','.join(TASKS)}")
        if self.layout not in LAYOUTS:
            raise UsageError(f"unknown --layout {self.layout!r}: use {' or '.join(LAYOUTS)}")
        if self.batch_size <= 0 or self.chunk <= 0:
            raise UsageError("--batch-size and --chunk must be positive")
        if self.limit is not None and self.limit < 0:
            raise UsageError(f"--limit must be 0 or more, got {self.limit}")


def annotate_dataset(config: AnnotateConfig, on_progress: Callable[[int, Stats], None] | None = None,
                     on_plan: Callable[[Stats, int], None] | None = None) -> Stats:
    """Plan (keys, hits, misses; `on_plan(stats, states_to_do)`), then annotate the missing states.
    Returns the run's counters."""
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.data.trajectories import open_table
    from illm_tools.llm.loading import load_model
    from illm_tools.tasks.state import TABLE_COLUMNS, records_from_table

    table = open_table(config.data, columns=TABLE_COLUMNS + ["renderer"])
    if table.num_rows and table.column("obs_text").null_count == table.num_rows:
        raise UsageError(f"{config.data} has no observation text: its env has no text renderer yet")
    cache = AnnotationCache(config.cache)  # refuses a folder that is not a cache before loading a model
    records, env_ids = records_from_table(table, config.history)
    renderers = table.column("renderer").to_pylist()
    lm = load_model(config.model, dtype=config.dtype, quant=config.quant)
    annotator = Annotator(lm, cache, model=config.model, tasks=config.tasks, history_len=config.history,
                          layout=config.layout, batch_size=config.batch_size, chunk=config.chunk)
    stats = Stats()
    plan = annotator.plan(records, env_ids, renderers, stats)
    if on_plan is not None:
        on_plan(stats, len(plan) if config.limit is None else min(len(plan), config.limit))
    return annotator.run(plan, limit=config.limit, stats=stats, on_progress=on_progress)

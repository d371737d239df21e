"""`illm annotate`: a trajectory dataset in, its distinct states' LLM answers into the cache."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from illm_tools.annotate.engine import Annotator, Stats
from illm_tools.errors import UsageError
from illm_tools.llm.spec import LLMSpec
from illm_tools.tasks.prompt_config import PromptConfig
from illm_tools.tasks.prompts import DEFAULT_TASKS
from illm_tools.tasks.registry import get_task, parse_tasks


MAX_PROCESSES = 4096
"""More annotating processes than any one launch starts (a typo, not a cluster)."""
DEFAULT_CHUNK = 32
"""States per written shard for a backend that names none (an LLM: about 20 s on 2 CPU cores)."""


@dataclass
class AnnotateConfig:
    """Everything that determines a bulk annotation run."""

    data: Path
    """Trajectory dataset written by `illm collect`."""
    cache: Path = Path("data/ann")
    """Annotation cache folder (created if absent; shared by every run that reads it)."""
    llm: LLMSpec = field(default_factory=LLMSpec)
    """The LLM that annotates (`illm_tools.llm.spec`); under `accelerate launch` (or --num-processes)
    each process takes its own device for cuda/auto."""
    tasks: tuple[str, ...] = DEFAULT_TASKS
    """Language tasks (`illm_tools.tasks.registry`): action (next-action ranking), summary (64-token
    history compression), goal (suggested goals: ELLM's, and a head of iLLM's), plan (a 2-7 action
    plan); any combination."""
    setup: PromptConfig = field(default_factory=PromptConfig)
    """How states become prompts (`illm_tools.tasks.prompt_config`): --history, --layout, and --mode hop
    (the raw observations translated into the LLM's embedding space, iLLM(hop), `illm_tools.hop`; any
    suite, Atari included) with the training run's --hop-seed and --hop-beta."""
    batch_size: int = 8
    """States per LLM batch."""
    limit: int | None = None
    """Annotate the `limit` most visited distinct states of the dataset, those the cache lacks
    (None: all). The same limit again annotates nothing."""
    max_minutes: float | None = None
    """Stop after this many minutes, between chunks, with every finished chunk written."""
    chunk: int | None = None
    """States per written shard: a killed run loses at most one chunk, and `max_minutes` is
    checked between chunks. None: the backend's (`chunk_states`: 32 for an LLM, about 20 s on 2
    CPU cores at history 0; 2,048 for the oracle, about 2 s)."""
    num_processes: int = 1
    """Annotate with N processes: the command runs `accelerate launch --num_processes N` on itself (the
    states are split between them)."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_folder, check_numbers

        self.data, self.cache = Path(self.data), Path(self.cache)
        check_numbers(self, positive=("batch_size", "chunk", "max_minutes", "num_processes"), non_negative=("limit",))
        if not self.data.is_dir():
            raise UsageError(f"no trajectory dataset at {self.data}: pass a folder `illm collect` wrote")
        from illm_tools.folders import owner

        held = owner(self.data)
        if held not in (None, "trajectory dataset"):  # a cache or a run given where the dataset belongs
            into = f" (`illm annotate DATA --cache {self.data}` adds to this cache)" if held == "annotation cache" else ""
            raise UsageError(f"{self.data} is {'an' if held[0] in 'aeiou' else 'a'} {held}, not a trajectory dataset: "
                             f"pass the folder `illm collect --out` wrote as DATA{into}")
        check_folder(self.cache, "--cache")
        self.tasks = parse_tasks(self.tasks)
        if self.num_processes > MAX_PROCESSES:
            raise UsageError(f"--num-processes must be between 1 and {MAX_PROCESSES:,}, got {self.num_processes}")
        unfit = [t for t in self.tasks if not get_task(t).hop]
        if self.setup.hop and unfit:
            raise UsageError(f"the {', '.join(unfit)} task has no hop form: annotate hop data with other --tasks")


@dataclass
class AnnotateResult:
    """A bulk run's counters and what the cache covers of the dataset afterwards."""

    stats: Stats
    dataset_states: int
    """Distinct states in the dataset (under this history length)."""
    dataset_steps: int
    selected_states: int
    """States the run was asked for: the `limit` most visited (all without a limit)."""
    selected_step_share: float
    """Share of the dataset's steps those states cover."""
    covered_states: int
    """Distinct states of the dataset the cache now answers for every task."""
    covered_step_share: float
    """Share of the dataset's steps they cover: the target coverage a run retracing it would get."""


def distributed_state():
    """accelerate's `PartialState` when this process is one of several (`accelerate launch
    --multi_gpu`, torchrun), else None. Without a GPU (or with ACCELERATE_USE_CPU) the processes
    are CPU processes joined by gloo. (accelerate's `--cpu` launcher starts several processes only
    through MPI, `--mpirun_hostfile`; without it, it starts one.)"""
    import os

    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return None
    import torch
    # Before the group exists: `torch.distributed.nn.functional` binds `group.WORLD` into its functions'
    # defaults when imported, and transformers imports it (through torch.distributed.fsdp) when the
    # model loads. Imported after the group is made, it pins the group: `destroy_process_group` then
    # leaves its gloo worker threads running into interpreter shutdown, where they can abort the
    # process after its work is done (pytorch PR 179291: "terminate called without an active
    # exception", SIGABRT; 7 runs in 40 of this module's collectives, 2 processes on a loaded 2-core
    # machine; 0 in 40 with this import first). Imported now, those defaults are None and
    # `destroy_process_group` joins the threads (tests/test_annotate_processes.py checks it).
    import torch.distributed.nn  # noqa: F401
    from accelerate import PartialState

    cpu = not torch.cuda.is_available() or os.environ.get("ACCELERATE_USE_CPU", "").lower() in ("1", "true")
    return PartialState(cpu=cpu)


def _gathered(stats: Stats, state) -> Stats:
    """Every process's counters summed (each annotated its own share of the plan)."""
    from accelerate.utils import gather_object

    parts = gather_object([(stats.annotated_states, stats.rows, stats.summaries, stats.summary_tokens,
                            stats.per_task, stats.stopped_early, stats.seconds)])
    total = Stats(states=stats.states, keys=stats.keys, hits=stats.hits, misses=stats.misses,
                  too_long=stats.too_long)  # planned alike by every process
    for annotated, rows, summaries, tokens, per_task, stopped, seconds in parts:
        total.annotated_states += annotated
        total.rows += rows
        total.summaries += summaries
        total.summary_tokens += tokens
        total.stopped_early |= stopped
        total.seconds = max(total.seconds, seconds)
        for task, n in per_task.items():
            total.per_task[task] = total.per_task.get(task, 0) + n
    return total


def annotate_dataset(config: AnnotateConfig, on_progress: Callable[[int, Stats], None] | None = None,
                     on_plan: Callable[[Stats, int], None] | None = None,
                     should_stop: Callable[[], bool] | None = None) -> AnnotateResult:
    """Count the dataset's distinct states, most visited first; plan the `limit` most visited that
    the cache lacks (`on_plan(stats, states_to_do)`); annotate them, stopping between chunks once
    `max_minutes` have passed or `should_stop()` says so; report the coverage."""
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.data.trajectories import open_table, require_text
    from illm_tools.tasks.state import TABLE_COLUMNS, records_from_table

    history = config.setup.history_len
    if config.setup.hop:
        from illm_tools.hop.context import RAW_COLUMNS, hop_records_from_table

        table = open_table(config.data, columns=RAW_COLUMNS)
        cache = AnnotationCache(config.cache)  # refuses a folder that is not a cache before loading a model
        records, env_ids = hop_records_from_table(table, history)
        renderers = [config.setup.hop_renderer] * len(records)
    else:
        table = open_table(config.data, columns=TABLE_COLUMNS + ["renderer"])
        require_text(table, config.data)
        cache = AnnotationCache(config.cache)  # refuses a folder that is not a cache before loading a model
        records, env_ids = records_from_table(table, history)
        renderers = table.column("renderer").to_pylist()
    state = distributed_state()
    llm = config.llm.placed(state)  # under accelerate: this process's own device
    lm = llm.load()
    annotator = Annotator.of_setup(lm, cache, llm, config.setup, tasks=config.tasks, batch_size=config.batch_size,
                                   chunk=config.chunk or getattr(lm, "chunk_states", DEFAULT_CHUNK))
    visited = annotator.visited(records, env_ids, renderers)
    selected = visited.top(config.limit)
    stats = Stats()
    plan = annotator.plan(selected, stats=stats)
    if state is not None:  # each process annotates its contiguous share of the states, writing its own shards
        with state.split_between_processes(plan) as mine:
            plan = list(mine)
    if on_plan is not None:
        on_plan(stats, len(plan))
    max_seconds = None if config.max_minutes is None else 60.0 * config.max_minutes
    annotator.run(plan, stats=stats, on_progress=on_progress, max_seconds=max_seconds, should_stop=should_stop)
    if state is not None:
        state.wait_for_everyone()
        stats = _gathered(stats, state)
        cache.refresh()
    covered = visited.covered(cache)
    return AnnotateResult(stats, len(visited), visited.total_steps, len(selected),
                          selected.total_steps / max(visited.total_steps, 1), int(covered.sum()),
                          visited.step_share(covered))

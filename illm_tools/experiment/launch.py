"""An `illm experiment`'s runs trained: `jobs` at a time in local processes (Ctrl-C stops them after
their update, with a checkpoint each) or as submitit jobs, each run's outcome reported as it ends."""
from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import replace
from pathlib import Path
from typing import Any

from illm_tools.errors import UsageError
from illm_tools.experiment.config import check_launcher
from illm_tools.experiment.plan import Run, claim_results, plan, select
from illm_tools.experiment.spec import Cluster, Spec

_STOP = None  # a local grid worker's copy of the grid's stop event (`_init_worker`)
POLL_S = 0.5  # how often the local grid's parent checks `should_stop` while runs train


def _init_worker(stop) -> None:
    """A local grid worker. Ctrl-C reaches the whole process group; the worker ignores it and the
    parent alone decides: it sets `stop`, which every run reads after each update (a checkpoint,
    then an early return), so no update is cut in half and no worker prints a traceback."""
    import signal

    global _STOP
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _STOP = stop


def _train_one(cfg) -> dict:
    """One run in a worker process (its metrics' last line; `stopped` when the grid's stop ended it
    early with a checkpoint)."""
    import os

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from illm_tools.rl.run import train

    return train(cfg, should_stop=_STOP.is_set if _STOP is not None else None)


def _outcome(run: Run, future: Future) -> str:
    """A finished future's (or submitit job's) run status set, and the event `on_run` hears: "done",
    "failed: <reason>", "stopped at N frames (checkpoint written)", or, stopped before its first
    update (the trainer writes no checkpoint then), "stopped before its first update" (status "new")."""
    try:
        result = future.result()
    except Exception as e:  # noqa: BLE001 - one failed run must not stop the grid; it is reported
        run.status = "failed"
        return _failure(e)
    if not result.get("stopped"):
        run.status = "done"
        return "done"
    if not result.get("global_step"):
        run.status = "new"
        return "stopped before its first update"
    run.status = "stopped"
    return f"stopped at {result['global_step']:,} frames (checkpoint written)"


def shared_cores(config, jobs: int):
    """A run's config as it trains beside `jobs - 1` others on this machine: its live annotator (a sync
    oracle or LLM) gets its share of the cores, `cpu_count // jobs` threads, where the spec leaves
    `llm_threads` at 0 ("all cores", right for one run alone). Without it 10 sync illm runs of a 15-job
    grid on a 16-core machine each ran their annotator on 16 threads: their first rollout's targets took
    371-411 s instead of under a second, and the ppo runs beside them fell from 2,174 to about 216
    steps/s (2026-11-28, docs/measured.md). `llm_threads` is not a setting (it changes no result), so a
    run resumed at another --jobs is the same run."""
    if jobs <= 1 or config.targets.llm_threads:
        return config
    share = max(1, (os.cpu_count() or 1) // jobs)
    return replace(config, targets=replace(config.targets, llm_threads=share))


def _failure(e: BaseException) -> str:
    """A failed run's reason in one line."""
    return f"failed: {str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__}"


def _submitit(spec: Spec, results: Path, todo: list[Run], jobs: int, launcher: str, cluster: Cluster,
              on_run: Callable[[Run, str], None] | None) -> None:
    """Each run a job through submitit (a SLURM job array, `jobs` of its tasks at a time; or
    submitit's local executor in waves of `jobs` processes, to try the path without a cluster).
    The jobs' logs go to RESULTS/.submitit/<job id>. Waits for every job: stopping this command
    leaves queued jobs running (`scancel` them), and a job whose run another job is training
    stops at once (the run folder's lock)."""
    try:
        import submitit
    except ImportError:
        raise UsageError(f"--launcher {launcher} needs the package submitit: pip install submitit") from None
    executor = submitit.AutoExecutor(folder=str(results / ".submitit" / "%j"),
                                     cluster="slurm" if launcher == "slurm" else "local")
    params: dict[str, Any] = {"name": f"illm-{spec.name}", "timeout_min": cluster.time_minutes,
                              "cpus_per_task": cluster.cpus}
    if cluster.gpus:
        params["gpus_per_node"] = cluster.gpus
    if cluster.mem_gb:
        params["mem_gb"] = cluster.mem_gb
    if launcher == "slurm":
        params["slurm_array_parallelism"] = jobs
        if cluster.partition:
            params["slurm_partition"] = cluster.partition
    executor.update_parameters(**params)
    configs = [replace(r.config, threads=cluster.cpus) for r in todo]
    waves = [range(len(todo))] if launcher == "slurm" else [range(i, min(i + jobs, len(todo)))
                                                             for i in range(0, len(todo), jobs)]
    for wave in waves:
        submitted = executor.map_array(_train_one, [configs[i] for i in wave])
        for i, job in zip(wave, submitted):
            event = _outcome(todo[i], job)
            if on_run is not None:
                on_run(todo[i], event)


def run_experiment(spec: Spec, results: str | Path, *, jobs: int = 1,
                   on_run: Callable[[Run, str], None] | None = None, launcher: str = "local",
                   cluster: Cluster | None = None, only: list[str] | tuple = (),
                   should_stop: Callable[[], bool] | None = None) -> list[Run]:
    """Plan, claim the results folder, and train every run not done (of those `only`'s patterns pick,
    `select`), `jobs` at a time, through the `launcher` (`LAUNCHERS`; `cluster` overrides the spec's
    resources). `on_run(run, event)` hears "done", "failed: <reason>" or "stopped at ..." as each run
    ends. Local launcher: once `should_stop()` (checked every POLL_S) says so, the runs in progress
    finish their update and write a checkpoint (status "stopped") and the runs not yet started stay as
    they were; an exception meanwhile (a second Ctrl-C) ends the workers at once. Returns the runs
    picked."""
    if jobs < 1:
        raise UsageError(f"--jobs must be at least 1, got {jobs}")
    check_launcher(launcher)
    runs = select(plan(spec, results), only)
    claim_results(spec, results)
    todo = [r for r in runs if r.status != "done"]
    if not todo:
        return runs
    if launcher != "local":
        _submitit(spec, Path(results), todo, jobs, launcher, cluster or spec.cluster, on_run)
        return runs
    import multiprocessing as mp

    context = mp.get_context("spawn")
    stop = context.Event()
    with ProcessPoolExecutor(max_workers=jobs, mp_context=context, initializer=_init_worker,
                             initargs=(stop,)) as pool:
        futures = {pool.submit(_train_one, shared_cores(run.config, jobs)): run for run in todo}
        pending = set(futures)
        try:
            while pending:
                finished, pending = wait(pending, timeout=POLL_S, return_when=FIRST_COMPLETED)
                for future in finished:
                    if future.cancelled():
                        continue
                    event = _outcome(futures[future], future)
                    if on_run is not None:
                        on_run(futures[future], event)
                if should_stop is not None and not stop.is_set() and should_stop():
                    stop.set()
                    for future in pending:
                        future.cancel()  # not started: left as it was; started ones stop after their update
        except BaseException:
            stop.set()
            for child in mp.active_children():  # the pool's workers: their runs keep the last checkpoint
                child.terminate()
            raise
    return runs

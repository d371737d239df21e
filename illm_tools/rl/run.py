"""Assembling a training run from its config: the env pool, the LLM target provider (cache, and the
live model when a budget is given), and the trainer; plus evaluation of a finished run."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Mapping
from contextlib import closing, contextmanager, nullcontext
from pathlib import Path
from typing import Any

import numpy as np

from illm_tools.errors import CacheError, IllmError, UsageError
from illm_tools.rl.config import TrainConfig
from illm_tools.rl.threads import torch_threads

EVAL_SEED_OFFSET = 2**40
"""Evaluation episodes use seeds from here on: training seeds (seed + steps) never get this far."""


def make_pool(cfg: TrainConfig, start_step: int = 0):
    """The env pool a run trains on. Text is rendered only when LLM targets need it. A run resumed
    at `start_step` frames (its checkpoint's) starts its episodes past every seed it can have used
    so far (the pool's episode k of env i has seed `seed + i + k * num_envs`, so
    `seed + start_step + num_envs` is unused)."""
    from illm_tools.envs.pool import EnvPool

    seed = cfg.seed + (start_step + cfg.num_envs if cfg.resume else 0)
    return EnvPool(cfg.env_id, cfg.num_envs, seed, render=cfg.needs_targets and not cfg.setup.hop,
                   action_space=cfg.action_space, episode_seeds=cfg.env_seeds,
                   num_dists=cfg.num_dists, vector=cfg.vector, **cfg.env_options)


def make_provider(cfg: TrainConfig, num_actions: int, started=None):
    """The target provider of a run whose bonus needs LLM targets, or None: the class registered for
    the kind of targets its bonus reads (`target_kind`, `illm_tools.rl.providers`: `CachedTargets`,
    the rows of iLLM's language tasks; ELLM's `GoalTargets`, its suggested goals), reading the cache under the run's `LLMSpec` and `AnnotationSetup`, with the live
    annotator (`make_live`; `started`: the async worker `early_live` started, taken over). `cfg` is
    the run's resolved config (`TrainConfig.resolved`: the LLM's device and dtype are this machine's)."""
    if not cfg.needs_targets:
        return None
    if cfg.targets.cache is None:
        raise UsageError(f"--method {cfg.method} reads LLM targets: pass --cache DIR (an annotation cache, "
                         "see `illm annotate`), or use --method ppo")
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.intrinsic.registry import get_method
    from illm_tools.rl.providers import provider_class
    from illm_tools.tasks.registry import get_task
    from illm_tools.tasks.served import model_identity
    from illm_tools.tasks.annotation_setup import check_setup

    method = get_method(cfg.method)
    cache = AnnotationCache(cfg.targets.cache)
    llm, setup = cfg.llm, cfg.annotation_setup  # resolved: the machine's device and dtype
    llm.check_use(setup.env_id, setup.renderer)
    fingerprint, unreachable = model_identity(llm, cache)
    answers = unreachable is None
    if unreachable and cfg.targets.live_budget != 0 and cfg.targets.annotator is None:
        import logging

        logging.getLogger(__name__).warning(
            "%s: this run trains from the cache's targets alone, its missed states are not annotated (start the "
            "engine for the live fallback, or pass --live-budget 0)", unreachable)
    if answers and any(get_task(t).kind == "ranking" for t in setup.tasks):
        llm.check_ranking()  # before the run starts: an engine that cannot rank (openai backend)
    builder = setup.builder(llm.model, fingerprint)
    if len(cache) == 0 and cfg.targets.live_budget == 0:
        raise CacheError(f"the cache {cfg.targets.cache} is empty and --live-budget is 0: nothing would give targets; "
                         "run `illm annotate` first or allow a live budget")
    if len(cache) and not cfg.targets.new_setup:
        check_setup(cache, builder, llm=llm, tasks=setup.tasks)
    provider = provider_class(method.bonus_class).for_run(cfg, cache, builder, num_actions=num_actions,
                                                          live=make_live(cfg, llm, setup, cache, started) if answers else None,
                                                          shuffle_seed=method.target_shuffle)  # illm-shuffled
    return provider


def early_live(cfg: TrainConfig):
    """The async live worker of a run that has one (`wants_worker`), started now, or None:
    `build_run` starts it before the env pool, the provider's checks and the network, unless
    `early_live_of_settings` started it sooner still. It imports what loading the model will
    (`LLMSpec.preload`) until `build_run` sends it its spec (the LLM placed, `configure`); then
    `make_provider` takes it over, or it is closed with the run."""
    if not wants_worker(cfg):
        return None
    from illm_tools.rl.live import AsyncLive

    return AsyncLive(budget=cfg.targets.live_limit, early=cfg.llm)


def early_live_of_settings(settings: Mapping[str, Any]):
    """`early_live` before the run's config exists, from its flat settings as typed (`illm train`'s
    options): building the config imports the method's bonus and with it torch (0.9 s on 2 cores),
    which the worker's own imports can run beside. A guess from what the settings say: a resumed run
    (its settings are in its folder) or settings that do not parse get none here (`build_run` starts
    one where the config wants it), and a worker the config turns out not to want (a method that
    reads no LLM targets) is closed by `build_run` at once, having only imported. The model it
    preloads is the one typed; a cache's adopted setup (`adopt_setup`) reaches it with its spec."""
    from illm_tools.intrinsic.registry import get_method
    from illm_tools.llm.spec import LLMSpec
    from illm_tools.rl.run_parts import TargetsConfig

    if settings.get("resume"):
        return None
    given = {k: v for k, v in settings.items() if v is not None}
    try:
        targets = TargetsConfig(**{k: given[k] for k in ("cache", "live_budget", "live_mode", "annotator") if k in given})
        llm = LLMSpec(**{k: given[k] for k in ("backend", "model") if k in given})
        bonus = get_method(given.get("method", TrainConfig.__dataclass_fields__["method"].default)).entry_point
    except IllmError:  # the config's own checks say what is wrong
        return None
    if not _wanted(bonus is not None, targets, llm.backend):
        return None
    from illm_tools.rl.live import AsyncLive

    return AsyncLive(budget=targets.live_limit, early=llm)


def wants_worker(cfg: TrainConfig) -> bool:
    """Whether the run's live annotator is an async worker worth starting early (`_wanted`)."""
    return _wanted(cfg.needs_targets, cfg.targets, cfg.llm.backend)


def _wanted(needs_targets: bool, targets, backend: str) -> bool:
    """An async worker (`live_kind`) of a run that reads targets from a cache, whose backend computes
    here (not the oracle, nor an engine's model: their workers start in no time, and an engine is
    first checked, `model_identity`)."""
    from illm_tools.llm.backend import backend_class

    return (needs_targets and targets.cache is not None and live_kind(targets) == "async"
            and getattr(backend_class(backend), "computes", True))


def live_kind(t) -> str | None:
    """Which live annotator a run's `TargetsConfig` asks for: None (no live budget), "remote" (an
    `illm serve` server, `--annotator`), "async" (a worker process) or "sync" (in the trainer's process)."""
    if t.live_budget == 0:
        return None
    if t.annotator is not None:
        return "remote"
    return "async" if t.live_mode == "async" else "sync"


def live_threads(cfg: TrainConfig) -> int:
    """Torch threads of the run's live LLM (`TargetsConfig.llm_threads`; 0: a sync annotator all the
    cores, an async worker the cores the policy's `threads` leave)."""
    if cfg.targets.llm_threads:
        return cfg.targets.llm_threads
    cores = os.cpu_count() or 1
    return cores if cfg.targets.live_mode == "sync" else max(1, cores - cfg.threads)


def worker_spec(cfg: TrainConfig, llm, setup):
    """What the run's async worker needs: its cache, LLM (placed), annotation setup and threads."""
    from illm_tools.rl.live import WorkerSpec

    return WorkerSpec(cache=str(cfg.targets.cache), llm=llm, setup=setup, threads=live_threads(cfg))


def make_live(cfg: TrainConfig, llm, setup, cache, started=None):
    """The live annotator of a run (`illm_tools.rl.live`) for its LLM (placed) and annotation setup,
    or None with no live budget (`live_kind`): sync writes through `cache`, the object the targets are
    read from; async is `started` (`early_live`'s worker) where the run started it; remote asks an
    `illm serve` server."""
    kind = live_kind(cfg.targets)
    if kind is None:
        return None
    if kind == "async":
        if started is not None:
            return started
        from illm_tools.rl.live import AsyncLive

        spec = worker_spec(cfg, llm, setup)
        return AsyncLive(spec, budget=cfg.targets.live_limit)
    if kind == "sync":
        from illm_tools.annotate.engine import Annotator
        from illm_tools.rl.live import SyncLive

        # one shard per rollout: a budget of "all" hands over a rollout's every missed state at once
        annotator = Annotator.of_setup(llm.load(), cache, llm, setup, chunk=4096)
        return SyncLive(annotator, setup, cfg.targets.live_limit, threads=live_threads(cfg))
    from illm_tools.rl.live_remote import SYNC_WAIT, RemoteLive

    return RemoteLive(cfg.targets.annotator, client=str(cfg.run_dir.resolve()), llm=llm, setup=setup,
                      budget=cfg.targets.live_limit, wait=SYNC_WAIT if cfg.targets.live_mode == "sync" else 0.0)


RUN_LOCK = ".lock"
"""flock'ed in a run's folder while a process trains it (`durable.exclusive`)."""


def train(cfg: TrainConfig, on_metrics: Callable[[dict], None] | None = None,
          should_stop: Callable[[], bool] | None = None, started=None) -> dict:
    """Build and run a training run to cfg.total_steps; returns the last update's metrics
    (`Trainer.train`: `should_stop` ends it early with a checkpoint), with `resumed_at` (the frames of
    the checkpoint a resumed run started from) and `live_at_close`. The run resolves its config
    here, once (a resumed run's recorded choices kept: `with_recorded_choices`), and reads its saved
    run once, its checkpoint under the run folder's lock (a second `illm train` of the same folder, a
    re-submitted cluster job or a second terminal, stops at once instead of interleaving checkpoints).
    An async live worker is started first of all (`early_live`), unless the caller started it
    (`started`: `early_live_of_settings`); it is closed with the run either way."""
    from illm_tools import durable
    from illm_tools.folders import refuse_foreign
    from illm_tools.rl.saved import read_run, with_recorded_choices

    live = started if started is not None else early_live(cfg)  # its imports run beside this process's
    # closed with the run either way: a run refused before its provider took the worker (closing twice does nothing)
    with closing(live) if live is not None else nullcontext(), torch_threads(cfg.threads):
        saved = read_run(cfg.run_dir) if cfg.resume else None
        # devices resolved (a GPU this machine lacks: one line before anything lands on disk) and auto
        # dtypes measured with the run's own thread count, as config.json records them
        cfg = with_recorded_choices(cfg, saved).resolved()
        made = not cfg.run_dir.exists()
        refuse_foreign(cfg.run_dir, "training run", "--out")  # before the lock file lands in someone else's folder
        cfg.run_dir.mkdir(parents=True, exist_ok=True)
        try:
            with durable.exclusive(cfg.run_dir / RUN_LOCK, busy=f"{cfg.run_dir} is being trained by another process; "
                                   "wait for it to end (or stop it), then pass --resume to continue the run"):
                checkpoint = saved.checkpoint if saved is not None else None
                with build_run(cfg, on_metrics, checkpoint, started=live) as trainer:
                    result = trainer.train(should_stop)
            # what the live annotator wrote while the run shut down (its worker's last chunk), counted once closed
            return {**result, "live_at_close": int(getattr(trainer.provider, "landed_at_close", 0)),
                    "resumed_at": int(checkpoint["global_step"]) if checkpoint is not None else None}
        except IllmError:  # refused before the run wrote anything: leave no folder holding only the lock
            if made and cfg.run_dir.is_dir() and {p.name for p in cfg.run_dir.iterdir()} <= {RUN_LOCK}:
                (cfg.run_dir / RUN_LOCK).unlink(missing_ok=True)
                cfg.run_dir.rmdir()
            raise


@contextmanager
def build_run(cfg: TrainConfig, on_metrics: Callable[[dict], None] | None = None,
              checkpoint: dict | None = None, started=None) -> Iterator:
    """The whole run assembled from its resolved config (`TrainConfig.resolved`), in one place: the
    env pool (`make_pool`), the method's target provider with its live annotator (`make_provider`),
    then the trainer, which builds the network, the bonus and the state sources and restores
    `checkpoint` (a resumed run's, read by `train`). An async live worker is started before all of
    them (`early_live`), unless `train` already started it (`started`); here it is configured. Yields the `Trainer`; closes the pool and the provider (its live worker)
    on the way out, also when a later piece is refused."""
    from illm_tools.rl.ppo import Trainer

    live, pool, provider = started if started is not None else early_live(cfg), None, None
    try:
        if live is not None and not wants_worker(cfg):  # started from settings the resolved config changed
            live.close()
            live = None
        if live is not None:
            live.configure(worker_spec(cfg, cfg.llm, cfg.annotation_setup), budget=cfg.targets.live_limit)
        pool = make_pool(cfg, int(checkpoint["global_step"]) if checkpoint is not None else 0)
        provider = make_provider(cfg, len(pool.action_names), started=live)
        yield Trainer(cfg, pool, provider, on_metrics=on_metrics, checkpoint=checkpoint)
    finally:
        if pool is not None:
            pool.close()
        if provider is not None:
            provider.close()
        if live is not None and getattr(provider, "live", None) is not live:  # refused before the provider took it
            live.close()


def evaluate(run_dir: str | Path, *, episodes: int = 100, seed: int = 0, greedy: bool = False,
             num_envs: int = 8) -> dict:
    """Success rate and mean return of a run's policy over `episodes` fresh episodes."""
    from illm_tools.envs.pool import EnvPool
    from illm_tools.rl.policy import load_policy
    from illm_tools.rl.saved import read_run

    run_dir = Path(run_dir)
    if episodes <= 0:
        raise UsageError(f"--episodes must be positive, got {episodes}")
    saved = read_run(run_dir)
    cfg = saved.config
    num_envs = min(num_envs, episodes)
    pool = EnvPool(cfg.env_id, num_envs, EVAL_SEED_OFFSET + seed, render=False, action_space=cfg.action_space,
                   episode_seeds=cfg.env_seeds,  # a fixed-layout run is evaluated on its layouts
                   num_dists=cfg.num_dists, vector=cfg.vector, **cfg.env_options)
    policy = load_policy(saved, pool, greedy=greedy, seed=seed)
    finished = []
    counted = np.zeros(num_envs, dtype=np.int64)  # episodes taken from each env: equal shares, no bias to short ones
    quota = [episodes // num_envs + (i < episodes % num_envs) for i in range(num_envs)]
    obs = pool.reset()
    with torch_threads(cfg.threads):
        while len(finished) < episodes:
            step = pool.step(policy.act(obs))
            for episode in step.episodes:
                if counted[episode.env_index] < quota[episode.env_index]:
                    counted[episode.env_index] += 1
                    finished.append(episode)
            obs = step.obs
    pool.close()
    figures = pool.suite.episode_metrics(finished)
    return {"run": str(run_dir), "env_id": cfg.env_id, "method": cfg.method, "episodes": episodes,
            "score": figures["score"], "score_name": pool.suite.score_name,
            "success_rate": figures["success_rate"],
            "mean_return": float(np.mean([e.episode_return for e in finished])),
            "mean_length": float(np.mean([e.length for e in finished])), "greedy": greedy, "policy": policy.name,
            "frames": policy.frames, **{k: v for k, v in figures.items() if k not in ("score", "success_rate")}}

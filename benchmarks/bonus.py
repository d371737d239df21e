"""Training throughput of every registered method (`illm_tools.intrinsic.registry.METHODS`) against
`--method ppo`, in the same run, with the same env, frames, envs x steps and threads: each printed
as steps/s, its time per update by phase, and its ratio to ppo's steps/s.

Methods whose bonus reads LLM targets (illm, illm-noreward, illm-shuffled, ellm) train on a cache
filled without an LLM, as benchmarks/train.py does: a first pass of the same method and seed fills
an empty cache through the live fallback with rows of deterministic pseudo-random scores,
embeddings and goals (the trainer's speed does not depend on what the LLM said); the second pass,
the one timed, reads the cache only, and its cache hit rate is printed. (A pass that leaves the
first's path, as illm-shuffled's can, whose partners move while the first pass fills the cache,
misses a few states: they get no target, which is what a run on that cache would see.) A method
that cannot run here (chibit without its model files, say) is skipped, with the reason printed.

    .venv/bin/python benchmarks/bonus.py [--env BabyAI-GoToLocal-v0] [--frames 20480]
                                         [--methods ngu,apt] [--skip chibit]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from train import DIM  # noqa: E402  (benchmarks/train.py's summary size)

from illm_tools.annotate.engine import Annotator  # noqa: E402
from illm_tools.llm.stub import StubBackend  # noqa: E402

from illm_tools.cache.store import AnnotationCache  # noqa: E402
from illm_tools.envs import renderer_of  # noqa: E402
from illm_tools.intrinsic.registry import METHODS, get_method  # noqa: E402
from illm_tools.rl.config import TrainConfig  # noqa: E402
from illm_tools.rl.live import SyncLive  # noqa: E402
from illm_tools.rl.ppo import Trainer  # noqa: E402
from illm_tools.rl.providers import provider_class  # noqa: E402
from illm_tools.rl.run import make_pool  # noqa: E402
from illm_tools.rl.threads import torch_threads  # noqa: E402
from record import options, record, settings  # noqa: E402

PHASES = ("time/rollout_s", "time/targets_s", "time/update_s")


class GoalAwareAnnotator(Annotator):
    """The stub backend's annotator (answers derived from the prompt), with `goal` rows of a fixed
    short goal list (the stub's own goal text would parse to no goal ELLM can match)."""

    def annotate(self, states):
        goal_jobs = [[j for j in jobs if j.prompt.task == "goal"] for jobs in states]
        others = [[j for j in jobs if j.prompt.task != "goal"] for jobs in states]
        rows = super().annotate([jobs for jobs in others if jobs])  # ELLM's states have only goal jobs
        gen = type("G", (), {"text": "1. go to the red ball\n2. pick up the key", "token_ids": [0] * 8,
                             "finished": True, "embedding": [0.0] * DIM})
        return rows + [self._text_row(job, gen) for jobs in goal_jobs for job in jobs]


def provider_for(method, cfg: TrainConfig, cache_dir: Path, num_actions: int, fill: bool):
    """The run's target provider over a synthetic cache (None for a method without targets)."""
    if not method.needs_targets:
        return None
    tasks = tuple(getattr(method, "target_tasks", ("action", "summary")))
    cache = AnnotationCache(cache_dir)
    annotator = GoalAwareAnnotator(StubBackend(f"synthetic-benchmark:{DIM}"), cache, model="synthetic", tasks=tasks,
                                   history_len=cfg.setup.history_len, chunk=10_000)
    builder = annotator.builder(cfg.env_id, renderer_of(cfg.env_id))
    live = SyncLive(annotator, cfg.annotation_setup, 10**9) if fill else None
    # the provider registered for the targets the method's bonus reads (CachedTargets, ELLM's GoalTargets), as a run
    # builds it
    return provider_class(method.bonus_class).for_run(cfg, cache, builder,  # cfg.embedding_dim: SmolLM2's, DIM
                                                      num_actions=num_actions, live=live,
                                                      shuffle_seed=method.target_shuffle)


def run(cfg: TrainConfig, cache_dir: Path, fill: bool = False) -> tuple[float, dict]:
    """Train `cfg`; returns (steps/s over the whole run, last metrics with the mean phase times)."""
    method = get_method(cfg.method)
    pool = make_pool(cfg)
    phases = dict.fromkeys(PHASES, 0.0)

    def on_metrics(m: dict) -> None:
        for k in PHASES:
            phases[k] += m[k] / cfg.num_updates

    try:
        provider = provider_for(method, cfg, cache_dir, len(pool.action_names), fill)
        trainer = Trainer(cfg.resolved(), pool, provider, on_metrics=on_metrics)
        start = time.perf_counter()
        last = trainer.train()
        elapsed = time.perf_counter() - start
    finally:
        pool.close()
    last["phases"] = "  ".join(f"{k[5:-2]} {v:.3f}s" for k, v in phases.items())
    return cfg.num_updates * cfg.batch_size / elapsed, last


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="BabyAI-GoToLocal-v0")
    parser.add_argument("--frames", type=int, default=20_480)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--num-steps", type=int, default=128)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--methods", default="", help="Comma-separated methods to time (default: all registered).")
    parser.add_argument("--skip", default="", help="Comma-separated methods not to time.")
    options(parser)
    args = parser.parse_args()
    chosen = [m for m in (args.methods.split(",") if args.methods else METHODS) if m and m != "ppo"]
    skip = set(filter(None, args.skip.split(",")))

    with tempfile.TemporaryDirectory() as tmp, torch_threads(args.threads):
        def config(mode: str, name: str) -> TrainConfig:
            return TrainConfig.from_dict(dict(env_id=args.env, run_dir=Path(tmp) / name, method=mode, seed=0, total_steps=args.frames,
                               num_envs=args.num_envs, num_steps=args.num_steps,
                               cache=Path(tmp) / f"ann-{mode}", live_budget=0, tensorboard=False,
                               checkpoint_every=0, threads=args.threads))

        print(f"env {args.env}, {args.frames} frames, {args.num_envs} envs x {args.num_steps} steps, "
              f"{args.threads} thread(s)", flush=True)
        sps_ppo, last = run(config("ppo", "ppo"), Path(tmp) / "unused")
        print(f"{'ppo':<14} {sps_ppo:8,.0f} steps/s  ratio  1.00  per update: {last['phases']}", flush=True)
        figures = {"ppo_steps_per_s": sps_ppo}
        for mode in chosen:
            if mode in skip:
                print(f"{mode:<14} skipped: --skip", flush=True)
                continue
            try:
                method = get_method(mode)
                if method.needs_targets:  # pass 1 fills the cache (untimed)
                    run(config(mode, f"{mode}-fill"), Path(tmp) / f"ann-{mode}", fill=True)
                sps, last = run(config(mode, mode), Path(tmp) / f"ann-{mode}")
            except Exception as e:  # noqa: BLE001 - a method that cannot run here is reported, not fatal
                reason = str(e).splitlines()[0] if str(e) else type(e).__name__
                print(f"{mode:<14} skipped: {type(e).__name__}: {reason}", flush=True)
                continue
            hit = f"  (cache hit rate {last['charts/cache_hit_rate']:.3f})" if method.needs_targets else ""
            print(f"{mode:<14} {sps:8,.0f} steps/s  ratio {sps / sps_ppo:5.2f}  per update: {last['phases']}{hit}",
                  flush=True)
            figures.update({f"{mode}_steps_per_s": sps, f"{mode}_over_ppo": sps / sps_ppo})
    if not args.no_record:
        record("bonus", figures, ratio=headline(figures), out=args.record, settings=settings(args))


def headline(figures: dict) -> dict | None:
    """The record's ratio: illm's steps/s over ppo's where illm was timed, else the first method timed
    (no target: the figures say what each method costs)."""
    timed = [k.removesuffix("_over_ppo") for k in figures if k.endswith("_over_ppo")]
    if not timed:
        return None
    mode = "illm" if "illm" in timed else timed[0]
    return {"name": f"{mode} / ppo steps/s", "value": figures[f"{mode}_over_ppo"]}


if __name__ == "__main__":
    main()

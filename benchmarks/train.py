"""Training throughput of `--method illm` against `--method ppo`, same env and settings, in the
same run, in two cases, each printed as a ratio of steps/s:
- every LLM target cached (target >= 0.8);
- async live annotation (target >= 0.7): the cache starts empty, so every rollout misses and the
  worker process annotates with the real embedded model (SmolLM2-135M, one thread) beside the
  rollouts (one thread) on this machine's cores, as `illm train --live-mode async` does.

"Every target cached" is made exact without an LLM in the loop: a first illm pass fills an
empty cache through the live-fallback path, with rows of deterministic pseudo-random scores and
embeddings (the trainer's speed does not depend on what the LLM said); training is deterministic
given the seed, so a second pass with the same seed meets exactly the same states and finds
every one of them in the cache (its cache hit rate is printed). Only that second pass is timed.

    .venv/bin/python benchmarks/train.py [--env BabyAI-GoToLocal-v0] [--frames 20480]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path


from illm_tools.annotate.synthetic import SyntheticAnnotator, SyntheticLM
from illm_tools.cache.store import AnnotationCache
from illm_tools.envs import renderer_of
from illm_tools.rl.config import TrainConfig
from illm_tools.rl.live import SyncLive
from illm_tools.rl.ppo import Trainer, make_pool
from illm_tools.rl.run import make_provider, torch_threads
from illm_tools.rl.targets import CachedTargets

DIM = 576  # SmolLM2-135M's hidden size: the f^hc head is as large as with the embedded model


def run(cfg: TrainConfig, cache_dir: Path | None, live_async: bool = False) -> tuple[float, dict]:
    pool = make_pool(cfg)
    provider = None
    if live_async:
        provider, cfg = make_provider(cfg, len(pool.action_names))
    elif cfg.uses_heads:
        cache = AnnotationCache(cache_dir)
        annotator = SyntheticAnnotator(SyntheticLM("synthetic-benchmark", DIM), cache, model="synthetic", history_len=cfg.history_len,
                                       chunk=10_000)
        builder = annotator.builder(cfg.env_id, renderer_of(cfg.env_id))
        live = SyncLive(annotator, cfg.env_id, builder.renderer, cfg.live_budget) if cfg.live_budget else None
        provider = CachedTargets(cache, builder, calibration="sum", num_actions=len(pool.action_names),
                                 embedding_dim=DIM, live=live)
    phases: dict[str, float] = {}

    def on_metrics(m: dict) -> None:
        for k in ("time/rollout_s", "time/targets_s", "time/update_s"):
            phases[k] = phases.get(k, 0.0) + m[k] / cfg.num_updates

    trainer = Trainer(cfg, pool, provider, on_metrics=on_metrics)
    start = time.perf_counter()
    try:
        last = trainer.train()
    finally:
        if live_async:
            provider.close()
    last["phases"] = "  ".join(f"{k[5:-2]} {v:.3f}s" for k, v in phases.items())
    return cfg.num_updates * cfg.batch_size / (time.perf_counter() - start), last


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="BabyAI-GoToLocal-v0")
    parser.add_argument("--frames", type=int, default=20_480)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--num-steps", type=int, default=128)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--async-frames", type=int, default=40_960,
                        help="Frames of the async case (long enough that the worker's start-up is a small part).")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp, torch_threads(args.threads):
        def config(mode: str, name: str, live_budget: int) -> TrainConfig:
            return TrainConfig(env_id=args.env, run_dir=Path(tmp) / name, mode=mode, seed=0, total_steps=args.frames,
                               num_envs=args.num_envs, num_steps=args.num_steps, embedding_dim=DIM,
                               live_budget=live_budget, tensorboard=False, checkpoint_every=0, threads=args.threads)

        run(config("illm", "fill", 10**9), Path(tmp) / "ann")  # pass 1: fills the cache
        sps_illm, last = run(config("illm", "illm", 0), Path(tmp) / "ann")
        sps_ppo, last_ppo = run(config("ppo", "ppo", 0), None)
        frames = args.frames
        args.frames = args.async_frames
        live = dataclasses.replace(config("illm", "async", 16), cache=Path(tmp) / "live-ann", live_mode="async",
                                   history_len=0)
        sps_async, last_async = run(live, None, live_async=True)
        sps_ppo_long, _ = run(config("ppo", "ppo-long", 0), None)
        args.frames = frames
    print(f"env {args.env}, {args.frames} frames, {args.num_envs} envs x {args.num_steps} steps, {args.threads} thread(s)")
    print(f"ppo               {sps_ppo:8,.0f} steps/s  per update: {last_ppo['phases']}")
    print(f"illm (all cached) {sps_illm:8,.0f} steps/s  per update: {last['phases']}  "
          f"(cache hit rate {last['charts/cache_hit_rate']:.3f})")
    print(f"illm/ppo ratio    {sps_illm / sps_ppo:8.2f}  (target >= 0.8)")
    print(f"async live annotation, {args.async_frames} frames, history 0, SmolLM2-135M worker "
          f"({live.live_threads} thread(s)) beside the trainer ({args.threads}):")
    print(f"ppo               {sps_ppo_long:8,.0f} steps/s")
    print(f"illm (async live) {sps_async:8,.0f} steps/s  per update: {last_async['phases']}  "
          f"(last rollout: targets on {last_async['charts/target_coverage']:.3f} of steps, "
          f"live queue {last_async.get('charts/live_queue', 0):.0f})")
    print(f"illm/ppo ratio    {sps_async / sps_ppo_long:8.2f}  (target >= 0.7)")


if __name__ == "__main__":
    main()

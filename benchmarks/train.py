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

With `--mode hop` (iLLM(hop), `illm_tools.hop`) it measures instead what the hop mode costs per
step, in the same run: ppo on the observation alone, ppo reading Z_h (the embedded SmolLM2-135M
run over every env's translated window at every step), and illm in hop mode with every target
cached (as above; the trainer's LLM computes Z_h, the targets are synthetic).

    .venv/bin/python benchmarks/train.py [--env BabyAI-GoToLocal-v0] [--frames 20480]
    .venv/bin/python benchmarks/train.py --mode hop --env MiniGrid-MultiRoom-N6-v0 --frames 2048 --num-steps 32
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path


from illm_tools.annotate.engine import Annotator
from illm_tools.llm.stub import StubBackend
from illm_tools.cache.store import AnnotationCache
from illm_tools.rl.config import TrainConfig
from illm_tools.rl.live import SyncLive
from illm_tools.rl.ppo import Trainer
from illm_tools.rl.run import make_pool
from illm_tools.llm.spec import LLMSpec
from illm_tools.rl.run import make_provider
from illm_tools.rl.threads import torch_threads
from illm_tools.rl.targets import CachedTargets

DIM = 576  # SmolLM2-135M's hidden size: the f^hc head is as large as with the embedded model


def run(cfg: TrainConfig, cache_dir: Path | None, live_async: bool = False) -> tuple[float, dict]:
    pool = make_pool(cfg)
    provider = None
    if live_async:
        cfg = cfg.resolved()
        provider = make_provider(cfg, len(pool.action_names))
    elif cfg.uses_heads:
        cache = AnnotationCache(cache_dir)
        annotator = Annotator(StubBackend(f"synthetic-benchmark:{DIM}"), cache, model="synthetic", history_len=cfg.setup.history_len,
                                       chunk=10_000)
        builder = annotator.builder(cfg.env_id, cfg.annotation_setup.renderer)
        live = SyncLive(annotator, cfg.annotation_setup, cfg.targets.live_budget) if cfg.targets.live_budget else None
        provider = CachedTargets(cache, builder, calibration="sum", num_actions=len(pool.action_names),
                                 embedding_dim=DIM, live=live)
    phases: dict[str, float] = {}

    def on_metrics(m: dict) -> None:
        for k in ("time/rollout_s", "time/targets_s", "time/update_s"):
            phases[k] = phases.get(k, 0.0) + m[k] / cfg.num_updates

    trainer = Trainer(cfg.resolved(), pool, provider, on_metrics=on_metrics)
    start = time.perf_counter()
    try:
        last = trainer.train()
        trained = time.perf_counter() - start  # the training's rate; the worker's shutdown is timed apart
    finally:
        if live_async:
            closing = time.perf_counter()
            provider.close()
            last_close = time.perf_counter() - closing
    last["phases"] = "  ".join(f"{k[5:-2]} {v:.3f}s" for k, v in phases.items())
    if live_async:
        last["phases"] += f"  (worker shutdown after the run: {last_close:.1f}s)"
    return cfg.num_updates * cfg.batch_size / trained, last


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="BabyAI-GoToLocal-v0")
    parser.add_argument("--frames", type=int, default=20_480)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--num-steps", type=int, default=128)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--mode", choices=("obs", "hop"), default="obs", help="hop: the cost of iLLM(hop) instead.")
    parser.add_argument("--history", type=int, default=3, help="hop: steps of history (the window is one more).")
    parser.add_argument("--dtype", default="bfloat16", help="hop: the LLM's compute dtype (float32 is faster on some CPUs).")
    parser.add_argument("--async-frames", type=int, default=40_960,
                        help="Frames of the async case (long enough that the worker's start-up is a small part).")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp, torch_threads(args.threads):
        def config(mode: str, name: str, live_budget: int) -> TrainConfig:
            return TrainConfig.from_dict(dict(env_id=args.env, run_dir=Path(tmp) / name, method=mode, seed=0, total_steps=args.frames,
                               num_envs=args.num_envs, num_steps=args.num_steps,  # SmolLM2's width: DIM
                               live_budget=live_budget, tensorboard=False, checkpoint_every=0, threads=args.threads))

        if args.mode == "hop":
            hop = {"obs_mode": "hop", "history_len": args.history, "llm": LLMSpec(dtype=args.dtype)}
            sps_ppo, last_ppo = run(config("ppo", "ppo", 0), None)
            sps_ppo_hop, last_ppo_hop = run(dataclasses.replace(config("ppo", "ppo-hop", 0), **hop), None)
            run(dataclasses.replace(config("illm", "fill", 10**9), **hop), Path(tmp) / "ann")  # fills the cache
            sps_illm, last = run(dataclasses.replace(config("illm", "illm", 0), **hop), Path(tmp) / "ann")
            print(f"env {args.env}, {args.frames} frames, {args.num_envs} envs x {args.num_steps} steps, "
                  f"{args.threads} thread(s), hop window {args.history + 1}, SmolLM2-135M {args.dtype}")
            print(f"ppo               {sps_ppo:8,.0f} steps/s  per update: {last_ppo['phases']}")
            print(f"ppo, hop (Z_h)    {sps_ppo_hop:8,.0f} steps/s  per update: {last_ppo_hop['phases']}")
            print(f"illm, hop (cached){sps_illm:8,.0f} steps/s  per update: {last['phases']}  "
                  f"(cache hit rate {last['charts/cache_hit_rate']:.3f})")
            print(f"hop cost per step: {1e3 / sps_ppo_hop - 1e3 / sps_ppo:.2f} ms (ppo hop/ppo ratio "
                  f"{sps_ppo_hop / sps_ppo:.3f}); illm hop/ppo ratio {sps_illm / sps_ppo:.3f}")
            return
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

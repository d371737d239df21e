"""Collection throughput against raw stepping of the same envs, measured in the same run.

Baseline: the same BabyAI envs (plain gym.make, no text, no logging) stepped with the same
random actions and reset on episode end. Measured: `illm collect` (text rendering, history-free
rows, Arrow shards on disk). Prints steps/s of both and the ratio of their times.
Target: collection costs at most 2x raw stepping.

    python benchmarks/collect.py [--env BabyAI-GoToLocal-v0] [--steps 20000] [--num-envs 8]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import minigrid  # noqa: F401  (registers the BabyAI/MiniGrid ids)
import numpy as np

from illm_tools.collect import CollectConfig, collect


def raw_stepping(env_id: str, steps: int, num_envs: int, seed: int) -> float:
    envs = [gym.make(env_id) for _ in range(num_envs)]
    for i, env in enumerate(envs):
        env.reset(seed=seed + i)
    rng = np.random.default_rng(seed)
    start = time.perf_counter()
    done = 0
    while done < steps:
        actions = rng.integers(0, 6, size=num_envs)
        for env, a in zip(envs, actions.tolist()):
            _, _, term, trunc, _ = env.step(a)
            if term or trunc:
                env.reset()
        done += num_envs
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="BabyAI-GoToLocal-v0")
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3, help="Best of N for each side.")
    args = parser.parse_args()

    raw, logged = [], []
    for r in range(args.repeats):
        raw.append(raw_stepping(args.env, args.steps, args.num_envs, seed=r))
        with tempfile.TemporaryDirectory() as tmp:
            config = CollectConfig(env_id=args.env, out=Path(tmp) / "traj", steps=args.steps,
                                   num_envs=args.num_envs, seed=r)
            start = time.perf_counter()
            collect(config)
            logged.append(time.perf_counter() - start)
    t_raw, t_log = min(raw), min(logged)
    print(f"env {args.env}, {args.steps} steps, {args.num_envs} envs, best of {args.repeats}")
    print(f"raw stepping      {args.steps / t_raw:10,.0f} steps/s")
    print(f"illm collect      {args.steps / t_log:10,.0f} steps/s")
    print(f"collect/raw time ratio: {t_log / t_raw:.2f}x (target <= 2.0x)")


if __name__ == "__main__":
    main()

"""Collection throughput against raw stepping of the same envs, per suite, measured in the same run.

Baseline: the suite's env made the same way but with no text (`make_env(..., render_text=False)`),
stepped in one process with the same kind of random actions and reset on episode end, nothing
logged. Measured: `illm collect` (gymnasium's vector env, text rendering, Arrow shards on disk).
Prints steps/s of both and the ratio of their times for each env. Target: collection costs at
most 2x raw stepping (Crafter's collection runs its envs in processes of their own, so with more
than one core it may beat the one-process baseline).

    python benchmarks/collect.py [--env ID ...] [--steps N] [--num-envs 8]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from illm_tools.collect import CollectConfig, collect  # noqa: E402
from illm_tools.envs import make_env  # noqa: E402
from record import options, record, settings  # noqa: E402

DEFAULT_STEPS = {"BabyAI-GoToLocal-v0": 20_000, "MiniGrid-MultiRoom-N6-v0": 20_000,
                 "MiniHack-River-Monster-v0": 5_000, "CrafterReward-v1": 2_000, "ALE/MontezumaRevenge-v5": 5_000}


def raw_stepping(env_id: str, steps: int, num_envs: int, seed: int) -> float:
    envs = [make_env(env_id, render_text=False) for _ in range(num_envs)]
    for i, env in enumerate(envs):
        env.reset(seed=seed + i)
    rng = np.random.default_rng(seed)
    actions_n = envs[0].action_space.n
    start = time.perf_counter()
    done = 0
    while done < steps:
        for env, a in zip(envs, rng.integers(0, actions_n, size=num_envs).tolist()):
            _, _, term, trunc, _ = env.step(a)
            if term or trunc:
                env.reset()
        done += num_envs
    seconds = time.perf_counter() - start
    for env in envs:
        env.close()
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", action="append", help=f"Env id (repeatable); default: {', '.join(DEFAULT_STEPS)}.")
    parser.add_argument("--steps", type=int, default=None, help="Steps per env id (default: per suite).")
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=2, help="Best of N for each side.")
    options(parser)
    args = parser.parse_args()

    figures, ratios = {}, {}
    for env_id in args.env or list(DEFAULT_STEPS):
        steps = args.steps or DEFAULT_STEPS.get(env_id, 5_000)
        raw, logged = [], []
        for r in range(args.repeats):
            raw.append(raw_stepping(env_id, steps, args.num_envs, seed=r))
            with tempfile.TemporaryDirectory() as tmp:
                config = CollectConfig(env_id=env_id, out=Path(tmp) / "traj", steps=steps, num_envs=args.num_envs,
                                       seed=r)
                start = time.perf_counter()
                collect(config)
                logged.append(time.perf_counter() - start)
        t_raw, t_log = min(raw), min(logged)
        print(f"{env_id}: {steps:,} steps, {args.num_envs} envs, best of {args.repeats}: raw stepping "
              f"{steps / t_raw:,.0f} steps/s, illm collect {steps / t_log:,.0f} steps/s, "
              f"collect/raw time ratio {t_log / t_raw:.2f}x (target <= 2.0x)", flush=True)
        figures.update({f"{env_id}:steps": steps, f"{env_id}:raw_steps_per_s": steps / t_raw,
                        f"{env_id}:collect_steps_per_s": steps / t_log, f"{env_id}:collect_over_raw_time": t_log / t_raw})
        ratios[env_id] = t_log / t_raw
    if not args.no_record:  # the headline: the suite whose collection costs the most against its raw stepping
        worst = max(ratios, key=ratios.get)
        record("collect", figures, ratio={"name": f"collect / raw stepping time, the largest over the envs ({worst})",
                                          "value": ratios[worst], "target": 2.0, "direction": "at_most"},
               out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()

"""The oracle backend's annotation throughput on one core, against the env stepping it annotates for,
measured in the same run.

Measured: the annotation engine (`Annotator.run`, the code `illm annotate` and the live fallback
use: prompts, keys, the oracle's planner and sentence embeddings, cache shards written) over every
distinct state of a random-policy collection of the level, history 0, the tasks action and summary,
one torch thread; the sentence model is loaded before the clock starts (a run loads it once).
Baseline: the same level's raw env stepping in the same process (random actions, text rendered), a
training run's upper bound on new states per second. Prints states/s (target: at least 1,000 on one
core, issue 19) and the ratio annotation/stepping: the share of a run's steps the oracle could
annotate as fast as they are played (a run repeats states, so it needs less).

    python benchmarks/oracle.py [--env BabyAI-GoToLocal-v0] [--steps 20000]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from record import options, record, settings  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="BabyAI-GoToLocal-v0")
    parser.add_argument("--steps", type=int, default=20_000, help="Random-policy steps whose distinct states are annotated.")
    parser.add_argument("--tasks", default="action,summary")
    options(parser)
    args = parser.parse_args()

    import numpy as np
    import torch

    torch.set_num_threads(1)
    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.collect import CollectConfig, collect
    from illm_tools.data.trajectories import open_table
    from illm_tools.envs import make_env
    from illm_tools.llm.backend import load_backend
    from illm_tools.tasks.state import TABLE_COLUMNS, records_from_table

    with tempfile.TemporaryDirectory() as tmp:
        collect(CollectConfig(env_id=args.env, steps=args.steps, num_envs=8, out=Path(tmp) / "traj", seed=0))
        table = open_table(Path(tmp) / "traj", columns=TABLE_COLUMNS + ["renderer"])
        records, env_ids = records_from_table(table, 0)
        renderers = table.column("renderer").to_pylist()

        env = make_env(args.env)
        env.reset(seed=0)
        rng = np.random.default_rng(0)
        start = time.perf_counter()
        for action in rng.integers(0, env.action_space.n, size=args.steps).tolist():
            _, _, term, trunc, _ = env.step(action)
            if term or trunc:
                env.reset()
        stepping = args.steps / (time.perf_counter() - start)
        env.close()

        lm = load_backend("oracle", "oracle")
        lm.embed(["warm up the sentence model"])
        annotator = Annotator(lm, AnnotationCache(Path(tmp) / "ann"), model="oracle", tasks=args.tasks.split(","),
                              history_len=0, chunk=lm.chunk_states)
        plan = annotator.plan(annotator.visited(records, env_ids, renderers))
        stats = annotator.run(plan)
    rate = stats.states_per_s
    print(f"oracle annotation, {args.env}, {len(plan):,} distinct states of {args.steps:,} random steps, history 0, "
          f"tasks {args.tasks}, 1 thread: {rate:,.0f} states/s ({stats.seconds:.2f} s; target >= 1,000)")
    print(f"raw env stepping, same process: {stepping:,.0f} steps/s")
    print(f"ratio annotation/stepping: {rate / stepping:.2f}")
    if not args.no_record:  # the target (1,000 states/s) is the rate's, not the ratio's
        record("oracle", {"oracle_states_per_s": rate, "oracle_seconds": stats.seconds, "distinct_states": len(plan),
                          "env_steps_per_s": stepping},
               ratio={"name": "oracle annotation states/s / raw env steps/s", "value": rate / stepping},
               out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()

"""The trainer's state keys: `PromptBuilder.state_keys` (each state's action and summary keys,
computed without rendering the prompts) against rendering both prompts and keying them
(`key(render(task, record))`, what `illm annotate` does), on the states of a random-policy
BabyAI rollout with three steps of history, in the same run; the keys are checked equal and the
ratio of the times printed. Target: the state keys at least 3x faster.

    .venv/bin/python benchmarks/keys.py [--env BabyAI-GoToLocal-v0] [--steps 4096]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from illm_tools.envs.pool import EnvPool
from illm_tools.tasks.prompts import PromptBuilder
from illm_tools.tasks.state import HistoryTracker
from record import options, record, settings


def records(env: str, steps: int, num_envs: int = 16) -> list:
    """The StateRecords of a random-policy rollout (`steps` in all), history 3."""
    pool = EnvPool(env, num_envs, seed=0)
    obs, rng, out = pool.reset(), np.random.default_rng(0), []
    history = HistoryTracker(num_envs, 3, pool.action_names)
    try:
        for _ in range(steps // num_envs):
            out += history.records(obs.missions, obs.texts)
            actions = rng.integers(0, len(pool.action_names), num_envs)
            step = pool.step(actions)
            history.push(obs.texts, actions.tolist(), np.logical_or(step.terminated, step.truncated).tolist())
            obs = step.obs
    finally:
        pool.close()
    return out


def timed(fn, recs) -> tuple[float, list]:
    start = time.perf_counter()
    keys = [fn(r) for r in recs]
    return (time.perf_counter() - start) / len(recs) * 1e6, keys


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="BabyAI-GoToLocal-v0")
    parser.add_argument("--steps", type=int, default=4096)
    options(parser)
    args = parser.parse_args()
    recs = records(args.env, args.steps)
    tasks = ("action", "summary")

    def builder() -> PromptBuilder:  # a fresh one per pass: no memo carried from one to the other
        return PromptBuilder(env_id=args.env, renderer="babyai-text@1", model_fingerprint="f" * 16, model="smollm2-135m")

    rendered = builder()
    slow, want = timed(lambda r: tuple(rendered.key(rendered.render(t, r)) for t in tasks), recs)
    fast_builder = builder()
    fast, got = timed(lambda r: fast_builder.state_keys(r, tasks), recs)
    if got != want:
        raise SystemExit("the state keys differ from the rendered prompts' keys")
    print(f"{len(recs):,} states of {args.env} ({len(set(recs)):,} distinct), history 3, two keys each")
    print(f"rendered and keyed: {slow:.2f} us a state; state_keys: {fast:.2f} us a state; "
          f"ratio {slow / fast:.2f}x (target >= 3x)")
    if not args.no_record:
        record("keys", {"rendered_and_keyed_us_per_state": slow, "state_keys_us_per_state": fast, "states": len(recs),
                        "distinct_states": len(set(recs))},
               ratio={"name": "rendered and keyed / state_keys, time a state", "value": slow / fast, "target": 3.0},
               out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()

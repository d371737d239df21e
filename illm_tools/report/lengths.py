"""Episode length per run: do the agents of a configuration end their episodes, or run them to the time limit?

A seed's final episode length is the mean of its last `final_points` curve points of episode length
(each point the episode-weighted mean length of the episodes that ended in the window, `curves.load_curve`),
the same points as its final score; over seeds, the IQM with rliable's stratified-bootstrap 95% interval
(`stats.iqm_interval`), as the score. Beside it: the mean over seeds of the first and the last window (has
the length grown or shrunk over training?) and the env's time limit (steps after which an episode is cut),
where the env can be made here to read it. On the levels where an episode ends only by success or by the
time limit (MiniGrid and BabyAI navigation), a length at the limit means no episode succeeded; a length
that grows towards it over training while the score falls means the agent learned not to end episodes.
"""

from __future__ import annotations

import functools
import json

import numpy as np

from illm_tools.report import stats


@functools.lru_cache(maxsize=None)
def time_limit(env_id: str, action_space: str = "auto", num_dists: int | None = None, options: str = "{}") -> int | None:
    """The env's step limit as a run of this config met it (`options`: its env options as JSON): MiniGrid's
    `max_steps` after a reset (BabyAI sets it there), else the registered `max_episode_steps`; None for an
    env this install cannot make or one without a limit."""
    import gymnasium as gym

    from illm_tools.envs import make_env
    from illm_tools.errors import IllmError

    try:
        env = make_env(env_id, action_space=action_space, num_dists=num_dists, render_text=False,
                       **json.loads(options))
    except (IllmError, gym.error.Error, ImportError, TypeError, ValueError):
        return None
    try:
        env.reset(seed=0)
        limit = getattr(env.unwrapped, "max_steps", None) or getattr(env.spec, "max_episode_steps", None)
    finally:
        env.close()
    return int(limit) if limit else None


def episode_length(curves: list, frames: list[int], final_points: int, reps: int, seed: int, config: dict) -> dict:
    """A row's episode length: {"n", "iqm", "ci_low", "ci_high", "mean", "std"} of the seeds' final lengths,
    "per_seed" [{"seed", "run", "length"}], "curve" (the mean over seeds at each of the row's `frames`),
    "first" and "last" (its first and last window) and "time_limit" (`time_limit`)."""
    table = np.array([[dict(zip(c.frames, c.lengths))[f] for f in frames] for c in curves],
                     dtype=float).reshape(len(curves), len(frames))
    finals = stats.final_scores(table, final_points)
    out = stats.iqm_interval(finals, reps, seed)
    with stats._quiet():
        curve = np.nanmean(table, axis=0) if len(curves) else np.zeros(len(frames))
    known = [float(v) for v in curve if not np.isnan(v)]
    options = json.dumps(config.get("env_options") or {}, sort_keys=True)
    out.update(per_seed=[{"seed": c.seed, "run": c.run, "length": s} for c, s in zip(curves, finals.tolist())],
               curve=curve.tolist(), first=known[0] if known else None, last=known[-1] if known else None,
               time_limit=time_limit(config["env_id"], config.get("action_space", "auto"), config.get("num_dists"),
                                     options))
    return out

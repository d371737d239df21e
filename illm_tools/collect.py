"""The collect stage: step a pool of text environments with a policy and log every step to a
trajectory dataset (schema `trajectory` v1)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import pyarrow.compute as pc

from illm_tools.data.trajectories import TrajectoryWriter
from illm_tools.errors import UsageError
from illm_tools.registry import Registry
from illm_tools.settings import setting

NO_RENDERER = "none"
"""The `renderer` of rows from a suite without a text observation (their `obs_text` is empty)."""


@dataclass
class CollectConfig:
    """Everything that determines a collection run."""

    env_id: str = setting(flag="--env")
    """Id of the environment, e.g. BabyAI-GoToLocal-v0, MiniHack-River-Monster-v0, CrafterReward-v1,
    ALE/MontezumaRevenge-v5 (`illm envs` lists them)."""
    out: Path
    """Folder of the trajectory dataset to write."""
    steps: int = 20_000
    """Total environment steps to log, summed over the parallel envs."""
    num_envs: int = 8
    """Environments stepped side by side in one process."""
    seed: int = 0
    """Base seed: episode seeds and the random policy derive from it."""
    policy: str = "random"
    """'random'; 'bot' (BabyAI levels: minigrid's expert bot, with --bot-epsilon random actions); or a training
    run folder whose policy picks the actions."""
    bot_epsilon: float = 0.25
    """With --policy bot: the share of uniformly random actions (states off the bot's path; it replans)."""
    action_space: str = "auto"
    """Action vocabulary: BabyAI's original (3), augmented (6) or irrelevant (9), paper Table 5
    (other suites offer one each); auto: the suite's default (BabyAI: original for the GoTo levels,
    paper Tables 1 and 5, augmented otherwise), or with a trained policy its run's own."""
    num_dists: int | None = None
    """Number of distractors for levels that take it (paper Table 1); None keeps the level's own."""
    save_raw: bool = setting(True, flag=("--raw",))
    """Store the raw observation array beside its text (needed by the Hopfield path)."""
    write: str = "new"
    """How the dataset folder is written: new refuses a folder that holds data; append adds to it;
    overwrite replaces it once done (`--append`, `--overwrite`)."""
    mix_envs: bool = False
    """With --append: allow adding steps of an env the dataset does not hold yet."""
    shard_rows: int = 50_000
    """Rows per Arrow shard."""
    env_options: dict = field(default_factory=dict)
    """Options of the environment, its suite's (`--env-option KEY=VALUE`)."""
    vector: str = "auto"
    """Vector env: sync (all envs in this process), async (a process each), auto (the suite's)."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_folder, check_numbers

        self.out = Path(self.out)
        check_numbers(self, positive=("steps", "num_envs", "shard_rows"), non_negative=("seed", "num_dists"),
                      unit=("bot_epsilon",))
        check_folder(self.out, "--out")
        if self.write not in ("new", "append", "overwrite"):
            raise UsageError(f"unknown write mode {self.write!r}: new, append or overwrite")
        if self.policy not in POLICIES and not (Path(self.policy) / "config.json").is_file():
            held = f"{self.policy} is a folder without a run's config.json" if Path(self.policy).is_dir() else \
                f"{self.policy!r} names no policy and no folder"
            raise UsageError(f"--policy {held}: pass one of {', '.join(POLICIES)}, or a run folder `illm train` wrote")


class Policy(Protocol):
    """Chooses one action index per environment from the pool's current observations."""

    name: str

    def act(self, obs) -> np.ndarray: ...


class RandomPolicy:
    """Uniform over the action vocabulary, seeded."""

    name = "random"

    def __init__(self, num_actions: int, seed: int):
        self.num_actions = num_actions
        self.rng = np.random.default_rng(seed)

    def act(self, obs) -> np.ndarray:
        return self.rng.integers(0, self.num_actions, size=len(obs.missions))


def resolved_action_space(config: CollectConfig) -> str:
    """config.action_space, or for "auto" with a trained policy the action space its run recorded
    (so the policy's actions fit the env); "auto" otherwise, resolved by the env pool."""
    if config.action_space != "auto" or config.policy in POLICIES:
        return config.action_space
    from illm_tools.rl.saved import read_run

    return read_run(Path(config.policy)).settings.get("action_space", "auto")


def check_append(config: CollectConfig, names: list[str]) -> None:
    """Appending must keep the dataset's action list for this env (it is in every row and every
    prompt), must not log episodes it already holds again (the pool's episode seeds run up from
    --seed), and adds another env only when asked (`mix_envs`). Each refusal is one line naming
    what the dataset holds and the option that works."""
    from illm_tools.data.trajectories import open_table

    if config.write != "append":
        return
    try:
        table = open_table(config.out, columns=["env_id", "valid_actions", "seed"])
    except UsageError:
        return  # nothing to append to yet (or not a dataset: the writer says so)
    if not table.num_rows:
        return
    envs = sorted(pc.unique(table["env_id"]).to_pylist())
    if config.env_id not in envs and not config.mix_envs:
        raise UsageError(f"{config.out} holds steps of {', '.join(envs)}, not {config.env_id}: pass --mix-envs to "
                         "add another env to it, or collect into another --out")
    rows = table.filter(pc.equal(table["env_id"], config.env_id))
    if not rows.num_rows:
        return
    if (old := rows["valid_actions"][0].as_py()) != names:
        raise UsageError(f"{config.out} holds {config.env_id} steps with the {len(old)} actions {old}; this run "
                         f"offers {names}: pass the --action-space the dataset was collected with")
    lo, hi = pc.min(rows["seed"]).as_py(), pc.max(rows["seed"]).as_py()
    if hi >= config.seed:
        raise UsageError(f"{config.out} already holds {config.env_id} episodes with seeds {lo:,}–{hi:,}, and this "
                         f"run's episodes take the seeds from {config.seed:,} up: pass --seed {hi + 1} (or higher) "
                         "to add new episodes")


def random_policy(config: CollectConfig, pool) -> Policy:
    """`--policy random`: uniform over the pool's actions, seeded by --seed."""
    return RandomPolicy(len(pool.action_names), config.seed)


def _factory_problem(entry) -> str | None:
    return None if callable(entry) else "is not a factory (a callable taking the CollectConfig and the env pool)"


POLICIES: Registry = Registry("collection policy", "illm.policies", check=_factory_problem, hint="--policy")
"""Named `--policy`s: name -> factory(config, pool) returning a `Policy`. Another is one file with its
factory plus one `register` here (or an `illm.policies` entry point of an installed package); a
--policy that names none of them is a trained run's folder."""
POLICIES.register("random", random_policy)
POLICIES.register("bot", "illm_tools.envs.babyai_bot:bot_policy")  # minigrid's expert bot, BabyAI levels


def make_policy(config: CollectConfig, pool) -> Policy:
    if config.policy in POLICIES:
        return POLICIES[config.policy](config, pool)
    from illm_tools.rl.policy import load_policy  # a trained run's policy

    return load_policy(config.policy, pool)


def collect(config: CollectConfig, on_progress: Callable[[int, dict], None] | None = None) -> dict:
    """Run the collection; returns a summary (rows, episodes finished and still running at the end,
    whether so few finished that the score leans toward the quick ones (`biased`), the score, the
    output folder)."""
    from illm_tools.envs.pool import EnvPool

    pool = EnvPool(config.env_id, config.num_envs, config.seed, action_space=resolved_action_space(config),
                   num_dists=config.num_dists, vector=config.vector, **config.env_options)
    names = list(pool.action_names)
    check_append(config, names)
    policy = make_policy(config, pool)
    renderer = pool.suite.renderer or NO_RENDERER  # Atari: no text; its rows keep the frames only
    raw_obs = pool.suite.raw_obs
    n = pool.num_envs
    part = {"env_id": config.env_id, "action_space": pool.action_space_name, "actions": len(names),
            "num_dists": config.num_dists, "seed": config.seed, "num_envs": n, "policy": policy.name,
            **({"env_options": dict(config.env_options)} if config.env_options else {})}
    writer = TrajectoryWriter(config.out, mode=config.write, shard_rows=config.shard_rows, part=part)
    next_episode = writer.first_episode_id
    episode_ids = np.arange(next_episode, next_episode + n)
    next_episode += n
    finished: list = []  # the EpisodeStats of the logged episodes
    running = np.zeros(n, dtype=bool)  # envs whose current episode has logged steps and has not ended
    with writer:
        obs = pool.reset()
        done_steps = 0
        while done_steps < config.steps:
            take = min(n, config.steps - done_steps)  # the last batch may log fewer envs
            actions = np.asarray(policy.act(obs), dtype=np.int64)
            result = pool.step(actions)
            raws = [raw_obs(obs.images[i]) for i in range(take)] if config.save_raw else []
            shape = list(raws[0].shape) if raws else None
            dtype = str(raws[0].dtype) if raws else None
            writer.add({
                "episode_id": episode_ids[:take].tolist(),
                "step": obs.steps[:take].tolist(),
                "env_id": [config.env_id] * take,
                "mission": obs.missions[:take],
                "obs_text": obs.texts[:take],
                "renderer": [renderer] * take,
                "obs_raw": [raw.tobytes() for raw in raws] if config.save_raw else [None] * take,
                "obs_shape": [shape] * take if config.save_raw else [None] * take,
                "obs_dtype": [dtype] * take if config.save_raw else [None] * take,
                "action": actions[:take].tolist(),
                "action_text": [names[a] for a in actions[:take]],
                "valid_actions": [names] * take,
                "reward": result.rewards[:take].tolist(),
                "terminated": result.terminated[:take].tolist(),
                "truncated": result.truncated[:take].tolist(),
                "seed": obs.seeds[:take].tolist(),
                "policy": [policy.name] * take,
            })
            done_steps += take
            running[:take] = True
            for episode in result.episodes:
                i = episode.env_index
                if i < take:  # an episode whose last step was logged
                    finished.append(episode)
                    running[i] = False
                episode_ids[i] = next_episode
                next_episode += 1
            obs = result.obs
            if on_progress is not None:
                on_progress(take, {"episodes": len(finished), **pool.suite.episode_metrics(finished)})
    figures = pool.suite.episode_metrics(finished)
    return {
        "out": str(config.out),
        "rows": writer.rows_written,
        "episodes_finished": len(finished),
        "episodes_running": int(running.sum()),
        "biased": bool(running.sum()) and len(finished) < 2 * int(running.sum()),
        "success_rate": figures["success_rate"],
        "score": figures["score"],
        "score_name": pool.suite.score_name,
        "mean_return": float(np.mean([e.episode_return for e in finished])) if finished else 0.0,
        "env_id": config.env_id,
        "action_space": pool.action_space_name,
        "policy": policy.name,
    }

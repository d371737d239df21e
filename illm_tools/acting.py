"""`illm act`: how well an annotator plays when it acts on its own ranking, before anyone trains on it.

Each step the state is rendered and prompted exactly as `illm annotate` renders and prompts it (the
suite's text renderer, the action task's template, `--history` pairs), its valid actions scored by
the annotation engine itself (`illm_tools.probe.score_records`: the rows `illm annotate` would write),
and the action with the highest calibrated score taken (`--calibration`, as training reads the
scores; ties, common where an oracle gives several actions one cost, broken at random by the
run's seeded generator, since always taking the first of them can walk into a loop). The same
episodes (env seeds `seed`, `seed + 1`, ...) are played by a uniformly random policy beside it.

What it reports per policy: episodes, the success rate with its 95% Wilson interval where the suite
has success (BabyAI, MiniGrid, MiniHack), the mean return and length, and the suite's own episode
figures (`Suite.episode_metrics`: Crafter's score and each achievement's success rate). This is the
quality of an annotator as a policy, the figure issue 70 asks of each oracle before a training run
leans on it as a positive control; an LLM can be measured the same way (slowly: one scoring call a
step).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from illm_tools.errors import UsageError
from illm_tools.llm.spec import LLMSpec
from illm_tools.settings import setting
from illm_tools.tasks.calibration import CALIBRATIONS, action_scores
from illm_tools.tasks.prompt_config import PromptConfig
from illm_tools.tasks.state import StateRecord

POLICIES = ("annotator", "random")


@dataclass
class ActConfig:
    """An `illm act` run: which env and annotator, how many episodes."""

    env_id: str = setting("MiniHack-Room-5x5-v0", flag="--env")
    """Any env with a text renderer (`illm envs`)."""
    llm: LLMSpec = field(default_factory=LLMSpec)
    """The annotator that acts (`illm_tools.llm.spec`; `--backend oracle` for the oracle of the env's game)."""
    episodes: int = 100
    """Episodes each policy plays."""
    setup: PromptConfig = field(default_factory=lambda: PromptConfig(history_len=0))
    """How the states become prompts, as `illm annotate` (--history, default 0 here; --layout)."""
    calibration: str = "sum"
    """How the raw scores rank the actions (sum | mean | pmi), as training reads them."""
    seed: int = 0
    """Seed of the first episode (episode i is seeded seed + i) and of the tie-breaks and random actions."""
    max_steps: int = 0
    """Cut an episode after this many steps (0: the env's own limit)."""
    action_space: str = "auto"
    """The suite's action vocabulary (as `illm collect`)."""
    env_options: dict = field(default_factory=dict)
    """The env's own options (as `illm train --env-option`), e.g. length=2000 for Crafter."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_numbers

        check_numbers(self, positive=("episodes",), non_negative=("seed", "max_steps"))
        if self.calibration not in CALIBRATIONS:
            raise UsageError(f"--calibration must be one of {', '.join(CALIBRATIONS)}, got {self.calibration!r}")
        if self.setup.hop:
            raise UsageError("illm act scores text states: drop --mode hop")


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The 95% Wilson score interval of a success rate (sound at 0 and n successes, unlike p +- z se)."""
    if n == 0:
        return float("nan"), float("nan")
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


@dataclass
class PolicyResult:
    """What one policy's episodes gave."""

    episodes: int
    mean_return: float
    mean_length: float
    success_rate: float | None
    """None where the suite has no success (Crafter)."""
    success_interval: tuple[float, float] | None
    metrics: dict[str, float]
    """The suite's episode figures (`Suite.episode_metrics`): score, per-achievement rates."""


def summarise(suite, episodes: list) -> PolicyResult:
    """One policy's figures from its finished episodes (`EpisodeStats`)."""
    outcomes = [e.success for e in episodes if e.success is not None]
    rate = float(np.mean(outcomes)) if outcomes else None
    metrics = {k: float(v) for k, v in suite.episode_metrics(episodes).items() if k != "success_rate"}
    return PolicyResult(len(episodes), float(np.mean([e.episode_return for e in episodes])),
                        float(np.mean([e.length for e in episodes])), rate,
                        wilson(int(sum(outcomes)), len(outcomes)) if outcomes else None, metrics)


def play(env, suite, choose: Callable[[StateRecord, np.random.Generator], int], *, seed: int, history: int,
         max_steps: int, rng: np.random.Generator):
    """One episode of `env` from seed `seed`, each action `choose(state, rng)`; its `EpisodeStats`."""
    from illm_tools.envs.suite import EpisodeStats

    _, info = env.reset(seed=seed)
    names = tuple(info["valid_actions"])
    past: deque = deque(maxlen=history)
    total, steps = 0.0, 0
    while True:
        record = StateRecord(info["mission"], tuple(past), info["text"], names)
        action = choose(record, rng)
        _, reward, terminated, truncated, info = env.step(action)
        total, steps = total + float(reward), steps + 1
        past.append((record.observation, names[action]))
        if terminated or truncated or (max_steps and steps >= max_steps):
            done = terminated or truncated
            return EpisodeStats(0, total, steps, info.get("success") if done else False,
                                suite.episode_info(info) if done else {})


class RankingPolicy:
    """Acts on an annotator's ranking: the engine's scores of the state's actions, calibrated, argmax
    with random tie-breaks. Its scores are memoised per state (an episode often comes back to one)."""

    def __init__(self, lm, builder, calibration: str):
        from illm_tools.probe import action_annotator

        self.lm, self.builder, self.calibration = lm, builder, calibration
        self.annotator = action_annotator(lm, builder)  # once: the policy scores a state every step
        self.memo: dict[StateRecord, np.ndarray] = {}

    def __call__(self, record: StateRecord, rng: np.random.Generator) -> int:
        from illm_tools.probe import score_records

        scores = self.memo.get(record)
        if scores is None:
            sums, counts, neutral = score_records(self.lm, self.builder, [record], annotator=self.annotator)
            scores = self.memo[record] = action_scores(sums, counts, neutral, self.calibration)[0]
        best = np.flatnonzero(scores >= scores.max() - 1e-9)
        return int(rng.choice(best))


def act(cfg: ActConfig, *, on_episode: Callable[[str, int, int], None] | None = None) -> dict:
    """Both policies' episodes; `on_episode(policy, done, total)` after each. Returns the figures."""
    from illm_tools.envs import make_env, suite_of

    suite = suite_of(cfg.env_id)
    if suite.renderer is None:
        raise UsageError(f"{cfg.env_id} has no text for an annotator to read: illm act needs a suite with a text "
                         "renderer (`illm envs` lists them)")
    setup = cfg.setup.of(cfg.env_id, ("action",))
    cfg.llm.check_use(setup.env_id, setup.renderer)
    llm = cfg.llm.placed()
    ranking = RankingPolicy(llm.load(), setup.builder_of(llm), cfg.calibration)
    env = make_env(cfg.env_id, action_space=cfg.action_space, **cfg.env_options)
    actions = env.action_space.n

    def uniform(_record: StateRecord, rng: np.random.Generator) -> int:
        return int(rng.integers(actions))

    out: dict = {"config": {"env_id": cfg.env_id, "model": llm.model, "backend": llm.backend,
                            "episodes": cfg.episodes, "history": cfg.setup.history_len, "calibration": cfg.calibration,
                            "seed": cfg.seed, "max_steps": cfg.max_steps, "env_options": dict(cfg.env_options)},
                 "policies": {}}
    try:
        for policy, choose in zip(POLICIES, (ranking, uniform)):
            rng = np.random.default_rng([cfg.seed, POLICIES.index(policy)])
            episodes = []
            for i in range(cfg.episodes):
                episodes.append(play(env, suite, choose, seed=cfg.seed + i, history=cfg.setup.history_len,
                                     max_steps=cfg.max_steps, rng=rng))
                if on_episode is not None:
                    on_episode(policy, i + 1, cfg.episodes)
            out["policies"][policy] = summarise(suite, episodes).__dict__
    finally:
        env.close()
    return out

"""`illm probe`: how much an LLM knows about a BabyAI level before anyone annotates with it.

States come from episodes played by minigrid's BabyAI expert bot (`minigrid.utils.baby_ai_bot`),
with a share of uniformly random actions (`epsilon`, default 0.25) so states off the expert's path
are probed too (the bot is told the action actually taken and replans). Each state is rendered
and prompted exactly as `illm annotate` renders and prompts it (the suite's text renderer, the
action task's template, `--history` pairs), its valid actions scored by the LLM as in
annotation, and the scores calibrated as training calibrates them (`sum`, `mean`, `pmi`,
`illm_tools.tasks.calibration`). Against the expert's action in each state:

- agreement: the share of states where the LLM's top action is the expert's, beside always
  choosing the expert's most frequent action (majority) and uniform chance;
- mutual information between state and ranking, in bits: I = H(mean_s p(.|s)) - mean_s H(p(.|s))
  over the LLM's softmax p, 0 when the distribution does not depend on the state; and the entropy
  of the LLM's top choice across states;
- log-loss: mean -log p(expert | s), nats, beside the expert actions' own frequencies (in
  sample) and uniform;
- pairwise AUROC: per state, the chance that the expert's action outscores another valid action
  (ties count 1/2), averaged: 0.5 is chance, 1 a ranking that always puts the expert's first.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from illm_tools.errors import UsageError
from illm_tools.llm.spec import LLMSpec
from illm_tools.settings import setting
from illm_tools.tasks.prompt_config import PromptConfig
from illm_tools.tasks.calibration import CALIBRATIONS, action_distribution, action_scores
from illm_tools.tasks.state import StateRecord


# --- metrics: small pure functions over scores [N, A] and expert action indices [N] ---------------
def agreement(scores: np.ndarray, expert: np.ndarray) -> float:
    """Share of states whose highest score (ties to the first) is the expert's action."""
    return float(np.mean(np.argmax(scores, axis=1) == expert))


def agreement_per_action(scores: np.ndarray, expert: np.ndarray, actions: tuple[str, ...]) -> dict[str, float]:
    """Per expert action, the share of its states where the LLM's top action is it (its recall): where the
    overall agreement comes from, e.g. a student right on "go forward" and never on the rare "pick up".
    Actions the expert never took are left out."""
    top = np.argmax(scores, axis=1)
    return {name: float(np.mean(top[expert == i] == i)) for i, name in enumerate(actions) if np.any(expert == i)}


def entropy_bits(p: np.ndarray) -> np.ndarray:
    """Entropy in bits along the last axis (0 log 0 = 0)."""
    p = np.asarray(p, dtype=np.float64)
    return 0.0 - np.sum(np.where(p > 0, p * np.log2(np.where(p > 0, p, 1.0)), 0.0), axis=-1)  # 0, not -0


def mutual_information_bits(probs: np.ndarray) -> float:
    """I(state; action) under a uniform choice of the probed states: H(mean p) - mean H(p)."""
    return float(max(entropy_bits(probs.mean(axis=0)) - entropy_bits(probs).mean(), 0.0))


def top_choice_entropy_bits(scores: np.ndarray) -> float:
    """Entropy (bits) of which action the LLM ranks first, across states."""
    counts = np.bincount(np.argmax(scores, axis=1), minlength=scores.shape[1])
    return float(entropy_bits(counts / counts.sum()))


def log_loss(probs: np.ndarray, expert: np.ndarray) -> float:
    """Mean -log p(expert action | state), nats."""
    return float(-np.mean(np.log(np.clip(probs[np.arange(len(expert)), expert], 1e-12, None))))


def pairwise_auroc(scores: np.ndarray, expert: np.ndarray) -> float:
    """Per state, P(score of the expert's action > score of another valid action), ties 1/2; mean."""
    n, a = scores.shape
    mine = scores[np.arange(n), expert][:, None]
    others = np.ones((n, a), bool)
    others[np.arange(n), expert] = False
    wins = ((mine > scores) & others).sum(1) + 0.5 * ((mine == scores) & others).sum(1)
    return float(np.mean(wins / (a - 1)))


# --- states ----------------------------------------------------------------------------------------
@dataclass
class ExpertStates:
    """Probed states, the expert's action index in each, and the action names."""

    records: list[StateRecord]
    expert: np.ndarray
    actions: tuple[str, ...]
    episodes: int = 0
    skipped: int = 0
    """States whose expert action is not one of the valid actions (e.g. "done"), left out."""
    bot_failures: int = 0
    """Episodes the bot gave up on (it raises on some states a random action led to); cut there."""


def expert_states(env_id: str, count: int, *, history: int = 0, seed: int = 0, epsilon: float = 0.25,
                  action_space: str = "auto", max_episode_steps: int = 256) -> ExpertStates:
    """`count` states of `env_id` played by minigrid's BabyAI bot, with `epsilon` random actions."""
    from minigrid.core.actions import Actions
    from minigrid.utils.baby_ai_bot import BabyAIBot

    from illm_tools.envs import make_env, suite_of
    from illm_tools.envs.babyai import _MINIGRID_ACTION

    if suite_of(env_id).name != "babyai" or not env_id.startswith("BabyAI-"):
        raise UsageError(f"{env_id} has no expert to compare with: the probe uses minigrid's BabyAI bot, which "
                         "solves BabyAI-* levels (e.g. BabyAI-GoToLocal-v0)")
    if count <= 0 or history < 0 or not 0.0 <= epsilon <= 1.0:
        raise UsageError("--states must be positive, --history >= 0 and --epsilon in [0, 1]")
    env = make_env(env_id, action_space=action_space)
    names = tuple(env.action_names)
    # the expert's MiniGrid action -> its name here; "done" (the bot's "mission accomplished") is no
    # valid action, even where the irrelevant action space maps sleep/do nothing/think onto it
    to_name = {int(_MINIGRID_ACTION[n]): n for n in names if _MINIGRID_ACTION[n] != Actions.done}
    rng = np.random.default_rng(seed)
    out = ExpertStates([], np.zeros(0, np.int64), names)
    labels: list[int] = []
    try:
        while len(out.records) < count:
            if out.episodes >= max(100, 10 * count):
                raise UsageError(f"minigrid's BabyAI bot gave only {len(out.records)} states in {out.episodes} "
                                 f"episodes of {env_id} ({out.bot_failures} failed, {out.skipped} states whose "
                                 "expert action is no valid action): probe fewer --states or another level")
            _, info = env.reset(seed=seed + out.episodes)
            out.episodes += 1
            bot, taken = BabyAIBot(env), None
            past: deque = deque(maxlen=history)
            for _ in range(max_episode_steps):
                try:
                    suggested = bot.replan(taken)
                except Exception:  # noqa: BLE001 - the bot asserts on some states; end its episode there
                    out.bot_failures += 1
                    break
                record = StateRecord(info["mission"], tuple(past), info["text"], names)
                name = to_name.get(int(suggested))
                if name is None:
                    out.skipped += 1
                else:
                    out.records.append(record)
                    labels.append(names.index(name))
                    if len(out.records) == count:
                        break
                act = names.index(name) if name is not None and rng.random() >= epsilon else int(rng.integers(len(names)))
                taken = _MINIGRID_ACTION[names[act]]
                _, _, terminated, truncated, info = env.step(act)
                past.append((record.observation, names[act]))
                if terminated or truncated:
                    break
    finally:
        env.close()
    out.expert = np.asarray(labels, np.int64)
    return out


# --- the probe -------------------------------------------------------------------------------------
@dataclass
class ProbeConfig:
    """An `illm probe` run: which level and annotator, and how many of the bot's states."""

    env_id: str = setting("BabyAI-GoToLocal-v0", flag="--env")
    """A BabyAI level (the expert is minigrid's BabyAI bot)."""
    llm: LLMSpec = field(default_factory=LLMSpec)
    """The LLM probed (`illm_tools.llm.spec`)."""
    states: int = 400
    """States to probe, from the bot's episodes."""
    setup: PromptConfig = field(default_factory=lambda: PromptConfig(history_len=0))
    """How the states become prompts, as `illm annotate` (--history, default 0 here; --layout): text
    states only."""
    seed: int = 0
    """Seed of the episodes and of the random actions."""
    epsilon: float = 0.25
    """Share of random actions in the bot's episodes (states off its path)."""
    action_space: str = "auto"
    """original | augmented | irrelevant | auto (as `illm collect`)."""
    batch_size: int = 8
    """States per LLM batch."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_numbers

        check_numbers(self, positive=("states", "batch_size"), non_negative=("seed",), unit=("epsilon",))
        if self.setup.hop:
            raise UsageError("illm probe scores text states: the bot's states have no hop form here (drop --mode hop)")


@dataclass
class ProbeResult:
    config: dict
    actions: tuple[str, ...]
    states: int
    distinct_states: int
    episodes: int
    skipped: int
    bot_failures: int
    expert_share: dict[str, float]
    baselines: dict[str, float]
    calibrations: dict[str, dict] = field(default_factory=dict)

    @property
    def best(self) -> str:
        return max(self.calibrations, key=lambda c: (self.calibrations[c]["agreement"], self.calibrations[c]["auroc"]))

    def to_dict(self) -> dict:
        return {**self.__dict__, "actions": list(self.actions), "best": self.best}


def action_annotator(lm, builder, batch_size: int = 8):
    """The annotation engine scoring the action task of `builder`'s setup with `lm`, no cache."""
    from illm_tools.annotate.engine import Annotator

    return Annotator(lm, None, model=builder.model, tasks=("action",), history_len=builder.history_len,
                     layout=builder.layout, batch_size=batch_size)


def score_records(lm, builder, records, *, batch_size: int = 8, chunk: int = 64,
                  on_progress: Callable[[int, int], None] | None = None,
                  annotator=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The action task's raw scores of these states, computed by the annotation engine itself
    (`Annotator.annotate`, no cache: the rows `illm annotate` would write), each distinct record
    once. Returns per record the summed log-probs [N, A], token counts [N, A] and neutral-prompt
    sums [N, A]; `on_progress(done, total)` after each chunk of distinct states. States go to the
    engine `chunk` at a time, as the annotator's chunks of 64 do: the backend batches by length
    within a call, and in bfloat16 a different batching moves scores by rounding (a near tie can
    flip). `annotator`: an `action_annotator` made once by a caller that scores state after state."""
    from illm_tools.annotate.engine import Job

    annotator = annotator or action_annotator(lm, builder, batch_size)
    distinct = list(dict.fromkeys(records))
    rows: list[dict] = []
    for i in range(0, len(distinct), chunk):
        prompts = [(r, builder.render("action", r)) for r in distinct[i:i + chunk]]
        rows += annotator.annotate([[Job(builder.key(p), p, builder, r)] for r, p in prompts])
        if on_progress is not None:
            on_progress(len(rows), len(distinct))
    where = {r: i for i, r in enumerate(distinct)}
    picked = [rows[where[r]] for r in records]
    return (np.asarray([r["cand_logprob_sum"] for r in picked], dtype=np.float64),
            np.asarray([r["cand_token_count"] for r in picked], dtype=np.int64),
            np.asarray([r["neutral_logprob_sum"] for r in picked], dtype=np.float64))


def calibration_metrics(sums: np.ndarray, counts: np.ndarray, neutral_sums: np.ndarray, expert: np.ndarray,
                        actions: tuple[str, ...], calibration: str) -> dict:
    """Every metric of one calibration of the LLM's raw scores against the expert's actions."""
    scores = action_scores(sums, counts, neutral_sums, calibration)
    probs = action_distribution(sums, counts, neutral_sums, calibration).astype(np.float64)
    top = np.bincount(np.argmax(scores, axis=1), minlength=len(actions))
    return {"agreement": agreement(scores, expert), "per_action": agreement_per_action(scores, expert, actions),
            "log_loss": log_loss(probs, expert),
            "auroc": pairwise_auroc(scores, expert), "mutual_information_bits": mutual_information_bits(probs),
            "top_choice_entropy_bits": top_choice_entropy_bits(scores),
            "top_action": actions[int(np.argmax(top))], "top_action_share": float(top.max() / len(expert))}


def baselines(expert: np.ndarray, actions: tuple[str, ...]) -> dict:
    """What needs no LLM: always the expert's most frequent action (agreement, and the log-loss of
    the expert actions' own frequencies, in sample), and uniform chance."""
    a = len(actions)
    freq = np.bincount(expert, minlength=a) / len(expert)
    majority = int(np.argmax(freq))
    return {"majority_action": actions[majority], "majority_agreement": float(freq[majority]),
            "chance_agreement": 1.0 / a, "marginal_log_loss": float(-np.mean(np.log(freq[expert]))),
            "uniform_log_loss": float(np.log(a))}


def probe(cfg: ProbeConfig, *, on_states: Callable[[ExpertStates], None] | None = None,
          on_progress: Callable[[int, int], None] | None = None) -> ProbeResult:
    """Collect the expert's states, score their actions with the LLM, compute every metric.
    `on_states` hears the collected states (before the model loads); `on_progress(done, total)`
    the distinct states scored so far."""
    import dataclasses

    data = expert_states(cfg.env_id, cfg.states, history=cfg.setup.history_len, seed=cfg.seed, epsilon=cfg.epsilon,
                         action_space=cfg.action_space)
    if on_states is not None:
        on_states(data)
    setup = cfg.setup.of(cfg.env_id, ("action",))
    cfg.llm.check_use(setup.env_id, setup.renderer)
    llm = cfg.llm.placed()
    lm = llm.load()
    builder = setup.builder_of(llm)
    sums, counts, neutral_sums = score_records(lm, builder, data.records, batch_size=cfg.batch_size,
                                               on_progress=on_progress)
    expert = data.expert
    freq = np.bincount(expert, minlength=len(data.actions)) / len(expert)
    result = ProbeResult(
        config={**{k: v for k, v in cfg.__dict__.items() if k not in ("llm", "setup")},  # as probe files name them
                "history": cfg.setup.history_len, "layout": cfg.setup.layout, **dataclasses.asdict(llm),  # as resolved
                "dtype": lm.fingerprint.get("dtype", llm.dtype)},
        actions=data.actions, states=len(expert),
        distinct_states=len(set(data.records)), episodes=data.episodes, skipped=data.skipped,
        bot_failures=data.bot_failures, expert_share={n: float(f) for n, f in zip(data.actions, freq)},
        baselines=baselines(expert, data.actions))
    for calibration in CALIBRATIONS:
        result.calibrations[calibration] = calibration_metrics(sums, counts, neutral_sums, expert, data.actions,
                                                               calibration)
    return result

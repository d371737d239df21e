"""A teacher's annotations as a student's lessons: which rows of a cache `illm distil` learns from,
how its states split into training and held-out ones, and their tokens.

A teacher is one model of the cache (its rows' `model` and fingerprint: `oracle`, a large model
annotated through vLLM, ...). A lesson is one state of the teacher's: for each task asked for, the
row's prompt as the annotator rendered it and what the teacher answered there, the candidates'
summed log-probabilities of a ranking task (`action`) and the text of a text task (`summary`,
`goal`, `plan`). The student reads the very prompt the annotator renders, so a state it annotates
later is asked the same way it was taught.

The split is by state, stable: states are ordered by a salted hash of what makes them one state
(renderer, history length, mission, history, observation); the first `held_out` are held out, the
next `states` are taught. The chosen rows' keys are written to the work folder when a run starts
(`LessonPlan`), so a resumed run teaches the same lessons whatever the cache gained meanwhile.

Tokens (`tokenise`): each task's prompt and its targets tokenised as the annotator tokenises them
(`illm_tools.llm.scoring.plan_state`: context and candidate together), a text target followed by
the end-of-text token (the student learns to stop where the teacher stopped). The prompts of a
state share their first part (the task line and the history, with the `shared` layout): that part
is one `shared` token list, run once per state (not on sliding-window models, `LoadedModel.sliding_window`).
"""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

from illm_tools.errors import UsageError
from illm_tools.keys import canonical_json

COLUMNS = ("key", "task", "renderer", "model", "model_fingerprint", "history_len", "goal", "history",
           "observation", "prompt", "candidates", "cand_logprob_sum", "chosen_index", "text")
"""The cache columns a lesson is made of."""
SPLIT_SALT = "illm-distil-split@1"


@dataclass(frozen=True)
class Target:
    """What the teacher answered to one task's prompt in one state."""

    task: str
    kind: str
    """ranking (the teacher's log-probabilities of the candidates) or text (its text)."""
    key: str
    """The teacher's cache row."""
    prompt: str
    candidates: tuple[str, ...] = ()
    """ranking: the candidates as scored after the prompt (with their leading space)."""
    teacher_logprobs: tuple[float, ...] = ()
    """ranking: the teacher's summed log-probability of each candidate."""
    text: str = ""
    """text: the teacher's text."""

    @property
    def best(self) -> int:
        """ranking: the teacher's top candidate (first on ties, as `chosen_index`)."""
        return max(range(len(self.teacher_logprobs)), key=self.teacher_logprobs.__getitem__)


@dataclass(frozen=True)
class Lesson:
    """One state of the teacher's, with its targets in task order."""

    state: str
    """Salted hash of the state (the split's order)."""
    targets: tuple[Target, ...]


@dataclass(frozen=True)
class Teacher:
    """A model whose rows a cache holds."""

    model: str
    fingerprint: str
    rows: int


def teachers(table) -> list[Teacher]:
    """The models of a cache table's rows (`COLUMNS`), most rows first."""
    counts: dict[tuple[str, str], int] = {}
    for model, fp in zip(table.column("model").to_pylist(), table.column("model_fingerprint").to_pylist()):
        counts[(model, fp)] = counts.get((model, fp), 0) + 1
    return [Teacher(m, fp, n) for (m, fp), n in sorted(counts.items(), key=lambda x: (-x[1], x[0]))]


def pick_teacher(found: Sequence[Teacher], name: str | None, cache: str) -> Teacher:
    """The teacher named (`--teacher`), or the cache's only one; refused in one line otherwise."""
    names = ", ".join(f"{t.model} ({t.rows:,} rows)" for t in found)
    if name is not None:
        found = [t for t in found if t.model == name]
        if not found:
            raise UsageError(f"the cache {cache} holds no rows of the teacher {name!r} for these tasks (it holds "
                             f"{names or 'none'}): pass one of those as --teacher")
    if len(found) > 1:
        if len({t.model for t in found}) == 1:
            raise UsageError(f"the cache {cache} holds rows of {found[0].model} under {len(found)} fingerprints "
                             "(another dtype, quantisation or revision): distil from a cache holding one of them "
                             "(`illm cache info` lists the setups)")
        raise UsageError(f"the cache {cache} holds rows of several models ({names}): name the teacher with --teacher")
    return found[0]


def state_hash(row: dict) -> str:
    """The salted hash of a row's state (its renderer, history length and rendered parts)."""
    return hash_state(row["renderer"], row["history_len"], row["goal"], row["history"], row["observation"])


def hash_state(renderer: str, history_len: int, goal: str, history: str, observation: str) -> str:
    """`state_hash` from the state's parts (a trajectory's record: its mission, `format_history`, observation)."""
    return hashlib.sha256(canonical_json([SPLIT_SALT, renderer, history_len, goal, history,
                                          observation]).encode()).hexdigest()


def lessons_of(rows: Sequence[dict], tasks: Sequence[str]) -> list[Lesson]:
    """The lessons of one teacher's rows: one per state holding a ranking task's row (a state the
    teacher never ranked teaches no ranking and is left out), its tasks in `tasks` order, in the
    split's order (by `state_hash`)."""
    from illm_tools.tasks.registry import get_task

    by_state: dict[str, dict[str, dict]] = {}
    for row in sorted(rows, key=lambda r: r["key"]):  # of a state's two rows of a task (two layouts): the first key
        by_state.setdefault(state_hash(row), {}).setdefault(row["task"], row)
    lessons = []
    for state in sorted(by_state):
        got = by_state[state]
        if not any(get_task(t).kind == "ranking" for t in got):
            continue
        lessons.append(Lesson(state, tuple(target_of(got[t]) for t in tasks if t in got)))
    return lessons


def target_of(row: dict) -> Target:
    """A cache row as a target (the candidates get back the leading space they were scored with)."""
    from illm_tools.tasks.registry import get_task

    kind = get_task(row["task"]).kind
    if kind == "ranking":
        return Target(row["task"], kind, row["key"], row["prompt"], tuple(" " + c for c in row["candidates"]),
                      tuple(float(x) for x in row["cand_logprob_sum"]))
    return Target(row["task"], kind, row["key"], row["prompt"], text=row["text"] or "")


@dataclass(frozen=True)
class LessonPlan:
    """The rows taught and held out, by key: what a run writes when it starts and a resumed run
    reads back (`lessons.json` in the work folder)."""

    teacher: str
    teacher_fingerprint: str
    tasks: tuple[str, ...]
    train: tuple[tuple[str, ...], ...]
    """Per training state, its rows' keys in task order."""
    held_out: tuple[tuple[str, ...], ...]

    def to_json(self) -> str:
        return json.dumps({"teacher": self.teacher, "teacher_fingerprint": self.teacher_fingerprint,
                           "tasks": list(self.tasks), "train": [list(k) for k in self.train],
                           "held_out": [list(k) for k in self.held_out]})

    @classmethod
    def from_json(cls, text: str) -> LessonPlan:
        d = json.loads(text)
        return cls(d["teacher"], d["teacher_fingerprint"], tuple(d["tasks"]), tuple(tuple(k) for k in d["train"]),
                   tuple(tuple(k) for k in d["held_out"]))

    @classmethod
    def split(cls, teacher: Teacher, tasks: Sequence[str], lessons: Sequence[Lesson], *, held_out: int,
              states: int | None, balance: float = 0.0, visits: Counter | None = None,
              seed: int = 0, min_share: float = 0.0) -> LessonPlan:
        """The first `held_out` lessons (in hash order) held out, then `states` lessons of the rest
        taught:
        - by default the first ones;
        - with `visits` (steps per state hash, `visits_of`), `states` draws (with replacement,
          seeded) in proportion to each state's visits; states never visited are not taught; with
          `balance` > 0 as well, each top action's share of the draws is its share of the visits to
          the power 1 - balance (`visit_balance`), its states keeping their visits' proportions;
          `min_share` > 0 then raises each action's share of the draws to at least that;
        - with `balance` or `min_share` > 0 each top action's quota (`balanced_quotas`), an action's lessons taken
          in hash order and repeated where its quota is larger than they are (oversampling: its
          distinct states are what the cache has), the whole in the order of a hash of (lesson,
          repeat), so a state's repeats fall in different batches."""
        keys = [tuple(t.key for t in lesson.targets) for lesson in lessons]
        rest = list(range(held_out, len(lessons)))
        if visits is not None:
            import numpy as np

            pool = [i for i in rest if visits.get(lessons[i].state, 0) > 0]
            if not pool:
                raise UsageError("no state of the cache (held-out ones aside) is visited in the --visits datasets: "
                                 "pass the trajectories the cache was annotated from")
            weights = np.array([visits[lessons[i].state] for i in pool], dtype=np.float64)
            if balance > 0 or min_share > 0:
                weights *= visit_balance([top_action(lessons[i]) for i in pool], weights, balance, min_share)
            drawn = np.random.default_rng(seed).choice(len(pool), size=states or len(pool), p=weights / weights.sum())
            rest = [pool[j] for j in drawn]
        elif (balance > 0 or min_share > 0) and rest:
            groups: dict[str, list[int]] = {}
            for i in rest:
                groups.setdefault(top_action(lessons[i]), []).append(i)
            quotas = balanced_quotas({a: len(g) for a, g in groups.items()}, states or len(rest), balance, min_share)
            chosen = [(g[n % len(g)], n // len(g)) for a, g in groups.items() for n in range(quotas[a])]
            rest = [i for i, _ in sorted(chosen, key=lambda c: hashlib.sha256(f"{lessons[c[0]].state}/{c[1]}".encode())
                                         .hexdigest())]
        elif states is not None:
            rest = rest[:states]
        return cls(teacher.model, teacher.fingerprint, tuple(tasks), tuple(keys[i] for i in rest),
                   tuple(keys[:held_out]))


def visits_of(datasets: Sequence, history_lens: Sequence[int]) -> Counter:
    """Steps per state (`state_hash`) in trajectory datasets, at each of the teacher's history lengths:
    how often an agent of those datasets met each state (a distinct state is one lesson; its visits
    say how much it matters). Refuses a folder that is no trajectory dataset, in one line."""
    from illm_tools.data.trajectories import open_table, require_text
    from illm_tools.tasks.prompts import format_history
    from illm_tools.tasks.state import TABLE_COLUMNS, records_from_table

    counts: Counter = Counter()
    for path in datasets:
        table = open_table(path, columns=TABLE_COLUMNS + ["renderer"])
        require_text(table, path)
        renderers = table.column("renderer").to_pylist()
        for k in sorted(set(history_lens)):
            records, _ = records_from_table(table, k)
            counts.update(hash_state(renderer, k, r.mission, format_history(r), r.observation)
                          for r, renderer in zip(records, renderers))
    return counts


def visit_balance(actions: Sequence[str], weights, balance: float, min_share: float = 0.0):
    """Per state, the factor that brings each top action's share of the visits `weights` (states in
    the order of `actions`) to that share to the power 1 - balance (`balanced_quotas`' shares, over
    visits rather than distinct states), then to at least `min_share` (`floor_shares`): an action's
    states all get its total visits ** -balance, times its floored share over its share."""
    import numpy as np

    totals: dict[str, float] = {}
    for a, w in zip(actions, weights):
        totals[a] = totals.get(a, 0.0) + float(w)
    powered = {a: t ** (1.0 - balance) for a, t in totals.items()}
    whole = sum(powered.values())
    shares = {a: v / whole for a, v in powered.items()}
    floored = floor_shares(shares, min_share)
    return np.array([totals[a] ** -balance * floored[a] / shares[a] for a in actions], dtype=np.float64)


def floor_shares(shares: dict[str, float], min_share: float) -> dict[str, float]:
    """`shares` (summing to 1) with each non-zero one raised to at least `min_share`, the others scaled
    down together so that they keep their proportions to one another (raising one may take another
    below the floor: repeated until none is). Unlike --balance's power, which also moves the common
    actions' shares toward each other (go forward's toward turn left's), a floor changes only the
    rare ones. Refuses, in one line, a floor that the actions cannot all have."""
    live = [a for a, v in shares.items() if v > 0]
    if min_share <= 0 or not live:
        return dict(shares)
    if min_share * len(live) > 1 + 1e-9:
        raise UsageError(f"--min-share {min_share} is more than 1 / {len(live)} (the number of the teacher's top "
                         f"actions among the lessons): pass at most {1 / len(live):.3f}")
    floored: set[str] = set()
    while True:
        free = [a for a in live if a not in floored]
        left = 1.0 - min_share * len(floored)
        rest = sum(shares[a] for a in free)
        out = {a: (min_share if a in floored else left * shares[a] / rest if rest else 0.0) for a in live}
        low = [a for a in free if out[a] < min_share]
        if not low:
            return {a: out.get(a, 0.0) for a in shares}
        floored.update(low)


def top_action(lesson: Lesson) -> str:
    """The teacher's top candidate of the lesson's (first) ranking task."""
    ranking = next(t for t in lesson.targets if t.kind == "ranking")
    return ranking.candidates[ranking.best]


def balanced_quotas(counts: dict[str, int], total: int, balance: float, min_share: float = 0.0) -> dict[str, int]:
    """How many of `total` lessons each group gets: shares in proportion to count ** (1 - balance)
    (0: the groups' own shares; 1: equal), each then at least `min_share` (`floor_shares`), a group's
    quota possibly more than its count (its lessons are then repeated); whole numbers summing to
    `total`, largest remainders first, a group with no lesson getting none."""
    weights = {a: n ** (1.0 - balance) if n else 0.0 for a, n in counts.items()}
    whole = sum(weights.values())
    if not whole:
        return {a: 0 for a in counts}
    floored = floor_shares({a: w / whole for a, w in weights.items()}, min_share)
    shares = {a: total * v for a, v in floored.items()}
    quotas = {a: int(v) for a, v in shares.items()}
    for a in sorted(shares, key=lambda a: (-(shares[a] - quotas[a]), a))[:total - sum(quotas.values())]:
        quotas[a] += 1
    return quotas


def lessons_from_plan(cache, keys: Sequence[Sequence[str]]) -> list[Lesson]:
    """The lessons of a plan's keys, read back from the cache; a key the cache no longer holds (a
    damaged shard dropped by `illm cache repair`) is refused in one line."""
    flat = [k for row in keys for k in row]
    rows = cache.lookup(flat)
    missing = [k for k in flat if k not in rows]
    if missing:
        raise UsageError(f"the cache {cache.root} no longer holds {len(missing):,} of the rows this distillation "
                         "was started with (a repaired cache?): start it afresh in another --out")
    return [Lesson(state_hash(rows[row[0]]), tuple(target_of(rows[k]) for k in row)) for row in keys]


# --- tokens ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Branch:
    """One target's tokens after the state's shared part: the rest of its prompt, then what is
    scored (a ranking task's candidates; a text task's one continuation, the text and the end)."""

    task: str
    kind: str
    suffix: tuple[int, ...]
    continuations: tuple[tuple[int, ...], ...]
    skip: tuple[int, ...]
    """Per continuation, the leading tokens that belong to the prompt (a token straddling the
    boundary, `plan_state`): fed, not scored."""
    teacher_logprobs: tuple[float, ...] = ()
    best: int = 0


@dataclass(frozen=True)
class Example:
    """A lesson's tokens: the shared part of its prompts, then one branch per target."""

    shared: tuple[int, ...]
    branches: tuple[Branch, ...]

    @property
    def tokens(self) -> int:
        """Tokens run through the model for this example."""
        return len(self.shared) + sum(len(b.suffix) + sum(len(c) for c in b.continuations) for b in self.branches)

    @property
    def longest(self) -> int:
        """The longest sequence the model reads for it (a prompt and its longest continuation)."""
        return len(self.shared) + max(len(b.suffix) + max(len(c) for c in b.continuations) for b in self.branches)


def text_target(text: str) -> str:
    """A teacher's text as the continuation of its prompt: after a space unless it starts with one."""
    return text if text[:1].isspace() else " " + text


def tokenise(lm, lesson: Lesson, *, share: bool = True) -> Example:
    """The lesson's tokens for the student `lm` (a `LoadedModel`; module docstring)."""
    from illm_tools.llm.scoring import common_prefix, plan_state

    plans = []
    for target in lesson.targets:
        if target.kind == "ranking":
            plans.append(plan_state(lm, target.prompt, list(target.candidates)))
        else:
            plan = plan_state(lm, target.prompt, [text_target(target.text)])
            eos = lm.eos_ids[:1] if lm.eos_ids else ()
            plans.append(type(plan)(plan.prefix, [[*plan.continuations[0], *eos]], plan.skip))
    shared = 0
    if share and len(plans) > 1:
        # keep one token of each prompt out of the shared part: its logits score the first token after it
        shared = min(min(common_prefix(plans[0].prefix, p.prefix), len(p.prefix) - 1) for p in plans)
    branches = tuple(Branch(t.task, t.kind, tuple(p.prefix[shared:]), tuple(tuple(c) for c in p.continuations),
                            tuple(p.skip), t.teacher_logprobs, t.best if t.kind == "ranking" else 0)
                     for t, p in zip(lesson.targets, plans))
    return Example(tuple(plans[0].prefix[:shared]) if shared else (), branches)

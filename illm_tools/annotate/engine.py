"""The annotation engine: states in, cache rows out. Used by `illm annotate` (bulk, from a
trajectory dataset) and by the trainer's live fallback (cache misses after a rollout), so both
write identical rows under identical keys.

For each distinct state it renders the language tasks' prompts (illm_tools.tasks), drops keys the
cache already holds, and runs the LLM on the rest in length-sorted batches: candidate scoring for
a ranking task (`action`: context KV computed once per state and shared by all candidates),
greedy generation for a text task (`summary` 64 tokens, `goal` 32, `plan` 48: the text and its
embedding, plus the goal task's parsed goals in `candidates`, `illm_tools.tasks.goals`); the
tasks are `illm_tools.tasks.registry`'s. Rows are written in chunks, so a run
killed at any point keeps every finished chunk and a restart does only what is missing.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from illm_tools.annotate.coverage import VisitedStates
from illm_tools.keys import canonical_json, fingerprint_hash
from illm_tools.cache.store import AnnotationCache
from illm_tools.errors import UsageError
from illm_tools.tasks.prompts import DEFAULT_TASKS, Prompt, PromptBuilder, format_history, neutral_prompt
from illm_tools.tasks.registry import get_task, parse_tasks
from illm_tools.tasks.annotation_setup import AnnotationSetup
from illm_tools.tasks.state import StateRecord

log = logging.getLogger(__name__)


@dataclass
class Job:
    """One (state, task) the LLM must answer."""

    key: str
    prompt: Prompt
    builder: PromptBuilder
    record: StateRecord | None = None
    """The state (a hop state's arrays ride on it: `illm_tools.hop.context.HopRecord`)."""


@dataclass
class Stats:
    """Counters of an annotation run (distinct states and (state, task) keys)."""

    states: int = 0
    """Distinct states planned."""
    keys: int = 0
    """Distinct (state, task) keys planned."""
    hits: int = 0
    """Keys the cache already held."""
    misses: int = 0
    """Keys the cache lacked."""
    annotated_states: int = 0
    """States the LLM answered in this run (all their missing tasks)."""
    rows: int = 0
    """Rows written to the cache."""
    summary_tokens: int = 0
    """Tokens generated for summaries (their mean length is summary_tokens / summaries)."""
    summaries: int = 0
    """Summaries generated."""
    stopped_early: bool = False
    """True when the time limit ended the run before its plan was done."""
    too_long: list = field(default_factory=list)
    """States refused before the engine, longer than the model's context: (rank among the visited
    states, most visited first; env id; tokens it needs)."""
    seconds: float = 0.0
    per_task: dict = field(default_factory=dict)

    @property
    def states_per_s(self) -> float:
        return self.annotated_states / self.seconds if self.seconds else 0.0

    @property
    def mean_summary_tokens(self) -> float:
        return self.summary_tokens / self.summaries if self.summaries else 0.0


HOP_MARK = "\x00HISTORY\x00"
"""Where a hop prompt's translated window is spliced: rendered as its history, then split at."""


def hop_parts(job: Job) -> tuple[str, str]:
    """A hop job's prompt text before and after its history, where its window of translated steps
    stands (`illm_tools.llm.spliced.SplicedPrompt`'s head and tail)."""
    mark = HOP_MARK
    while (text := job.builder.render(job.prompt.task, job.record, mark).text).count(mark) > 1:
        mark += "\x00"  # a state's own text holds the mark: a longer one it cannot hold
    head, _, tail = text.partition(mark)
    return head, tail


class Annotator:
    """Owns a loaded model, a cache and the prompt builders of the envs it has seen."""

    def __init__(self, lm, cache: AnnotationCache, *, model: str, tasks: Sequence[str] = DEFAULT_TASKS,
                 history_len: int = 3, layout: str = "shared", batch_size: int = 8, chunk: int = 64):
        tasks = parse_tasks(tasks)
        from illm_tools.llm.backend import as_backend

        self.lm = as_backend(lm)
        """The LLM backend (`illm_tools.llm.backend`); a loaded transformers model is wrapped."""
        self.cache = cache
        self.model = model
        self.tasks = tuple(tasks)
        self.history_len = history_len
        self.layout = layout
        self.batch_size = batch_size
        self.chunk = chunk
        self.model_fingerprint = fingerprint_hash(self.lm.fingerprint)
        check = getattr(type(self.lm), "check_ranking", None)  # a backend that cannot rank refuses (openai)
        if check is not None and any(get_task(t).kind == "ranking" for t in self.tasks):
            check(model)
        self._builders: dict[tuple[str, str], PromptBuilder] = {}
        self._neutral: dict[tuple[str, ...], list[float]] = {}
        self._hop: dict[tuple, object] = {}
        self._said_too_long = False

    @classmethod
    def of_setup(cls, lm, cache: AnnotationCache | None, llm, setup, *, tasks: Sequence[str] | None = None,
                 **options) -> Annotator:
        """The annotator of a loaded `llm` (its `LLMSpec`) for a setup's history and layout: a stage's
        `PromptConfig` with its `tasks`, or an `AnnotationSetup` (its own tasks); `options`:
        batch_size, chunk. How every stage makes its annotator (annotate, serve, probe, the live
        fallback)."""
        return cls(lm, cache, model=llm.model, tasks=setup.tasks if tasks is None else tasks,
                   history_len=setup.history_len, layout=setup.layout, **options)

    def builder(self, env_id: str, renderer: str) -> PromptBuilder:
        key = (env_id, renderer)
        if key not in self._builders:
            check = getattr(type(self.lm), "check_use", None)  # a backend refuses what it cannot read (the oracle: hop)
            if check is not None:
                check(env_id, renderer)
            setup = AnnotationSetup(env_id, renderer, self.tasks, self.history_len, self.layout)
            self._builders[key] = setup.builder(self.model, self.model_fingerprint)
        return self._builders[key]

    def visited(self, records: Sequence[StateRecord], env_ids: Sequence[str],
                renderers: Sequence[str]) -> VisitedStates:
        """The distinct states of these steps, most visited first, keyed for this run's tasks."""
        return VisitedStates.count(records, env_ids, renderers, self.builder, self.tasks)

    def plan(self, visited: VisitedStates, stats: Stats | None = None) -> list[list[Job]]:
        """Jobs for the (state, task) keys the cache misses, grouped per state, in `visited`'s
        order (most visited first); take `visited.top(n)` to plan only the n most visited."""
        stats = stats if stats is not None else Stats()
        flat = [k for keys in visited.keys for k in keys]
        found = self.cache.contains(flat) if flat else np.zeros(0, bool)
        present = {k for k, f in zip(flat, found) if f}
        stats.states += len(visited)
        stats.keys += len(set(flat))
        stats.hits += len(present)
        stats.misses += len(set(flat)) - len(present)
        plan = []
        for rank, (record, builder, keys) in enumerate(zip(visited.records, visited.builders, visited.keys)):
            history = None
            jobs = []
            for task, key in zip(visited.tasks, keys):
                if key in present:
                    continue
                present.add(key)  # a key shared by two states (e.g. one summary prompt) is planned once
                history = format_history(record) if history is None else history
                jobs.append(Job(key, builder.render(task, record, history), builder, record))
            needed = self.tokens_needed(jobs)
            if needed is not None:
                stats.too_long.append((rank, builder.env_id, needed))
                self._say_too_long(builder.env_id, needed)
            elif jobs:
                plan.append(jobs)
        return plan

    @property
    def context_length(self) -> int | None:
        """The backend's context in tokens, where it states one (None: no gate here)."""
        return getattr(self.lm, "context_length", None)

    def tokens_needed(self, jobs: Sequence[Job]) -> int | None:
        """The tokens a state's jobs need when the longest is more than the model's context (its prompt
        plus its longest candidate, or plus the generated tokens; a hop prompt's head, window of
        translated steps and tail in place of its prompt), else None: such a state is refused
        before the engine."""
        limit = self.context_length
        if limit is None or not jobs:
            return None
        needed = max(self._job_tokens(j) for j in jobs)
        return needed if needed > limit else None

    def _job_tokens(self, job: Job) -> int:
        """The positions one job takes in the engine (the backend's `tokens_needed`)."""
        new_tokens = get_task(job.prompt.task).max_new_tokens
        if not job.builder.renderer.startswith("hop@"):
            return self.lm.tokens_needed(job.prompt.text, job.prompt.candidates, new_tokens)
        head, tail = hop_parts(job)
        return self.lm.tokens_needed(head, job.prompt.candidates, new_tokens,
                                     window=len(getattr(job.record, "frames", ())), tail=tail)

    def state_too_long(self, record: StateRecord, env_id: str, renderer: str) -> int | None:
        """The tokens `record` needs under this annotator's tasks when more than the model's context
        (`tokens_needed`; a hop state's too), else None (`illm serve` refuses such a state at arrival)."""
        if self.context_length is None:
            return None
        builder = self.builder(env_id, renderer)
        history = format_history(record)
        jobs = [Job("", builder.render(task, record, history), builder, record) for task in self.tasks]
        return self.tokens_needed(jobs)

    def _say_too_long(self, env_id: str, needed: int) -> None:
        """Log the first state refused for its length (later ones are counted in `Stats.too_long`)."""
        if not self._said_too_long:
            log.warning("a state of %s needs %d tokens, more than %s's context of %d: refused before the engine "
                        "(further ones are counted, not logged)", env_id, needed, self.model, self.context_length)
        self._said_too_long = True

    def annotate_states(self, records: Sequence[StateRecord], env_id: str, renderer: str,
                        **run_options) -> Stats:
        """Annotate what the cache lacks of these states of one env now (the live fallback's call),
        most visited first; `run_options` go to `run`."""
        stats = Stats()
        plan = self.plan(self.visited(records, [env_id] * len(records), [renderer] * len(records)), stats=stats)
        return self.run(plan, stats=stats, **run_options)

    def run(self, plan: list[list[Job]], *, stats: Stats | None = None,
            on_progress: Callable[[int, Stats], None] | None = None, max_seconds: float | None = None,
            should_stop: Callable[[], bool] | None = None) -> Stats:
        """Annotate the planned states, writing a shard per chunk. Stops
        between chunks once `max_seconds` have passed or `should_stop()` says so: every chunk is
        written whole or not at all, so what is done stays in the cache."""
        stats = stats if stats is not None else Stats()
        start = time.perf_counter()
        for i in range(0, len(plan), self.chunk):
            if (max_seconds is not None and time.perf_counter() - start >= max_seconds) or \
                    (should_stop is not None and should_stop()):
                stats.stopped_early = True
                break
            chunk = plan[i:i + self.chunk]
            rows = self.annotate(chunk)
            for row in rows:
                stats.per_task[row["task"]] = stats.per_task.get(row["task"], 0) + 1
                tokens = row.pop("_tokens", None)  # not a cache column: counted, then dropped
                if tokens is not None:
                    stats.summaries += 1
                    stats.summary_tokens += tokens
            self.cache.write(rows)
            stats.rows += len(rows)
            stats.annotated_states += len(chunk)
            stats.seconds = time.perf_counter() - start
            if on_progress is not None:
                on_progress(len(chunk), stats)
        stats.seconds = time.perf_counter() - start
        return stats

    # ---- the LLM calls ---------------------------------------------------------------------

    def annotate(self, states: list[list[Job]]) -> list[dict]:
        """Cache rows for the jobs of these states (no writing). A state needing both action and
        summary under the shared layout runs their common prompt prefix once for both; every other
        ranking task is scored, every other text task generated, in batches of its own."""
        rows: list[dict] = []
        ranking: list[Job] = []
        text: dict[str, list[Job]] = {}
        pairs: list[tuple[Job, Job]] = []
        share = self.layout == "shared" and getattr(self.lm, "shares_prefix", False)
        hop = [jobs for jobs in states if jobs[0].builder.renderer.startswith("hop@")]
        if hop:
            rows += self._annotate_hop(hop)
            states = [jobs for jobs in states if not jobs[0].builder.renderer.startswith("hop@")]
        for jobs in states:
            by_task = {j.prompt.task: j for j in jobs}
            if share and "action" in by_task and "summary" in by_task:
                pairs.append((by_task["action"], by_task["summary"]))
                jobs = [j for j in jobs if j.prompt.task not in ("action", "summary")]
            for j in jobs:
                if get_task(j.prompt.task).kind == "ranking":
                    ranking.append(j)
                else:
                    text.setdefault(j.prompt.task, []).append(j)
        if pairs:
            scores, gens = self.lm.score_and_generate(
                [a.prompt.text for a, _ in pairs], [list(a.prompt.candidates) for a, _ in pairs],
                [s.prompt.text for _, s in pairs], max_new_tokens=get_task("summary").max_new_tokens,
                batch_size=self.batch_size)
            rows += [self._action_row(a, sc) for (a, _), sc in zip(pairs, scores)]
            rows += [self._text_row(s, g) for (_, s), g in zip(pairs, gens)]
        if ranking:
            scores = self.lm.score([j.prompt.text for j in ranking], [list(j.prompt.candidates) for j in ranking],
                                   batch_size=self.batch_size)
            rows += [self._action_row(j, sc) for j, sc in zip(ranking, scores)]
        for task, jobs in text.items():
            gens = self.lm.generate([j.prompt.text for j in jobs], max_new_tokens=get_task(task).max_new_tokens,
                                    batch_size=self.batch_size)
            rows += [self._text_row(j, g) for j, g in zip(jobs, gens)]
        return rows

    def hop_context(self, renderer: str, obs_dim: int, num_actions: int):
        """The `HopContext` (translation over this model's input embeddings) of a hop renderer."""
        from illm_tools.hop.context import HopContext
        from illm_tools.tasks.annotation_setup import parse_hop_renderer

        settings = parse_hop_renderer(renderer)
        key = (obs_dim, num_actions, settings["seed"], settings["beta"])
        if key not in self._hop:
            self._hop[key] = HopContext(self.lm, obs_dim, num_actions, seed=settings["seed"], beta=settings["beta"])
        return self._hop[key]

    def _annotate_hop(self, states: list[list[Job]]) -> list[dict]:
        """iLLM(hop)'s language tasks: each prompt is its template with the translated window
        spliced in as input embeddings where the written history would stand (B.2's prompts, D.7);
        the backend scores a ranking task's candidates after it and decodes a text task from it
        (one call per generation length: the ranking tasks ride with the first)."""
        from illm_tools.llm.spliced import SplicedPrompt

        groups: dict[int, tuple[list[Job], list]] = {}  # max_new_tokens -> (jobs, prompts)
        for jobs in states:
            record = jobs[0].record
            if not getattr(record, "frames", ()):
                raise UsageError("a hop state reached the annotator without its observations (a HopRecord is needed)")
            unfit = sorted({j.prompt.task for j in jobs if not get_task(j.prompt.task).hop})
            if unfit:
                raise UsageError(f"the {', '.join(unfit)} task has no hop form: annotate hop data with other --tasks")
            context = self.hop_context(jobs[0].builder.renderer, int(np.asarray(record.frames[0]).size),
                                       len(record.valid_actions))
            window = context.window_embeddings(record.frames, record.prev_actions)
            for job in jobs:
                head, tail = hop_parts(job)
                group = groups.setdefault(get_task(job.prompt.task).max_new_tokens, ([], []))
                group[0].append(job)
                group[1].append(SplicedPrompt(head, window, tail, job.prompt.candidates))
        if 0 in groups and len(groups) > 1:  # ranking tasks ride with a generating call
            ranked = groups.pop(0)
            first = groups[next(iter(groups))]
            first[0][:0], first[1][:0] = ranked
        rows = []
        for tokens, (jobs, prompts) in groups.items():
            answers = self.lm.spliced(prompts, max_new_tokens=max(tokens, 1), batch_size=self.batch_size)
            rows += [self._action_row(job, answer) if get_task(job.prompt.task).kind == "ranking"
                     else self._text_row(job, answer) for job, answer in zip(jobs, answers)]
        return rows

    def neutral_scores(self, candidates: tuple[str, ...]) -> list[float]:
        """Each candidate's summed log-prob after the neutral prompt (once per candidate set)."""
        if candidates not in self._neutral:
            (scores,) = self.lm.score([neutral_prompt()], [list(candidates)], batch_size=1)
            self._neutral[candidates] = [float(s) for s in scores.sums]
        return self._neutral[candidates]

    def _base_row(self, job: Job) -> dict:
        p, b = job.prompt, job.builder
        return {
            "key": job.key, "task": p.task, "template_version": b.template(p.task)[1],
            "renderer": b.renderer, "model": self.model, "model_fingerprint": self.model_fingerprint,
            "decoding": canonical_json(b.decoding(p.task)), "history_len": b.history_len,
            "goal": p.goal, "history": p.history, "observation": p.observation, "prompt": p.text,
            "candidates": None, "cand_token_logprobs": None, "cand_logprob_sum": None,
            "cand_token_count": None, "neutral_logprob_sum": None, "chosen_index": None,
            "text": None, "embedding": None, "embedding_dim": None, "created_unix": time.time(),
        }

    def _action_row(self, job: Job, scores) -> dict:
        row = self._base_row(job)
        sums = [float(s) for s in scores.sums]
        row.update(
            candidates=[c.strip() for c in job.prompt.candidates],
            cand_token_logprobs=[[float(x) for x in t] for t in scores.token_logprobs],
            cand_logprob_sum=sums,
            cand_token_count=[int(n) for n in scores.token_counts],
            neutral_logprob_sum=self.neutral_scores(job.prompt.candidates),
            chosen_index=int(np.argmax(sums)),
        )
        return row

    def _text_row(self, job: Job, gen) -> dict:
        """A text task's row: the generation in `text`, its embedding, and the task's parse of the
        text (the goal task's goals) in `candidates`."""
        row = self._base_row(job)
        task = get_task(job.prompt.task)
        emb = np.asarray(gen.embedding, dtype=np.float32)
        row.update(text=gen.text, embedding=emb.tolist(), embedding_dim=int(emb.shape[0]))
        if task.parse is not None:
            row["candidates"] = task.parse(gen.text, not gen.finished)
        if task.name == "summary":
            row["_tokens"] = len(gen.token_ids)  # counted for the run's mean summary length
        return row

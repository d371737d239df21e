"""The helpers the tests share (one module: no test module imports another). The trainer's fakes: `FakePool` (the EnvPool interface over a toy task),
`FakeProvider` (deterministic LLM targets from a hash of each record), `RefusingProvider` (for
methods that must never ask), `make_trainer` (a small Trainer over them) and `plugins_installed`
(entry points as an installed package would declare them); `run_wide` (a folder built once per test
run, read by every xdist worker); annotation cache rows (`make_rows`, `keys_of`, `run_writers`),
trajectory rows, file damage (`flip`, `truncate`), fake run folders for `illm report` (`fake_run`); a
backend and a suite defined outside illm (`TinyBackend`, `TinySuite`); `illm serve` requests of the
stub's setup (`serve_state`, `serve_request`, `hop_states`), a server in a thread of the test
(`running_server`), `illm serve` with slow batches (`SLOW_SERVER`) and `wait_for`.

Over 400 lines: these are the suite's shared helpers, kept in one module on purpose (issue 48); each
block names the test files that use it."""

from __future__ import annotations

import asyncio
import csv
import functools
import http.server
import importlib.metadata
import json
import os
import random
import stat
import threading
import time
import urllib.error
import urllib.request
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from illm_tools.envs.suite import EpisodeStats, ObsSpec, Suite
from illm_tools.keys import fingerprint_hash
from illm_tools.llm.spec import LLMSpec
from illm_tools.llm.stub import StubBackend
from illm_tools.tasks.state import StateRecord

ACTIONS = ("turn left", "turn right", "go forward", "pick up", "drop", "toggle")


class FakePool:
    """The EnvPool interface over a toy task: an episode ends after 3-9 steps; 'go forward'
    on the last step succeeds (reward 1). With `positions`, the agent of env i stands at (step, i)."""

    def __init__(self, num_envs, seed=0, positions=False, env_id="BabyAI-GoToLocal-v0"):
        from illm_tools.envs import suite_of

        self.num_envs, self.action_names, self.suite = num_envs, ACTIONS, suite_of(env_id)
        self.rng = np.random.default_rng(seed)
        self.positions = positions

    def _obs(self):
        n = self.num_envs
        obs = SimpleNamespace(
            images=self.rng.integers(0, 6, size=(n, 7, 7, 3)).astype(np.uint8),
            missions=[f"go to the {c} ball" for c in self.colours],
            texts=[f"you see a wall {s} steps forward" for s in self.steps], seeds=np.arange(n),
            steps=self.steps.copy())
        if self.positions:
            obs.positions = np.stack([self.steps, np.arange(n)], 1)
        return obs

    def reset(self):
        self.steps = np.zeros(self.num_envs, np.int64)
        self.lengths = self.rng.integers(3, 10, self.num_envs)
        self.returns = np.zeros(self.num_envs)
        self.colours = self.rng.choice(["red", "blue"], self.num_envs).tolist()
        return self._obs()

    def step(self, actions):
        self.steps += 1
        done = self.steps >= self.lengths
        rewards = (done & (np.asarray(actions) == 2)).astype(np.float32)
        self.returns += rewards
        episodes = [EpisodeStats(int(i), float(self.returns[i]), int(self.steps[i]), bool(rewards[i] > 0))
                    for i in np.flatnonzero(done)]
        for i in np.flatnonzero(done):
            self.steps[i], self.returns[i] = 0, 0.0
            self.lengths[i] = self.rng.integers(3, 10)
        return SimpleNamespace(rewards=rewards, terminated=done, truncated=np.zeros_like(done),
                               obs=self._obs(), episodes=episodes)


class FakeProvider:
    """Deterministic targets from a hash of each record; about one record in four has none."""

    def __init__(self, num_actions, dim):
        self.num_actions, self.dim, self.calls, self.records = num_actions, dim, 0, []

    def targets(self, records):
        from illm_tools.intrinsic import Targets

        self.calls += 1
        self.records.extend(records)
        probs = np.zeros((len(records), self.num_actions), np.float32)
        emb = np.zeros((len(records), self.dim), np.float32)
        mask = np.zeros(len(records), bool)
        for i, r in enumerate(records):
            key = zlib.crc32(repr((r.mission, r.history, r.observation)).encode())
            rng = np.random.default_rng(key)
            probs[i], emb[i], mask[i] = rng.dirichlet(np.ones(self.num_actions)), rng.normal(size=self.dim), key % 4 != 0
        return Targets(probs, emb, mask)

    def stats(self):
        return {"cache_hit_rate": 0.25, "live_annotations": 7}


class RefusingProvider:
    def targets(self, records):
        raise AssertionError("ppo mode must not ask for LLM targets")

    def stats(self):
        return {}


def make_trainer(tmp_path, mode="illm", updates=2, pool=None, **kw):
    # settings by their option names (lambda_a=..., backend=...); the stub's 8-wide embeddings size the heads
    from illm_tools.rl import TrainConfig, Trainer

    cfg = TrainConfig.from_dict(dict(run_dir=tmp_path / "run", method=mode, num_envs=4, num_steps=32,
                                     total_steps=4 * 32 * updates, backend="stub", model="stub:8", head_hidden=32,
                                     tensorboard=False, update_epochs=2, num_minibatches=2, **kw))
    pool = pool or FakePool(cfg.num_envs)
    provider = FakeProvider(len(pool.action_names), cfg.embedding_dim) if mode != "ppo" else RefusingProvider()
    return Trainer(cfg.resolved(), pool, provider), provider


def one_update_seen(trainer, monkeypatch) -> SimpleNamespace:
    """One `trainer.train_one_update()` with what its update step was handed: `logged` (its logs), `ro`
    (the rollout), `adv` (the advantages the loss used), `bonus` (the reward the trainer computed), `next`
    (the rollout's bootstrap values, the network not yet updated), and the advantages
    `two_stream_advantages` gives from them with the bonus (`expected`) and without (`without`)."""
    import torch

    from illm_tools.rl import two_stream_advantages

    seen = {}
    real_update, real_rewards = trainer.update, trainer.intrinsic_rewards

    def rewards(ro, *args, **kwargs):
        seen["bonus"] = out = real_rewards(ro, *args, **kwargs)
        return out

    def capture(ro, adv):
        seen.update(ro=ro, adv=adv)
        with torch.no_grad():
            seen["next"] = trainer.net(*trainer._policy_inputs(trainer.obs))
        return real_update(ro, adv)

    with monkeypatch.context() as patch:
        patch.setattr(trainer, "intrinsic_rewards", rewards)
        patch.setattr(trainer, "update", capture)
        logged = trainer.train_one_update()
    cfg, ro, nxt = trainer.cfg, seen["ro"], seen["next"]
    kw = dict(gamma=cfg.ppo.gamma, int_gamma=cfg.bonus.int_gamma, lam=cfg.ppo.gae_lambda, ext_coef=cfg.bonus.ext_coef,
              int_coef=cfg.bonus.int_coef, int_episodic=cfg.bonus.int_episodic, int_ext_cap=cfg.bonus.int_ext_cap)
    return SimpleNamespace(logged=logged, ro=ro, adv=seen["adv"], bonus=seen["bonus"].reward, next=nxt,
                           expected=two_stream_advantages(ro, seen["bonus"].reward, nxt.value_ext, nxt.value_int, **kw),
                           without=two_stream_advantages(ro, None, nxt.value_ext, nxt.value_int, **kw))


@contextmanager
def plugins_installed(monkeypatch, points: dict[str, list[tuple[str, str]]], also: tuple = ()) -> Iterator[list[list[str]]]:
    """Plug-ins as if installed: `importlib.metadata.entry_points` answers `points` ({group: [(name,
    "module:object")]}) for their groups and the installed ones for other groups; every registry
    reads them, and the registries in `also` (e.g. the oracles'). Yields the names each registry added
    (methods, tasks, backends, suites, then `also`'s in order); removes them after."""
    from illm_tools.envs import SUITES
    from illm_tools.intrinsic.registry import METHODS
    from illm_tools.llm.backend import BACKENDS
    from illm_tools.tasks.registry import LANGUAGE_TASKS

    real = importlib.metadata.entry_points

    def entry_points(**selection):
        group = selection.get("group")
        if group not in points:  # other libraries' look-ups: the installed ones
            return real(**selection)
        return [importlib.metadata.EntryPoint(name, value, group) for name, value in points[group]]

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    registries = (METHODS, LANGUAGE_TASKS, BACKENDS, SUITES, *also)
    added = [registry.read_plugins(again=True) for registry in registries]
    try:
        yield added
    finally:
        for registry, names in zip(registries, added):
            for name in names:
                del registry[name]


@contextmanager
def fake_hub(repos: dict[str, "Path"], *, refuse: dict[str, tuple[int, str]] | None = None) -> Iterator[str]:
    """A Hugging Face hub on 127.0.0.1 serving each `repos[repo_id]` folder as that repository's main
    revision (the API routes `snapshot_download` calls: revision info, tree listing, file HEAD and
    GET), or answering a repository in `refuse` with (status, X-Error-Code) as the hub does for gated
    (403, GatedRepo) and missing (404, RepoNotFound) ones. Yields its URL, for HF_ENDPOINT; requests
    it served are counted in `fake_hub.requests`."""
    import asyncio
    import hashlib
    import threading
    from pathlib import Path

    from aiohttp import web

    refuse = refuse or {}
    commits = {repo: hashlib.sha1(repo.encode()).hexdigest() for repo in repos}

    def files(repo):
        root = Path(repos[repo])
        return {p.name: p.read_bytes() for p in sorted(root.iterdir()) if p.is_file()}

    def refused(repo):
        status, code = refuse[repo]
        return web.Response(status=status, headers={"X-Error-Code": code, "X-Error-Message": f"{code} (fake hub)"})

    async def info(request):
        repo = f"{request.match_info['org']}/{request.match_info['name']}"
        fake_hub.requests += 1
        if repo in refuse:
            return refused(repo)
        if repo not in repos:
            return web.Response(status=404, headers={"X-Error-Code": "RepoNotFound"})
        return web.json_response({"id": repo, "sha": commits[repo],
                                  "siblings": [{"rfilename": n} for n in files(repo)]})

    async def tree(request):
        repo = f"{request.match_info['org']}/{request.match_info['name']}"
        fake_hub.requests += 1
        if repo in refuse:
            return refused(repo)
        return web.json_response([{"type": "file", "path": n, "size": len(b), "oid": hashlib.sha1(b).hexdigest()}
                                  for n, b in files(repo).items()])

    async def resolve(request):
        repo = f"{request.match_info['org']}/{request.match_info['name']}"
        fake_hub.requests += 1
        if repo in refuse:
            return refused(repo)
        body = files(repo).get(request.match_info["file"])
        if body is None:
            return web.Response(status=404, headers={"X-Error-Code": "EntryNotFound"})
        headers = {"X-Repo-Commit": commits[repo], "ETag": f'"{hashlib.sha1(body).hexdigest()}"',
                   "Content-Length": str(len(body))}
        if request.method == "HEAD":
            return web.Response(headers=headers)
        return web.Response(body=body, headers=headers)

    app = web.Application()
    app.router.add_get("/api/models/{org}/{name}/revision/{rev}", info)
    app.router.add_get("/api/models/{org}/{name}/tree/{rev:.*}", tree)
    app.router.add_route("*", "/{org}/{name}/resolve/{rev}/{file}", resolve)
    loop = asyncio.new_event_loop()
    runner = web.AppRunner(app)
    loop.run_until_complete(runner.setup())
    site = web.TCPSite(runner, "127.0.0.1", 0)
    loop.run_until_complete(site.start())
    port = site._server.sockets[0].getsockname()[1]
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    fake_hub.requests = 0
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        loop.run_until_complete(runner.cleanup())
        loop.close()


def collected(out, steps: int, num_envs: int = 2, env: str = "BabyAI-GoToLocal-v0", seed: int = 0):
    """`illm collect` of `steps` random steps of `env` into `out` (the trajectories a test annotates)."""
    from typer.testing import CliRunner

    from cli.main import app

    done = CliRunner().invoke(app, ["collect", "--env", env, "--steps", str(steps), "--num-envs", str(num_envs),
                                    "--seed", str(seed), "--out", str(out)])
    assert done.exit_code == 0, done.output
    return out


def run_wide(tmp_path_factory, name: str, build, *, read_only: tuple[str, ...] = (".",)) -> Path:
    """A folder built once per test run, whichever xdist worker asks first (the others wait on a file
    lock, then read it): `build(folder)` fills it; then the paths `read_only` names under it (the
    folder itself by default) are made read-only, so a test that writes there fails instead of
    changing what the other tests read. Under xdist the workers' base temp folders are siblings, and
    the folder lies beside them; without xdist, in the run's own base temp folder."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent
    folder, done = base / name, base / f"{name}.done"
    with FileLock(str(base / f"{name}.lock")):
        if not done.exists():
            folder.mkdir(exist_ok=True)
            build(folder)
            for part in read_only:
                _read_only(folder / part)
            done.touch()
    return folder


def _read_only(root: Path) -> None:
    """Write permission off every file and folder under `root` (pytest's clean-up restores it)."""
    writable = stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH
    for path in sorted(root.rglob("*"), reverse=True) + [root]:
        path.chmod(path.stat().st_mode & ~writable)


# --- annotation cache rows (tests/test_cache_store.py, test_cache_share.py, test_first_hour.py) -----------
def make_rows(start: int, stop: int, tag: str = "t") -> list[dict]:
    """Valid rows: even i are action rows, odd i summary rows (embedding dim 4)."""
    from illm_tools.cache import make_key

    rows = []
    for i in range(start, stop):
        action = i % 2 == 0
        rows.append({
            "key": make_key(tag=tag, i=i), "task": "action" if action else "summary",
            "template_version": 1, "renderer": "babyai-text@1", "model": "smollm2-135m",
            "model_fingerprint": "f" * 64, "decoding": '{"temperature":0}', "history_len": 3,
            "goal": "go to the red ball", "history": "turn left", "observation": f"obs {i}",
            "prompt": f"prompt {i}",
            "candidates": ["turn left", "go forward"] if action else None,
            "cand_token_logprobs": [[-0.5, -0.25], [-1.5]] if action else None,
            "cand_logprob_sum": [-0.75, -1.5] if action else None,
            "cand_token_count": [2, 1] if action else None,
            "neutral_logprob_sum": [-1.0, -2.0] if action else None,
            "chosen_index": 0 if action else None,
            "text": None if action else f"summary {i}",
            "embedding": None if action else [float(i), 0.5, -0.25, 1.0],
            "embedding_dim": None if action else 4,
            "created_unix": 1700000000.5,
        })
    return rows


def stub_annotated(root, n: int = 6) -> Path:
    """A cache at `root` of `n` BabyAI-like states annotated by the stub backend (history 0, action and
    summary): real rows, whose keys their own columns give (what an import checks)."""
    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache

    annotator = Annotator(StubBackend(STUB_MODEL), AnnotationCache(root), model=STUB_LLM.model, history_len=0)
    annotator.annotate_states([serve_state(i) for i in range(n)], "BabyAI-GoToLocal-v0", "babyai-text@1")
    return Path(root)


def trains_with_the_engine_stopped(ann, run, entries: int, env: str = "BabyAI-GoToRedBallNoDists-v0",
                                   reach: tuple[str, ...] = ("--endpoint", "http://127.0.0.1:9/v1")) -> str:
    """Issue 54's checks of a cache annotated through an engine at two addresses, the engine stopped:
    `illm cache info` lists one setup per task (served at both addresses, `entries` states each) and
    `illm train --live-budget 0` adopts it and trains on its targets; returns the run's output.
    `reach`: the user's own options that say where the engine is (issue 69: never the cache's)."""
    from typer.testing import CliRunner

    from cli.main import app
    from illm_tools.llm import openai_wire

    runner = CliRunner()
    openai_wire.forget_engines()  # what this process asked the engine: a later command starts afresh
    info = runner.invoke(app, ["cache", "info", str(ann), "--json"])
    assert info.exit_code == 0, info.output
    setups = json.loads(info.output)["setups"]
    assert sorted(u["task"] for u in setups) == ["action", "summary"], setups  # one setup per task
    assert all(len(u["served_at"]) == 2 and u["entries"] == entries for u in setups), setups
    assert all("another file or revision" not in u["model_options"] for u in setups)
    done = runner.invoke(app, ["train", "--env", env, "--method", "illm", "--cache", str(ann), "--live-budget", "0",
                               "--num-envs", "4", "--num-steps", "32", "--frames", "256", "--seed", "0", "--out",
                               str(run), "--device", "cpu", *reach])
    assert done.exit_code == 0, done.output
    metrics = [json.loads(line) for line in (Path(run) / "metrics.jsonl").read_text().splitlines()]
    assert max(m.get("charts/target_coverage", 0.0) for m in metrics) > 0  # targets of the cached states
    return done.output


def keys_of(rows: list[dict]) -> list[str]:
    return [r["key"] for r in rows]


def run_writers(target, root, count: int, timeout: float = 90) -> list[int]:
    """Start `count` spawned processes `target(root, worker, barrier)` together; their exit codes."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(count)
    procs = [ctx.Process(target=target, args=(str(root), w, barrier)) for w in range(count)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout)
    return [p.exitcode for p in procs]


# --- trajectory rows, damage, fake runs (test_trajectories.py, test_faults.py, test_resume.py, test_report.py) --
def trajectory_rows(n: int, episode: int = 0) -> dict:
    """`n` valid rows of one episode of a trajectory dataset, as columns."""
    return {
        "episode_id": [episode] * n,
        "step": list(range(n)),
        "env_id": ["BabyAI-GoToLocal-v0"] * n,
        "mission": ["go to the red ball"] * n,
        "obs_text": [f"You see a wall {i + 1} steps forward" for i in range(n)],
        "renderer": ["babyai-text@1"] * n,
        "obs_raw": [bytes(147)] * n,
        "obs_shape": [[7, 7, 3]] * n,
        "obs_dtype": ["uint8"] * n,
        "action": [2] * n,
        "action_text": ["go forward"] * n,
        "valid_actions": [["turn left", "turn right", "go forward"]] * n,
        "reward": [0.0] * (n - 1) + [0.5],
        "terminated": [False] * (n - 1) + [True],
        "truncated": [False] * n,
        "seed": [7] * n,
        "policy": ["random"] * n,
    }


def truncate(path, rng: random.Random) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:rng.randrange(len(data))])


def flip(path, rng: random.Random) -> None:
    data = bytearray(path.read_bytes())
    at = rng.randrange(len(data))
    data[at] ^= 1 << rng.randrange(8)
    path.write_bytes(bytes(data))


def fake_run(path, seed, rows, mode="illm", env_id="BabyAI-GoToLocal-v0"):
    """A run folder `illm report` reads: config.json and metrics.csv of `rows` (global step, success
    rate, episodes[, mean length])."""
    from illm_tools.rl.metrics_log import CSV_COLUMNS

    path.mkdir()
    (path / "config.json").write_text(json.dumps({"mode": mode, "env_id": env_id, "seed": seed}))
    with open(path / "metrics.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for step, success, episodes, *length in rows:  # (global step, success rate, episodes[, mean length])
            writer.writerow({"global_step": step, "success_rate": success, "episodes": episodes,
                             "target_coverage": 0.5, "cache_hit_rate": 0.25,
                             "episodic_length": length[0] if length and episodes else ""})


# --- a backend and a suite defined outside illm (test_backends.py, test_suites.py, test_plugins.py) --------
class TinyBackend(StubBackend):
    """A third backend, defined here: the stub under another name, with its own fingerprint."""

    name = "tiny"

    @classmethod
    def model_fingerprint(cls, model, *, dtype="bfloat16", quant="none"):
        return {"model_id": f"{cls.name}:{model}", "source": cls.name, "sha256": None, "revision": "1",
                "dtype": dtype, "quant": quant}


TINY = "Tiny-Corridor-v0"
EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples"
"""The plug-in examples the docs tell a user to copy (test_docs_examples.py, test_example_*.py)."""


def cli_ok(*args) -> str:
    """`illm ARGS` (each turned into a string) through Typer's runner: its output, the exit code 0."""
    from typer.testing import CliRunner

    from cli.main import app

    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result.output


def _docs_example(name: str):
    """A module of docs/examples loaded from its file (under a name of its own, so the plug-in test that
    installs it as `corridor_suite` still imports it afresh): the docs' corridor is the tests' corridor."""
    import importlib.util

    path = EXAMPLES / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"illm_docs_example_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


Corridor = _docs_example("corridor_suite").Corridor
"""Cells in a row; 'go right' from the last but one reaches the goal (reward 1), the agent a key (MiniGrid
code 5) in a 7x7x3 grid: docs/examples/corridor_suite.py's environment."""


class TinySuite(Suite):
    name = "tiny"
    renderer = "tiny-text@1"
    description = "a corridor"

    def env_ids(self):
        return [TINY]

    def options(self, env_id):
        return ("length",)

    def make(self, env_id, *, action_space, render_text=True, **options):
        return Corridor(render_text=render_text, **options)

    def obs_spec(self, env_id):
        return ObsSpec(shape=(7, 7, 3), dtype="uint8", kind="grid", description="a corridor as MiniGrid codes")


# --- `illm serve`'s requests and servers (test_serve.py, test_serve_hardening.py, test_trust_serve.py) ------
SHORT_ACTIONS = ("turn left", "turn right", "go forward")
STUB_MODEL = "stub:16"
STUB_LLM = LLMSpec(backend="stub", model=STUB_MODEL, dtype="float32")


@functools.cache
def stub_fingerprint() -> str:
    """The stub's fingerprint hash (built on first use: the stub resolves its dtype, which imports torch)."""
    return fingerprint_hash(StubBackend(STUB_MODEL).fingerprint)


def serve_state(i: int) -> StateRecord:
    """A BabyAI-like state of the short action list, told apart by `i`."""
    return StateRecord("go to the red ball", (), f"You see a red ball {i} steps forward", SHORT_ACTIONS)


def serve_request(pending, client="run-a", session="s1", **changes) -> dict:
    """A `POST /annotate` body of the stub's setup for `pending` [(state, visits)]; `changes` override."""
    from illm_tools.serve import record_to_json

    body = {"client": client, "session": session, "model_fingerprint": stub_fingerprint(), "env_id": "BabyAI-GoToLocal-v0", "renderer": "babyai-text@1",
            "history_len": 0, "layout": "shared", "tasks": ["action", "summary"],
            "states": [{**record_to_json(s), "visits": n} for s, n in pending]}
    body.update(changes)
    return body


@contextmanager
def running_server(server, *, token: str | None = None, timeout: float | None = None, port: int = 0) -> Iterator[str]:
    """`server` (an `AnnotationServer`) listening on 127.0.0.1 (a free port, or `port`) in a thread of
    its own, its URL yielded; stopped at the end. `timeout`: the request timeout (default the server's)."""
    from illm_tools.serve import serve

    ready, box = threading.Event(), {}

    async def main() -> None:
        box["stop"], box["loop"] = asyncio.Event(), asyncio.get_running_loop()
        await serve(server, "127.0.0.1", port, box["stop"], token=token, request_timeout=timeout,
                    on_ready=lambda addresses: (box.update(port=addresses[0][1]), ready.set()))

    thread = threading.Thread(target=lambda: asyncio.run(main()), daemon=True)
    thread.start()
    assert ready.wait(30), "the server did not start"
    try:
        yield f"http://127.0.0.1:{box['port']}"
    finally:
        box["loop"].call_soon_threadsafe(box["stop"].set)
        thread.join(30)


SLOW_SERVER = """
import os, sys, time
from illm_tools.llm.backend import BACKENDS
from illm_tools.llm.stub import StubBackend

class SlowStub(StubBackend):  # the stub's answers and fingerprint, each batch taking SLOW_S seconds
    def score(self, *args, **kwargs):
        time.sleep(float(os.environ["SLOW_S"]))
        return super().score(*args, **kwargs)

BACKENDS.register("slow", SlowStub)
from cli.main import main
sys.argv = ["illm", *sys.argv[1:]]
main()
"""
"""`illm serve` as `python -c SLOW_SERVER serve ... --backend slow`: the stub, each batch taking the
environment's SLOW_S seconds."""


def call(url: str, body=None, raw: bytes | None = None, token: str | None = None,
         headers: dict | None = None, timeout: float = 30.0) -> tuple[int, dict]:
    """(status, JSON answer) of a GET (no body) or POST to an `illm serve` server; `headers` gets a
    refusal's headers."""
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    sent = {"Content-Type": "application/json", **({"Authorization": f"Bearer {token}"} if token else {})}
    try:
        with urllib.request.urlopen(urllib.request.Request(url, data=data, method="GET" if data is None else "POST",
                                                           headers=sent), timeout=timeout) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        if headers is not None:
            headers.update(e.headers)
        return e.code, json.loads(e.read())


def wait_for(check, seconds: float = 60.0, what: str = ""):
    """Poll `check()` every 0.1 s until it returns something true (returned), at most `seconds`."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        found = check()
        if found:
            return found
        time.sleep(0.1)
    raise AssertionError(f"not within {seconds:g} s: {what}")


def hop_states(n: int = 3):
    """Hop records of one env's first steps, as a hop trainer builds them (window 2)."""
    import numpy as np

    from illm_tools.hop.context import HopTracker

    tracker = HopTracker(1, 1, SHORT_ACTIONS)
    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        (record,) = tracker.records(["get to the green goal square"], [rng.integers(0, 9, (7, 7, 3), dtype=np.uint8)])
        out.append(record)
        tracker.push([2], [False])
    return out


class QuietHandler(http.server.BaseHTTPRequestHandler):
    """A fake HTTP peer's handler (an engine, an `illm serve`): `reply` sends a body with its length
    and headers; nothing is logged."""

    def reply(self, status: int, body: bytes, headers: dict | None = None) -> None:
        self.send_response(status)
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@contextmanager
def http_fake(handler: type[http.server.BaseHTTPRequestHandler]) -> Iterator[str]:
    """`handler` served on 127.0.0.1 from a thread; yields its base URL, shut down after."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, args=(0.02,), daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_port}"
    finally:
        server.shutdown()
        server.server_close()

"""Fakes shared by the trainer's tests: `FakePool` (the EnvPool interface over a toy task),
`FakeProvider` (deterministic LLM targets from a hash of each record), `RefusingProvider` (for
methods that must never ask), `make_trainer` (a small Trainer over them) and `plugins_installed`
(entry points as an installed package would declare them); `run_wide` (a folder built once per test
run, read by every xdist worker)."""

from __future__ import annotations

import importlib.metadata
import os
import stat
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from illm_tools.envs.suite import EpisodeStats
from illm_tools.intrinsic import Targets
from illm_tools.rl import TrainConfig, Trainer

ACTIONS = ("turn left", "turn right", "go forward", "pick up", "drop", "toggle")


class FakePool:
    """The EnvPool interface over a toy task: an episode ends after 3-9 steps; 'go forward'
    on the last step succeeds (reward 1). With `positions`, the agent of env i stands at (step, i)."""

    def __init__(self, num_envs, seed=0, positions=False):
        self.num_envs, self.action_names = num_envs, ACTIONS
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
    cfg = TrainConfig.from_dict(dict(run_dir=tmp_path / "run", method=mode, num_envs=4, num_steps=32,
                                     total_steps=4 * 32 * updates, backend="stub", model="stub:8", head_hidden=32,
                                     tensorboard=False, update_epochs=2, num_minibatches=2, **kw))
    pool = pool or FakePool(cfg.num_envs)
    provider = FakeProvider(len(pool.action_names), cfg.embedding_dim) if mode != "ppo" else RefusingProvider()
    return Trainer(cfg, pool, provider), provider


@contextmanager
def plugins_installed(monkeypatch, points: dict[str, list[tuple[str, str]]]) -> Iterator[list[list[str]]]:
    """Plug-ins as if installed: `importlib.metadata.entry_points` answers `points` ({group: [(name,
    "module:object")]}) for their groups and the installed ones for other groups; every registry
    reads them. Yields the names each registry added (methods, tasks, backends, suites); removes them
    after."""
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
    registries = (METHODS, LANGUAGE_TASKS, BACKENDS, SUITES)
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

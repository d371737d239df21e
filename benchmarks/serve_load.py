"""Load, soak and restart test of `illm serve`: simulated trainers sending real rollouts' states to one
server with the embedded model, measured from the trainers' side and the server's.

Each simulated trainer plays back its own random-policy BabyAI-GoToLocal collection (history 0, its
own seed) a rollout at a time (`--rollout-steps` steps every `--rollout-seconds`), and does what
`illm train --annotator URL` does after each rollout: looks its states up in the shared cache,
counts their visits, and hands the missed ones, most visited first, to the trainer's own client
(`RemoteLive`: its sender thread, back-off and re-sending are the real ones) with a budget of
`--budget`. Halfway (`--restart-at`) the server is killed (SIGKILL: its queue and the batch in
progress are lost; `--restart-signal term` stops it gracefully instead) and started again on the
same port; the trainers go on. After `--minutes` the trainers stop moving, keep their last lists
queued, and the server drains them (at most `--drain-minutes`).

Printed: throughput (states landed per second of the load phase, and the server's while
annotating); p50/p99 of the time from a state's first request to its landing in the cache (seen
by a watcher every 0.5 s); errors (requests refused, unanswered outside the outage, failed
batches: all 0 expected); 503s (back-offs, not errors); the server's resident memory at start,
after its first batch, at the end and its peak (for each server: a soak is flat); across the
restart, the states the trainers were asking for at the kill: landed after it, superseded by their
trainers' newer lists (by design: a trainer's newest list replaces its older one), lost (asked for
to the end and never landed: 0 expected); and the cache: it verifies, nothing stored twice.

Everything runs on 127.0.0.1 with a token; every loop is bounded in count and time.
One script past 400 lines: a benchmark a user runs and reads top to bottom (trainers, server, watcher,
the figures), not a module others import.

    .venv/bin/python benchmarks/serve_load.py --minutes 10                 # the full run: 8 trainers
    .venv/bin/python benchmarks/serve_load.py --minutes 1 --budget 4       # a short check
    .venv/bin/python benchmarks/serve_load.py --backend stub --model stub --minutes 1   # the harness alone
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("HF_HUB_OFFLINE", "1")
from record import cpu_name, options, record, settings  # noqa: E402

ENV_ID = "BabyAI-GoToLocal-v0"


def collections(folder: Path, trainers: int, steps: int) -> list[list]:
    """Each trainer's states in step order: a random-policy collection of its own seed (history 0)."""
    from illm_tools.collect import CollectConfig, collect
    from illm_tools.data.trajectories import open_table
    from illm_tools.tasks.state import TABLE_COLUMNS, records_from_table

    out = []
    for i in range(trainers):
        collect(CollectConfig(env_id=ENV_ID, out=folder / f"traj{i}", steps=steps, num_envs=8, seed=1000 + i))
        records, _ = records_from_table(open_table(folder / f"traj{i}", columns=TABLE_COLUMNS), 0)
        out.append(records)
    return out


class Server:
    """`illm serve` in a subprocess on 127.0.0.1, its token in the environment, its RSS sampled."""

    def __init__(self, args, cache: Path, token: str, log: Path, port: int = 0):
        self.log = log
        env = {**os.environ, "ILLM_SERVE_TOKEN": token, "PYTHONWARNINGS": "ignore"}
        cmd = [sys.executable, "-m", "cli.main", "serve", "--cache", str(cache), "--backend", args.backend,
               "--model", args.model, "--dtype", args.dtype, "--history", "0", "--host", "127.0.0.1", "--port", str(port),
               "--chunk", str(args.chunk), "--threads", str(args.server_threads)]
        self.started = time.monotonic()
        with open(log, "w") as f:
            self.proc = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, text=True)
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline:
            found = re.search(r"http://127\.0\.0\.1:(\d+)", log.read_text())
            if found:
                break
            if self.proc.poll() is not None:
                raise SystemExit(f"the server did not start: {log.read_text().strip()[-500:]}")
            time.sleep(0.2)
        else:
            raise SystemExit("the server did not start within 600 s")
        self.port = int(found.group(1))
        self.ready = time.monotonic()
        self.samples: list[tuple[float, int]] = []
        self._stop = threading.Event()
        self._sampler = threading.Thread(target=self._sample, daemon=True)
        self._sampler.start()

    def _sample(self) -> None:
        process = psutil.Process(self.proc.pid)
        while not self._stop.is_set():
            try:
                self.samples.append((time.monotonic(), process.memory_info().rss))
            except psutil.Error:
                return
            self._stop.wait(2.0)

    def stop(self, how: str) -> None:
        """Stop it: `kill` (SIGKILL, nothing finished) or `term` (SIGTERM: the batch in progress written)."""
        self._stop.set()
        self._sampler.join()
        self.proc.send_signal(signal.SIGKILL if how == "kill" else signal.SIGTERM)
        self.proc.wait(300)


def stats(url: str, token: str) -> dict | None:
    import json
    import urllib.request

    request = urllib.request.Request(url + "/stats", headers={"Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(request, timeout=10) as r:
            return json.loads(r.read())
    except OSError:
        return None


class Trainer:
    """One simulated trainer: its rollouts' states looked up, counted and sent as `illm train` does."""

    def __init__(self, i: int, records: list, url: str, token: str, args, llm, setup, cache_root: Path):
        from illm_tools.cache.store import AnnotationCache
        from illm_tools.rl.live_remote import RemoteLive

        self.records, self.args, self.setup = records, args, setup
        self.cache = AnnotationCache(cache_root)  # its own reader, as a trainer process has
        self.builder = setup.builder_of(llm)
        self.live = RemoteLive(url, client=f"sim-trainer-{i}", llm=llm, setup=setup, budget=args.budget, token=token)
        self.visits: Counter = Counter()
        self.keys: dict = {}
        self.first_asked: dict = {}  # state -> when it was first in a list handed to the client
        self.last_list: list = []
        self.rollouts = 0

    def rollout(self) -> None:
        import numpy as np

        n, k = self.args.rollout_steps, self.rollouts
        start = (k * n) % max(len(self.records) - n, 1)
        rollout = self.records[start: start + n]
        self.cache.refresh()
        distinct = list(dict.fromkeys(rollout))
        for r in distinct:
            if r not in self.keys:
                self.keys[r] = self.builder.state_keys(r, self.setup.tasks)
        found = np.logical_and.reduce([self.cache.contains([self.keys[r][t] for r in distinct])
                                       for t in range(len(self.setup.tasks))])
        self.visits.update(rollout)
        missing = sorted((r for r, f in zip(distinct, found) if not f), key=self.visits.__getitem__, reverse=True)
        now = time.monotonic()
        self.last_list = missing[: self.args.budget]
        for r in self.last_list:
            self.first_asked.setdefault(r, now)
        self.live.submit(missing, [self.visits[r] for r in missing])
        self.rollouts += 1

    def run(self, until: float, stop: threading.Event) -> None:
        """Rollouts every `rollout_seconds` until `until` (monotonic) or `stop`; at most as many as fit."""
        period = self.args.rollout_seconds
        for _ in range(int((until - time.monotonic()) / period) + 1):
            if stop.is_set() or time.monotonic() >= until:
                return
            began = time.monotonic()
            self.rollout()
            stop.wait(max(0.0, period - (time.monotonic() - began)))


class Watcher:
    """Sees states land: every 0.5 s, which asked-for states the cache now answers (all tasks)."""

    def __init__(self, cache_root: Path, trainers: list[Trainer], tasks):
        from illm_tools.cache.store import AnnotationCache

        self.cache, self.trainers, self.tasks = AnnotationCache(cache_root), trainers, tasks
        self.landed: dict = {}  # (trainer index, state) -> when it was seen in the cache
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def check(self) -> None:
        import numpy as np

        self.cache.refresh()
        now = time.monotonic()
        for i, t in enumerate(self.trainers):
            waiting = [r for r in list(t.first_asked) if (i, r) not in self.landed]
            if not waiting:
                continue
            found = np.logical_and.reduce([self.cache.contains([t.keys[r][j] for r in waiting])
                                           for j in range(len(self.tasks))])
            for r, f in zip(waiting, found):
                if f:
                    self.landed[(i, r)] = now

    def _run(self) -> None:
        while not self._stop.wait(0.5):
            self.check()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self.check()


def memory_line(name: str, server: Server, first_batch_at: float | None, end: float) -> str:
    mb = [(t, rss / 2**20) for t, rss in server.samples if t <= end]
    if not mb:
        return f"{name}: no samples"
    after = next((f"{m:,.0f} MB" for t, m in mb if first_batch_at is not None and t >= first_batch_at),
                 "(no batch finished)")
    return (f"{name}: at start {mb[0][1]:,.0f} MB, after its first batch {after}, at the end {mb[-1][1]:,.0f} MB "
            f"(peak {max(m for _, m in mb):,.0f} MB; {len(mb)} samples over {(mb[-1][0] - mb[0][0]) / 60:.1f} min)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the load phase")
    parser.add_argument("--trainers", type=int, default=8)
    parser.add_argument("--model", default="smollm2-135m")
    parser.add_argument("--backend", default="transformers")
    parser.add_argument("--dtype", default="auto", help="auto: resolved once here and given to the server")
    parser.add_argument("--budget", type=int, default=16, help="missed states per trainer per rollout (--live-budget)")
    parser.add_argument("--chunk", type=int, default=16, help="the server's --chunk")
    parser.add_argument("--server-threads", type=int, default=0, help="the server's --threads (0: every core)")
    parser.add_argument("--steps", type=int, default=8192, help="collected steps per trainer (played back in a loop)")
    parser.add_argument("--rollout-steps", type=int, default=256)
    parser.add_argument("--rollout-seconds", type=float, default=1.0)
    parser.add_argument("--restart-at", type=float, default=0.5, help="share of the load phase; 0: no restart")
    parser.add_argument("--restart-signal", choices=("kill", "term"), default="kill")
    parser.add_argument("--drain-minutes", type=float, default=5.0, help="at most this long for the last lists to land")
    options(parser)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="  [trainer client] %(message)s")

    from illm_tools.envs import renderer_of
    from illm_tools.llm.spec import LLMSpec
    from illm_tools.tasks.annotation_setup import AnnotationSetup

    llm = LLMSpec(backend=args.backend, model=args.model, dtype=args.dtype).placed()
    args.dtype = llm.dtype
    setup = AnnotationSetup(ENV_ID, renderer_of(ENV_ID), history_len=0)
    token = secrets.token_urlsafe(32)
    cpu = cpu_name()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        began = time.monotonic()
        states = collections(tmp, args.trainers, args.steps)
        print(f"collected {args.trainers} x {args.steps:,} steps in {time.monotonic() - began:.0f} s", flush=True)
        cache = tmp / "ann"
        servers = [Server(args, cache, token, tmp / "server1.log")]
        try:
            run = Run(args, servers, trainers_states=states, token=token, llm=llm, setup=setup, cache=cache, tmp=tmp)
            run.go()
        finally:
            for server in servers:
                if server.proc.poll() is None:
                    server.stop("term")
        figures = report(args, run, cache, cpu)
    if not args.no_record:  # lost states are the figure a restart must keep at 0 (unknown without a finished drain)
        asked = figures["asked_at_the_end"]
        value = figures["lost"] / asked if figures["lost"] is not None and asked else (0.0 if asked == 0 else None)
        record("serve_load", figures, ratio={"name": "states lost / states asked for at the end", "value": value,
                                             "target": 0.0, "direction": "at_most"},
               out=args.record, settings=settings(args))


class Run:
    """The load phase (with the restart), then the drain; what happened, for `report`."""

    def __init__(self, args, servers: list[Server], *, trainers_states, token, llm, setup, cache: Path, tmp: Path):
        self.args, self.servers, self.token, self.cache, self.tmp = args, servers, token, cache, tmp
        self.url = f"http://127.0.0.1:{servers[0].port}"
        print(f"server ready in {servers[0].ready - servers[0].started:.0f} s on {self.url}", flush=True)
        self.trainers = [Trainer(i, trainers_states[i], self.url, token, args, llm, setup, cache)
                         for i in range(args.trainers)]
        self.watcher = Watcher(cache, self.trainers, setup.tasks)
        self.first_batch: dict = {}  # server -> when its first batch was seen done
        self.restart: dict = {}
        self.drained = False
        self.final: dict = {}

    def stats(self) -> dict:
        return stats(self.url, self.token) or {}

    def wait(self, until: float, what: str, done=None) -> bool:
        """Until `until` (or `done(stats)` is true: returns True): note the server's first batch, and a
        progress line a minute."""
        said = time.monotonic()
        while time.monotonic() < until:
            s, server = self.stats(), self.servers[-1]
            if s.get("batches") and server not in self.first_batch:
                self.first_batch[server] = time.monotonic()
            if done is not None and s and done(s):
                return True
            if time.monotonic() - said >= 60:
                said = time.monotonic()
                rss = server.samples[-1][1] / 2**20 if server.samples else 0.0
                landed = len({r for _, r in list(self.watcher.landed)})
                print(f"{(said - self.t0) / 60:.0f} min in ({what}): {landed:,} states landed, {s.get('queue', '?')} queued, "
                      f"server RSS {rss:,.0f} MB", flush=True)
            time.sleep(1.0)
        return False

    def go(self) -> None:
        args, trainers = self.args, self.trainers
        stop = threading.Event()
        self.t0 = time.monotonic()
        end = self.t0 + args.minutes * 60
        threads = [threading.Thread(target=t.run, args=(end, stop), daemon=True) for t in trainers]
        for th in threads:
            th.start()
        if args.restart_at > 0:
            self.wait(self.t0 + args.restart_at * args.minutes * 60, "load")
            first = self.servers[0]
            self.restart["asked"] = {(i, r) for i, t in enumerate(trainers) for r in t.last_list} - \
                set(self.watcher.landed)
            self.restart["errors"] = self.stats().get("errors", 0)
            self.restart["unanswered_before"] = sum(t.live.counts["unanswered"] for t in trainers)
            self.restart["at"] = time.monotonic()
            first.stop(args.restart_signal)
            self.servers.append(Server(args, self.cache, self.token, self.tmp / "server2.log", port=first.port))
            self.restart["ready"] = time.monotonic()
            self.restart["unanswered_at_ready"] = sum(t.live.counts["unanswered"] for t in trainers)
            print(f"restarted ({args.restart_signal}) at {self.restart['at'] - self.t0:.0f} s; the new server answered "
                  f"{self.restart['ready'] - self.restart['at']:.1f} s later", flush=True)
        self.wait(end, "load")
        stop.set()
        for th in threads:
            th.join(60)
        self.load_end = time.monotonic()
        # the drain: the trainers stand still, their last lists queued, until the server has done them
        self.drained = self.wait(self.load_end + args.drain_minutes * 60, "drain", done=lambda s: (
            not s["queue"] and not s["annotating"] and all(t.live.idle for t in trainers)))
        self.drain_end = time.monotonic()
        self.final = self.stats()
        self.watcher.stop()
        for t in trainers:
            t.live.close()


def report(args, run: Run, cache: Path, cpu: str) -> dict:
    """Print the figures (module docstring); returns them as the record keeps them."""
    from illm_tools.cache import AnnotationCache, verify

    trainers, restart, final, servers = run.trainers, run.restart, run.final, run.servers
    t0, load_end, drain_end, drained = run.t0, run.load_end, run.drain_end, run.drained
    landed = run.watcher.landed
    asked = {(i, r): t.first_asked[r] for i, t in enumerate(trainers) for r in t.first_asked}
    waits = sorted(landed[k] - asked[k] for k in landed)
    in_load = len({r for (_, r), when in landed.items() if when <= load_end})  # distinct states
    final_lists = {(i, r) for i, t in enumerate(trainers) for r in t.last_list}
    unlanded = final_lists - set(landed)  # lost if the drain finished; else perhaps still queued
    counts = Counter()
    for t in trainers:
        counts.update(t.live.counts)
    outage_unanswered = restart.get("unanswered_at_ready", 0) - restart.get("unanswered_before", 0)
    # unanswered before the kill or after the new server was ready: errors
    late_unanswered = counts["unanswered"] - outage_unanswered
    failed_states = final.get("failed_states", 0) + restart.get("first_stats", {}).get("failed_states", 0)
    errors = counts["refused"] + final.get("errors", 0) + restart.get("errors", 0) + failed_states
    check = verify(cache)
    rows = len(AnnotationCache(cache))
    minutes = (load_end - t0) / 60

    def pct(q: float) -> str:
        return f"{waits[min(len(waits) - 1, int(q * len(waits)))]:.1f} s" if waits else "n/a"

    print()
    print(f"illm serve under load: {args.trainers} trainers, {minutes:.1f} min load + {drain_end - load_end:.0f} s "
          f"drain ({'drained' if drained else 'NOT drained: give more --drain-minutes'}), {args.model} "
          f"({args.backend}, {args.dtype}), --chunk {args.chunk}, budget {args.budget} states per trainer per "
          f"{args.rollout_seconds:g} s rollout of {args.rollout_steps} steps; CPU: {cpu}, {os.cpu_count()} cores")
    print(f"throughput: {in_load / (load_end - t0):.2f} states/s landed during the load phase ({in_load:,} distinct "
          f"states); the server {final.get('states_per_s', 0.0):.2f} states/s while annotating")
    print(f"first request -> landing: p50 {pct(0.5)}, p99 {pct(0.99)} (a trainer's state: {len(waits):,} landed of "
          f"{len(asked):,} asked for; the rest superseded by their trainers' newer lists"
          + ("" if drained else ", or still queued") + ")")
    print(f"errors: {errors + max(late_unanswered, 0)} (requests: {counts['sent']:,} sent, {counts['accepted']:,} "
          f"accepted, {counts['busy']:,} answered 503 or 429 and backed off, {counts['refused']} refused; "
          f"{outage_unanswered} unanswered during the outage, {max(late_unanswered, 0)} outside it; "
          f"failed batches {final.get('errors', 0) + restart.get('first_stats', {}).get('errors', 0)}, states failed "
          f"in the engine {failed_states})")
    for n, server in enumerate(servers):
        until = restart["at"] if n == 0 and restart else drain_end
        print("memory, " + memory_line(f"server {n + 1}", server, run.first_batch.get(server), until))
    if restart:
        risk = restart["asked"]
        after = {k for k in risk if k in landed}
        kept = {k for k in risk if k in final_lists} - after
        print(f"restart ({args.restart_signal}) at {restart['at'] - t0:.0f} s, answered again "
              f"{restart['ready'] - restart['at']:.1f} s later: the trainers were asking for {len(risk)} states; "
              f"{len(after)} landed after the restart, {len(risk - after - kept)} superseded by their trainers' "
              f"newer lists, {len(kept)} " + ("lost" if drained else "still asked for when the drain ended"))
    if drained:
        print(f"lost: {len(unlanded)} (states still asked for at the end that never landed)")
    else:
        print(f"lost: unknown, the drain did not finish: {len(unlanded)} states still asked for had not landed and "
              f"the server held {final.get('queue', '?')} (give more --drain-minutes)")
    print(f"cache: {AnnotationCache(cache).tasks()} rows by task, {check.rows:,} rows in the manifest, "
          f"{rows:,} distinct keys: {'verifies' if check.ok else 'DAMAGED'}, "
          f"{'nothing stored twice' if check.rows == rows else 'ROWS STORED TWICE'}")
    figures = {"load_minutes": minutes, "drain_s": drain_end - load_end, "drained": int(drained),
               "landed_states_per_s_in_load": in_load / (load_end - t0), "distinct_states_landed_in_load": in_load,
               "server_states_per_s_annotating": final.get("states_per_s", 0.0),
               "landed_p50_s": waits[int(0.5 * len(waits))] if waits else None,
               "landed_p99_s": waits[min(len(waits) - 1, int(0.99 * len(waits)))] if waits else None,
               "errors": errors + max(late_unanswered, 0), "requests_sent": counts["sent"],
               "requests_backed_off": counts["busy"], "unanswered_in_outage": outage_unanswered,
               "asked_at_the_end": len(final_lists), "lost": len(unlanded) if drained else None,
               "cache_rows": check.rows, "cache_distinct_keys": rows, "cache_verifies": int(check.ok)}
    for n, server in enumerate(servers):
        until = restart["at"] if n == 0 and restart else drain_end
        mb = [rss / 2**20 for t, rss in server.samples if t <= until]
        figures.update({f"server_{n + 1}:rss_start_mb": mb[0], f"server_{n + 1}:rss_end_mb": mb[-1],
                        f"server_{n + 1}:rss_peak_mb": max(mb)} if mb else {})
    return figures




if __name__ == "__main__":
    main()
